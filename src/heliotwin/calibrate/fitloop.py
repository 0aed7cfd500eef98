"""The one fit loop of every per-heliostat, early-stopped fit in ``calibrate`` (gradient, images, hybrid, mlp).

All heliostats of a run are fitted at once: the loss is a sum of independent per-heliostat terms, so one
optimiser over a tensor (or a :class:`~heliotwin.calibrate.methods.nets.BatchedMLP`) with a leading heliostat axis
equals H separate fits. What differs between heliostats is *when to stop*: every ``check_every``
iterations the validation error of each heliostat is evaluated and its best state so far is kept
(:func:`early_stopping_fit`); heliostats without validation records keep the final state.

The rigid-body fits (``gradient``, ``images``) share the rest of their setup here too: the scaled,
prior-regularised start (:func:`prior_and_start`), the box :data:`BOUNDS`, the actuator barrier
(:func:`actuator_barrier`) and the projection after every step (:func:`box_and_validity`: back into the
box, and a heliostat whose actuator triangle broke or whose state went non-finite goes back to its last
valid state).

Checkpoints. Under an active :mod:`heliotwin.io.checkpoint` (``calibrate --resume``) every loop claims a key
(``fit/0``, ``fit/1``, ...) and saves its full state: the live and best states, the early-stopping
bookkeeping, the state of every optimiser that steps inside it (found by torch's global optimiser-step
hooks, so no method has to hand its optimiser over) and of the generators it is given. A resumed run
restores a finished loop instead of running it, and continues an unfinished one after its last saved step.

Surface fits run in the same loop (:mod:`heliotwin.surfaces.fit`, one "heliostat"). They use two options that
no calibration method sets (so calibration's loop is unchanged): an early end (:class:`EarlyEnd`: patience on
the validation error, a relative tolerance on the training loss, or a condition of the caller's) and steps
that build a fresh optimiser every call (``optimiser_states=False``: L-BFGS rounds whose history is reset, so
no optimiser state is saved or restored). A ``swap`` changes the step function, and with it the optimiser,
at a given iteration (e.g. Adam, then L-BFGS); the checkpoint then holds the optimiser of the running phase.
"""
from __future__ import annotations

import contextlib
import copy
from dataclasses import dataclass, field
from typing import Callable

import torch
from torch.optim.optimizer import register_optimizer_step_pre_hook
from tqdm import tqdm

from ..errors import HeliotwinError
from ..field.plant import Kinematics
from ..io import checkpoint as _checkpoint
from .params import actuator_margin, kinds, units

#: Box bounds per kind (physical units): far outside any real deviation, they only stop runaways.
BOUNDS = {"angle": 0.5, "tilt": 0.2, "increment": 0.2, "translation": 0.5, "actuator_length": 0.05}

#: Smallest law-of-cosines margin [m] the barrier defends (1 mm of stroke).
MIN_MARGIN = 1e-3

#: Weight of the squared relative margin shortfall: steep enough that no fit trades a broken actuator
#: triangle for a smaller data term (one record's term at 1 mrad error is ~1).
BARRIER_WEIGHT = 1e4


def actuator_barrier(kin: Kinematics) -> torch.Tensor:
    """Penalty (scalar) for linear actuators closer than :data:`MIN_MARGIN` to an invalid triangle.

    ``kin`` has H heliostats with deviations applied; 0 when every margin is at least :data:`MIN_MARGIN`.
    """
    return (torch.relu(MIN_MARGIN - actuator_margin(kin)) / MIN_MARGIN).pow(2).sum() * BARRIER_WEIGHT


