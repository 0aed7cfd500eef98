"""The batched Levenberg-Marquardt (all heliostats at once) against scipy's least_squares per chunk of
heliostats, on a synthetic plant with known deviations."""
from dataclasses import replace

import pytest
import torch
from helpers.calibrate import synthetic_plant

from heliotwin.calibrate import priors
from heliotwin.calibrate.methods import batched
from heliotwin.calibrate.methods.lm import fit_lm, fit_lm_method
from heliotwin.calibrate.params import STONE8

NATURAL = 1e-3  # one natural unit of every Stone/Jülich parameter (mrad, 0.1 %)


@pytest.fixture(scope="module")
def plant():
    return synthetic_plant(6, 25, seed=3)


@pytest.mark.parametrize("case", ["loose", "robust", "plant_prior", "recency", "no_prior"])
def test_batched_solve_reaches_scipys_minimum(plant, case):
    ds, true = plant
    kin, records = ds.plant.field.kinematics, ds.records
    pp = priors.plant_prior(true, STONE8, [f"h{i}" for i in range(len(true))])
    options = {"loose": dict(prior_sigma=priors.LOOSE_SIGMA),
               "robust": dict(prior_sigma=priors.STONE8_SIGMA, loss="soft_l1", f_scale=1e-3),
               "plant_prior": dict(prior_mean=pp.mean.expand(len(true), 8).clone(), prior_whitening=pp.whitening(),
                                   loss="soft_l1", f_scale=1e-3),
               "recency": dict(prior_sigma=priors.STONE8_SIGMA, half_life_days=60.0),
               "no_prior": dict(prior_sigma={})}[case]
    ref, ref_info = fit_lm(kin, records, solver="scipy", **options)
    got, info = fit_lm(kin, records, solver="batched", **options)
    assert info["status"] == 1 and info["method"] == "batched"
    assert info["cost"] == pytest.approx(ref_info["cost"], rel=1e-7)
    # the same minimum: parameters agree far below what a record can resolve (1e-4 mrad)
    assert float((got - ref).abs().max()) < 1e-4 * NATURAL
    # and it is the synthetic truth to within the noise (1 mrad per record)
    assert float((got - true)[:, :2].abs().median()) < 3e-3


def test_bagged_lm_method_equals_the_scipy_solver(plant, monkeypatch):
    """The whole ``lm`` method (field prior, robust loss, bags starting from the full-data fit) gives the
    deviations of the per-chunk scipy solver."""
    from heliotwin.calibrate.methods import lm

    ds, _ = plant
    kin, records = ds.plant.field.kinematics, ds.records
    cut = records.time < records.time.median()
    train, val = records.subset(cut), None
    got = fit_lm_method(kin, train, val, settings=None, bags=2).delta
    monkeypatch.setattr(lm, "SOLVER", "scipy")
    ref = fit_lm_method(kin, train, val, settings=None, bags=2).delta
    assert float((got - ref).abs().max()) < 1e-4 * NATURAL


def test_solver_converges_per_heliostat_and_follows_dtype():
    """Independent quadratic problems of different curvature: each converges to its own minimum."""
    g = torch.Generator().manual_seed(0)
    h, p, r = 5, 3, 40
    a = torch.randn(h * r, 3, p, generator=g, dtype=torch.float64) * torch.linspace(0.1, 10, h).repeat_interleave(
        r)[:, None, None]
    b = torch.randn(h * r, 3, generator=g, dtype=torch.float64)
    owner = torch.arange(h).repeat_interleave(r)

    def evaluate(x_rows, rows):
        aa, bb = (a, b) if rows is None else (a[rows], b[rows])
        return torch.einsum("rcp,rp->rc", aa, x_rows) - bb, aa

    x, info = batched.solve(evaluate, torch.zeros(h, p, dtype=torch.float64), owner)
    for k in range(h):
        m = owner == k
        exact = torch.linalg.lstsq(a[m].reshape(-1, p), b[m].reshape(-1, 1)).solution.flatten()
        assert torch.allclose(x[k], exact, atol=1e-9)
    assert info["converged"] == h and x.dtype == torch.float64


@pytest.mark.slow  # spawns two torch processes (~40 s on 2 busy cores)
def test_two_processes_give_the_one_process_calibration():
    """``nproc=2``: each rank fits its shard of the heliostats (gloo), every rank runs the rest; the deviations,
    errors and intervals are those of one process."""
    from heliotwin.workflows.calibrate import CalibrationSettings, calibrate

    ds, _ = synthetic_plant(7, 60, seed=5)
    settings = CalibrationSettings(min_records=50, train=30, test=20)
    one = calibrate(None, ds, settings)
    two = calibrate(None, ds, replace(settings, nproc=2))
    assert torch.allclose(one.model.delta, two.model.delta, atol=1e-12, rtol=0)
    o1, o2 = one.report["overall"], two.report["overall"]
    assert o1["median_of_mean_test_mrad"] == pytest.approx(o2["median_of_mean_test_mrad"], rel=1e-9)
    assert o1["interval_90_coverage"] == o2["interval_90_coverage"]
