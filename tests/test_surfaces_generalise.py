"""Generalising surface learning: camera nuisance, edge penalty, acceptance rule, outlier rule, optics start."""
from __future__ import annotations

import dataclasses

import pytest
import torch
from helpers.surfaces import dome_scene, small_scene

from heliotwin.field.plant import Facets, SunSettings
from heliotwin.surfaces import losses
from heliotwin.surfaces.acceptance import ALPHAS, robust_outliers, shrink_to_accept, wilson_interval
from heliotwin.surfaces.edges import edge_ridge_mrad, high_order, slope_penalties, slope_penalty
from heliotwin.surfaces.fit import fit_surface, minibatch_rows
from heliotwin.surfaces.fitbatch import FitProblem, fit_surfaces
from heliotwin.surfaces.generalise import (
    SurfaceSettings,
    canting_focal_length,
    choose_optics,
    cv_folds,
    evaluate_with_camera,
    fit_generalising,
    focused_start,
    spread_images,
)
from heliotwin.surfaces.imaging import predict_images
from heliotwin.surfaces.learning import LearnableSurface, learnable_surfaces, normal_heights
from heliotwin.surfaces.mismatch import camera_truth
from heliotwin.surfaces.nuisance import SATURATED, apply_camera, estimate_camera, gaussian_blur


def _spot(n=48, sigma=6.0, b=2):
    y, x = torch.meshgrid(torch.arange(n, dtype=torch.float64), torch.arange(n, dtype=torch.float64), indexing="ij")
    out = [torch.exp(-((x - 24 - 2 * i) ** 2 + (y - 22) ** 2) / (2 * sigma ** 2)) for i in range(b)]
    return torch.stack(out)


