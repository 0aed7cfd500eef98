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
from ..io.records import RecordTable, normalise_source

#: Fewest training records per heliostat a method accepts (below, the heliostat is skipped with a reason).
MIN_TRAIN = 4

#: Centroid source the rigid-body fits train on, where a record has it (the metric keeps ``--focal-spot``).
#: ``"UTIS"``, ``"HeliOS"``, ``"average"`` or ``None`` (= the metric's source). Chosen by validation that
#: never touches the test records (see docs in :func:`fit_spots`).
FIT_FOCAL_SPOT = "UTIS"

#: Robust loss of the Stone/Jülich LM fits (scipy ``least_squares`` loss, scale [rad] per residual).
LM_LOSS, LM_F_SCALE = "soft_l1", 1e-3


def fit_spots(batch: RecordTable, source: str | None = FIT_FOCAL_SPOT) -> RecordTable:
    """The batch with the centroids a fit trains on.

    Both camera systems measure the same spot; on the 11 PAINT heliostats, training on UTIS where a record
    has it (HeliOS elsewhere) extrapolated better to *later* records evaluated in HeliOS (median of the
    per-heliostat mean error on the records between the chronological train and test blocks: 1.14 vs
    1.22 mrad at N=30, 1.77 vs 1.85 at N=10; pseudo-splits inside the 30 training records could not
    separate the variants: 0.55 vs 0.53). ``average`` = mean of both where both exist.
    """
    if source is None or batch.spot_other is None or len(batch) == 0:
        return batch
    src = source if source == "average" else normalise_source(source)
    has = torch.isfinite(batch.spot_other).all(-1)
    if src == "average":
        new = torch.where(has.unsqueeze(-1), 0.5 * (batch.spot + batch.spot_other), batch.spot)
    else:
        use_other = has & torch.tensor([s != src for s in batch.source], dtype=torch.bool)
        new = torch.where(use_other.unsqueeze(-1), batch.spot_other, batch.spot)
    out = batch.subset(torch.arange(len(batch)))
    out.spot = new
    return out


def _ok(train: RecordTable, h: int) -> torch.Tensor:
    return train.counts() >= MIN_TRAIN if h else torch.zeros(0, dtype=torch.bool)


def stone8_field_fit(nominal: Kinematics, batch: RecordTable, usable: torch.Tensor, *, field_prior: bool = True,
                     loss: str = LM_LOSS, f_scale: float = LM_F_SCALE):
    """LM on the Stone/Jülich 8 with the field prior (nominal prior when the run is too small for one).

    The first (loose) pass is plain least squares; the final fit uses the robust ``loss`` (one bad centroid
    in 10-30 records otherwise tilts the whole fit: AC33's pseudo-validation error halves with it).

    Returns
    -------
    delta : torch.Tensor, [H, 8]
    prior : (mean [8], sigma [8]) or None
    """
    first, _ = fit_lm(nominal, batch, names=STONE8, prior_sigma=priors.LOOSE_SIGMA)
    fp = priors.field_prior(first, usable, STONE8) if field_prior else None
    if fp is None:
        from .lm import PRIOR_SIGMA

        delta, _ = fit_lm(nominal, batch, names=STONE8, prior_sigma=PRIOR_SIGMA, loss=loss, f_scale=f_scale)
        return delta, None
    delta, _ = fit_lm(nominal, batch, names=STONE8, prior_sigma=priors.LOOSE_SIGMA,
                      prior_mean=fp[0].expand_as(first).clone(), prior_sigma_vector=fp[1], loss=loss, f_scale=f_scale)
    return delta, fp


#: Bootstrap bags averaged by ``lm`` (0 = one fit on all records). Validation on later records that no run
#: trains or tests on (between the chronological train and test blocks): median of the per-heliostat mean
#: error 1.80 -> 1.34 mrad at N=10 and 1.15 -> 1.14 at N=30 with 10 bags (subsampling 80 %: 1.36 / 1.13).
LM_BAGS = 10


