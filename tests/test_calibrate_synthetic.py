"""Calibration physics on a synthetic heliostat with known deviations (no real data needed)."""
import math

import pytest
import torch

from heliotwin.calibrate import metrics
from heliotwin.calibrate.gradient import fit_gradient
from heliotwin.calibrate.lm import fit_lm
from heliotwin.calibrate.params import STONE8, actuator_margin, apply_deviations, read_deviations
from heliotwin.io.records import RecordTable
from heliotwin.field import kinematics as K
from heliotwin.field.plant import Kinematics
from heliotwin.field.targets import PlanarTarget

TRUE = {"initial_angle_1": -0.011, "initial_angle_2": 0.004, "joint_tilt_1_n": 0.003, "joint_tilt_1_u": -0.02,
        "joint_tilt_2_n": 0.002, "concentrator_tilt_e": 0.009, "increment_1": 0.004, "increment_2": -0.003}


def jueliche_like(h=1):
    """PAINT-typical Jülich heliostat(s) north of the tower (values as in the PAINT properties files)."""
    t = lambda v: torch.tensor(v, dtype=torch.float64).expand(h, *torch.tensor(v).shape).clone()  # noqa: E731
    pos = torch.tensor([[8.0 * i - 10.0, 60.0 + 5 * i, 1.5] for i in range(h)], dtype=torch.float64)
    return Kinematics(position=pos, joint_translation=torch.zeros(h, 2, 3, dtype=torch.float64),
                      concentrator_translation=t([0.0, 0.175, 0.0]), joint_tilt=torch.zeros(h, 2, 3, dtype=torch.float64),
                      concentrator_tilt=torch.zeros(h, 3, dtype=torch.float64), increment=t([154166.6667, 154166.6667]),
                      offset=t([0.33531, 0.34077]), pivot_radius=t([0.33809, 0.3191]), initial_angle=t([0.0135, 0.937]),
                      initial_stroke_length=t([0.0757, 0.077]), clockwise=torch.tensor([[False, True]] * h),
                      linear=torch.tensor([[True, True]] * h), min_steps=t([0.0, 0.0]), max_steps=t([69000.0, 75000.0]),
                      min_angle=t([0.0, 0.0]), max_angle=t([1.0, 1.0]))


TARGET = PlanarTarget.from_center_normal("synthetic_target", [0.0, -3.24, 40.0], [0.0, 1.0, 0.0], 6.0, 6.0)


def simulate(kin_true, n, seed, noise=0.0):
    """Records of every heliostat: sun over a year-like range, aim at the target centre +-1 m."""
    g = torch.Generator().manual_seed(seed)
    h = kin_true.num_heliostats
    az = (torch.rand(h * n, generator=g, dtype=torch.float64) - 0.5) * 2.4
    el = 0.15 + torch.rand(h * n, generator=g, dtype=torch.float64) * 0.9
    hidx = torch.arange(h).repeat_interleave(n)
    from heliotwin.sun import direction_from_paint_angles

    sun = direction_from_paint_angles(az, el)
    jit = (torch.rand(h * n, 2, generator=g, dtype=torch.float64) - 0.5) * 2
    spot = TARGET.to_world(jit)
    steps, ok = K.inverse(kin_true.index(hidx), spot, sun, strict=False)
    assert bool(ok.all())
    if noise:
        # Move the measured spot: a pointing noise of `noise` rad at ~60 m slant range.
        spot = spot + TARGET.to_world(torch.randn(h * n, 2, generator=g, dtype=torch.float64) * noise * 2 * 60) - TARGET.center
    return RecordTable.from_arrays([f"S{i}" for i in range(h)], hidx, az, el, steps, spot, TARGET)


def test_angle_metric_uses_atan2_precision():
    a = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    for ang in (1e-7, 1e-4, 0.5, math.pi - 1e-6):
        b = torch.tensor([math.cos(ang), math.sin(ang), 0.0], dtype=torch.float64)
        assert metrics.angle_between(a, b).item() == pytest.approx(ang, rel=1e-9)


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