def test_wilson_interval_matches_the_closed_form():
    lo, hi = wilson_interval(7, 7)
    assert lo == pytest.approx(0.6457, abs=1e-4) and hi == 1.0
    lo, hi = wilson_interval(5, 10)
    assert lo == pytest.approx(0.2366, abs=1e-4) and hi == pytest.approx(0.7634, abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_outlier_rule_drops_only_the_inconsistent_image():
    drop, z = robust_outliers([0.20, 0.21, 0.19, 0.60])
    assert drop == [3] and z[3] > 3
    # Two-sided: an image the others predict far better than each other (it pulled the shared optics).
    assert robust_outliers([0.42, 0.08, 0.38, 0.40])[0] == [1]
    assert robust_outliers([0.20, 0.24, 0.21])[0] == []  # ordinary scatter (below the metric's floor)
    assert robust_outliers([0.2, 0.9], keep_at_least=2)[0] == []


def test_acceptance_shrinks_until_no_training_image_is_worse():
    ideal = [0.30, 0.20]
    # Image 0 improves with alpha; image 1 gets worse than ideal beyond alpha = 0.5.
    alpha, tried = shrink_to_accept(lambda a: [0.30 - 0.1 * a, 0.20 + 0.1 * max(0.0, a - 0.5)], ideal)
    assert alpha == 0.4 and not tried[0]["ok"] and tried[-1]["ok"]
    assert shrink_to_accept(lambda a: [0.3 + a, 0.2 + a], ideal)[0] == 0.0


def test_camera_rules_recover_cut_and_saturation_of_a_recorded_spot():
    true = _spot()
    rec = camera_truth(true, saturation=0.7, cut=0.1)
    cam = estimate_camera(rec)
    assert torch.all(cam.threshold >= 0.1) and torch.all(cam.threshold < 0.13)
    assert torch.equal(cam.n_saturated, (rec >= SATURATED).sum((-2, -1)))
    # The model image (the unsaturated truth) through the estimated camera reproduces the recording.
    assert losses.l1(apply_camera(true, cam), rec).max() < 0.02
    assert losses.l1(true, rec).min() > 0.05


def test_blur_keeps_the_power_and_is_differentiable_in_sigma():
    img = _spot(48, 3.0)
    out = gaussian_blur(img, torch.tensor([1.0, 2.5], dtype=torch.float64))
    assert torch.allclose(out.sum((-2, -1)), img.sum((-2, -1)), rtol=1e-6)
    assert torch.allclose(gaussian_blur(img, torch.zeros(2, dtype=torch.float64)), img, atol=1e-12)
    sig = torch.tensor([1.2, 2.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda s: gaussian_blur(img[:, 14:30, 14:30], s), (sig,))


def test_blur_equals_the_grouped_separable_conv2d():
    """The banded-matmul blur is the zero-padded separable convolution with each image's own kernel."""
    import torch.nn.functional as F

    from heliotwin.surfaces.nuisance import BLUR_RADIUS_PX

    img = torch.rand(3, 40, 33, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    sig = torch.tensor([0.0, 1.3, 4.0], dtype=torch.float64)
    r = BLUR_RADIUS_PX
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x[None, :] / sig.clamp_min(0.05)[:, None]) ** 2)
    g = g / g.sum(-1, keepdim=True)
    ref = F.conv2d(F.conv2d(img[None], g[:, None, :, None], padding=(r, 0), groups=3), g[:, None, None, :],
                   padding=(0, r), groups=3)[0]
    assert torch.allclose(gaussian_blur(img, sig), ref, rtol=0, atol=1e-14)


def test_batched_slope_penalty_and_laplacian_equal_the_serial_ones():
    facets, _, _ = small_scene()
    base = LearnableSurface(facets, (5, 5), (2, 2))
    d = torch.randn(3, 4, 5, 5, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * 1e-3
    surf = learnable_surfaces(facets, base.base, d, (2, 2))
    ref = normal_heights(facets, base.surfaces().control_points, (2, 2), (16, 16))[1]
    w = torch.tensor([1e-3, 0.0, 1e-1], dtype=torch.float64)
    got = slope_penalties(surf, ref, w)
    for k in range(3):
        one = learnable_surfaces(facets, base.base, d[k:k + 1], (2, 2))
        want = slope_penalty(one, ref, facets, float(w[k])) if w[k] else torch.zeros((), dtype=torch.float64)
        assert torch.allclose(got[k], want, rtol=1e-12, atol=0)
        assert torch.allclose(losses.laplacian_per_row(d / 1e-3)[k], losses.laplacian(d[k:k + 1] / 1e-3), rtol=1e-12)


def test_batched_fits_equal_the_serial_fits():
    """The leave-one-out fits as one batch (fit_surfaces) take the serial fits' steps: same held-out curves, blurs
    and surfaces, up to float rounding (the objective is a sum of independent problems; Adam is elementwise)."""
    facets, obs, sun, truth = dome_scene(samples=(10, 10))
    s = SurfaceSettings(control_points=(4, 4), degree=(2, 2), samples=(8, 8), resolution=32, size_m=4.0, steps=20,
                        lr=0.3, eval_every=5)
    cam = estimate_camera(obs.images.to(torch.float32))
    problems = [FitProblem(obs.subset(keep), cam.subset(keep), torch.tensor([1.0, 2.0]), w,
                           (obs.subset([k]), cam.subset([k])))
                for w in (1e-3, 1e-1) for k in range(3) for keep in ([i for i in range(3) if i != k],)]
    batched = fit_surfaces(facets, problems, sun, s)
    for p, b in zip(problems, batched):
        serial = fit_surface(facets, p.obs, sun, s, camera=p.camera, sigma0=p.sigma0, slope_weight=p.slope_weight,
                             heldout=p.heldout)
        assert [st for st, _ in b.curve] == [st for st, _ in serial.curve] == [5, 10, 15, 20]
        assert max(abs(x - y) for (_, x), (_, y) in zip(b.curve, serial.curve)) < 1e-5
        assert torch.allclose(b.sigma, serial.sigma, rtol=1e-5, atol=0)
        ds, db = serial.model.displacement.detach(), b.model.displacement.detach()
        assert float((db - ds).abs().max()) < 1e-5 * float(ds.abs().max())
        assert b.evaluations == serial.evaluations == 20


def test_minibatches_cycle_through_each_fits_images_and_are_seeded():
    rows = minibatch_rows([5, 2, 3], 2, steps=10, seed=4)
    assert rows.shape == (10, 2 + 2 + 2)
    first = rows[:, :2].reshape(-1)  # the 5-image fit: one random order after the other, in chunks of two
    for k in range(0, 20, 5):
        assert sorted(first[k:k + 5].tolist()) == [0, 1, 2, 3, 4]
    assert (rows[:, 2:4].sort(1).values == torch.tensor([5, 6])).all()  # two images: both, every step
    third = rows[:, 4:].reshape(-1)
    for k in range(0, 18, 3):
        assert sorted(third[k:k + 3].tolist()) == [7, 8, 9]
    assert torch.equal(rows, minibatch_rows([5, 2, 3], 2, steps=10, seed=4))
    assert not torch.equal(rows, minibatch_rows([5, 2, 3], 2, steps=10, seed=5))
    assert minibatch_rows([2, 1], 2, steps=10) is None and minibatch_rows([5], None, steps=10) is None


def test_the_optics_choice_scores_on_spread_images_and_finds_every_images_blur():
    assert spread_images(10, 12) is None and spread_images(50, None) is None
    pick = spread_images(40, 12)
    assert len(pick) == 12 and pick[0] == 0 and pick[-1] == 39 and pick == sorted(set(pick))
    facets, obs, sun, _ = dome_scene(samples=(8, 8), n=4)
    s = SurfaceSettings(control_points=(4, 4), degree=(2, 2), samples=(8, 8), resolution=32, size_m=4.0,
                        focus_grid=(None, 1.0, 4.0), slope_grid=(0.5e-3, 2e-3, 4e-3))
    cam = estimate_camera(obs.images.to(torch.float32))
    assert choose_optics(facets, obs, sun, cam, dataclasses.replace(s, optics_images=4))["scores"] == \
        choose_optics(facets, obs, sun, cam, s)["scores"]  # no more images than the bound: unchanged
    bounded = choose_optics(facets, obs, sun, cam, dataclasses.replace(s, optics_images=3))
    on = spread_images(4, 3)
    assert on == [0, 2, 3] and bounded["scored_on"]["records"] == [obs.ids[i] for i in on]
    sub = choose_optics(facets, obs.subset(on), sun, cam.subset(on), s)
    assert [r["mean_l1"] for r in bounded["scores"]] == [r["mean_l1"] for r in sub["scores"]]
    # the chosen ideal's best blur for every image (4), as the unbounded choice finds it for that candidate
    full = choose_optics(facets, obs, sun, cam, dataclasses.replace(
        s, focus_grid=(bounded["chosen"]["focus_multiple"],), slope_grid=(bounded["chosen"]["slope_error_rad"],)))
    assert len(bounded["chosen"]["blur_px"]) == 4 and bounded["chosen"]["blur_px"] == full["chosen"]["blur_px"]


def test_cross_validation_folds_hold_every_image_out_once():
    assert cv_folds(7, 3) == [[0, 3, 6], [1, 4], [2, 5]]
    assert cv_folds(3, 3) == cv_folds(3, None) == cv_folds(3, 8) == [[0], [1], [2]]  # leave one out


def test_batched_minibatch_fits_with_held_out_folds_equal_the_serial_fits():
    """Mini-batches (one image per step) and folds of two held-out images: the batched fits still take the serial
    fits' steps (the same seeded batches), and each held-out image's evaluation is its own."""
    facets, obs, sun, truth = dome_scene(samples=(10, 10))
    s = SurfaceSettings(control_points=(4, 4), degree=(2, 2), samples=(8, 8), resolution=32, size_m=4.0, steps=12,
                        lr=0.3, eval_every=4, batch_images=1)
    cam = estimate_camera(obs.images.to(torch.float32))
    split = [([0, 1], [2]), ([2], [0, 1])]
    problems = [FitProblem(obs.subset(keep), cam.subset(keep), torch.ones(len(keep)), w,
                           (obs.subset(held), cam.subset(held))) for w in (1e-3, 1e-1) for keep, held in split]
    batched = fit_surfaces(facets, problems, sun, s)
    for p, b in zip(problems, batched):
        serial = fit_surface(facets, p.obs, sun, s, camera=p.camera, sigma0=p.sigma0, slope_weight=p.slope_weight,
                             heldout=p.heldout)
        assert [st for st, _ in b.curve] == [st for st, _ in serial.curve] == [4, 8, 12]
        assert max(abs(x - y) for (_, x), (_, y) in zip(b.curve, serial.curve)) < 1e-5
        ds, db = serial.model.displacement.detach(), b.model.displacement.detach()
        assert float((db - ds).abs().max()) < 1e-5 * float(ds.abs().max())
        for st in (4, 8, 12):
            hb, hs = b.heldout[st], serial.heldout[st]
            assert len(hb["l1"]) == len(p.heldout[0]) and hb["images"].shape == (len(p.heldout[0]), 32, 32)
            assert max(abs(x - y) for x, y in zip(hb["l1"], hs["l1"])) < 1e-5
            assert abs(sum(hb["l1"]) / len(hb["l1"]) - dict(b.curve)[st]) < 1e-12  # the curve is their mean
    # one image per step is not the full batch: the two-image fits learn something else
    full = fit_surface(facets, problems[0].obs, sun, dataclasses.replace(s, batch_images=None),
                       camera=problems[0].camera, sigma0=problems[0].sigma0, slope_weight=1e-3)
    assert float((full.model.displacement - batched[0].model.displacement).detach().abs().max()) > 1e-6


def test_residual_slope_ignores_tilt_and_bowl_but_sees_bumps():
    f, su, sv = 2, 12, 12
    u = torch.linspace(-0.5, 0.5, su, dtype=torch.float64)
    aff = torch.zeros(f, su, sv, 3, dtype=torch.float64)
    aff[..., 0] = 1e-3 + 4e-3 * u[:, None]
    aff[..., 1] = -2e-3 * u[None, :]
    assert high_order(aff).abs().max() < 1e-12
    bump = aff.clone()
    bump[:, 0, :, 0] += 5e-3  # an edge ridge
    assert high_order(bump).norm(dim=-1).max() > 2e-3


def test_a_focused_facet_has_no_edge_ridge_and_the_canting_focal_length_is_recovered():
    f0 = 65.0
    t = torch.tensor([[[-0.8, 0.6, 0.0], [0.8, 0.6, 0.0], [-0.8, -0.6, 0.0], [0.8, -0.6, 0.0]]], dtype=torch.float64)
    tilt_e, tilt_n = t[0, :, 0] / (2 * f0), t[0, :, 1] / (2 * f0)
    ce = torch.stack([0.8 * torch.cos(tilt_e), torch.zeros(4, dtype=torch.float64), 0.8 * torch.sin(tilt_e)], -1)
    cn = torch.stack([torch.zeros(4, dtype=torch.float64), 0.6 * torch.cos(tilt_n), 0.6 * torch.sin(tilt_n)], -1)
    facets = Facets(t, ce[None], cn[None])
    assert canting_focal_length(facets) == pytest.approx(f0, rel=1e-3)
    start = focused_start(facets, f0, (7, 7), (3, 3))
    flat = LearnableSurface(facets).surfaces()
    bowl = LearnableSurface(facets, initial=start).surfaces()
    r = edge_ridge_mrad(bowl, flat, facets)
    # A paraboloid tilts the edge by x / (2 f) = 0.8 / 130 = 6.2 mrad; beyond that low-order shape: nothing.
    assert r["total_edge_max_mrad"] > 5.0 and r["edge_max_mrad"] < 0.5


def test_slope_penalty_is_zero_at_the_start_and_has_a_finite_gradient():
    facets, _, _ = small_scene()
    model = LearnableSurface(facets, (5, 5), (2, 2))
    ref = normal_heights(facets, model.surfaces().control_points.detach(), (2, 2), (6, 6))[1]
    p0 = slope_penalty(model.surfaces(), ref, facets, 1e-2, (6, 6))
    p0.backward()
    assert float(p0.detach()) == pytest.approx(0.0, abs=1e-12)
    assert torch.isfinite(model.displacement_mm.grad).all()
    with torch.no_grad():
        model.displacement_mm[0, 0, 2, 2] += 2.0  # a 2 mm bump in facet 0
    assert float(slope_penalty(model.surfaces(), ref, facets, 1e-2, (6, 6)).detach()) > 0.0


def _small_fit_case():
    facets, obs, _ = small_scene(distance=20.0, n=3)
    truth = LearnableSurface(facets, (4, 4), (2, 2))
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        truth.displacement_mm.copy_(torch.randn(truth.displacement_mm.shape, generator=gen, dtype=torch.float64))
        img, _, _ = predict_images(truth.surfaces(), obs, SunSettings(sunshape="gaussian", sigma=2.5e-3),
                                   samples=(6, 6), resolution=16, size_m=4.0)
    obs.images = camera_truth(img, 0.8, 0.05)
    s = SurfaceSettings(control_points=(4, 4), degree=(2, 2), samples=(6, 6), resolution=16, size_m=4.0,
                        focus_grid=(None,), slope_grid=(1e-3, 2e-3), blur_grid_px=(0.0, 1.0),
                        slope_weight_grid=(1e-2,), steps=4, eval_every=2, blur_modes=("none",))
    return facets, obs, s


class _Stop(Exception):
    pass


def test_an_interrupted_fit_resumes_to_the_uninterrupted_surface(tmp_path):
    """Under a checkpoint every fit (the batch of leave-one-out fits, the final fit) saves its state; a run stopped
    inside the leave-one-out batch and resumed reaches the uninterrupted run's surface and choices exactly."""
    from heliotwin.io.checkpoint import Checkpoint, active

    facets, obs, s = _small_fit_case()
    sun = SunSettings(sunshape="buie", csr=0.05)
    ref, ref_info = fit_generalising(facets, obs, sun, s)

    def stop(event, key, step):
        if event == "step" and key == "fit/0" and step == 3:
            raise _Stop

    path = tmp_path / "run.ckpt"
    with pytest.raises(_Stop), active(Checkpoint(path, "t", every=1, min_interval_s=0.0, hook=stop)):
        fit_generalising(facets, obs, sun, s)
    seen = []
    ck = Checkpoint(path, "t", resume=True, every=1, min_interval_s=0.0,
                    hook=lambda e, k, st: seen.append((k, st)) if e == "step" else None)
    with active(ck):
        model, info = fit_generalising(facets, obs, sun, s)
    assert ("fit/0", 1) not in seen and ("fit/0", 3) not in seen  # restored, not rerun
    assert ("fit/0", 4) in seen and ("fit/1", 1) in seen
    assert torch.equal(model.displacement_mm, ref.displacement_mm)
    assert info["report"]["selection"] == ref_info["report"]["selection"]
    assert info["report"]["acceptance"] == ref_info["report"]["acceptance"]


def test_fit_never_leaves_a_training_image_worse_than_the_ideal():
    facets, obs, s = _small_fit_case()
    model, info = fit_generalising(facets, obs, SunSettings(sunshape="buie", csr=0.05), s)
    assert info["report"]["selection"]["steps"] in (2, 4)  # a cross-validated step count
    kw = dict(sun=info["optics"], camera=info["camera"], sigma=info["sigma"], s=info["settings"])
    learned = evaluate_with_camera(model.surfaces(), obs, **kw)["l1"]
    ideal = evaluate_with_camera(info["ideal"], obs, **kw)["l1"]
    assert all(a <= b + 1e-6 for a, b in zip(learned, ideal))
    assert info["report"]["acceptance"]["alpha"] in ALPHAS


@pytest.mark.slow
def test_aa39_generalising_meets_the_issue_figures(paint_dir):
    """Real AA39 (3 earliest images train, 7 test): no training image worse than the ideal, median test L1
    below the retired legacy learner's 0.146, most test images improved, no residual edge ridge above 5 mrad
    (~4 min)."""
    from heliotwin.workflows.reconstruct import ReconstructionSettings, reconstruct

    _, rep, _ = reconstruct(None, paint_dir, "AA39", ReconstructionSettings(train_first=3, device="cpu"),
                            progress=False)
    assert rep["train_worse_than_ideal"] == 0
    assert rep["median_l1_learned"] < 0.146 and rep["median_l1_learned_raw"] < 0.146
    assert rep["test_improved_wilson95"][0] > 0.5
    assert rep["edge_ridge"]["edge_max_mrad"] < 5.0


def _reconstruct_generalising(capsys, paint_dir, tmp_path, *extra):
    from helpers.cli import run_cli

    return run_cli(capsys, "reconstruct", "--paint", paint_dir, "--heliostat", "AA39",
                   "--steps", "4", "--control-points", "4x4", "--degree", "2", "--slope-error", "2", "--quiet",
                   "--json", tmp_path / "r.json", *extra)


def test_cli_generalising_on_a_scenario_stores_an_accepted_surface(paint_dir, tmp_path, capsys):
    """``reconstruct --scenario S -o`` on real AA39 with a 4-step budget (~8 s): no
    training image worse than the ideal, the choices and per-image rows reported, and the learned surface
    (the accepted one) stored under /learned/surfaces/AA39 with the method's provenance."""
    import json

    from helpers.cli import run_cli

    from heliotwin.io.scenario import load_scenario
    from heliotwin.surfaces.state import learned_surface

    code, _, err = run_cli(capsys, "scenario", "from-paint", paint_dir, "--heliostats", "AA39", "-o", tmp_path / "a.h5",
                           "--quiet")
    assert code == 0, err
    code, _, err = _reconstruct_generalising(capsys, paint_dir, tmp_path, "--scenario", tmp_path / "a.h5",
                                             "-o", tmp_path / "b.h5")
    assert code == 0, err
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["plant"] == "scenario"
    # the current surface: every one of the 10 centred images trains; the test rows are their cross-validation
    assert len(rep["train"]) == 10 and len(rep["test"]) == 10 and rep["test_is"] == "cross-validation"
    assert rep["split"]["current"] and rep["selection"]["folds"] == 3
    assert rep["train_worse_than_ideal"] == 0
    assert all(r["l1_learned"] <= r["l1_ideal"] + 1e-6 for r in rep["train"])
    for key in ("test_improved_wilson95", "edge_ridge", "dropped", "acceptance", "choices", "selection", "optics"):
        assert key in rep, key
    assert rep["choices"]["steps"] in (2, 4) and rep["choices"]["slope_error_rad"] == pytest.approx(2e-3)
    lo, hi = rep["test_improved_wilson95"]
    assert 0.0 <= lo <= rep["test_improved"] / rep["test_images"] + 1e-12 and hi <= 1.0
    for path in rep["plots"].values():
        assert (tmp_path / path.rsplit("/", 1)[-1]).stat().st_size > 0
    sc = load_scenario(tmp_path / "b.h5")
    assert sc.provenance[-1]["step"] == "reconstruct" and list(sc.learned["surfaces"]) == ["AA39"]
    item = learned_surface(sc, "AA39")
    assert item["settings"]["chosen"] == rep["choices"]
    assert item["optics"].slope_error == pytest.approx(2e-3) and item["train_records"] == [
        int(r["record"]) for r in rep["train"]]
    cp = item["surfaces"].control_points
    assert cp.shape[2:4] == (4, 4) and torch.isfinite(cp).all()
    if rep["acceptance"]["alpha"] == 0.0 and rep["choices"]["focal_length_m"] is None:
        # Nothing accepted: what is stored is the flat canted ideal itself.
        assert torch.allclose(cp, item["ideal"].control_points, atol=1e-9)


@pytest.mark.parametrize("flags, needle", [(["--loss", "kl"], "--loss"),
                                           (["--integrator", "mc"], "--integrator"),
                                           (["--background", "0.1"], "--background"),
                                           (["--start-from-deflectometry"], "--start-from-deflectometry"),
                                           (["--method", "legacy"], "--method legacy")])
def test_cli_refuses_the_retired_learners_flags_in_one_line(tmp_path, capsys, flags, needle):
    """The retired legacy learner's flags: one line saying what replaces them, before any file is read."""
    from helpers.cli import assert_one_line_error

    code, _, err = _reconstruct_generalising(capsys, tmp_path / "missing", tmp_path, *flags)
    assert_one_line_error(code, err, needle, "retired legacy learner")
    assert code == 2 and not (tmp_path / "r.json").exists()


class _Interrupt(KeyboardInterrupt):
    pass


@pytest.mark.slow  # three real AA39 runs (~25 s)
def test_cli_generalising_interrupted_resumes_to_the_same_report(paint_dir, tmp_path, capsys, monkeypatch):
    """``reconstruct --method generalising`` stopped (Ctrl-C) in its second leave-one-out fit: exit 130 with
    the checkpoint kept; ``--resume`` with other settings is one line; ``--resume`` finishes with the
    uninterrupted run's rows and choices and removes the checkpoint."""
    import json

    from helpers.cli import assert_one_line_error

    from heliotwin.io import checkpoint as ckmod

    def run(out, *extra):
        return _reconstruct_generalising(capsys, paint_dir, tmp_path, "--checkpoint-interval", "0", "--json", out,
                                         *extra)

    ref = tmp_path / "ref.json"
    code, _, err = run(ref)
    assert code == 0, err

    def hook(event, key, step):
        if event == "step" and key == "fit/1" and step == 2:
            raise _Interrupt

    out = tmp_path / "run.json"
    real_init = ckmod.Checkpoint.__init__
    monkeypatch.setattr(ckmod.Checkpoint, "__init__", lambda self, *a, **kw: real_init(self, *a, **dict(kw, hook=hook)))
    code, _, err = run(out)
    monkeypatch.undo()
    assert code == 130 and "--resume" in err.splitlines()[-1]
    assert not out.exists() and (tmp_path / "run.json.ckpt").exists()
    code, _, err = run(out, "--control-points", "5x5", "--resume")
    assert_one_line_error(code, err, "other settings")
    code, _, err = run(out, "--resume")
    assert code == 0, err
    assert not (tmp_path / "run.json.ckpt").exists()
    a, b = json.loads(out.read_text()), json.loads(ref.read_text())
    assert a["train"] == b["train"] and a["test"] == b["test"] and a["choices"] == b["choices"]


def test_a_reconstruction_checkpoint_of_the_serial_leave_one_out_layout_is_not_resumed(tmp_path, monkeypatch):
    # The leave-one-out fits of a blur mode share one checkpoint key since they run batched; a checkpoint of the
    # serial layout holds nine keys per mode, so its tag must differ (resume refuses it instead of misreading it).
    from heliotwin.workflows import reconstruct as rc

    paint = tmp_path / "paint"
    paint.mkdir()
    now = rc.reconstruction_checkpoint(tmp_path / "a.ckpt", paint, "AA39", rc.ReconstructionSettings(device="cpu"))
    monkeypatch.setattr(rc, "CHECKPOINT_LAYOUT", 1)
    old = rc.reconstruction_checkpoint(tmp_path / "b.ckpt", paint, "AA39", rc.ReconstructionSettings(device="cpu"))
    assert now.tag != old.tag
