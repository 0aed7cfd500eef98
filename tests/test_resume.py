"""Checkpoint and resume of long fits: an interrupted fit, resumed, reaches the uninterrupted fit's result.

Interruptions are deterministic: the checkpoint's test hook raises after a chosen step of a chosen loop
(between two saves, so the resumed run redoes some steps), as Ctrl-C would. Synthetic data (no real data)
for the library loops; the CLI tests use a copy of two real heliostats (the reconstruct CLI's own resume test is in
test_surfaces_generalise.py).
"""
from __future__ import annotations

import dataclasses
import json
import os

import pytest
import torch
from helpers.calibrate import TRUE, jueliche_like, simulate
from helpers.cli import assert_one_line_error, run_cli
from helpers.surfaces import dome_scene as make_dome_scene

from heliotwin.calibrate.methods.gradient import fit_gradient_method
from heliotwin.calibrate.methods.hybrid import fit_hybrid_method
from heliotwin.calibrate.methods.lm import fit_lm_method
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.errors import HeliotwinError
from heliotwin.io.checkpoint import Checkpoint, active, checkpoint_path, make_tag
from heliotwin.surfaces.fit import SurfaceSettings, fit_surface
from heliotwin.surfaces.insilico import choose_laplacian
from heliotwin.surfaces.nuisance import estimate_camera


class Interrupt(KeyboardInterrupt):
    """What the hook raises: Ctrl-C in the middle of a fit."""


def _stop_at(key: str, step: int, seen: list | None = None):
    def hook(event, k, s):
        if seen is not None and event == "step":
            seen.append((k, s))
        if event == "step" and k == key and s == step:
            raise Interrupt()
    return hook


def _interrupted_then_resumed(tmp_path, fit, key, step, every=3):
    """Run ``fit()`` under a checkpoint until ``key`` reaches ``step``; resume; return (result, steps redone)."""
    path = tmp_path / "run.ckpt"
    with pytest.raises(Interrupt):
        with active(Checkpoint(path, "tag", every=every, min_interval_s=0, hook=_stop_at(key, step))):
            fit()
    assert path.exists()
    seen: list = []
    ck = Checkpoint(path, "tag", resume=True, every=every, min_interval_s=0, hook=_stop_at("-", -1, seen))
    assert ck.resumed and key in ck.entries
    with active(ck):
        out = fit()
    return out, seen


@pytest.fixture(scope="module")
def synthetic_records():
    nom = jueliche_like(2)
    true = apply_deviations(nom, torch.tensor([list(TRUE.values())] * 2, dtype=torch.float64), STONE8)
    recs = simulate(true, 18, seed=3, noise=1e-3)
    idx = torch.arange(len(recs))
    return nom, recs.subset(idx % 3 != 0), recs.subset(idx % 3 == 0)


@pytest.fixture(scope="module")
def gradient_reference(synthetic_records):
    nom, tr, va = synthetic_records
    return fit_gradient_method(nom, tr, va, seed=0, iterations=6)


def test_gradient_fit_resumed_mid_loop_equals_the_uninterrupted_fit(tmp_path, synthetic_records, gradient_reference):
    """The rigid-body gradient fit (L-BFGS, two early-stopping passes): interrupted at step 5 of its first
    loop (last save at step 3), resumed: the same deviations, bit for bit, and only steps 4.. are rerun."""
    nom, tr, va = synthetic_records
    ref = gradient_reference
    out, seen = _interrupted_then_resumed(tmp_path, lambda: fit_gradient_method(nom, tr, va, seed=0, iterations=6),
                                          "fit/0", 5)
    assert torch.equal(out.delta, ref.delta)
    first = [s for k, s in seen if k == "fit/0"]
    assert first[0] == 4  # continued after the saved step 3, not from the start


def test_gradient_fit_interrupted_in_its_second_loop_restores_the_first(tmp_path, synthetic_records,
                                                                         gradient_reference):
    nom, tr, va = synthetic_records
    ref = gradient_reference
    out, seen = _interrupted_then_resumed(tmp_path, lambda: fit_gradient_method(nom, tr, va, seed=0, iterations=6),
                                          "fit/1", 1, every=1)
    assert torch.equal(out.delta, ref.delta)
    assert not any(k == "fit/0" for k, _ in seen)  # the finished first loop is restored, not rerun


