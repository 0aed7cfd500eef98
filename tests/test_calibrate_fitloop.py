"""The one early-stopping loop, the method registry and the learners' dtype: unit-level, no real data."""
import dataclasses

import pytest
import torch
from helpers.calibrate import TRUE, jueliche_like, simulate, walk_fit

from heliotwin.calibrate import metrics
from heliotwin.calibrate.fitloop import box_and_validity
from heliotwin.calibrate.methods import METHODS, get_method
from heliotwin.calibrate.methods.gradient import fit_gradient
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.errors import HeliotwinError


def test_loop_keeps_each_heliostats_best_validated_state():
    x, log = walk_fit([2.2, 4.9, 1.0], 6, [True, True, False])
    assert log.best[:, 0].tolist() == [2.0, 5.0, 6.0]  # the third has no validation: its final state
    assert log.best_iteration.tolist() == [2, 5, 6]
    assert float(x[0, 0]) == 6.0  # the live state is left alone
    assert log.losses == [3.0, 6.0, 9.0, 12.0, 15.0, 18.0]
    assert log.history[0] == (0, pytest.approx(1000 * 2.2))  # median over heliostats of the start, mrad


def test_loop_checks_every_n_and_after_the_last_step():
    _, log = walk_fit([2.2, 4.9], 7, [True, True], check_every=3)
    assert log.best[:, 0].tolist() == [3.0, 6.0]
    assert [h[0] for h in log.history] == [0, 3, 6, 7]


def test_refit_mode_stops_each_heliostat_at_its_iteration():
    _, log = walk_fit([100.0, 100.0, 100.0], 6, [False, False, False], check_every=3,
                   stop_at=torch.tensor([0, 3, 6]))
    assert log.best[:, 0].tolist() == [0.0, 3.0, 6.0]
    assert log.best_iteration.tolist() == [0, 3, 6]


def test_projection_clamps_and_restores_the_last_valid_state():
    x = torch.tensor([[0.0, 0.0], [0.0, 0.0]], dtype=torch.float64)
    project = box_and_validity(x, torch.tensor([10.0, 1.0], dtype=torch.float64), lambda xx: xx[:, 0] < 2.5)
    for _ in range(4):
        x.add_(torch.tensor([[1.0, 1.0], [0.0, 0.0]], dtype=torch.float64))
        project()
    assert x[0].tolist() == [2.0, 1.0]  # invalid from step 3: back to step 2's state (already clamped)
    x[1, 0] = float("nan")
    project()
    assert x[1].tolist() == [0.0, 0.0]


def test_per_heliostat_mean_is_inf_without_records():
    m = metrics.per_heliostat_mean(torch.tensor([1.0, 3.0, 5.0]), torch.tensor([0, 0, 2]), 3)
    assert m.tolist() == [2.0, float("inf"), 5.0]


def test_registry_is_plain_and_complete():
    from heliotwin.cli.calibrate import METHOD_CHOICES  # the CLI lists them without importing torch

    assert set(METHODS) == set(METHOD_CHOICES)
    for name, fit in METHODS.items():
        assert fit.__module__ == f"heliotwin.calibrate.methods.{name}" and get_method(name) is fit
    with pytest.raises(HeliotwinError, match="known: lm"):
        get_method("nope")


def _records_as(batch, dtype):
    return dataclasses.replace(batch, **{f.name: getattr(batch, f.name).to(dtype)
                                         for f in dataclasses.fields(batch)
                                         if isinstance(getattr(batch, f.name), torch.Tensor)
                                         and getattr(batch, f.name).is_floating_point()})


def test_gradient_fit_follows_the_inputs_dtype():
    nominal = jueliche_like(2)
    delta = torch.tensor([[TRUE[n] for n in STONE8]] * 2, dtype=torch.float64)
    true = apply_deviations(nominal, delta, STONE8)
    train, val = simulate(true, 20, 5), simulate(true, 6, 6)
    n32 = nominal.to(torch.float32)
    d, _ = fit_gradient(n32, _records_as(train, torch.float32), _records_as(val, torch.float32), names=STONE8,
                        prior_sigma={"angle": 0.5, "tilt": 0.1, "increment": 0.05}, iterations=10)
    assert d.dtype == torch.float32
    err = metrics.pointing_error(apply_deviations(nominal, d.double(), STONE8), val)
    assert float(err.mean()) < 1e-3 < float(metrics.pointing_error(nominal, val).mean())
