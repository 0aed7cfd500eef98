"""Predictive pointing error (Laplace posterior of the lm fit), its interval, aim's answer and the choice of
settings by leave-heliostats-out cross-validation."""
import math

import pytest
import torch
from helpers.calibrate import TRUE, jueliche_like, scenario_round_trip, simulate

from heliotwin.calibrate.methods.lm import fit_lm_method
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.calibrate.protocol import selection
from heliotwin.calibrate.protocol.pipeline import RunConfig, Split, evaluate, predict_intervals
from heliotwin.calibrate.scenario import aim
from heliotwin.calibrate.uncertainty import predictive

F64 = torch.float64


def test_noise_only_prediction_is_rayleigh():
    """No parameter uncertainty: |e| of an isotropic 2-D Gaussian (sd s) has mean s sqrt(pi/2), median
    s sqrt(2 ln 2) and 90 % quantile s sqrt(-2 ln 0.1) (Rayleigh)."""
    s = 1e-3
    normal = torch.tensor([[0.0, 0.6, 0.8]], dtype=F64)
    pred = predictive(torch.zeros(1, 3, 8, dtype=F64), normal, 1e-20 * torch.eye(8, dtype=F64)[None],
                      torch.tensor([s], dtype=F64), samples=200000)
    assert pred["expected"].item() == pytest.approx(s * math.sqrt(math.pi / 2), rel=0.01)
    assert pred["median"].item() == pytest.approx(s * math.sqrt(2 * math.log(2)), rel=0.01)
    assert pred["lower"].item() == 0.0
    assert pred["upper"].item() == pytest.approx(s * math.sqrt(-2 * math.log(0.1)), rel=0.01)
    # an offset drift adds in quadrature
    wider = predictive(torch.zeros(1, 3, 8, dtype=F64), normal, 1e-20 * torch.eye(8, dtype=F64)[None],
                       torch.tensor([s], dtype=F64), samples=200000, drift=s)
    assert wider["expected"].item() == pytest.approx(math.sqrt(2) * pred["expected"].item(), rel=0.01)


def _run(n_train: int, seed: int):
    kin = jueliche_like(4)
    true = apply_deviations(kin, torch.tensor([[TRUE[n] for n in STONE8]] * 4, dtype=F64), STONE8)
    train, test = simulate(true, n_train, seed, noise=5e-4), simulate(true, 80, seed + 1, noise=5e-4)
    model = fit_lm_method(kin, train, None, bags=0, field_prior=False, fit_focal_spot=None)
    parts = Split(train, train.subset(torch.zeros(len(train), dtype=torch.bool)), test)
    run = predict_intervals(RunConfig(paint="synthetic"), model, parts, evaluate(model, kin, parts))
    return run, kin, model


def test_laplace_interval_covers_when_the_model_is_right():
    """Correct model, Gaussian centroid noise: ~90 % of new records fall in their 90 % interval, and the
    expected error is the mean error; fewer training records give a larger expected error."""
    run, _, _ = _run(12, 3)
    cover = run.intervals["inside"].double().mean().item()
    assert 0.8 <= cover <= 0.97, cover
    mean_err, mean_exp = run.errors["test"][0].mean().item(), run.intervals["expected"].mean().item()
    assert mean_exp == pytest.approx(mean_err, rel=0.25)
    few, _, _ = _run(4, 3)
    assert few.intervals["expected"].mean().item() > 1.1 * mean_exp


def test_aim_returns_expected_error_and_interval(tmp_path):
    _, kin, model = _run(12, 5)
    sc = scenario_round_trip(tmp_path, kin, model)
    ans = aim(sc, "S0", 0.3, 0.7, [0.0, -3.24, 40.0])
    lo, hi = ans["error_interval_90_mrad"]
    assert lo == 0 and 0 < ans["expected_error_mrad"] < hi < 3.0, ans
    # the same heliostat calibrated on 4 records: aim says it is less sure
    _, kin4, model4 = _run(4, 5)
    (tmp_path / "few").mkdir()
    ans4 = aim(scenario_round_trip(tmp_path / "few", kin4, model4), "S0", 0.3, 0.7, [0.0, -3.24, 40.0])
    assert ans4["error_interval_90_mrad"][1] > hi


def test_choose_drift_recovers_the_offset_the_training_records_cannot_show():
    """Records whose errors hold noise s plus an offset tau: the chosen drift is tau (coverage ~0.9)."""
    g = torch.Generator().manual_seed(0)
    n, s, tau = 1000, 5e-4, 1e-3
    err = (torch.randn(n, 2, generator=g, dtype=F64) * math.hypot(s, tau)).norm(dim=-1)
    inputs = [{"jacobian": torch.zeros(n, 3, 8, dtype=F64), "normal": torch.tensor([[0.0, 0.0, 1.0]] * n, dtype=F64),
               "covariance": 1e-20 * torch.eye(8, dtype=F64).expand(n, 8, 8), "noise": torch.full((n,), s, dtype=F64),
               "error": err}]
    drift, cov = selection.choose_drift(inputs, samples=1000)
    assert drift == 1e-3 and abs(cov[drift] - 0.9) < 0.03 and cov[0.0] < 0.7
    assert all(a <= b for a, b in zip(list(cov.values()), list(cov.values())[1:]))  # wider drift, more coverage


def test_selection_folds_and_choice_are_plain_code():
    ids = [f"H{i}" for i in range(11)]
    folds = selection.folds_of(ids, 4, seed=0)
    assert sorted(sum(folds, [])) == sorted(ids) and sorted(len(f) for f in folds) == [2, 3, 3, 3]
    assert selection.folds_of(ids, 4, seed=0) == folds  # seeded
    cands = selection.CANDIDATES[:3]
    scores = {selection.label(c): {"a": 1.0 + i, "b": 2.0 - 0.1 * i} for i, c in enumerate(cands)}
    scores[selection.label(cands[1])] = {"a": 0.5, "b": 0.9}
    assert selection.select(scores, cands) is cands[1]
    cfg = selection.config_of(RunConfig(paint="p"), cands[1], archive="ARCHIVE")
    assert cfg.prior == "plant" and cfg.prior_from == "ARCHIVE" and cfg.prior_options["shrink"] == 0.2
    assert selection.config_of(RunConfig(paint="p"), cands[0]).prior_from is None