def bagged(fit_one, batch: RecordTable, bags: int, seed: int):
    """Average of ``fit_one(resampled batch)`` [H, P] over bootstrap resamples of every heliostat's records.

    Returns (mean delta, the first return value's extras of the full-data fit).
    """
    full, extra = fit_one(batch)
    if bags <= 0 or len(batch) == 0:
        return full, extra
    g = torch.Generator().manual_seed(int(seed))
    acc = torch.zeros_like(full)
    for _ in range(bags):
        idx = []
        for h in range(batch.num_heliostats):
            rows = batch.of(h)
            if len(rows):
                idx.append(rows[torch.randint(len(rows), (len(rows),), generator=g)])
        d, _ = fit_one(batch.subset(torch.cat(idx)))
        acc += d
    return acc / bags, extra


def fit_lm_method(nominal, train, validation, *, seed=0, progress=False, field_prior=True,
                  fit_focal_spot=FIT_FOCAL_SPOT, loss=LM_LOSS, f_scale=LM_F_SCALE, bags=LM_BAGS) -> Calibrated:
    """``lm``: the Stone/Jülich 8 by Levenberg-Marquardt on every record it may see (train + validation).

    LM has no iteration count to stop early, so the validation records are used for fitting too (they
    still count towards ``--train``; their error is reported as validation error = in-sample). Fitted on
    :data:`FIT_FOCAL_SPOT` centroids with the robust :data:`LM_LOSS`, averaged over :data:`LM_BAGS`
    bootstrap resamples (bagging: with 10 records one outlier or one unlucky sun position otherwise
    decides the extrapolation).
    """
    seen = RecordTable.concatenate([train, validation]) if validation is not None and len(validation) else train
    ok = seen.counts() >= MIN_TRAIN
    fit_on = fit_spots(seen.subset(ok[seen.heliostat_index]), fit_focal_spot)
    delta, fp = bagged(lambda b: stone8_field_fit(nominal, b, ok, field_prior=field_prior, loss=loss, f_scale=f_scale),
                       fit_on, bags, seed)
    delta[~ok] = 0.0
    extras = {"field_prior": None if fp is None else {"mean": fp[0].tolist(), "sigma": fp[1].tolist()},
              "summary": {"bags": bags, "fit_focal_spot": fit_focal_spot, "loss": loss}}
    return Calibrated("lm", list(train.heliostat_ids), nominal, STONE8, delta, ok, extras=extras)


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
        Field prior on the Stone/Jülich 8 where available, nominal prior on the rest.
    field_prior_fit : tuple or None
        The field prior (mean, sigma) of the Stone/Jülich 8, if one was fitted.
    """
    h = nominal.num_heliostats
    ok = train.counts() >= MIN_TRAIN
    tr = fit_spots(train.subset(ok[train.heliostat_index]), fit_focal_spot)
    va = validation.subset(ok[validation.heliostat_index]) if validation is not None else None
    d8, fp = stone8_field_fit(nominal, tr, ok, field_prior=field_prior)
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
    return ok, tr, va, init, mu, sig, fp


def fit_gradient_method(nominal, train, validation, *, seed=0, progress=False, field_prior=True,
                        names=GRADIENT_PARAMETERS, optimizer="lbfgs", iterations=25, refit=True,
                        fit_focal_spot=FIT_FOCAL_SPOT) -> Calibrated:
    """``gradient``: all deviations of the chain, pre-aligned by the Stone/Jülich LM fit, then LBFGS.

    Prior: the field prior on the Stone/Jülich 8 (they carry the field-wide systematic deviations), the
    nominal prior :data:`~heliotwin.calibrate.gradient.PRIOR_SIGMA` on the rest; early stopping on the
    validation records restores each heliostat's best state.
    """
    ok, tr, va, init, mu, sig, fp = prealign(nominal, train, validation, tuple(names), fit_focal_spot, field_prior)
    names = tuple(names)
    delta, info = fit_gradient(nominal, tr, va, names=names, prior_mean=mu, prior_sigma=sig, init=init,
                               optimizer=optimizer, iterations=iterations, progress=progress)
    if refit and va is not None and len(va):
        # Early stopping found each heliostat's best iteration on validation; refit on every record it may
        # see (train + validation) and stop each heliostat there. With 10 records, 2 more matter.
        seen = RecordTable.concatenate([tr, fit_spots(va, fit_focal_spot)])
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
