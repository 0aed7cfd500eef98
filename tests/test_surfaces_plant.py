"""Surfaces at plant scale: ``reconstruct --heliostats`` learns every heliostat with centred images in one run.

The plant is simulated in code (``heliotwin simulate``: 6 heliostats, 3 of them with 10 flux-centred images each);
the learner runs with a tiny budget (4 steps, 4x4 control points, a fixed slope error) so that a heliostat takes
seconds. What is checked: the learned and skipped heliostats and why, each heliostat's result equal to the
single-heliostat ``reconstruct`` (same learner and acceptance rule), ``--nproc 2`` equal to one process, resume after
an interruption, a failing heliostat reported while the others finish, one-line errors for bad selections.
"""
from __future__ import annotations

import json
import shutil

import pytest
import torch
from helpers.cli import assert_one_line_error, run_cli

from heliotwin import api
from heliotwin.errors import HeliotwinError
from heliotwin.io.scenario import load_scenario
from heliotwin.surfaces.state import learned_surface
from heliotwin.workflows import reconstruct_plant as plant_module
from heliotwin.workflows.reconstruct import ReconstructionSettings, reconstruct
from heliotwin.workflows.reconstruct_plant import reconstruct_plant

SMALL = dict(steps=4, control_points="4x4", degree=2, slope_error_mrad=1.5, device="cpu")
FLAGS = ("--steps", "4", "--control-points", "4x4", "--degree", "2", "--slope-error", "1.5", "--device", "cpu",
         "--quiet")


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    """A simulated PAINT folder and the heliostats that have centred images there."""
    folder = tmp_path_factory.mktemp("plant") / "paint"
    api.simulate(folder, heliostats=6, images=3, years=1, seed=0)
    with_images = sorted({p.parts[-3] for p in folder.glob("*/Calibration/*-flux-centered.png")})
    assert len(with_images) == 3
    return folder, with_images


@pytest.fixture(scope="module")
def learned(plant):
    """``--heliostats all`` in this process (the reference of the other tests)."""
    folder, _ = plant
    return reconstruct_plant(None, folder, "all", ReconstructionSettings(**SMALL), progress=False)


def _cp(scenario, heliostat):
    return learned_surface(scenario, heliostat)["surfaces"].control_points


def test_every_heliostat_with_images_is_learned_and_the_others_are_skipped_with_the_reason(plant, learned):
    folder, with_images = plant
    scenario, report = learned
    rows = {r["heliostat"]: r for r in report["heliostats"]}
    assert len(rows) == 6 and [r["heliostat"] for r in report["heliostats"]] == sorted(rows)
    assert sorted(h for h, r in rows.items() if r["status"] == "learned") == with_images
    for h, r in rows.items():
        if h not in with_images:
            assert r["status"] == "skipped" and r["reason"].startswith("0 centred image(s), needs 3")
    s = report["summary"]
    assert (s["learned"], s["skipped"], s["failed"], s["resumed"], s["nproc"]) == (3, 3, 0, 0, 1)
    # The plant learns what it is meant to: on images its fits never saw, the learned surfaces beat the ideal one.
    assert s["median_test_l1_learned"] < s["median_test_l1_ideal"]
    for h in with_images:
        r = rows[h]
        # every image trained (the current surface); the test rows are its cross-validation, one per image
        assert (r["train"]["images"], r["test"]["images"], r["test"]["is"]) == (10, 10, "cross-validation")
        assert r["accepted"] == (r["acceptance_alpha"] > 0) and r["train"]["worse_than_ideal"] == 0
    # One scenario holds every learned surface, with one provenance step naming them.
    assert sorted(scenario.learned["surfaces"]) == with_images
    assert scenario.provenance[-1]["step"] == "reconstruct" and scenario.provenance[-1]["heliostats"] == with_images
    assert [p["step"] for p in scenario.provenance].count("reconstruct") == 1
    ideal = learned_surface(scenario, with_images[0])["ideal"].control_points
    assert (_cp(scenario, with_images[0]) - ideal).abs().max() > 1e-6  # learned, not the ideal start


