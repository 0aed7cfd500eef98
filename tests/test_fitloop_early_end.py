"""The fit loop's early end, optimiser swap and fresh-optimiser steps (what the surface fits use): unit-level."""
import pytest
import torch
from helpers.calibrate import walk_fit

from heliotwin.calibrate.fitloop import EarlyEnd, Swap, early_stopping_fit, tensor_state
from heliotwin.io.checkpoint import Checkpoint, active, make_tag


def test_without_rules_the_loop_is_the_plain_loop():
    x0, plain = walk_fit([2.2, 4.9], 7, check_every=3)
    x1, off = walk_fit([2.2, 4.9], 7, check_every=3, early_end=EarlyEnd())
    assert torch.equal(x0, x1) and torch.equal(plain.best, off.best)
    assert plain.history == off.history and plain.losses == off.losses and plain.ended_at == off.ended_at == 7


def test_patience_ends_after_checks_without_a_better_validation_error():
    # Best at x = 3 (target 3.1); checks at 4 and 5 are worse: two bad checks end the loop at 5, best kept.
    x, log = walk_fit([3.1], 20, early_end=EarlyEnd(patience=2))
    assert log.ended_at == 5 and float(x[0, 0]) == 5.0
    assert log.best[:, 0].tolist() == [3.0] and log.best_iteration.tolist() == [3]
    # min_delta: gains of 1 and then 2 below the start do not count as better (2.5 needed): ended at the second.
    _, log = walk_fit([30.0], 20, early_end=EarlyEnd(patience=2, min_delta=2.5))
    assert log.ended_at == 2 and log.best_iteration.tolist() == [0]


def test_tolerance_ends_when_the_training_loss_stops_falling():
    x = torch.zeros(1, 1, dtype=torch.float64)
    values = [10.0, 5.0, 4.0, 3.99, 1.0, 0.5]  # the relative gain 4.0 -> 3.99 is below 1 %

    def step():
        x.add_(1.0)
        return values[int(x[0, 0]) - 1]

    log = early_stopping_fit(step, lambda: torch.full((1,), float("inf")), tensor_state(x), 6,
                             validated=torch.zeros(1, dtype=torch.bool), early_end=EarlyEnd(tolerance=1e-2))
    assert log.ended_at == 4 and log.losses == values[:4]
    assert log.best_iteration.tolist() == [4] and float(log.best[0, 0]) == 4.0  # without validation: the last state
    # Steps before ``after`` are not counted (a continuation phase may stall without ending the fit).
    x.zero_()
    log = early_stopping_fit(step, lambda: torch.full((1,), float("inf")), tensor_state(x), 6,
                             validated=torch.zeros(1, dtype=torch.bool), early_end=EarlyEnd(tolerance=1e-2, after=5))
    assert log.ended_at == 6


def test_a_callers_condition_ends_the_loop():
    calls = []
    x, log = walk_fit([100.0], 20, early_end=EarlyEnd(done=lambda: calls.append(1) or len(calls) >= 7))
    assert log.ended_at == 7 and float(x[0, 0]) == 7.0


def _swap_fit():
    """Minimise (w - 3)^2 with Adam for 5 steps, then L-BFGS from where Adam ended."""
    w = torch.zeros(1, 1, dtype=torch.float64, requires_grad=True)
    adam = torch.optim.Adam([w], lr=0.1)
    lbfgs = {}

    def loss():
        return (w - 3.0).pow(2).sum()

    def adam_step():
        adam.zero_grad()
        value = loss()
        value.backward()
        adam.step()
        return value

    def lbfgs_step():
        opt = lbfgs.setdefault("opt", torch.optim.LBFGS([w], lr=1.0, max_iter=2, line_search_fn="strong_wolfe"))

        def closure():
            opt.zero_grad()
            value = loss()
            value.backward()
            return value
        return opt.step(closure)

    log = early_stopping_fit(adam_step, lambda: torch.full((1,), float("inf")), tensor_state(w.data), 8,
                             validated=torch.zeros(1, dtype=torch.bool), swap=Swap(5, lbfgs_step))
    return w, log, adam, lbfgs


def test_swap_changes_the_optimiser_mid_fit():
    w, log, adam, lbfgs = _swap_fit()
    assert adam.state[adam.param_groups[0]["params"][0]]["step"] == 5  # Adam stepped 5 times, then L-BFGS
    assert "opt" in lbfgs and abs(float(w.detach()) - 3.0) < 1e-6 and len(log.losses) == 8
    assert log.losses[4] > 0.1 > log.losses[-1]  # Adam (lr 0.1) is still far from 3 after 5 steps


def test_swap_resumed_after_the_swap_equals_the_uninterrupted_fit(tmp_path):
    ref, _, _, _ = _swap_fit()

    def stop(event, key, step):
        if event == "step" and step == 7:
            raise KeyboardInterrupt

    path = tmp_path / "run.ckpt"
    with pytest.raises(KeyboardInterrupt), active(Checkpoint(path, make_tag({}), hook=stop, every=1, min_interval_s=0)):
        _swap_fit()
    with active(Checkpoint(path, make_tag({}), resume=True, every=1, min_interval_s=0)):
        out, log, adam, lbfgs = _swap_fit()
    assert torch.equal(out, ref) and adam.state == {}  # only the running phase's optimiser was restored
    assert len(log.losses) == 8