def test_hybrid_network_fit_resumed_equals_the_uninterrupted_fit(tmp_path, synthetic_records):
    """Adam on per-heliostat networks: parameters, Adam moments and the best-so-far networks all restored."""
    nom, tr, va = synthetic_records
    ref = fit_hybrid_method(nom, tr, va, seed=0, steps=40)
    out, _ = _interrupted_then_resumed(tmp_path, lambda: fit_hybrid_method(nom, tr, va, seed=0, steps=40),
                                       "fit/0", 25, every=10)
    assert torch.equal(out.delta, ref.delta)
    a, b = out.extras["net"].state_dict(), ref.extras["net"].state_dict()
    assert all(torch.equal(a[k], b[k]) for k in b)


def test_lm_bagging_resumed_after_some_bags_equals_the_uninterrupted_fit(tmp_path, synthetic_records):
    """``lm`` (the default method): a checkpoint after the full-data fit and after every bootstrap bag (the
    resampling generator's state with it); interrupted after bag 2 of 4, the resumed fit redoes bags 3-4 only."""
    nom, tr, va = synthetic_records
    ref = fit_lm_method(nom, tr, va, seed=5, bags=4)
    out, seen = _interrupted_then_resumed(tmp_path, lambda: fit_lm_method(nom, tr, va, seed=5, bags=4), "bags/0", 3)
    assert torch.equal(out.delta, ref.delta)
    assert [s for k, s in seen if k == "bags/0"] == [4, 5]


@pytest.fixture(scope="module")
def dome_scene():
    facets, obs, sun, _ = make_dome_scene(samples=(10, 10))
    return facets, obs, sun


@pytest.mark.parametrize("batch", [None, 1])
def test_surface_adam_fit_with_camera_and_heldout_curve_resumed_equals_the_uninterrupted_fit(tmp_path, dome_scene,
                                                                                             batch):
    """The learner's Adam fit (camera model, learned per-image blur, slope penalty, held-out curve) in the fit
    loop: interrupted between two saves, resumed, it takes the same steps to the same surface and curve. With
    one image per step (``batch`` 1, every-image learning) the same seeded batches and the same kernels, restored
    without their spectra, which the resumed fit makes again."""
    facets, obs, sun = dome_scene
    s = SurfaceSettings(control_points=(4, 4), degree=(2, 2), samples=(8, 8), resolution=32, size_m=4.0, steps=14,
                        lr=0.3, eval_every=3, batch_images=batch)
    cam = estimate_camera(obs.images.to(torch.float32))

    def fit():
        return fit_surface(facets, obs.subset([0, 1]), sun, s, camera=cam.subset([0, 1]), sigma0=torch.ones(2),
                           slope_weight=1e-2, heldout=(obs.subset([2]), cam.subset([2])))

    ref = fit()
    out, seen = _interrupted_then_resumed(tmp_path, fit, "fit/0", 8, every=3)
    assert [s for k, s in seen if k == "fit/0"][0] == 7  # continued after the last save (step 6)
    assert torch.equal(out.model.displacement, ref.model.displacement) and torch.equal(out.sigma, ref.sigma)
    assert out.curve == ref.curve and [st for st, _ in out.curve] == [3, 6, 9, 12]
    assert out.heldout.keys() == ref.heldout.keys()


def test_surface_lbfgs_study_resumed_equals_the_uninterrupted_one(tmp_path, dome_scene):
    """L-BFGS rounds with a Laplacian weight chosen by held-out fits (many fits, each its own key)."""
    facets, obs, sun = dome_scene
    s = SurfaceSettings(control_points=(3, 3), degree=(2, 2), samples=(8, 8), resolution=32, loss="l1",
                        optimizer="lbfgs", continuation=(1.5,), continuation_iters=4, lbfgs_round=6, steps=16)

    def fit():
        chosen, record = choose_laplacian(facets, obs, sun, s, (1e-3, 1e-2))
        return fit_surface(facets, obs, sun, chosen), record

    ref, ref_record = fit()
    (out, record), seen = _interrupted_then_resumed(tmp_path, fit, "fit/1", 2, every=1)
    assert torch.equal(out.model.displacement, ref.model.displacement) and out.log == ref.log
    assert record == ref_record
    assert not any(k == "fit/0" for k, _ in seen) and ("fit/1", 3) in seen  # fit/0 restored, fit/1 continued