def test_a_heliostat_learned_in_the_plant_run_is_the_single_heliostat_reconstruction(plant, learned):
    folder, with_images = plant
    h = with_images[1]
    single, report, _ = reconstruct(None, folder, h, ReconstructionSettings(**SMALL), progress=False)
    row = next(r for r in learned[1]["heliostats"] if r["heliostat"] == h)
    assert row["test"]["median_l1_learned"] == report["median_l1_learned"]
    assert row["test"]["median_l1_ideal"] == report["median_l1_ideal"]
    assert row["acceptance_alpha"] == report["acceptance"]["alpha"] and row["choices"] == report["choices"]
    assert torch.equal(_cp(learned[0], h), _cp(single, h))
    # the current surface: every image trained it, and each test row is that image held out of its fold's fits
    assert report["split"]["current"] and report["test_is"] == "cross-validation" and not report["dropped"]
    assert [r["record"] for r in report["test"]] == [r["record"] for r in report["train"]]
    assert [r["l1_learned"] for r in report["test"]] == report["selection"]["heldout_l1"]
    assert report["selection"]["folds"] == 3
    assert torch.equal(learned[0].learned["surfaces"][h]["displacement"], single.learned["surfaces"][h]["displacement"])


def test_two_worker_processes_give_the_same_surfaces_and_the_scenario_lists_them(plant, learned, tmp_path, capsys):
    folder, with_images = plant
    out, rep = tmp_path / "plant.h5", tmp_path / "plant.json"
    code, _, err = run_cli(capsys, "reconstruct", "--paint", folder, "--heliostats", "all", "--nproc", "2", *FLAGS,
                           "-o", out, "--json", rep)
    assert code == 0, err
    scenario, report = load_scenario(out), json.loads(rep.read_text())
    assert report["summary"]["nproc"] == 2 and report["summary"]["learned"] == 3
    assert torch.equal(scenario.plant.field.surfaces.control_points, learned[0].plant.field.surfaces.control_points)
    drop = ("seconds",)
    for a, b in zip(report["heliostats"], learned[1]["heliostats"]):
        assert {k: v for k, v in a.items() if k not in drop} == {k: v for k, v in b.items() if k not in drop}
    for h in with_images:
        assert torch.equal(scenario.learned["surfaces"][h]["displacement"],
                           learned[0].learned["surfaces"][h]["displacement"])
    code, shown, _ = run_cli(capsys, "scenario", "show", out)
    assert code == 0 and f"surfaces: learned for {', '.join(with_images)}" in shown


def test_an_interrupted_run_resumes_from_its_finished_heliostats(plant, learned, tmp_path, capsys, monkeypatch):
    folder, with_images = plant
    out, rep = tmp_path / "plant.h5", tmp_path / "plant.json"
    ckpt = tmp_path / "plant.h5.ckpt"
    real, calls = plant_module.learn_surface, []

    def interrupted(scenario, paint, heliostat, *a, **kw):  # Ctrl-C while the second heliostat is learned
        calls.append(heliostat)
        if heliostat == with_images[1]:
            raise KeyboardInterrupt
        return real(scenario, paint, heliostat, *a, **kw)

    monkeypatch.setattr(plant_module, "learn_surface", interrupted)
    argv = ("reconstruct", "--paint", folder, "--heliostats", "all", *FLAGS, "-o", out, "--json", rep)
    code, _, err = run_cli(capsys, *argv)
    assert code == 130 and "checkpoint" in err and "--resume" in err
    assert not out.exists() and not rep.exists()  # nothing half-written
    assert sorted(p.name for p in ckpt.iterdir()) == [f"{with_images[0]}.ckpt"]
    assert_one_line_error(*run_cli(capsys, *argv)[::2], "rerun with --resume")
    code, _, err = run_cli(capsys, *argv[:-4], "--steps", "5", "-o", out, "--json", rep, "--resume")
    assert_one_line_error(code, err, "other settings or inputs")

    monkeypatch.setattr(plant_module, "learn_surface", lambda *a, **kw: (calls.append(a[2]), real(*a, **kw))[1])
    calls.clear()
    code, _, err = run_cli(capsys, *argv, "--resume")
    assert code == 0, err
    assert calls == with_images[1:]  # the finished heliostat is not learned again
    report, scenario = json.loads(rep.read_text()), load_scenario(out)
    rows = {r["heliostat"]: r for r in report["heliostats"]}
    assert rows[with_images[0]]["resumed"] and not rows[with_images[1]]["resumed"]
    assert report["summary"]["resumed"] == 1 and report["summary"]["learned"] == 3
    assert torch.equal(scenario.plant.field.surfaces.control_points, learned[0].plant.field.surfaces.control_points)
    assert not ckpt.exists()  # removed once the outputs are in place


