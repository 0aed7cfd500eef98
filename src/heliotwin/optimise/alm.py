"""The solver's inner loop: augmented-Lagrangian Adam steps on the corrected image model (one round).

Hestenes-Powell: multipliers per map cell, ``lambda_c <- max(0, lambda_c + rho g_c)`` with ``g_c = F_c / L'_c - 1``
against the round's internal limit map ``L' = (1 - m) L`` (kept across rounds), Adam steps on
``weight * objective + penalty``, every aim point projected back onto the receiver's height and its visible arc.
The corrected model is ``S(a) + (F_k - S(a_k))`` (the exact map at the round's start ``a_k``), optionally with a
first-order power correction (:class:`RoundStart.linear`).
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
from dataclasses import dataclass

import torch

from .images import ImageModel
from .problem import _Group

__all__ = ["ALM_PROFILE_DTYPE", "ALM_SETTLE", "Frame", "RoundStart", "Steps", "alm_round"]

#: Precision of the image profiles (erf, exp) in the augmented-Lagrangian steps: float32 is ~2.5x faster on a
#: CPU. Only these element-wise, per-heliostat terms: every sum over heliostats (the map, the power, their
#: all-reduce when sharded) stays in the aim points' float64, so a sharded run takes one process's steps.
ALM_PROFILE_DTYPE = torch.float32
#: The augmented-Lagrangian steps end once the model's limit holds and its objective (relative power, or the
#: target mismatch) moved by less than this over two multiplier updates [-].
ALM_SETTLE = 1e-5


@dataclass(frozen=True)
class Frame:
    """What one solve's rounds share.

    Attributes
    ----------
    grp : _Group
        The process group's all-reduce (one process: the identity).
    half_height : float
        Half the receiver's height [m]: every aim point stays within ``|y| <= half_height``.
    x_bounds : (torch.Tensor, torch.Tensor) or None
        Lateral range ``(lo, hi)`` [h] each [m] every aim point stays in (None: any).
    p0 : float
        The power the objective is relative to [W] (equator aiming's).
    weight : float
        Weight of the objective against the penalty [-] (the heliostat count).
    target : torch.Tensor, [rows, cols], optional
        The target shape (None: maximise power).
    """

    grp: _Group
    half_height: float
    x_bounds: tuple | None
    p0: float
    weight: float
    target: torch.Tensor | None = None


@dataclass(frozen=True)
class RoundStart:
    """One round's start on the corrected image model.

    Attributes
    ----------
    x, y : torch.Tensor, [h] each
        The aim points' map coordinates [m] the steps start from.
    defect : torch.Tensor, [rows, cols]
        Exact map minus the image model's at the round's start [W/m^2].
    power_defect : float
        Exact power minus the image model's there [W].
    limit : torch.Tensor, [rows, cols]
        The internal limit per cell [W/m^2].
    lam : torch.Tensor, [rows, cols]
        The multipliers (updated in place).
    linear : (torch.Tensor, torch.Tensor), optional
        ``(cx, cy)``, [h] each [W/m]: a first-order power correction ``sum cx (x - x_k) + cy (y - y_k)`` [W].
    """

    x: torch.Tensor
    y: torch.Tensor
    defect: torch.Tensor
    power_defect: float
    limit: torch.Tensor
    lam: torch.Tensor
    linear: tuple | None = None


@dataclass(frozen=True)
class Steps:
    """How many steps of what size: ``steps`` Adam steps of size ``lr`` [m] (decaying to a tenth), penalty weight
    ``rho`` [-], a multiplier update every ``inner`` steps, at most ``restore`` restoration steps, and the
    objective change ``settle`` [-] below which the steps end early (see :func:`alm_round`)."""

    steps: int
    lr: float
    rho: float
    inner: int
    restore: int = 0
    settle: float = ALM_SETTLE


@contextlib.contextmanager
def _intra_op_threads(n: int):
    """Run the block with ``n`` intra-op threads (restored after): the image model's steps are hundreds of
    small element-wise ops, for which a second thread only adds synchronisation, and on a loaded machine
    (more runnable processes than cores) its spin-waits multiplied the steps' CPU time 30-fold (measured:
    whole command 10 s with one thread against 251 s with two, 2 cores, load ~5)."""
    before = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(before)


class _Adam:
    """Adam (Kingma & Ba 2015; ``torch.optim.Adam``'s defaults and update, bias-corrected) on a few tensors.

    Written out because the first ``torch.optim`` optimiser of a process imports ``torch._dynamo`` (~1 s on a
    CPU, a fifth of a 2,000-heliostat ``aimpoints`` command) for two parameter tensors that need none of it.
    """

    def __init__(self, params, lr: float, betas=(0.9, 0.999), eps: float = 1e-8):
        self.params, self.lr, self.betas, self.eps, self.t = tuple(params), float(lr), betas, float(eps), 0
        self.m = [torch.zeros_like(p) for p in self.params]
        self.v = [torch.zeros_like(p) for p in self.params]

    def step(self, grads, scale: float = 1.0) -> None:
        """One update in place (call under ``torch.no_grad``) with ``grads`` (one per parameter, same shapes)
        and the step size ``scale * lr``."""
        self.t += 1
        b1, b2 = self.betas
        c1, c2 = 1.0 - b1 ** self.t, 1.0 - b2 ** self.t
        for p, g, m, v in zip(self.params, grads, self.m, self.v):
            m.mul_(b1).add_(g, alpha=1.0 - b1)
            v.mul_(b2).addcmul_(g, g, value=1.0 - b2)
            p.addcdiv_(m, (v.sqrt() / math.sqrt(c2)).add_(self.eps), value=-scale * self.lr / c1)




@_intra_op_threads(1)
def alm_round(model: ImageModel, start: RoundStart, steps: Steps, frame: Frame):
    """Augmented-Lagrangian Adam steps on the corrected image model (``start.lam`` updated in place).

    The image profiles are evaluated in :data:`ALM_PROFILE_DTYPE`. The steps end early once the model's limit holds
    (every cell within 0.1 % of its internal limit) and the objective moved by less than ``steps.settle`` over the
    last two multiplier updates (an optimum of the model: more steps only shuffle aim points it cannot tell apart).
    Then at most ``steps.restore`` steps on the excess over the internal limit alone
    (:attr:`~heliotwin.optimise.solver.AimSettings.restore_steps`).

    Returns
    -------
    x, y : torch.Tensor, shape (h,) each
        The new aim points' map coordinates [m].
    predicted : float
        The corrected model's objective key at them: ``P / p0`` (maximising power) or ``-mismatch`` (with a
        target), as :func:`~heliotwin.optimise.solver.solve` keys the exact checks [-].
    done : int
        Steps taken.
    """
    grp, half_height, x_bounds, p0 = frame.grp, frame.half_height, frame.x_bounds, frame.p0
    defect, power_defect, limit_int, lam, linear = (start.defect, start.power_defect, start.limit, start.lam,
                                                    start.linear)
    lr, rho = steps.lr, steps.rho
    model = dataclasses.replace(model, profile_dtype=ALM_PROFILE_DTYPE)
    x0, y0 = start.x.clone(), start.y.clone()
    x = start.x.clone().requires_grad_()
    y = start.y.clone().requires_grad_()
    adam = _Adam((x, y), lr)
    t = None if frame.target is None else frame.target / frame.target.sum()

    def corrected(x, y):
        f_loc, p_loc = model.flux(x, y)
        f = grp.sum(f_loc) + defect
        p_loc = p_loc.sum()
        if linear is not None:
            p_loc = p_loc + (linear[0] * (x - x0) + linear[1] * (y - y0)).sum()
        p = grp.sum(p_loc) + power_defect
        mismatch = None if t is None else ((f / f.sum() - t) ** 2).sum() / (t ** 2).sum()
        return f, p, mismatch

    def step(opt: _Adam, gx, gy, scale: float) -> None:
        # one Adam step, then back onto the receiver's height and each heliostat's visible arc (under no_grad)
        opt.step((gx, gy), scale)
        y.clamp_(-half_height, half_height)
        if x_bounds is not None:
            x.copy_(torch.minimum(torch.maximum(x, x_bounds[0]), x_bounds[1]))

    n, inner = int(steps.steps), int(steps.inner)
    check = 2 * inner
    last, done = None, 0
    for it in range(n):
        f, p, mismatch = corrected(x, y)
        obj = -p / p0 if t is None else mismatch - 0.1 * p / p0
        g = f / limit_int - 1.0
        penalty = (torch.clamp(lam + rho * g, min=0.0) ** 2 - lam ** 2).sum() / (2 * rho)
        loss = frame.weight * obj + penalty
        gx, gy = torch.autograd.grad(loss, (x, y))
        done = it + 1
        with torch.no_grad():
            step(adam, gx, gy, 1.0 - 0.9 * it / max(1, n))
            if (it + 1) % inner == 0:
                lam.copy_(torch.clamp(lam + rho * g.detach(), min=0.0))
            if (it + 1) % check == 0:
                now = float(obj)
                if last is not None and abs(now - last) < steps.settle and float(g.max()) <= 1e-3:
                    break
                last = now
    # restoration: the multipliers lag where the limit binds hard, and the model's peak still stood 2-4 % over the
    # internal limit after the steps (2,000 heliostats on Jülich's tilted receiver): the exact checks then failed
    # and the margin grew a round at a time. Steps on the excess alone, at a tenth of the step size, with moments
    # of their own (the objective's moments point along its gradient, not the excess's)
    restoring = _Adam((x, y), lr) if steps.restore else None
    for _ in range(int(steps.restore)):
        f, _, _ = corrected(x, y)
        excess = f / limit_int - 1.0
        if float(excess.detach().max()) <= 0.0:
            break
        gx, gy = torch.autograd.grad((torch.clamp(excess, min=0.0) ** 2).sum(), (x, y))
        done += 1
        with torch.no_grad():
            step(restoring, gx, gy, 0.1)
    with torch.no_grad():
        _, p, mismatch = corrected(x, y)
    predicted = float(p) / p0 if t is None else -math.sqrt(float(mismatch))
    return x.detach(), y.detach(), predicted, done
