"""``hybrid``: rigid body with static parameters plus deviations predicted by a small SELU network.

Per record, the deviations are ``delta_static + scale * net(features)`` where

* ``delta_static`` is the pre-aligned rigid body (the ``lm`` Stone/Jülich fit with the field prior, on the
  training records only, so that validation stays honest);
* ``features`` (7): motor steps normalised to the actuator range and encoded as sin/cos (4), the age
  (time since the heliostat's first training record over the span of its training records, clamped to
  [0, 1]: a record after the last training record is treated like the last one -- no extrapolation in
  wear) and the month as sin/cos (season; bounded by construction);
* ``scale`` makes one network unit ~ 10 mrad for angles/tilts, 1 m for translations, 1 % for increments;
* the network is 14 hidden layers x 2 neurons (as published; ``depth``/``hidden`` configurable), SELU, its
  output layer starts at zero (the hybrid starts exactly at its rigid body), trained with Adam and weight
  decay, early-stopped on validation.

Fallback: a heliostat keeps its network only when, on its validation records (the latest of the ``--train``
records in a chronological run), the network beats its own pre-aligned rigid body *significantly*: at
least :data:`MIN_VALIDATION` records, a mean gain of at least ``1 - FALLBACK_MARGIN`` (10 %) of the rigid
body's error, and a paired gain larger than :data:`SIGNIFICANCE` standard errors (per-record errors,
rigid minus hybrid). Otherwise it uses the rigid body alone (exactly ``lm`` on train + validation);
the report says which did and why.
"""
from __future__ import annotations

import math
import time

import torch

from ...field import kinematics as K
from ...io.records import RecordTable
from .. import metrics
from ..fitloop import early_stopping_fit, net_state
from ..inputs import FIT_FOCAL_SPOT, fit_spots, restrict, trainable
from ..model import Calibrated
from ..params import STONE8, apply_deviations, kinds
from .lm import fit_lm_method, stone8_field_fit, stone8_plant_fit
from .nets import BatchedMLP

#: Physical size of one network output unit per kind (see module docstring).
OUTPUT_SCALE = {"angle": 0.01, "tilt": 0.01, "translation": 1.0, "actuator_length": 1.0, "increment": 0.01}
SECONDS_PER_YEAR = 365.25 * 86400.0
FALLBACK_MARGIN = 0.9
#: Fewest validation records to trust a gain at all, and the paired-gain significance (standard errors).
#: With 4 (isolation 20 + 20 on PAINT) the two networks that passed lost 0.06-0.3 mrad on test: 4 records
#: do not even estimate the gain's standard error.
MIN_VALIDATION = 6
SIGNIFICANCE = 2.0


def features(batch: RecordTable, kin, t0: torch.Tensor, span: torch.Tensor | None = None) -> torch.Tensor:
    """Network inputs [R, 7] (see module docstring).

    ``t0`` [H] = first training time per heliostat [s]; ``span`` [H] = span of the training times [s] (age
    is ``(t - t0) / span`` clamped to [0, 1]; default one year).
    """
    k = kin.index(batch.heliostat_index)
    s = (batch.motor_steps - k.min_steps) / (k.max_steps - k.min_steps)
    enc = torch.cat([torch.sin(math.pi * s), torch.cos(math.pi * s)], -1)
    t = batch.time
    known = torch.isfinite(t)
    sp = torch.full_like(t0, SECONDS_PER_YEAR) if span is None else span.clamp_min(86400.0)
    age = torch.where(known, ((t - t0[batch.heliostat_index]) / sp[batch.heliostat_index]).clamp(0.0, 1.0),
                      torch.zeros_like(t))
    month = torch.where(known, torch.remainder(t / (SECONDS_PER_YEAR / 12.0), 12.0), torch.zeros_like(t))
    season = torch.stack([torch.sin(2 * math.pi * month / 12), torch.cos(2 * math.pi * month / 12)], -1)
    season = torch.where(known.unsqueeze(-1), season, torch.zeros_like(season))
    return torch.cat([enc, age.unsqueeze(-1), season], -1)


class HybridModel(Calibrated):
    """Calibrated hybrid: static deviations plus network deviations per record."""

    def normals(self, batch: RecordTable):
        """Model mirror normals of ``batch``'s R records with the network's deviations added where it is kept:
        ``(normals (R, 3) unit ENU, centroids (R, 3) [m])`` as :func:`heliotwin.calibrate.metrics.model_normals`."""
        net, scale, t0 = self.extras["net"], self.extras["scale"], self.extras["t0"]
        use, span = self.extras["use_net"], self.extras.get("span")
        with torch.no_grad():
            x = features(batch, self.nominal, t0, span)
            d = self.delta[batch.heliostat_index] + scale * net(x, batch.heliostat_index) \
                * use[batch.heliostat_index].unsqueeze(-1).to(scale)
            k = apply_deviations(self.nominal.index(batch.heliostat_index), d, self.names)
            return metrics.model_normals(k, batch, per_record=True)


