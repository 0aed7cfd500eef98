"""Batched Levenberg-Marquardt: every heliostat's least-squares problem solved at once, in tensors.

The heliostats of a calibration are independent problems of P parameters each (the Stone/Jülich 8). One
problem per heliostat, one after another, costs Python and solver overhead per heliostat; one joint problem
for a dense solver costs the cube of the heliostats. Here the H problems advance together: per iteration
one residual and Jacobian evaluation of every record still in play, per heliostat the P x P normal
equations (summed over its rows by ``index_add``), one batched solve, and an accept / reject, damping and
convergence test of its own. Cost per iteration is linear in records; the iterations are those of the
slowest heliostat, and heliostats that converged leave the evaluation.

The objective of a heliostat is scipy's ``least_squares`` cost, ``0.5 sum rho(f_i^2)`` over its residuals
``f`` (measurement rows and prior rows alike), with ``rho`` the ``linear`` or ``soft_l1`` loss of scale
``f_scale``: the same minimum as :func:`scipy.optimize.least_squares`, which the tests check. The robust
loss enters as iteratively reweighted Gauss-Newton (gradient ``J^T rho' f``, curvature
``J^T (rho' + 2 rho'' f^2) J``, as scipy scales it). Damping: Marquardt's ``A + lambda diag(A)`` with
Nielsen's update of ``lambda`` (H. B. Nielsen, *Damping parameter in Marquardt's method*, IMM-REP-1999-05).

Device and dtype follow ``x0``.
"""
from __future__ import annotations

from contextlib import contextmanager
from typing import Callable

import torch
import torch.distributed as dist

#: Losses of :func:`solve` (scipy ``least_squares`` names).
LOSSES = ("linear", "soft_l1")

_SHARDING: dict = {"group": None}


@contextmanager
def sharded(group):
    """Within this context the batched fits (:func:`heliotwin.calibrate.methods.lm.fit_lm`) solve only this
    rank's contiguous shard of the heliostats and sum the deviations over ``group`` (a
    :mod:`torch.distributed` process group; None: unsharded). Every rank runs the same calibration; the
    heliostats' problems are independent, so the result is the one-process result."""
    before = _SHARDING["group"]
    _SHARDING["group"] = group
    try:
        yield
    finally:
        _SHARDING["group"] = before


def shard_group():
    """The process group of :func:`sharded` when it has more than one rank, else None."""
    group = _SHARDING["group"]
    if group is None or not dist.is_available() or not dist.is_initialized():
        return None
    return group if dist.get_world_size(group) > 1 else None


def contiguous_shard(n: int, rank: int, world: int) -> torch.Tensor:
    """Indices, shape (k,), long, of rank ``rank``'s contiguous share of ``n`` items (sizes differ by at most one)."""
    base, extra = divmod(int(n), int(world))
    start = rank * base + min(rank, extra)
    return torch.arange(start, start + base + (1 if rank < extra else 0))