def test_a_failing_heliostat_is_reported_in_one_line_and_the_others_finish(plant, tmp_path, capsys):
    folder, with_images = plant
    copy = tmp_path / "paint"
    shutil.copytree(folder, copy)
    bad = sorted((copy / with_images[0] / "Calibration").glob("*-flux-centered.png"))[0]
    bad.write_bytes(b"not a png")
    skipped = next(p.name for p in sorted(copy.iterdir()) if p.is_dir() and p.name not in with_images
                   and (p / "Properties").is_dir())
    scenario, report = reconstruct_plant(None, copy, [with_images[0], skipped, with_images[1]],
                                         ReconstructionSettings(**SMALL), progress=True)
    # In a log: one line per heliostat learned or failed; the learner's own leave-one-out progress stays quiet.
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split(" (")[0] for ln in lines if "/2 " in ln] == [
        f"heliotwin reconstruct: 1/2 {with_images[0]} failed", f"heliotwin reconstruct: 2/2 {with_images[1]} learned"]
    assert not any("leave-one-out" in ln for ln in lines)
    rows = report["heliostats"]
    assert [r["heliostat"] for r in rows] == [with_images[0], skipped, with_images[1]]  # selection order
    assert [r["status"] for r in rows] == ["failed", "skipped", "learned"]
    assert bad.name in rows[0]["reason"] and "\n" not in rows[0]["reason"]
    assert sorted(scenario.learned["surfaces"]) == [with_images[1]]
    assert scenario.provenance[-1]["failed"] == [with_images[0]] and scenario.provenance[-1]["skipped"] == [skipped]
    # The command line writes the others and exits 3, so a script sees that the plant is not complete.
    out, rep = tmp_path / "plant.h5", tmp_path / "plant.json"
    code, _, err = run_cli(capsys, "reconstruct", "--paint", copy, "--heliostats", f"{with_images[0]},{with_images[1]}",
                           *FLAGS, "-o", out, "--json", rep)
    assert code == 3 and "1 heliostat(s) failed" in err and len(err.strip().splitlines()) == 1
    assert sorted(load_scenario(out).learned["surfaces"]) == [with_images[1]]
    assert json.loads(rep.read_text())["summary"]["failed"] == 1


def _parse_error(capsys, *argv):
    """An argument the parser refuses: (exit status, stderr)."""
    with pytest.raises(SystemExit) as exc:
        run_cli(capsys, *argv)
    return exc.value.code, capsys.readouterr().err


def test_bad_selections_and_single_heliostat_options_are_one_line_errors(plant, tmp_path, capsys):
    folder, with_images = plant
    base = ("reconstruct", "--paint", folder, "--json", tmp_path / "r.json")
    assert_one_line_error(*run_cli(capsys, *base, "--heliostats", f"{with_images[0]},ZZ99")[::2],
                          "--heliostats", "unknown heliostat(s) ZZ99")
    assert_one_line_error(*_parse_error(capsys, *base, "--heliostats", "all", "--heliostat", "AA45"),
                          "--heliostat", "not allowed")
    assert_one_line_error(*run_cli(capsys, *base, "--heliostat", with_images[0], "--nproc", "2")[::2],
                          "--nproc", "--heliostats")
    assert_one_line_error(*run_cli(capsys, *base, "--heliostats", "all", "--train-records", "1,2")[::2],
                          "--train-records", "--train-first")
    assert_one_line_error(*_parse_error(capsys, *base, "--heliostats", "all", "--nproc", "0"), "--nproc")
    with pytest.raises(HeliotwinError, match="--nproc"):
        reconstruct_plant(None, folder, "all", ReconstructionSettings(**SMALL), nproc=0)
    assert not (tmp_path / "r.json").exists()


@pytest.mark.slow
def test_the_real_plant_learns_its_one_heliostat_with_images_and_skips_the_others(paint_dir):
    report, scenario = api.reconstruct_plant(paint_dir, "all", ReconstructionSettings(steps=30, device="cpu"),
                                             progress=False)
    rows = {r["heliostat"]: r for r in report["heliostats"]}
    learned = [h for h, r in rows.items() if r["status"] == "learned"]
    assert learned == ["AA39"] and report["summary"]["failed"] == 0
    assert all(r["status"] == "skipped" and "centred image" in r["reason"] for h, r in rows.items() if h != "AA39")
    assert sorted(scenario.learned["surfaces"]) == ["AA39"]
    assert rows["AA39"]["test"]["images"] >= 1