def make_optimizer(x: torch.Tensor, objective, optimizer: str, lr: float, lbfgs_max_iter: int = 20):
    """Optimiser over the deviation tensor ``x`` and the closure that evaluates ``objective(x)``.

    Parameters
    ----------
    x : torch.Tensor, [H, P]
        Leaf tensor of deviations (natural units), requires grad.
    objective : callable
        ``objective(x) -> scalar`` loss.
    optimizer : {"lbfgs", "adam"}
    lr : float
        Adam step size (L-BFGS starts from a unit step with a strong-Wolfe line search).
    lbfgs_max_iter : int
        Function evaluations per L-BFGS ``step``.

    Returns
    -------
    opt : torch.optim.Optimizer
    closure : callable
        For ``opt.step(closure)``.
    """
    if optimizer == "lbfgs":
        opt = torch.optim.LBFGS([x], lr=1.0, max_iter=lbfgs_max_iter, history_size=20, line_search_fn="strong_wolfe",
                                tolerance_grad=1e-9, tolerance_change=1e-12)
    elif optimizer == "adam":
        opt = torch.optim.Adam([x], lr=lr)
    else:
        raise HeliotwinError(f"unknown optimizer {optimizer!r}; known: lbfgs, adam")

    def closure():
        opt.zero_grad()
        loss = objective(x)
        loss.backward()
        return loss

    return opt, closure


def prior_and_start(names, num_heliostats: int, prior_sigma, prior_mean=None, init=None, *, like: torch.Tensor):
    """Scaled parameters of a bounded, prior-regularised fit (shared by ``gradient`` and ``images``).

    Parameters
    ----------
    names : list of str
        Deviation parameter names (checked by the caller).
    num_heliostats : int
        H.
    prior_sigma : dict kind -> sigma, or tensor [P] / [H, P]
        Prior standard deviations in physical units ([rad] for angles and tilts, [m] for lengths, [1] for
        relative increments; ``inf`` or a missing kind: no prior).
    prior_mean, init : torch.Tensor, [H, P], optional
        Prior mean (default 0) and start (default the prior mean), physical units ([rad], [m], [1] as above).
    like : torch.Tensor, any shape (...)
        Every tensor returned follows its dtype and device (the nominal kinematics').

    Returns
    -------
    unit : torch.Tensor, [P]
        Physical units per optimiser unit.
    mu, inv_sig : torch.Tensor, [H, P]
        Prior mean and inverse sigma (0 where there is no prior).
    bound : torch.Tensor, [P]
        Box bound in optimiser units.
    x : torch.Tensor, [H, P]
        The start in optimiser units, clamped into the box, a leaf that requires grad.
    """
    h, p = int(num_heliostats), len(names)
    fk = dict(dtype=like.dtype, device=like.device)
    unit = units(names, **fk)
    kk = kinds(names)
    if isinstance(prior_sigma, dict):
        sig = torch.tensor([float(prior_sigma.get(k, float("inf"))) for k in kk], **fk)
    else:
        sig = torch.as_tensor(prior_sigma).to(**fk)
    sig = sig.expand(h, p)
    inv_sig = torch.where(torch.isfinite(sig), 1.0 / sig, torch.zeros_like(sig))
    mu = torch.zeros(h, p, **fk) if prior_mean is None else torch.as_tensor(prior_mean).to(**fk).expand(h, p)
    bound = torch.tensor([BOUNDS[k] for k in kk], **fk) / unit
    start = mu if init is None else init.detach().to(**fk)
    x = (start / unit).clamp(-bound, bound).clone().requires_grad_(True)
    return unit, mu, inv_sig, bound, x


def box_and_validity(x: torch.Tensor, bound: torch.Tensor, valid: Callable[[torch.Tensor], torch.Tensor]):
    """The projection after every optimiser step of a bounded rigid-body fit.

    Parameters
    ----------
    x : torch.Tensor, [H, P]
        The optimised leaf (optimiser units); changed in place.
    bound : torch.Tensor, [P]
        Box bound in optimiser units.
    valid : callable
        ``valid(x) -> [H] bool``: every linear actuator of the heliostat realises its whole motor range.

    Returns
    -------
    callable
        ``project()``: clamp into the box; a heliostat whose state is invalid or non-finite goes back to
        its last valid state (the barrier keeps this rare; an L-BFGS line search can still overshoot).
    """
    last_valid = x.detach().clone()

    def project() -> None:
        with torch.no_grad():
            x.data = torch.maximum(torch.minimum(x.data, bound), -bound)
            ok = valid(x) & torch.isfinite(x).all(-1)
            x.data[~ok] = last_valid[~ok]
            last_valid.copy_(x.detach())

    def sync() -> None:  # a restored checkpoint: the live state is the last valid one
        last_valid.copy_(x.detach())

    project.sync = sync
    return project