def training_times(train: RecordTable, h: int) -> tuple[torch.Tensor, torch.Tensor]:
    """First training time ``t0`` [H] [s] and span of the training times [H] [s] (>= 1 day; a year without).

    Heliostats without a timed training record get ``t0 = 0`` and a span of one year.
    """
    like = train.spot
    t0 = like.new_zeros(h)
    span = like.new_full((h,), SECONDS_PER_YEAR)
    for i in range(h):
        t = train.time[(train.heliostat_index == i) & torch.isfinite(train.time)]
        t0[i] = t.min() if len(t) else 0.0
        if len(t) > 1:
            span[i] = (t.max() - t.min()).clamp_min(86400.0)
    return t0, span


class _HybridFit:
    """The hybrid's deviations per record: ``static + scale * net(features)`` on a fixed record batch."""

    def __init__(self, nominal, static, names, scale, t0, span, batch: RecordTable):
        self.nominal, self.static, self.names, self.scale, self.batch = nominal, static, names, scale, batch
        self.x = features(batch, nominal, t0, span) if len(batch) else None
        self.kin = nominal.index(batch.heliostat_index)

    def deltas(self, net) -> torch.Tensor:
        """[R, P]; ``net=None`` = the rigid body alone."""
        d = self.static[self.batch.heliostat_index]
        return d if net is None else d + self.scale * net(self.x, self.batch.heliostat_index)

    def residuals(self, net) -> torch.Tensor:
        """Model minus measured normal [R, 3]."""
        return metrics.normal_residuals(apply_deviations(self.kin, self.deltas(net), self.names), self.batch,
                                        per_record=True)

    def errors(self, net) -> torch.Tensor:
        """Pointing error per record [rad], [R] (no gradient)."""
        with torch.no_grad():
            return metrics.pointing_error(apply_deviations(self.kin, self.deltas(net), self.names), self.batch,
                                          per_record=True)


def _fallback(fit_va: _HybridFit, best, best_err, rigid_val, ok) -> tuple[torch.Tensor, dict]:
    """Which heliostats keep their network ``best`` (see module docstring), and why the others do not.

    ``best_err``/``rigid_val``: validation error per heliostat [H] of the network and of the rigid body.
    """
    h, va = len(ok), fit_va.batch
    use_net = torch.zeros(h, dtype=torch.bool, device=ok.device)
    why = {}
    if not len(va):
        return use_net, why
    gain = fit_va.errors(None) - fit_va.errors(best)  # per record, rigid minus hybrid
    for i in range(h):
        g = gain[va.heliostat_index == i]
        n = len(g)
        if n < MIN_VALIDATION:
            why[i] = f"{n} validation records < {MIN_VALIDATION}"
            continue
        se = float(g.std()) / math.sqrt(n) if n > 1 else math.inf
        m = float(g.mean())
        if not best_err[i] < FALLBACK_MARGIN * rigid_val[i]:
            why[i] = "validation gain below 10 %"
        elif not m > SIGNIFICANCE * se:
            why[i] = f"validation gain {m * 1e3:.2f} mrad not significant (< {SIGNIFICANCE} x {se * 1e3:.2f})"
        else:
            use_net[i] = True
    return use_net, why


def _mrad(x) -> float | None:
    return float(x) * 1e3 if math.isfinite(x) else None