def test_changed_settings_stale_and_corrupt_checkpoints_are_one_line_errors(tmp_path):
    path = tmp_path / "run.ckpt"
    ck = Checkpoint(path, make_tag({"steps": 10}), min_interval_s=0)
    ck.put("fit/0", {"step": 1})
    assert make_tag({"steps": 10}) == make_tag({"steps": 10}) != make_tag({"steps": 11})
    with pytest.raises(HeliotwinError, match="other settings or inputs"):
        Checkpoint(path, make_tag({"steps": 11}), resume=True)
    with pytest.raises(HeliotwinError, match="rerun with --resume"):
        Checkpoint(path, make_tag({"steps": 10}))  # an interrupted run's work is never overwritten silently
    assert Checkpoint(path, make_tag({"steps": 10}), resume=True).get("fit/0") == {"step": 1}
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(HeliotwinError, match="not a readable heliotwin checkpoint"):
        Checkpoint(path, "t", resume=True)
    torch.save({"format": "something else"}, path)
    with pytest.raises(HeliotwinError, match="field 'format'"):
        Checkpoint(path, "t", resume=True)
    assert sorted(os.listdir(tmp_path)) == ["run.ckpt"]  # no temporary file left by the writes
    # Inputs are part of the tag: a changed input file is a different run.
    data = tmp_path / "in.txt"
    data.write_text("a")
    before = make_tag({}, [data])
    data.write_text("ab")
    assert make_tag({}, [data]) != before
    # A folder's fingerprint ignores the run's own checkpoint (an output may be written into an input folder).
    folder = tmp_path / "inputs"
    folder.mkdir()
    (folder / "a.json").write_text("{}")
    before = make_tag({}, [folder])
    (folder / "report.json.ckpt").write_bytes(b"x")
    assert make_tag({}, [folder]) == before


# ------------------------------------------------------------------------------------------- CLI
@pytest.fixture()
def two_heliostats(tmp_path, paint_dir):
    from helpers.paint import copy_paint

    return copy_paint(paint_dir, tmp_path, heliostats=("AA39", "AK46", "BG23"), metadata=True)


def _calibrate(capsys, paint, out, *extra):
    return run_cli(capsys, "calibrate", "--paint", paint, "--heliostats", "AK46,BG23", "--method", "gradient",
                   "--train", "12", "--test", "10",
                   "--min-records", "20", "--no-plots", "--checkpoint-interval", "0", "--json", out, *extra)


@pytest.mark.slow  # three real gradient fits (~15 s)
def test_cli_calibrate_interrupted_resumes_to_the_same_report(tmp_path, two_heliostats, capsys, monkeypatch):
    """``calibrate`` interrupted by Ctrl-C in its fit: exit 130, the checkpoint kept, nothing else written;
    ``--resume`` finishes with the uninterrupted run's numbers and removes the checkpoint; a resume with
    other settings is one line, exit 2."""
    from heliotwin.io import checkpoint as ckmod

    ref_json = tmp_path / "ref.json"
    code, _, err = _calibrate(capsys, two_heliostats, ref_json)
    assert code == 0, err
    assert not os.path.exists(checkpoint_path(ref_json))

    out = tmp_path / "run.json"
    real_init = ckmod.Checkpoint.__init__

    def init_with_hook(self, *a, **kw):
        real_init(self, *a, **dict(kw, hook=_stop_at("fit/0", 12)))

    monkeypatch.setattr(ckmod.Checkpoint, "__init__", init_with_hook)
    code, _, err = _calibrate(capsys, two_heliostats, out)
    monkeypatch.undo()
    assert code == 130 and "--resume" in err
    assert not out.exists() and os.path.exists(checkpoint_path(out))

    code, _, err = _calibrate(capsys, two_heliostats, out, "--seed", "1", "--resume")
    assert_one_line_error(code, err, "other settings")
    code, _, err = _calibrate(capsys, two_heliostats, out)
    assert_one_line_error(code, err, "--resume")

    code, _, err = _calibrate(capsys, two_heliostats, out, "--resume")
    assert code == 0, err
    assert not os.path.exists(checkpoint_path(out))
    a, b = json.loads(out.read_text()), json.loads(ref_json.read_text())
    for hid, rep in b["heliostats"].items():
        assert a["heliostats"][hid].get("parameters") == rep.get("parameters")
        assert a["heliostats"][hid]["test"] == rep["test"]


