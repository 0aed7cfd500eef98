"""The calibration methods behind ``--method``, with one signature.

``METHODS[name](nominal, train, validation, *, seed, progress) -> Calibrated``: ``nominal`` has the run's H
heliostats, ``train``/``validation`` are batches over the same heliostat axis (validation carved out of
the ``--train`` records). Heliostats without training records come back with ``ok = False``.
"""
from __future__ import annotations

import torch

from ..errors import HeliotwinError
from ..field.plant import Kinematics
from . import priors
from .gradient import GRADIENT_PARAMETERS, PRIOR_SIGMA as GRADIENT_SIGMA, fit_gradient
from .lm import fit_lm
from .model import Calibrated
from .params import STONE8, kinds
from .records import RecordBatch

#: Fewest training records per heliostat a method accepts (below, the heliostat is skipped with a reason).
MIN_TRAIN = 4


def _ok(train: RecordBatch, h: int) -> torch.Tensor:
    return train.counts() >= MIN_TRAIN if h else torch.zeros(0, dtype=torch.bool)


def stone8_field_fit(nominal: Kinematics, batch: RecordBatch, usable: torch.Tensor, *, field_prior: bool = True):
    """LM on the Stone/Jülich 8 with the field prior (nominal prior when the run is too small for one).

    Returns
    -------
    delta : torch.Tensor, [H, 8]
    prior : (mean [8], sigma [8]) or None
    """
    first, _ = fit_lm(nominal, batch, names=STONE8, prior_sigma=priors.LOOSE_SIGMA)
    fp = priors.field_prior(first, usable, STONE8) if field_prior else None
    if fp is None:
        from .lm import PRIOR_SIGMA

        delta, _ = fit_lm(nominal, batch, names=STONE8, prior_sigma=PRIOR_SIGMA)
        return delta, None
    delta, _ = fit_lm(nominal, batch, names=STONE8, prior_sigma=priors.LOOSE_SIGMA,
                      prior_mean=fp[0].expand_as(first).clone(), prior_sigma_vector=fp[1])
    return delta, fp


def fit_lm_method(nominal, train, validation, *, seed=0, progress=False, field_prior=True) -> Calibrated:
    """``lm``: the Stone/Jülich 8 by Levenberg-Marquardt on every record it may see (train + validation).

    LM has no iteration count to stop early, so the validation records are used for fitting too (they
    still count towards ``--train``; their error is reported as validation error = in-sample).
    """
    h = nominal.num_heliostats
    seen = RecordBatch.concatenate([train, validation]) if validation is not None and len(validation) else train
    ok = seen.counts() >= MIN_TRAIN
    fit_on = seen.subset(ok[seen.heliostat_index])
    delta, fp = stone8_field_fit(nominal, fit_on, ok, field_prior=field_prior)
    delta[~ok] = 0.0
    extras = {"field_prior": None if fp is None else {"mean": fp[0].tolist(), "sigma": fp[1].tolist()}}
    return Calibrated("lm", list(train.heliostat_ids), nominal, STONE8, delta, ok, extras=extras)


def fit_gradient_method(nominal, train, validation, *, seed=0, progress=False, field_prior=True,
                        names=GRADIENT_PARAMETERS, optimizer="lbfgs", iterations=25, refit=True) -> Calibrated:
    """``gradient``: all deviations of the chain, pre-aligned by the Stone/Jülich LM fit, then LBFGS.

    Prior: the field prior on the Stone/Jülich 8 (they carry the field-wide systematic deviations), the
    nominal prior :data:`~heliotwin.calibrate.gradient.PRIOR_SIGMA` on the rest; early stopping on the
    validation records restores each heliostat's best state.
    """
    h = nominal.num_heliostats
    ok = train.counts() >= MIN_TRAIN
    tr = train.subset(ok[train.heliostat_index])
    va = validation.subset(ok[validation.heliostat_index]) if validation is not None else None
    d8, fp = stone8_field_fit(nominal, tr, ok, field_prior=field_prior)
    names = tuple(names)
    p = len(names)
    mu = torch.zeros(p, dtype=torch.float64)
    sig = torch.tensor([GRADIENT_SIGMA[k] for k in kinds(names)], dtype=torch.float64)
    init = torch.zeros(h, p, dtype=torch.float64)
    for j, n in enumerate(STONE8):
        if n in names:
            i = names.index(n)
            init[:, i] = d8[:, j]
            if fp is not None:
                mu[i], sig[i] = fp[0][j], fp[1][j]
    delta, info = fit_gradient(nominal, tr, va, names=names, prior_mean=mu, prior_sigma=sig, init=init,
                               optimizer=optimizer, iterations=iterations, progress=progress)
    if refit and va is not None and len(va):
        # Early stopping found each heliostat's best iteration on validation; refit on every record it may
        # see (train + validation) and stop each heliostat there. With 10 records, 2 more matter.
        seen = RecordBatch.concatenate([tr, va])
        d8, _ = stone8_field_fit(nominal, seen, ok, field_prior=field_prior)
        for j, n in enumerate(STONE8):
            if n in names:
                init[:, names.index(n)] = d8[:, j]
        stop = torch.tensor(info["best_iteration"], dtype=torch.long)
        delta, _ = fit_gradient(nominal, seen, None, names=names, prior_mean=mu, prior_sigma=sig, init=init,
                                optimizer=optimizer, iterations=max(1, int(stop.max())), progress=progress,
                                stop_at=stop)
    delta[~ok] = 0.0
    extras = {"best_iteration": info["best_iteration"], "history": info["history"],
              "field_prior": None if fp is None else {"mean": fp[0].tolist(), "sigma": fp[1].tolist()}}
    return Calibrated("gradient", list(train.heliostat_ids), nominal, names, delta, ok, extras=extras)


def _lazy(module: str, attr: str):
    def call(*args, **kwargs):
        import importlib

        return getattr(importlib.import_module(f"heliotwin.calibrate.{module}"), attr)(*args, **kwargs)

    return call


METHODS = {
    "lm": fit_lm_method,
    "gradient": fit_gradient_method,
    "hybrid": _lazy("hybrid", "fit_hybrid_method"),
    "mlp": _lazy("mlp", "fit_mlp_method"),
    "images": _lazy("images", "fit_images_method"),
}


def get_method(name: str):
    """The fit function of a method (one-line error listing the known ones)."""
    if name not in METHODS:
        raise HeliotwinError(f"unknown calibration method {name!r}; known: {', '.join(METHODS)}")
    return METHODS[name]
