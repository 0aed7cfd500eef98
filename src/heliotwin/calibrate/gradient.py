"""``gradient``: every deviation of the rigid-body chain, learned by gradient descent (LBFGS or Adam).

Parameters (default :data:`GRADIENT_PARAMETERS`, 26 of the 28 in :mod:`~heliotwin.calibrate.params`: the
two tilts of a joint about its own axis are invisible) are learned for all heliostats at once: the loss
is a sum of independent per-heliostat terms, so one optimiser over the [H, P] tensor equals H separate
fits. The loss is the negative log posterior

    sum_records |n_model - n_measured|^2 / noise^2 + sum_params ((delta - mean) / sigma)^2

(Gaussian prior towards nominal, scaled per parameter type, or the field prior of
:mod:`~heliotwin.calibrate.priors`). Bounds: a box per parameter type plus a barrier that keeps every
linear actuator's law of cosines valid over its whole motor range; a step that still leaves a heliostat
invalid is undone for that heliostat. Early stopping: the validation error of every heliostat is
evaluated every ``check_every`` iterations and the best state per heliostat is restored at the end.
"""
from __future__ import annotations

import math

import torch

from ..field.plant import Kinematics
from . import metrics
from .params import ALL, REDUNDANT, actuator_margin, apply_deviations, check_names, kinds, units
from ..io.records import RecordTable

#: The learnable deviations of the chain (all but the two invisible ones).
GRADIENT_PARAMETERS = tuple(n for n in ALL if n not in REDUNDANT)

#: Prior sigma per kind towards nominal (physical units) when no field prior is available.
PRIOR_SIGMA = {"angle": 0.02, "tilt": 0.03, "increment": 5e-3, "translation": 0.02, "actuator_length": 2e-3}

#: Box bounds per kind (physical units): far outside any real deviation, they only stop runaways.
BOUNDS = {"angle": 0.5, "tilt": 0.2, "increment": 0.2, "translation": 0.5, "actuator_length": 0.05}

#: Smallest law-of-cosines margin [m] the barrier defends (1 mm of stroke).
MIN_MARGIN = 1e-3


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
        from ..errors import HeliotwinError

        raise HeliotwinError(f"unknown optimizer {optimizer!r}; known: lbfgs, adam")

    def closure():
        opt.zero_grad()
        loss = objective(x)
        loss.backward()
        return loss

    return opt, closure