def test_cli_refuses_a_corrupt_or_unresumed_checkpoint_before_any_work(tmp_path, capsys):
    """Checked before the PAINT folder is even read: a corrupt checkpoint, a checkpoint without --resume and
    --resume without an output are one line each (exit 2), and the file is left alone."""
    out = tmp_path / "run.json"
    ck = tmp_path / "run.json.ckpt"
    ck.write_bytes(b"\x00garbage")
    for command in (["reconstruct", "--heliostat", "AA39", "--json", out],
                    ["calibrate", "--json", out]):
        code, _, err = run_cli(capsys, *command, "--paint", tmp_path / "missing", "--resume")
        assert_one_line_error(code, err, str(ck), "not a readable heliotwin checkpoint")
        assert code == 2
        code, _, err = run_cli(capsys, *command, "--paint", tmp_path / "missing")
        assert_one_line_error(code, err, str(ck), "--resume")
    assert ck.read_bytes() == b"\x00garbage" and not out.exists()
    code, _, err = run_cli(capsys, "calibrate", "--paint", tmp_path / "missing", "--resume")
    assert_one_line_error(code, err, "--resume needs -o or --json")


@pytest.mark.slow  # a real subprocess and a real signal; waits for the first checkpoint to appear
@pytest.mark.skipif(os.name != "posix", reason="POSIX signals")
def test_sigterm_during_reconstruct_keeps_the_checkpoint_and_resume_finishes(tmp_path, two_heliostats):
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    import heliotwin

    src = Path(heliotwin.__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(src), OMP_NUM_THREADS="1", HELIOTWIN_DEBUG="0")
    out = tmp_path / "run.json"
    argv = [sys.executable, "-m", "heliotwin", "reconstruct", "--paint", str(two_heliostats), "--heliostat", "AA39",
            "--steps", "40", "--control-points", "4x4", "--degree", "2", "--slope-error", "1",
            "--checkpoint-interval", "0", "--json", str(out), "--quiet"]
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not os.path.exists(checkpoint_path(out)):
        if proc.poll() is not None:
            pytest.skip(f"the fit ended before the first checkpoint ({proc.returncode})")
        if time.monotonic() - t0 > 300:
            proc.kill()
            pytest.fail("no checkpoint appeared")
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    if proc.returncode == 0:
        pytest.skip("the fit finished before the signal arrived")
    assert proc.returncode == 143, err
    assert "--resume" in err and os.path.exists(checkpoint_path(out)) and not out.exists()
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".heliotwin")]
    done = subprocess.run(argv + ["--resume"], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert out.exists() and not os.path.exists(checkpoint_path(out))


def test_library_settings_hash_ignores_progress():
    from heliotwin.calibrate.protocol.pipeline import RunConfig, calibration_checkpoint

    tags = set()
    for progress in (True, False):
        cfg = RunConfig(paint="/nonexistent", progress=progress)
        tags.add(calibration_checkpoint(cfg, "/nonexistent/x.ckpt").tag)
    assert len(tags) == 1
    cfg = dataclasses.replace(RunConfig(paint="/nonexistent"), train=10)
    assert calibration_checkpoint(cfg, "/nonexistent/x.ckpt").tag not in tags


def test_settings_cv_interrupted_resumes_after_its_finished_candidates(tmp_path, paint_dir):
    """The settings CV (``--settings cv`` / ``--learn-settings``) under the run's checkpoint: Ctrl-C after two
    of three candidates keeps them; the resumed choice scores only the third and makes the same choice."""
    from heliotwin.calibrate.protocol import pipeline, selection
    from heliotwin.calibrate.protocol.config import RunConfig

    cands = [{"prior": "run", "bags": 0}, {"prior": "run", "bags": 0, "loss": "linear"},
             {"prior": "run", "bags": 0, "half_life_days": 60.0}]
    cfg = RunConfig(paint=str(paint_dir), split="chrono", train=30, test=30, prior_from=str(paint_dir),
                    settings="cv")
    calls = []

    def runner(c, dataset):
        calls.append(c.method_options.get("loss"))
        with active(None):
            return pipeline.run_calibration(c, dataset)

    _, ref = selection.choose_for_run(cfg, [], runner=runner, candidates=cands, run_size=11)
    assert len(calls) == 3
    path = tmp_path / "cv.ckpt"
    with pytest.raises(Interrupt):
        with active(Checkpoint(path, "tag", min_interval_s=0, hook=_stop_at("settings_cv/0", 2))):
            selection.choose_for_run(cfg, [], runner=runner, candidates=cands, run_size=11)
    calls.clear()
    with active(Checkpoint(path, "tag", resume=True, min_interval_s=0)):
        _, resumed = selection.choose_for_run(cfg, [], runner=runner, candidates=cands, run_size=11)
    assert len(calls) == 1  # the third candidate only
    assert resumed["table"] == ref["table"] and resumed["chosen"] == ref["chosen"]
    assert resumed["drift_mrad"] == ref["drift_mrad"] and resumed["walk_scale"] == ref["walk_scale"]