def _rho(f: torch.Tensor, loss: str, f_scale: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per residual element: ``rho(f^2)`` (cost = half its sum), ``rho'`` and ``rho' + 2 rho'' f^2``."""
    if loss == "linear":
        one = torch.ones_like(f)
        return f * f, one, one
    z = (f / f_scale) ** 2
    s = (1.0 + z).sqrt()
    return 2.0 * f_scale ** 2 * (s - 1.0), 1.0 / s, 1.0 / (s * (1.0 + z))


def solve(evaluate: Callable, x0: torch.Tensor, record_owner: torch.Tensor, prior_matrix: torch.Tensor | None = None,
          prior_centre: torch.Tensor | None = None, *, loss: str = "linear", f_scale: float = 1.0,
          max_iterations: int = 200, xtol: float = 1e-10, ftol: float = 1e-12, gtol: float = 1e-14,
          subset_records: bool = True, near: bool = False) -> tuple[torch.Tensor, dict]:
    """Minimise every heliostat's robust least-squares cost at once.

    Parameters
    ----------
    evaluate : callable
        ``evaluate(x_rows, rows)`` -> ``(residuals [n, 3], jacobian [n, 3, P])`` of the records ``rows``
        (a long index [n] into the problem's records, or None for all of them) at their heliostats'
        parameters ``x_rows`` [n, P] (the solver's units).
    x0 : torch.Tensor, [H, P]
        Start (float64).
    record_owner : torch.Tensor, [R], long
        Heliostat (row of ``x0``) of each record.
    prior_matrix : torch.Tensor, [H, Q, P], optional
        Prior residuals ``prior_matrix[h] @ (x[h] - prior_centre[h])`` (Q per heliostat; linear in x).
    prior_centre : torch.Tensor, [H, P], optional
    loss, f_scale :
        ``"linear"`` or ``"soft_l1"`` (:data:`LOSSES`) per residual element, scale in residual units.
    max_iterations : int
        Most Jacobian evaluations per heliostat.
    xtol, ftol, gtol :
        A heliostat has converged when an accepted step is smaller than ``xtol (xtol + |x|)``, its gradient's
        largest entry is below ``gtol``, or a step's actual and predicted gains are both below ``ftol`` of its
        cost (rounding level).
    subset_records : bool
        Evaluate only the records of heliostats still iterating (False: every record, every iteration; for
        an ``evaluate`` that needs the whole table, e.g. a whitening across records).
    near : bool
        ``x0`` is already near the minimum (e.g. the fit of the same heliostats on other records): no plain
        least-squares warm start for a robust loss.

    Returns
    -------
    x : torch.Tensor, [H, P]
    info : dict
        ``iterations`` (of the slowest heliostat), ``evaluations`` (record evaluations summed over
        iterations, in units of the whole table), ``converged`` (heliostats), ``cost`` (summed).
    """
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    warm = None
    if loss != "linear" and not near:
        # Far from the minimum a robust loss has almost no curvature (large residuals), so damped steps crawl;
        # the plain least-squares minimum is a start near the robust one, and the minimum does not depend on
        # the start.
        x0, warm = solve(evaluate, x0, record_owner, prior_matrix, prior_centre, loss="linear",
                         max_iterations=max_iterations, xtol=1e-6, ftol=1e-8, subset_records=subset_records)
    x = x0.detach().clone()
    h, p = x.shape
    dev, dt = x.device, x.dtype
    owner = record_owner.to(dev)
    n_rec = len(owner)
    if prior_matrix is None:
        prior_matrix = x.new_zeros(h, 0, p)
        prior_centre = torch.zeros_like(x)

    def records_of(which: torch.Tensor):
        """Rows of the records of heliostats ``which`` [H] bool (None = all)."""
        if not subset_records or bool(which.all()):
            return None
        return which[owner].nonzero().flatten()

    def assemble(xh, res, jac, own, heliostats):
        """Per heliostat in ``heliostats``: cost, gradient, curvature (records ``own``-owned, + prior)."""
        k = len(heliostats)
        local = torch.full((h,), -1, dtype=torch.long, device=dev)
        local[heliostats] = torch.arange(k, device=dev)
        lo = local[own]
        c, w1, w2 = _rho(res, loss, f_scale)
        cost = x.new_zeros(k).index_add_(0, lo, c.sum(-1))
        grad = x.new_zeros(k, p).index_add_(0, lo, torch.einsum("rc,rcp->rp", w1 * res, jac))
        curv = x.new_zeros(k, p, p).index_add_(0, lo, torch.einsum("rcp,rc,rcq->rpq", jac, w2, jac))
        pm = prior_matrix[heliostats]
        pres = torch.einsum("hqp,hp->hq", pm, xh - prior_centre[heliostats])
        pc, pw1, pw2 = _rho(pres, loss, f_scale)
        cost += pc.sum(-1)
        grad += torch.einsum("hqp,hq->hp", pm, pw1 * pres)
        curv += torch.einsum("hqp,hq,hqr->hpr", pm, pw2, pm)
        return 0.5 * cost, grad, curv

    def run(xh_all, heliostats_mask):
        rows = records_of(heliostats_mask)
        own = owner if rows is None else owner[rows]
        res, jac = evaluate(xh_all[own], rows)
        if rows is None:  # keep only the heliostats asked for
            keep = heliostats_mask[own]
            res, jac, own = res[keep], jac[keep], own[keep]
        return res, jac, own

    everyone = torch.ones(h, dtype=torch.bool, device=dev)
    res, jac, own = run(x, everyone)
    ids = torch.arange(h, device=dev)
    cost, grad, curv = assemble(x, res, jac, own, ids)
    lam = torch.full((h,), 1e-3, dtype=dt, device=dev)  # Marquardt's damping is relative to diag(A)
    nu = torch.full((h,), 2.0, dtype=dt, device=dev)
    done = grad.abs().amax(-1) <= gtol
    evaluations = 1.0
    it = 0
    for it in range(1, max_iterations + 1):
        act = (~done).nonzero().flatten()
        if len(act) == 0:
            break
        a, g = curv[act], grad[act]
        d = torch.diagonal(a, dim1=-2, dim2=-1).clamp_min(1e-12 * torch.diagonal(a, dim1=-2, dim2=-1).amax(-1,
                                                                                                            True))
        lhs = a + lam[act, None, None] * torch.diag_embed(d)
        step, info = torch.linalg.solve_ex(lhs, -g.unsqueeze(-1))
        step = step.squeeze(-1)
        bad = (info != 0) | ~torch.isfinite(step).all(-1)
        step = torch.where(bad[:, None], torch.zeros_like(step), step)
        trial = x.clone()
        trial[act] = x[act] + step
        mask = torch.zeros(h, dtype=torch.bool, device=dev)
        mask[act] = True
        r_new, j_new, own_new = run(trial, mask)
        evaluations += len(own_new) / max(n_rec, 1)
        c_new, g_new, a_new = assemble(trial[act], r_new, j_new, own_new, act)
        predicted = -(g * step).sum(-1) - 0.5 * torch.einsum("hp,hpq,hq->h", step, a, step)
        actual = cost[act] - c_new
        ratio = actual / predicted.clamp_min(1e-300)
        accept = (ratio > 0) & ~bad & torch.isfinite(c_new) & (predicted > 0)
        # Nielsen: shrink lambda by the model's fit on success, double-and-grow on failure
        shrink = (1.0 - (2.0 * ratio - 1.0) ** 3).clamp(min=1.0 / 3.0)
        lam[act] = torch.where(accept, lam[act] * shrink, lam[act] * nu[act])
        nu[act] = torch.where(accept, torch.full_like(nu[act], 2.0), nu[act] * 2.0)
        small_step = step.norm(dim=-1) <= xtol * (xtol + trial[act].norm(dim=-1))
        # a gain (actual or predicted) at the cost's rounding level: nothing left to gain, accepted or not
        tiny = ftol * cost[act].clamp_min(1e-300)
        small_gain = (actual.abs() <= tiny) & (predicted.abs() <= tiny)
        acc = act[accept]
        x[acc] = trial[acc]
        cost[acc], grad[acc], curv[acc] = c_new[accept], g_new[accept], a_new[accept]
        converged = small_gain | (accept & (small_step | (g_new.abs().amax(-1) <= gtol)))
        # a step that no damping makes decrease the cost: at the minimum to machine precision
        stuck = ~accept & ((lam[act] > 1e16) | (step.norm(dim=-1) <= 1e-15 * (1.0 + x[act].norm(dim=-1))))
        done[act] = converged | stuck
    if warm is not None:
        it, evaluations = it + warm["iterations"], evaluations + warm["evaluations"]
    return x, {"iterations": it, "evaluations": evaluations, "converged": int(done.sum()),
               "cost": float(cost.sum())}


__all__ = ["solve", "LOSSES", "sharded", "shard_group", "contiguous_shard"]