def fit_hybrid_method(nominal, train, validation, *, seed=0, progress=False, field_prior=True, depth=14, hidden=2,
                      steps=400, lr=3e-3, weight_decay=1e-3, noise=1e-3, fit_focal_spot=FIT_FOCAL_SPOT,
                      plant_prior=None) -> HybridModel:
    """``hybrid``: the pre-aligned rigid body plus a small network per heliostat (see module docstring).

    ``plant_prior`` (:class:`~heliotwin.calibrate.priors.PlantPrior`): the pre-alignment's prior instead of
    the run's field prior. The network follows the nominal kinematics' dtype and device; every random draw
    takes ``seed``.
    """
    def prealign(batch):
        if plant_prior is not None:
            return stone8_plant_fit(nominal, batch, plant_prior), None
        return stone8_field_fit(nominal, batch, ok, field_prior=field_prior)

    h = nominal.num_heliostats
    ok = trainable(train)
    tr = fit_spots(restrict(train, ok), fit_focal_spot)
    va = restrict(validation, ok) if validation is not None else train.subset([])  # never None below
    static, _ = prealign(tr)
    names = STONE8
    like = nominal.position
    static = static.to(like)
    scale = torch.tensor([OUTPUT_SCALE[k] for k in kinds(names)], dtype=like.dtype, device=like.device)
    t0, span = training_times(tr, h)
    gen = torch.Generator().manual_seed(int(seed))
    net = BatchedMLP(h, 7, len(names), hidden, depth, gen, zero_output=True, dtype=like.dtype).to(like.device)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    fit_tr = _HybridFit(nominal, static, names, scale, t0, span, tr)
    fit_va = _HybridFit(nominal, static, names, scale, t0, span, va)

    def step():
        opt.zero_grad()
        r = fit_tr.residuals(net)
        loss = (r * r).sum() / noise ** 2 + weight_decay * net.weight_norm().sum()
        loss.backward()
        opt.step()
        return loss

    def val_err(model_net=net):
        if not len(va):
            return like.new_full((h,), float("inf"))
        return metrics.per_heliostat_mean(fit_va.errors(model_net), va.heliostat_index, h)

    rigid_val = val_err(None)
    # The network starts with a zero output layer: the loop's start is exactly the rigid body.
    log = early_stopping_fit(step, val_err, net_state(net), steps, validated=va.counts() > 0, check_every=10,
                             progress=progress, desc="hybrid")
    best, best_err = log.best, log.best_error
    # Fallback unless the net beats its own rigid body on validation by a clear (10 %) AND significant
    # paired gain on enough records: a gain on 2-6 records is mostly noise, and the net extrapolates in time.
    use_net, why = _fallback(fit_va, best, best_err, rigid_val, ok)
    # Fallback heliostats: exactly lm on every record they may see (bagged: at 20 records an unbagged refit
    # alone is ~0.2 mrad worse than lm, which would make the hybrid lose where its network is not even used).
    refit = fit_lm_method(nominal, train, validation, seed=seed, plant_prior=plant_prior, field_prior=field_prior,
                          fit_focal_spot=fit_focal_spot).delta
    static = torch.where(use_net.unsqueeze(-1), static, refit.to(static))
    static[~ok] = 0.0
    ids = list(train.heliostat_ids)
    per_h = {hid: {"uses_network": bool(use_net[i]), "fallback_reason": why.get(i),
                   "rigid_validation_mrad": _mrad(rigid_val[i]), "hybrid_validation_mrad": _mrad(best_err[i])}
             for i, hid in enumerate(ids) if bool(ok[i])}
    networks = {hid: {"config": dict(best.config, kind="hybrid", names=list(names), scale=scale.tolist(),
                                     t0=float(t0[i]), span=float(span[i]), use_net=bool(use_net[i])),
                      "state": best.state_of(i)} for i, hid in enumerate(ids) if bool(ok[i])}
    extras = {"net": best, "scale": scale, "t0": t0, "span": span, "use_net": use_net, "per_heliostat": per_h,
              "networks": networks,
              "summary": {"heliostats_using_network": int((use_net & ok).sum()), "depth": depth, "hidden": hidden}}
    return HybridModel("hybrid", ids, nominal, names, static, ok, extras=extras)


def aim_hybrid(net_entry: dict, kin, sun: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Motor steps for one heliostat with its hybrid network: fixed point over steps -> deviations -> inverse.

    ``kin`` is the static calibrated kinematics (1 heliostat); network deviations are added on top. ``sun``:
    (3,) unit vector towards the sun, ENU; ``target``: (3,) aim point [m], ENU. Returns the motor steps (1, 2)
    [increments].
    """
    cfg = net_entry["config"]
    steps, _ = K.inverse(kin, target, sun, strict=False)
    if not cfg.get("use_net"):
        return steps
    net = BatchedMLP.from_state(cfg, net_entry["state"])
    scale = torch.tensor(cfg["scale"], dtype=torch.float64)
    now = time.time()
    z = torch.zeros(1, dtype=torch.float64)
    for _ in range(5):
        b = RecordTable(["h"], torch.zeros(1, dtype=torch.long), torch.zeros(1, dtype=torch.long), z, z,
                        sun.reshape(1, 3), steps.reshape(1, 2), target.reshape(1, 3), target.reshape(1, 3),
                        target.reshape(1, 3),
                        target.reshape(1, 3), target.reshape(1, 3), torch.tensor([now], dtype=torch.float64),
                        torch.zeros(1, 5, dtype=torch.float64))
        with torch.no_grad():
            d = scale * net(features(b, kin, torch.tensor([cfg["t0"]], dtype=torch.float64),
                                     torch.tensor([cfg.get("span", SECONDS_PER_YEAR)], dtype=torch.float64)),
                            b.heliostat_index)
        k = apply_deviations(kin, d, cfg["names"])
        steps, _ = K.inverse(k, target, sun, strict=False)
    return steps