@dataclass
class State:
    """How the fit loop copies per-heliostat states: ``snapshot()`` -> a copy, ``keep(copy, rows [H] bool)``
    overwrites those heliostats' rows of the copy with the live state.

    For checkpoints (optional; without them the loop is not checkpointed): ``live`` is the live state,
    ``dump(obj)`` turns it or a snapshot into tensors and containers (a copy), ``load(obj, data)`` writes such
    a dump back into it in place."""

    snapshot: Callable
    keep: Callable
    live: object = None
    dump: Callable | None = None
    load: Callable | None = None


def _copy_into(obj: torch.Tensor, data: torch.Tensor) -> None:
    with torch.no_grad():
        obj.copy_(data)


def tensor_state(x: torch.Tensor) -> State:
    """:class:`State` of a leaf tensor of shape (H, ...) (a leading heliostat axis)."""
    def keep(best, rows):
        best[rows] = x.detach()[rows]

    return State(lambda: x.detach().clone(), keep, x, lambda obj: obj.detach().clone(), _copy_into)


def net_state(net) -> State:
    """:class:`State` of a :class:`~heliotwin.calibrate.methods.nets.BatchedMLP` (one network per heliostat)."""
    return State(lambda: copy.deepcopy(net), lambda best, rows: best.copy_rows(net, rows), net,
                 lambda obj: {k: v.detach().clone() for k, v in obj.state_dict().items()},
                 lambda obj, data: obj.load_state_dict(data))


class _Optimisers:
    """The optimisers that step inside a loop, in the order of their first step (torch's global step hook):
    their states go into the checkpoint; on resume, saved states are loaded into them before their first step."""

    def __init__(self, pending=None):
        self.seen: list = []
        self.pending = list(pending or [])

    @contextlib.contextmanager
    def watching(self):
        def before(opt, args, kwargs):
            if not any(o is opt for o in self.seen):
                self.seen.append(opt)
                if self.pending:
                    opt.load_state_dict(self.pending.pop(0))

        handle = register_optimizer_step_pre_hook(before)
        try:
            yield self
        finally:
            handle.remove()

    def dump(self) -> list:
        return [copy.deepcopy(o.state_dict()) for o in self.seen]


@dataclass
class EarlyEnd:
    """When a loop may end before its iteration budget (every rule off by default).

    Attributes
    ----------
    patience : int, optional
        End after this many validation checks in a row in which no heliostat's best validation error fell by
        more than ``min_delta``.
    min_delta : float
        What counts as a better validation error (same units as the error).
    tolerance : float, optional
        End when a step's training loss (what ``step`` returned) is lower than the previous counted step's by
        at most ``tolerance`` times its magnitude (relative; the first counted step never ends the loop).
    after : int
        Iterations before this one are not counted by ``tolerance`` (e.g. a warm-up or continuation phase).
    done : callable, optional
        ``done() -> bool``, asked after every step: a condition of the caller's (e.g. a spent budget of loss
        evaluations).
    """

    patience: int | None = None
    min_delta: float = 0.0
    tolerance: float | None = None
    after: int = 0
    done: Callable | None = None


@dataclass
class _Ending:
    """The early end's bookkeeping (checkpointed with the loop)."""

    rule: EarlyEnd
    bad_checks: int = 0
    previous: float = float("inf")
    ended: bool = False

    def after_step(self, it: int, loss) -> None:
        if self.rule.tolerance is not None and loss is not None and it >= self.rule.after:
            value = float(loss.detach()) if isinstance(loss, torch.Tensor) else float(loss)
            if self.previous - value <= self.rule.tolerance * abs(value):
                self.ended = True
            else:
                self.previous = value
        if self.rule.done is not None and self.rule.done():
            self.ended = True

    def after_check(self, improved: bool) -> None:
        if self.rule.patience is None:
            return
        self.bad_checks = 0 if improved else self.bad_checks + 1
        self.ended = self.ended or self.bad_checks >= self.rule.patience

    def dump(self) -> dict:
        return {"bad_checks": self.bad_checks, "previous": self.previous, "ended": self.ended}

    def load(self, data: dict) -> None:
        self.bad_checks, self.previous = int(data["bad_checks"]), float(data["previous"])
        self.ended = bool(data["ended"])


