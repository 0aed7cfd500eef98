"""``gradient``: every deviation of the rigid-body chain, learned by gradient descent (LBFGS or Adam).

Parameters (default :data:`GRADIENT_PARAMETERS`, 26 of the 28 in :mod:`~heliotwin.calibrate.params`: the
two tilts of a joint about its own axis are invisible) are learned for all heliostats at once: the loss
is a sum of independent per-heliostat terms, so one optimiser over the [H, P] tensor equals H separate
fits. The loss is the negative log posterior

    sum_records |n_model - n_measured|^2 / noise^2 + sum_params ((delta - mean) / sigma)^2

(Gaussian prior towards nominal, scaled per parameter type, or the field prior of
:mod:`~heliotwin.calibrate.priors`) plus the actuator barrier. Bounds, validity restore and the
per-heliostat early stopping on the validation records are the shared loop of
:mod:`~heliotwin.calibrate.fitloop`.
"""
from __future__ import annotations

import torch

from ...field.plant import Kinematics
from ...io.records import RecordTable
from .. import metrics, priors
from ..fitloop import (
    actuator_barrier,
    box_and_validity,
    early_stopping_fit,
    make_optimizer,
    prior_and_start,
    tensor_state,
)
from ..inputs import FIT_FOCAL_SPOT, fit_spots, restrict, trainable
from ..model import Calibrated
from ..params import ALL, REDUNDANT, STONE8, actuators_valid, apply_deviations, check_names, kinds
from .lm import field_prior_extras, stone8_field_fit

#: The learnable deviations of the chain (all but the two invisible ones).
GRADIENT_PARAMETERS = tuple(n for n in ALL if n not in REDUNDANT)


