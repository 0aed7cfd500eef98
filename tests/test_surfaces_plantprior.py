"""Plant surface prior: low-order facet shape, the prior over heliostats, its penalty, storage, no leakage,
and the outcome that matters: a 1-image fit pulled toward the truth."""
from __future__ import annotations

import pytest
import torch
from helpers.surfaces import small_scene

from heliotwin.errors import HeliotwinError, InputFileError
from heliotwin.field.demo import demo_plant
from heliotwin.field.plant import SunSettings
from heliotwin.io.scenario import load_scenario, save_scenario, write_scenario
from heliotwin.surfaces.generalise import SurfaceSettings, fit_generalising, focused_start
from heliotwin.surfaces.imaging import predict_images
from heliotwin.surfaces.learning import LearnableSurface, learnable_surfaces
from heliotwin.surfaces.mismatch import camera_truth
from heliotwin.surfaces.plantprior import (
    FLOOR_RAD,
    KEY,
    NAMES,
    SurfacePrior,
    load_surface_prior,
    low_order_coefficients,
    low_order_start,
    prior_from_scenarios,
    prior_penalty,
    surface_prior,
)
from heliotwin.surfaces.state import with_learned_surface


def _coef(seed, scale=1e-3, f=4):
    return scale * torch.randn(f, len(NAMES), generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_coefficients_read_a_paraboloid_as_focus_and_round_trip_a_low_order_shape():
    facets, _, _ = small_scene()
    f0 = 50.0
    c = low_order_coefficients(facets, focused_start(facets, f0, (5, 5), (3, 3)), (3, 3))
    half = (0.39 * 0.29) ** 0.5  # the facet's half size L [m]: focus coefficient = slope at L = L / (2 f)
    assert torch.allclose(c[:, 2], torch.full((4,), half / (2 * f0), dtype=torch.float64), rtol=1e-9)
    assert c[:, [0, 1, 3, 4]].abs().max() < 1e-15
    want = _coef(0)
    start = low_order_start(facets, want, (5, 5), (2, 2))  # degree 2 holds every basis mode exactly
    assert torch.allclose(low_order_coefficients(facets, start, (2, 2)), want, atol=1e-12)
    # A facet piston is not a shape: the coefficients ignore it.
    model = LearnableSurface(facets, (5, 5), (2, 2), initial=start)
    with torch.no_grad():
        model.displacement_mm[0, 1] += 3.0
    assert torch.allclose(low_order_coefficients(facets, model.surfaces().control_points, (2, 2)), want, atol=1e-12)


def test_prior_is_floored_shrunk_positive_definite_and_needs_two_sources():
    same = torch.stack([_coef(1)] * 3)  # three identical heliostats: no spread at all
    p = surface_prior(same, ["a", "b", "c"])
    assert torch.allclose(p.sigma, torch.full_like(p.sigma, FLOOR_RAD))
    torch.linalg.cholesky(p.covariance)
    two = surface_prior(torch.stack([_coef(1), _coef(2)]), ["a", "b"])  # rank-1 sample covariance, shrunk
    torch.linalg.cholesky(two.covariance)
    assert torch.allclose(two.mean, 0.5 * (_coef(1) + _coef(2)))
    assert two.mahalanobis2(two.mean) == pytest.approx(0.0, abs=1e-20)
    with pytest.raises(HeliotwinError, match=">= 2 source heliostats"):
        surface_prior(_coef(1)[None], ["a"])


def test_prior_penalty_gradcheck_float64():
    facets, _, _ = small_scene()
    prior = surface_prior(torch.stack([_coef(3), _coef(4), _coef(5)]), ["a", "b", "c"])
    model = LearnableSurface(facets, (4, 4), (2, 2))
    d0 = (0.3 * torch.randn(model.displacement_mm.shape, generator=torch.Generator().manual_seed(0),
                            dtype=torch.float64)).requires_grad_(True)

    def pen(d):
        surf = learnable_surfaces(facets, model.base, d * 1e-3, (2, 2))
        return prior_penalty(prior, surf, facets, samples=(6, 6))

    assert torch.autograd.gradcheck(pen, (d0,))
    assert float(pen(d0).detach()) > 0.0


def _scenario_with_learned(tmp_path, name, heliostats, seed, plant=None):
    """A demo-plant scenario with learned surfaces (random low-order shapes) for ``heliostats`` (row indices)."""
    plant = plant or demo_plant(num_heliostats=6)
    path, previous = tmp_path / name, None
    for i, h in enumerate(heliostats):
        fac = plant.field.facets
        facets = type(fac)(*(getattr(fac, a)[h:h + 1] for a in ("translation", "canting_e", "canting_n")))
        model = LearnableSurface(facets, (4, 4), (2, 2), initial=low_order_start(facets, _coef(seed + i), (4, 4),
                                                                                   (2, 2)))
        write_scenario(with_learned_surface(previous, previous.plant if previous else plant, plant.field.ids[h],
                                            model.surfaces(), model.displacement.detach(), SunSettings()), path)
        previous = load_scenario(path)
    return path, plant


def test_prior_from_scenarios_stores_round_trips_and_refuses_leakage(tmp_path):
    a, plant = _scenario_with_learned(tmp_path, "a.h5", [0, 1], seed=10)
    b, _ = _scenario_with_learned(tmp_path, "b.h5", [2], seed=20, plant=plant)
    prior = prior_from_scenarios([a, b])
    ids = plant.field.ids
    assert sorted(prior.heliostats) == sorted(ids[:3])
    assert torch.allclose(prior.mean, (_coef(10) + _coef(11) + _coef(20)) / 3, atol=1e-9)
    with pytest.raises(HeliotwinError, match="no leakage"):
        prior_from_scenarios([a, b], exclude=[ids[1]])
    with pytest.raises(HeliotwinError, match="needs >= 2"):
        prior_from_scenarios([b])
    with pytest.raises(HeliotwinError, match="no such scenario"):
        prior_from_scenarios([tmp_path / "missing.h5"])
    # Stored and read back bit for bit; a stored prior is refused for one of its sources.
    save_scenario(plant, tmp_path / "p.h5", learned={KEY: prior.state()})
    back = load_surface_prior([tmp_path / "p.h5"], heliostat_id=ids[4])
    assert torch.equal(back.mean, prior.mean) and torch.equal(back.covariance, prior.covariance)
    assert back.heliostats == prior.heliostats and back.settings == prior.settings
    with pytest.raises(HeliotwinError, match="reconstructed"):
        load_surface_prior([tmp_path / "p.h5"], heliostat_id=ids[0])
    bad = prior.state()
    bad["covariance"] = -bad["covariance"]
    with pytest.raises(InputFileError, match="positive definite"):
        SurfacePrior.from_state(bad, "x.h5")


def _truth_and_images(facets, obs, coef, seed):
    """Truth = low-order ``coef`` + a small random residual; mismatch images (Gaussian sun, camera)."""
    truth = LearnableSurface(facets, (4, 4), (2, 2), initial=low_order_start(facets, coef, (4, 4), (2, 2)))
    with torch.no_grad():
        truth.displacement_mm.add_(0.05 * torch.randn(truth.displacement_mm.shape, dtype=torch.float64,
                                                      generator=torch.Generator().manual_seed(seed)))
        img, _, _ = predict_images(truth.surfaces(), obs, SunSettings(sunshape="gaussian", sigma=2.5e-3),
                                   samples=(8, 8), resolution=24, size_m=4.0)
    return truth.surfaces(), camera_truth(img, 0.8, 0.05)


def test_the_prior_pulls_a_one_image_fit_toward_the_truth():
    """Sources share a plant pattern (canting errors + focus); a new heliostat of the same plant with one image:
    with the prior (learned from the sources' shapes, not the new one's) its low-order shape ends closer to
    the truth than without."""
    facets, obs, _ = small_scene(distance=20.0, n=1)
    pattern = 2.0 * _coef(100)
    pattern[:, 0:2] -= pattern[:, 0:2].mean(0)  # a common tilt is invisible in centred windows
    sources = torch.stack([pattern + _coef(200 + i, 0.2e-3) for i in range(4)])
    prior = surface_prior(sources, [f"S{i}" for i in range(4)])
    coef = pattern + _coef(300, 0.2e-3)
    truth, obs.images = _truth_and_images(facets, obs, coef, 1)
    s = SurfaceSettings(control_points=(4, 4), degree=(2, 2), samples=(8, 8), resolution=24, size_m=4.0,
                        focus_grid=(None,), slope_grid=(1e-3,), blur_grid_px=(0.0,), steps=30, eval_every=10,
                        blur_modes=("none",))
    sun = SunSettings(sunshape="buie", csr=0.05)
    errs = {}
    for name, p in (("without", None), ("with", prior)):
        model, info = fit_generalising(facets, obs, sun, s, prior=p)
        c = low_order_coefficients(facets, model.surfaces().control_points.detach(), (2, 2))
        errs[name] = float((c - coef).pow(2).mean().sqrt())
        if p is not None:
            rep = info["report"]["prior"]
            # One image: no held-out evidence, so no penalty; the prior mean is the start the training L1 chose.
            assert rep["weight"] == 0.0 and rep["start_is_prior_mean"] and rep["heliostats"] == prior.heliostats
    assert errs["with"] < 0.5 * errs["without"], errs



def test_the_prior_weight_is_cross_validated_over_folds_and_mini_batches():
    """With a prior the cross-validation's fits run one by one (the serial path): two folds of four images, one
    image per step; every image is held out once, the table spans both prior weights at every checked step,
    and the held-out rows of the choice are the chosen setting's (a fit per fold, the same schedule)."""
    from heliotwin.surfaces.generalise import loo_select
    from heliotwin.surfaces.nuisance import estimate_camera

    facets, obs, _ = small_scene(distance=20.0, n=4)
    sources = torch.stack([_coef(400) + _coef(500 + i, 0.2e-3) for i in range(3)])
    prior = surface_prior(sources, ["S0", "S1", "S2"])
    _, obs.images = _truth_and_images(facets, obs, _coef(600, 2e-3), 2)
    s = SurfaceSettings(control_points=(4, 4), degree=(2, 2), samples=(8, 8), resolution=24, size_m=4.0,
                        steps=4, eval_every=2, blur_lr=0.0, slope_weight_grid=(1e-2,), folds=2, batch_images=1)
    sun = SunSettings(sunshape="buie", csr=0.05, slope_error=1e-3)
    cam = estimate_camera(obs.images.to(torch.float32))
    sel = loo_select(facets, obs, cam, torch.zeros(4), sun, None, s, prior=prior, prior_grid=(0.0, 0.1))
    assert sel["folds"] == 2 and len(sel["heldout_rows"]) == len(sel["heldout_l1"]) == 4
    assert {(r["prior_weight"], r["steps"]) for r in sel["table"]} == {(p, st) for p in (0.0, 0.1) for st in (2, 4)}
    best = next(r for r in sel["table"] if (r["prior_weight"], r["steps"]) == (sel["prior_weight"], sel["steps"]))
    assert best["mean_heldout_l1"] == pytest.approx(sum(sel["heldout_l1"]) / 4, rel=1e-12)
    assert best["mean_heldout_l1"] == min(r["mean_heldout_l1"] for r in sel["table"])
    assert all(r["image"].shape == (24, 24) for r in sel["heldout_rows"])


def test_the_penalty_holds_the_low_order_shape_near_the_prior_mean():
    """One Adam fit (before the acceptance rule) of a heliostat unlike the prior: with the penalty it ends
    much nearer the prior mean, in Mahalanobis distance, than with weight 0 from the same start."""
    from heliotwin.surfaces.fit import fit_surface
    from heliotwin.surfaces.nuisance import estimate_camera

    facets, obs, _ = small_scene(distance=20.0, n=1)
    sources = torch.stack([_coef(400) + _coef(500 + i, 0.2e-3) for i in range(3)])
    prior = surface_prior(sources, ["S0", "S1", "S2"])
    _, obs.images = _truth_and_images(facets, obs, _coef(600, 2e-3), 2)
    s = SurfaceSettings(control_points=(4, 4), degree=(2, 2), samples=(8, 8), resolution=24, size_m=4.0,
                        steps=30, blur_lr=0.0)
    sun = SunSettings(sunshape="buie", csr=0.05, slope_error=1e-3)
    cam = estimate_camera(obs.images.to(torch.float32))
    m2 = {}
    for w in (0.0, 0.1):
        model = fit_surface(facets, obs, sun, s, camera=cam, sigma0=torch.zeros(1), slope_weight=1e-2, prior=prior,
                            prior_weight=w).model
        m2[w] = float(prior_penalty(prior, model.surfaces(), facets).detach())
    assert m2[0.1] < 0.5 * m2[0.0], m2


def _reconstruct(capsys, paint_dir, tmp_path, *extra):
    from helpers.cli import run_cli

    return run_cli(capsys, "reconstruct", "--paint", paint_dir, "--heliostat", "AA39", "--steps", "4",
                   "--control-points", "4x4", "--degree", "2", "--slope-error", "2", "--quiet",
                   "--json", tmp_path / "r.json", *extra)


def test_cli_surface_prior_is_used_reported_and_stored(paint_dir, tmp_path, capsys):
    """``reconstruct --surface-prior-from A.h5,B.h5 -o`` on real AA39 (4-step budget, ~10 s): the report says which
    heliostats the prior came from and the weight the rule chose (the latest 3 images train, a study's split that
    keeps it quick: leave-one-out over a grid with 0; the every-image folds are the test above);
    no training image worse than the ideal; the output scenario stores the prior, which a later run reads
    back from that one file."""
    import json

    from heliotwin.surfaces.state import learned_surface

    a, plant = _scenario_with_learned(tmp_path, "a.h5", [0, 1], seed=10)
    b, _ = _scenario_with_learned(tmp_path, "b.h5", [2], seed=20, plant=plant)
    code, _, err = _reconstruct(capsys, paint_dir, tmp_path, "--surface-prior-from", f"{a},{b}",
                                "--train-latest", "3", "-o", tmp_path / "o.h5")
    assert code == 0, err
    rep = json.loads((tmp_path / "r.json").read_text())
    assert sorted(rep["prior"]["heliostats"]) == sorted(plant.field.ids[:3])
    assert rep["prior"]["weight"] in rep["prior"]["grid"] and 0.0 in rep["prior"]["grid"]
    assert any(r["prior_weight"] == 0.0 for r in rep["selection"]["table"])  # 0 was a candidate of the LOO
    assert rep["choices"]["surface_prior_weight"] == rep["prior"]["weight"]
    assert rep["train_worse_than_ideal"] == 0
    sc = load_scenario(tmp_path / "o.h5")
    stored = SurfacePrior.from_state(sc.learned[KEY])
    assert torch.equal(stored.mean, prior_from_scenarios([a, b]).mean)
    assert stored.heliostats == rep["prior"]["heliostats"]
    assert learned_surface(sc, "AA39")["settings"]["chosen"]["surface_prior_weight"] == rep["prior"]["weight"]
    # The output names the prior's sources: it is a valid one-file prior for another heliostat, not for AA39.
    assert load_surface_prior([tmp_path / "o.h5"], heliostat_id="AA35").heliostats == stored.heliostats


def test_cli_surface_prior_errors_are_one_line(paint_dir, tmp_path, capsys):
    """Missing file, a scenario without learned surfaces, a prior of another facet count, leakage (the prior
    learned from AA39 itself), and the retired legacy method: each one line, no report written."""
    from helpers.cli import assert_one_line_error

    from heliotwin.surfaces.plantprior import surface_prior

    plant = demo_plant(num_heliostats=3)
    save_scenario(plant, tmp_path / "bare.h5")
    two_facets = surface_prior(torch.stack([_coef(1, f=2), _coef(2, f=2)]), ["AA35", "AB38"])
    save_scenario(plant, tmp_path / "f2.h5", learned={KEY: two_facets.state()})
    leaky = surface_prior(torch.stack([_coef(1), _coef(2)]), ["AA39", "AB38"])
    save_scenario(plant, tmp_path / "leak.h5", learned={KEY: leaky.state()})
    cases = [(tmp_path / "missing.h5", ["missing.h5", "no such scenario"]),
             (tmp_path / "bare.h5", ["bare.h5", "no learned surface"]),
             (tmp_path / "f2.h5", ["2 facets", "has 4"]),
             (tmp_path / "leak.h5", ["AA39", "other heliostats"])]
    for path, needles in cases:
        code, _, err = _reconstruct(capsys, paint_dir, tmp_path, "--surface-prior-from", path)
        assert_one_line_error(code, err, *needles)
        assert not (tmp_path / "r.json").exists()
    code, _, err = _reconstruct(capsys, paint_dir, tmp_path, "--method", "legacy", "--surface-prior-from", "x.h5")
    assert_one_line_error(code, err, "--method legacy", "retired", "one learner")