@dataclass
class Swap:
    """From iteration ``at + 1`` on the loop calls ``step`` instead of its own step function (a new optimiser:
    e.g. Adam first, then L-BFGS from Adam's end point). ``step`` builds its optimiser on its first call."""

    at: int
    step: Callable


def _entry(it: int, state: State, log, optimisers: _Optimisers, generators, ending: _Ending | None = None) -> dict:
    """The checkpoint entry of a loop after iteration ``it``."""
    out = {"step": int(it), "live": state.dump(state.live), "best": state.dump(log.best),
           "best_error": log.best_error.detach().clone(), "best_iteration": log.best_iteration.clone(),
           "history": [(int(i), m) for i, m in log.history], "losses": list(log.losses),
           "optimisers": optimisers.dump(), "generators": [g.get_state() for g in generators]}
    if ending is not None:
        out["early_end"] = ending.dump()
    return out


def _restore(saved: dict, state: State, log, generators) -> int:
    """Load a checkpoint entry into the live state and the log; returns the iteration to continue after."""
    state.load(state.live, saved["live"])
    state.load(log.best, saved["best"])
    log.best_error = saved["best_error"].to(log.best_error)
    log.best_iteration = saved["best_iteration"].to(log.best_iteration.device)
    log.history = [tuple(h) for h in saved["history"]]
    log.losses = list(saved["losses"])
    for g, st in zip(generators, saved["generators"]):
        g.set_state(st)
    return int(saved["step"])


@dataclass
class FitLog:
    """What the loop saw.

    Attributes
    ----------
    best : object
        The kept state (a snapshot of :class:`State`): per heliostat its best validated state, the final
        state without validation records, or its ``stop_at`` state in refit mode.
    best_error : torch.Tensor, [H]
        Validation error of the kept state (inf without validation records).
    best_iteration : torch.Tensor, [H], long
        Iteration of the kept state (0 = the start).
    history : list of (iteration, median over heliostats of the validation error [mrad] or None)
    losses : list of float
        Training loss per iteration (what ``step`` returned).
    ended_at : int
        The last iteration run (``iterations`` unless an :class:`EarlyEnd` rule ended the loop).
    """

    best: object
    best_error: torch.Tensor
    best_iteration: torch.Tensor
    history: list = field(default_factory=list)
    losses: list = field(default_factory=list)
    ended_at: int | None = None


def _median_mrad(err: torch.Tensor):
    fin = torch.isfinite(err)
    return float(err[fin].median()) * 1e3 if fin.any() else None


def _iterations(iterations: int, progress: bool, desc: str, first: int = 1):
    it = range(first, iterations + 1)
    if progress:
        it = tqdm(it, desc=desc, leave=False, initial=first - 1, total=iterations)
    return it