def fit_gradient(nominal: Kinematics, train: RecordTable, validation: RecordTable | None = None, *,
                 names=GRADIENT_PARAMETERS, prior_mean: torch.Tensor | None = None,
                 prior_sigma: torch.Tensor | dict | None = None, noise: float = 1e-3, optimizer: str = "lbfgs",
                 iterations: int = 60, lr: float = 0.05, check_every: int = 5, init: torch.Tensor | None = None,
                 progress: bool = False, stop_at: torch.Tensor | None = None) -> tuple[torch.Tensor, dict]:
    """Learn deviations by gradient descent with a prior, bounds and early stopping.

    Parameters
    ----------
    nominal : Kinematics
        H heliostats; the fit follows its dtype and device.
    train, validation : RecordTable
        Records over the same H heliostats; ``validation`` may be None or empty (then the last state is kept).
    names : sequence of str
        Parameters to learn.
    prior_mean : torch.Tensor, [H, P] or [P], optional
        Prior centre (physical units); default nominal (0).
    prior_sigma : torch.Tensor [P] or [H, P], or dict per kind, optional
        Prior sigma (physical units: [rad] for angles and tilts, [m] for lengths, [1] for relative
        increments); default :data:`~heliotwin.calibrate.priors.CHAIN_SIGMA`.
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
    sigma = priors.CHAIN_SIGMA if prior_sigma is None else prior_sigma
    unit, mu, inv_sig, bound, x = prior_and_start(names, h, sigma, prior_mean, init, like=nominal.position)
    kin_tr = nominal.index(train.heliostat_index)
    hidx = train.heliostat_index
    has_val = validation is not None and len(validation) > 0

    def objective(xx):
        delta = xx * unit
        r = metrics.normal_residuals(apply_deviations(kin_tr, delta[hidx], names), train, per_record=True)
        data = (r * r).sum() / noise ** 2
        prior = (((delta - mu) * inv_sig) ** 2).sum()
        return data + prior + actuator_barrier(apply_deviations(nominal, delta, names))

    def val_error():
        with torch.no_grad():
            if not has_val:
                return torch.full((h,), float("inf"), dtype=x.dtype, device=x.device)
            e = metrics.pointing_error(apply_deviations(nominal, x.detach() * unit, names), validation)
            return metrics.per_heliostat_mean(e, validation.heliostat_index, h)

    opt, closure = make_optimizer(x, objective, optimizer, lr)
    validated = validation.counts() > 0 if has_val else torch.zeros(h, dtype=torch.bool, device=x.device)
    log = early_stopping_fit(lambda: opt.step(closure), val_error, tensor_state(x), iterations,
                             validated=validated, check_every=check_every, stop_at=stop_at, progress=progress,
                             desc="gradient",
                             project=box_and_validity(x, bound, lambda xx: actuators_valid(
                                 apply_deviations(nominal, xx * unit, names))))
    return log.best * unit, {"best_iteration": log.best_iteration.tolist(), "history": log.history}


def prealign(nominal, train, validation, names, fit_focal_spot, field_prior):
    """Shared start of the chain methods: Stone/Jülich LM pre-alignment and the prior of every parameter.

    Parameters
    ----------
    names : tuple of str
        Parameters the method learns (see :mod:`heliotwin.calibrate.params`).

    Returns
    -------
    ok : torch.Tensor of bool, [H]
        Heliostats with enough training records.
    train, validation : RecordTable
        Restricted to ``ok`` heliostats, training spots from ``fit_focal_spot``.
    init : torch.Tensor, [H, P]
        Initial deviations (the Stone/Jülich fit on its 8 parameters, 0 elsewhere) [parameter units].
    prior_mean, prior_sigma : torch.Tensor, [P]
        Field prior on the Stone/Jülich 8 where available, :data:`~heliotwin.calibrate.priors.CHAIN_SIGMA`
        on the rest (physical units: [rad] for angles and tilts, [m] for lengths, [1] for relative increments).
    field_prior_fit : tuple or None
        The field prior (mean, sigma) of the Stone/Jülich 8, if one was fitted.
    """
    ok = trainable(train)
    tr = fit_spots(restrict(train, ok), fit_focal_spot)
    va = restrict(validation, ok)
    d8, fp = stone8_field_fit(nominal, tr, ok, field_prior=field_prior)
    fk = dict(dtype=nominal.position.dtype, device=nominal.position.device)
    mu = torch.zeros(len(names), **fk)
    sig = torch.tensor([priors.CHAIN_SIGMA[k] for k in kinds(names)], **fk)
    init = _with_stone8(torch.zeros(nominal.num_heliostats, len(names), **fk), d8, names)
    if fp is not None:
        for j, n in enumerate(STONE8):
            if n in names:
                mu[names.index(n)], sig[names.index(n)] = fp[0][j], fp[1][j]
    return ok, tr, va, init, mu, sig, fp


def _with_stone8(init: torch.Tensor, d8: torch.Tensor, names) -> torch.Tensor:
    """``init`` [H, P] with the Stone/Jülich columns set from ``d8`` [H, 8] (in place; returned)."""
    for j, n in enumerate(STONE8):
        if n in names:
            init[:, names.index(n)] = d8[:, j].to(init)
    return init


def fit_gradient_method(nominal, train, validation, *, seed=0, progress=False, field_prior=True,
                        names=GRADIENT_PARAMETERS, optimizer="lbfgs", iterations=25, refit=True,
                        fit_focal_spot=FIT_FOCAL_SPOT) -> Calibrated:
    """``gradient``: all deviations of the chain, pre-aligned by the Stone/Jülich LM fit, then LBFGS.

    Prior: the field prior on the Stone/Jülich 8 (they carry the field-wide systematic deviations), the
    nominal prior :data:`~heliotwin.calibrate.priors.CHAIN_SIGMA` on the rest; early stopping on the
    validation records restores each heliostat's best state.
    """
    names = tuple(names)
    ok, tr, va, init, mu, sig, fp = prealign(nominal, train, validation, names, fit_focal_spot, field_prior)
    delta, info = fit_gradient(nominal, tr, va, names=names, prior_mean=mu, prior_sigma=sig, init=init,
                               optimizer=optimizer, iterations=iterations, progress=progress)
    if refit and va is not None and len(va):
        # Early stopping found each heliostat's best iteration on validation; refit on every record it may
        # see (train + validation) and stop each heliostat there. With 10 records, 2 more matter.
        seen = RecordTable.concatenate([tr, fit_spots(va, fit_focal_spot)])
        d8, _ = stone8_field_fit(nominal, seen, ok, field_prior=field_prior)
        stop = torch.tensor(info["best_iteration"], dtype=torch.long, device=init.device)
        delta, _ = fit_gradient(nominal, seen, None, names=names, prior_mean=mu, prior_sigma=sig,
                                init=_with_stone8(init, d8, names), optimizer=optimizer,
                                iterations=max(1, int(stop.max())), progress=progress, stop_at=stop)
    delta[~ok] = 0.0
    extras = {"best_iteration": info["best_iteration"], "history": info["history"],
              "field_prior": field_prior_extras(fp)}
    return Calibrated("gradient", list(train.heliostat_ids), nominal, names, delta, ok, extras=extras)