def prior_and_start(names, num_heliostats: int, prior_sigma, prior_mean=None, init=None):
    """Scaled parameters of a bounded, prior-regularised fit (shared by ``gradient`` and ``images``).

    Parameters
    ----------
    names : list of str
        Deviation parameter names (checked).
    num_heliostats : int
        H.
    prior_sigma : dict kind -> sigma, or tensor [P] / [H, P]
        Prior standard deviations in physical units (``inf`` or a missing kind: no prior).
    prior_mean, init : torch.Tensor, [H, P], optional
        Prior mean (default 0) and start (default the prior mean), physical units.

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
    unit = units(names)
    kk = kinds(names)
    if isinstance(prior_sigma, dict):
        sig = torch.tensor([float(prior_sigma.get(k, float("inf"))) for k in kk], dtype=torch.float64)
    else:
        sig = torch.as_tensor(prior_sigma, dtype=torch.float64)
    sig = sig.expand(h, p)
    inv_sig = torch.where(torch.isfinite(sig), 1.0 / sig, torch.zeros_like(sig))
    mu = torch.zeros(h, p, dtype=torch.float64) if prior_mean is None else \
        torch.as_tensor(prior_mean, dtype=torch.float64).expand(h, p)
    bound = torch.tensor([BOUNDS[k] for k in kk], dtype=torch.float64) / unit
    x = ((mu if init is None else init.detach().double()) / unit).clamp(-bound, bound).clone().requires_grad_(True)
    return unit, mu, inv_sig, bound, x

def fit_gradient(nominal: Kinematics, train: RecordTable, validation: RecordTable | None = None, *,
                 names=GRADIENT_PARAMETERS, prior_mean: torch.Tensor | None = None,
                 prior_sigma: torch.Tensor | dict | None = None, noise: float = 1e-3, optimizer: str = "lbfgs",
                 iterations: int = 60, lr: float = 0.05, check_every: int = 5, init: torch.Tensor | None = None,
                 progress: bool = False, stop_at: torch.Tensor | None = None) -> tuple[torch.Tensor, dict]:
    """Learn deviations by gradient descent with a prior, bounds and early stopping.

    Parameters
    ----------
    nominal : Kinematics
        H heliostats.
    train, validation : RecordTable
        Records over the same H heliostats; ``validation`` may be None or empty (then the last state is kept).
    names : sequence of str
        Parameters to learn.
    prior_mean : torch.Tensor, [H, P] or [P], optional
        Prior centre (physical units); default nominal (0).
    prior_sigma : torch.Tensor [P] or [H, P], or dict per kind, optional
        Prior sigma; default :data:`PRIOR_SIGMA`.
    noise : float
        Per-record pointing noise [rad] the prior is weighed against.
    optimizer : ``"lbfgs"`` or ``"adam"``
    iterations : int
        LBFGS outer iterations (each up to 20 function evaluations) or Adam steps.
    lr : float
        Step size in natural units (Adam) or LBFGS initial step.
    init : torch.Tensor, [H, P], optional
        Starting deviations (e.g. an LM pre-alignment); default the prior mean.
    stop_at : torch.Tensor, [H], long, optional
        Refit mode (no validation): keep each heliostat's state at this iteration (a multiple of
        ``check_every``, 0 = the start), e.g. the best iteration found on validation in a first pass.

    Returns
    -------
    delta : torch.Tensor, [H, P]
        Best state per heliostat (physical units).
    info : dict
        ``best_iteration`` [H], ``history`` of (iteration, median validation error [mrad]).
    """
    names = check_names(names)
    h = nominal.num_heliostats
    unit, mu, inv_sig, bound, x = prior_and_start(names, h, PRIOR_SIGMA if prior_sigma is None else prior_sigma,
                                                  prior_mean, init)
    kin_tr = nominal.index(train.heliostat_index)
    hidx = train.heliostat_index
    has_val = validation is not None and len(validation) > 0
    counts_val = validation.counts() if has_val else torch.zeros(h, dtype=torch.long)

    def objective(xx):
        delta = xx * unit
        r = metrics.normal_residuals(apply_deviations(kin_tr, delta[hidx], names), train, per_record=True)
        data = (r * r).sum() / noise ** 2
        prior = (((delta - mu) * inv_sig) ** 2).sum()
        margin = actuator_margin(apply_deviations(nominal, delta, names))
        barrier = (torch.relu(MIN_MARGIN - margin) / MIN_MARGIN).pow(2).sum() * 1e4
        return data + prior + barrier

    def val_error():
        with torch.no_grad():
            if not has_val:
                return torch.full((h,), math.inf, dtype=torch.float64)
            k = apply_deviations(nominal, x.detach() * unit, names)
            e = metrics.pointing_error(k, validation)
            s = torch.zeros(h, dtype=torch.float64).index_add_(0, validation.heliostat_index, e)
            return torch.where(counts_val > 0, s / counts_val.clamp_min(1), torch.full_like(s, math.inf))

    opt, closure = make_optimizer(x, objective, optimizer, lr)

    best = x.detach().clone()
    best_err = val_error()
    best_it = torch.zeros(h, dtype=torch.long)
    history = [(0, float(best_err[torch.isfinite(best_err)].median()) * 1e3 if torch.isfinite(best_err).any() else None)]
    last_valid = x.detach().clone()
    iterator = range(1, iterations + 1)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc="gradient", leave=False)
    for it in iterator:
        opt.step(closure)
        with torch.no_grad():
            x.data = torch.maximum(torch.minimum(x.data, bound), -bound)
            ok = (actuator_margin(apply_deviations(nominal, x * unit, names)) > 0).all(-1)
            # A heliostat whose actuator triangle broke goes back to its last valid state.
            x.data[~ok] = last_valid[~ok]
            last_valid = x.detach().clone()
            if not torch.isfinite(x).all():
                bad = ~torch.isfinite(x).all(-1)
                x.data[bad] = best[bad]
        if it % check_every == 0 or it == iterations:
            err = val_error()
            better = err < best_err
            if not has_val:
                better = torch.ones(h, dtype=torch.bool) if stop_at is None else (stop_at >= it)
            best[better] = x.detach()[better]
            best_err = torch.where(better, err, best_err)
            best_it[better] = it
            fin = torch.isfinite(err)
            history.append((it, float(err[fin].median()) * 1e3 if fin.any() else None))
    # Heliostats without validation records keep the final (MAP) state (or their stop_at state).
    no_val = counts_val == 0
    if stop_at is None:
        best[no_val] = x.detach()[no_val]
    return best * unit, {"best_iteration": best_it.tolist(), "history": history}