def early_stopping_fit(step: Callable, validation_error: Callable, state: State, iterations: int, *,
                       validated: torch.Tensor, check_every: int = 1, project: Callable | None = None,
                       stop_at: torch.Tensor | None = None, progress: bool = False, desc: str = "fit",
                       generators=(), early_end: EarlyEnd | None = None, swap: Swap | None = None,
                       optimiser_states: bool = True) -> FitLog:
    """Run ``iterations`` optimiser steps and keep every heliostat's best state on validation.

    Parameters
    ----------
    step : callable
        ``step() -> loss`` (tensor or float, or None): one optimiser step on the training loss.
    validation_error : callable
        ``validation_error() -> [H]`` of the live state (inf for heliostats without validation records);
        lower is better.
    state : State
        How to copy the live state (:func:`tensor_state`, :func:`net_state`).
    iterations : int
    validated : torch.Tensor, [H], bool
        Heliostats with validation records; the others keep the final state (the MAP of the training
        loss) unless ``stop_at`` is given.
    check_every : int
        Validation every this many iterations and after the last one.
    project : callable, optional
        Called after every step (bounds, validity: :func:`box_and_validity`).
    stop_at : torch.Tensor, [H], long, optional
        Refit mode: keep each heliostat's state at this iteration (a checked one, 0 = the start), e.g. the
        best iteration found on validation in a first pass; the validation error is not consulted.
    progress : bool
        tqdm bar titled ``desc``.
    generators : sequence of torch.Generator
        Generators ``step`` draws from (their states are checkpointed with the loop's).
    early_end : EarlyEnd, optional
        Rules to end before ``iterations`` (default: run them all). The loop then validates once more after
        its last step, and ``best_iteration`` of heliostats without validation is that step.
    swap : Swap, optional
        Change the step function (and so the optimiser) after iteration ``swap.at``.
    optimiser_states : bool
        False when ``step`` builds a fresh optimiser on every call (nothing to checkpoint or restore).

    Returns
    -------
    FitLog
        ``ended_at``: the last iteration run.
    """
    ck = _checkpoint.current()
    key = ck.claim("fit") if ck is not None and state.dump is not None else None
    best = state.snapshot()
    best_err = validation_error()
    best_it = torch.zeros(len(best_err), dtype=torch.long, device=best_err.device)
    log = FitLog(best, best_err, best_it, history=[(0, _median_mrad(best_err))])
    ending = None if early_end is None else _Ending(early_end)
    saved = ck.get(key) if key is not None else None
    optimisers = _Optimisers(saved["optimisers"] if saved is not None and optimiser_states else None)
    done = _restore(saved, state, log, generators) if saved is not None else 0
    if saved is not None and ending is not None:
        ending.load(saved["early_end"])
    if done and getattr(project, "sync", None) is not None:
        project.sync()
    first = iterations + 1 if ending is not None and ending.ended else done + 1
    steps = _Steps(step, swap, optimisers if key is not None and optimiser_states else None)
    with optimisers.watching() if key is not None and optimiser_states else contextlib.nullcontext():
        last = _steps(steps, validation_error, state, iterations, log, check_every, project, stop_at,
                      _iterations(iterations, progress, desc, first), ck, key, optimisers, generators, ending)
    log.ended_at = last if last is not None else (done if ending is not None and ending.ended else iterations)
    if stop_at is None:
        final = ~validated.to(best_it.device)
        state.keep(log.best, final)
        log.best_iteration[final] = log.ended_at
    return log


class _Steps:
    """The step function of iteration ``it`` (before or after a :class:`Swap`). At the swap the optimisers seen
    so far leave the checkpoint: it holds the running phase's (loaded into it on resume)."""

    def __init__(self, step, swap: Swap | None, optimisers: _Optimisers | None):
        self.step, self.swap, self.optimisers = step, swap, optimisers

    def __call__(self, it: int):
        if self.swap is not None and it > self.swap.at:
            if it == self.swap.at + 1 and self.optimisers is not None:
                self.optimisers.seen.clear()
            return self.swap.step()
        return self.step()


def _steps(step, validation_error, state, iterations, log, check_every, project, stop_at, its, ck, key, optimisers,
           generators, ending: _Ending | None = None):
    """The iterations ``its`` of :func:`early_stopping_fit` (saving the loop's state when a checkpoint is due);
    returns the last iteration run (None if none ran)."""
    best = log.best
    last = None
    for it in its:
        last = it
        loss = step(it)
        if loss is not None:
            log.losses.append(float(loss.detach()) if isinstance(loss, torch.Tensor) else float(loss))
        if project is not None:
            project()
        if ending is not None:
            ending.after_step(it, loss)
        if it % check_every == 0 or it == iterations or (ending is not None and ending.ended):
            err = validation_error()
            if stop_at is not None:
                better = stop_at >= it
            elif ending is not None and ending.rule.min_delta:
                better = err < log.best_error - ending.rule.min_delta
            else:
                better = err < log.best_error
            state.keep(best, better)
            log.best_error = torch.where(better, err, log.best_error)
            log.best_iteration[better] = it
            log.history.append((it, _median_mrad(err)))
            if ending is not None:
                ending.after_check(bool(better.any()))
        finished = it == iterations or (ending is not None and ending.ended)
        if key is not None:
            if finished or ck.due(it):
                ck.put(key, _entry(it, state, log, optimisers, generators, ending))
            ck.notify("step", key, it)
        if finished:
            break
    return last


__all__ = ["BOUNDS", "MIN_MARGIN", "BARRIER_WEIGHT", "actuator_barrier", "make_optimizer", "prior_and_start",
           "box_and_validity", "State", "tensor_state", "net_state", "FitLog", "EarlyEnd", "Swap", "early_stopping_fit"]
