"""Calibration physics on a synthetic heliostat with known deviations (no real data needed)."""
import math

import pytest
import torch
from helpers.calibrate import TRUE, jueliche_like, simulate

from heliotwin.calibrate import metrics
from heliotwin.calibrate.methods.gradient import fit_gradient
from heliotwin.calibrate.methods.lm import fit_lm
from heliotwin.calibrate.params import STONE8, actuator_margin, apply_deviations, read_deviations
from heliotwin.geometry import angle_between


def test_angle_metric_uses_atan2_precision():
    a = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    for ang in (1e-7, 1e-4, 0.5, math.pi - 1e-6):
        b = torch.tensor([math.cos(ang), math.sin(ang), 0.0], dtype=torch.float64)
        assert angle_between(a, b).item() == pytest.approx(ang, rel=1e-9)


def test_true_model_has_zero_error_and_nominal_does_not():
    nominal = jueliche_like(2)
    delta = torch.tensor([[TRUE[n] for n in STONE8]] * 2, dtype=torch.float64)
    true = apply_deviations(nominal, delta, STONE8)
    b = simulate(true, 20, 0)
    assert metrics.pointing_error(true, b).max().item() < 1e-9
    assert metrics.miss_distance(true, b).max().item() < 1e-6
    assert metrics.pointing_error(nominal, b).mean().item() > 5e-3
    assert torch.allclose(read_deviations(true, nominal, STONE8), delta, atol=1e-12)


def test_lm_recovers_known_deviations_batched():
    nominal = jueliche_like(3)
    delta = torch.tensor([[TRUE[n] * (1 + 0.3 * i) for n in STONE8] for i in range(3)], dtype=torch.float64)
    true = apply_deviations(nominal, delta, STONE8)
    train, test = simulate(true, 40, 1), simulate(true, 30, 2)
    fitted, info = fit_lm(nominal, train, prior_sigma={})
    assert torch.allclose(fitted, delta, atol=2e-5), (fitted - delta).abs().max()
    err = metrics.pointing_error(apply_deviations(nominal, fitted, STONE8), test)
    assert err.max().item() < 1e-6


def test_lm_fits_a_large_field_in_independent_chunks(monkeypatch):
    """Above LM_CHUNK heliostats fit_lm solves one problem per chunk (a joint dense problem costs ~H^3): each
    heliostat still gets its own minimum, the one it gets fitted alone, and one without records stays nominal."""
    import heliotwin.calibrate.methods.lm as lm

    monkeypatch.setattr(lm, "LM_CHUNK", 2)
    nominal = jueliche_like(5)
    delta = torch.tensor([[TRUE[n] * (1 + 0.2 * i) for n in STONE8] for i in range(5)], dtype=torch.float64)
    records = simulate(apply_deviations(nominal, delta, STONE8), 30, 5, noise=3e-4)
    train = records.subset(records.heliostat_index != 2)  # heliostat 2 has no record
    fitted, info = fit_lm(nominal, train, solver="scipy")
    assert info["chunks"] == 2 and bool((fitted[2] == 0).all())
    together, _ = fit_lm(nominal, train, solver="batched")  # all at once: each heliostat its own convergence
    assert bool((together[2] == 0).all())
    for h in (0, 4):
        alone, _ = fit_lm(nominal, train.subset(train.heliostat_index == h), solver="scipy")
        assert torch.allclose(fitted[h], alone[h], atol=1e-9), (fitted[h] - alone[h]).abs().max()
        alone, _ = fit_lm(nominal, train.subset(train.heliostat_index == h), solver="batched")
        assert torch.allclose(together[h], alone[h], atol=1e-9), (together[h] - alone[h]).abs().max()
    test = simulate(apply_deviations(nominal, delta, STONE8), 20, 6)
    test = test.subset(test.heliostat_index != 2)
    err = metrics.pointing_error(apply_deviations(nominal, fitted, STONE8), test)
    assert err.mean().item() < 1e-3 < 1e-2 < metrics.pointing_error(nominal, test).mean().item(), err.mean()


def test_prior_helps_with_noise_and_few_records():
    nominal = jueliche_like(4)
    delta = torch.tensor([[TRUE[n] for n in STONE8]] * 4, dtype=torch.float64)
    true = apply_deviations(nominal, delta, STONE8)
    train, test = simulate(true, 10, 3, noise=5e-4), simulate(true, 40, 4)
    fitted, _ = fit_lm(nominal, train)
    err = metrics.pointing_error(apply_deviations(nominal, fitted, STONE8), test).mean().item()
    assert err < 1.5e-3  # 0.5 mrad noise, 10 records: calibrated to ~1 mrad against > 10 mrad nominal
    assert metrics.pointing_error(nominal, test).mean().item() > 1e-2


def test_gradient_recovers_and_respects_actuator_bounds():
    nominal = jueliche_like(2)
    delta = torch.tensor([[TRUE[n] for n in STONE8]] * 2, dtype=torch.float64)
    true = apply_deviations(nominal, delta, STONE8)
    train, val = simulate(true, 30, 5), simulate(true, 8, 6)
    names = STONE8 + ("offset_1", "pivot_radius_2", "initial_stroke_length_1")
    d, info = fit_gradient(nominal, train, val, names=names, prior_sigma={"angle": 0.5, "tilt": 0.1, "increment": 0.05,
                                                                        "actuator_length": 0.002}, iterations=40)
    fitted = apply_deviations(nominal, d, names)
    assert metrics.pointing_error(fitted, val).mean().item() < 5e-5
    assert bool((actuator_margin(fitted) > 0).all())
    assert torch.isfinite(d).all()
