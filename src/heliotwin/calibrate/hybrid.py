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
rigid minus hybrid). Otherwise it uses the rigid body alone (refitted on train + validation like ``lm``);
the report says which did and why.
"""
from __future__ import annotations

import math

import torch

from . import metrics
from .methods import FIT_FOCAL_SPOT, MIN_TRAIN, fit_spots, stone8_field_fit
from .model import Calibrated
from .nets import BatchedMLP
from .params import STONE8, apply_deviations, kinds
from ..io.records import RecordTable

#: Physical size of one network output unit per kind (see module docstring).
OUTPUT_SCALE = {"angle": 0.01, "tilt": 0.01, "translation": 1.0, "actuator_length": 1.0, "increment": 0.01}
SECONDS_PER_YEAR = 365.25 * 86400.0
FALLBACK_MARGIN = 0.9
#: Fewest validation records to trust a gain at all, and the paired-gain significance (standard errors).
MIN_VALIDATION = 4
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


def _per_h_mean(err: torch.Tensor, batch: RecordTable, h: int) -> torch.Tensor:
    s = torch.zeros(h, dtype=torch.float64).index_add_(0, batch.heliostat_index, err)
    c = batch.counts()
    return torch.where(c > 0, s / c.clamp_min(1), torch.full_like(s, math.inf))


class HybridModel(Calibrated):
    """Calibrated hybrid: static deviations plus network deviations per record."""

    def normals(self, batch: RecordTable):
        net, scale, t0 = self.extras["net"], self.extras["scale"], self.extras["t0"]
        use, span = self.extras["use_net"], self.extras.get("span")
        with torch.no_grad():
            d = self.delta[batch.heliostat_index] + scale * net(features(batch, self.nominal, t0, span), batch.heliostat_index) \
                * use[batch.heliostat_index].unsqueeze(-1).double()
            k = apply_deviations(self.nominal.index(batch.heliostat_index), d, self.names)
            return metrics.model_normals(k, batch, per_record=True)


def fit_hybrid_method(nominal, train, validation, *, seed=0, progress=False, field_prior=True, depth=14, hidden=2,
                      steps=400, lr=3e-3, weight_decay=1e-3, noise=1e-3, fit_focal_spot=FIT_FOCAL_SPOT) -> HybridModel:
    h = nominal.num_heliostats
    ok = train.counts() >= MIN_TRAIN
    tr = fit_spots(train.subset(ok[train.heliostat_index]), fit_focal_spot)
    va = validation.subset(ok[validation.heliostat_index]) if validation is not None else train.subset([])
    static, _ = stone8_field_fit(nominal, tr, ok, field_prior=field_prior)
    names = STONE8
    scale = torch.tensor([OUTPUT_SCALE[k] for k in kinds(names)], dtype=torch.float64)
    t0 = torch.zeros(h, dtype=torch.float64)
    span = torch.full((h,), SECONDS_PER_YEAR, dtype=torch.float64)
    for i in range(h):
        t = tr.time[(tr.heliostat_index == i) & torch.isfinite(tr.time)]
        t0[i] = t.min() if len(t) else 0.0
        if len(t) > 1:
            span[i] = (t.max() - t.min()).clamp_min(86400.0)
    gen = torch.Generator().manual_seed(int(seed))
    net = BatchedMLP(h, 7, len(names), hidden, depth, gen, zero_output=True)
    best = BatchedMLP(h, 7, len(names), hidden, depth, gen, zero_output=True)
    best.copy_rows(net, torch.ones(h, dtype=torch.bool))
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    x_tr, kin_tr = features(tr, nominal, t0, span), nominal.index(tr.heliostat_index)
    x_va = features(va, nominal, t0, span) if len(va) else None

    def val_err(model_net, per_record=False):
        if not len(va):
            return torch.full((h,), math.inf, dtype=torch.float64)
        with torch.no_grad():
            d = static[va.heliostat_index] + scale * model_net(x_va, va.heliostat_index)
            e = metrics.pointing_error(apply_deviations(nominal.index(va.heliostat_index), d, names), va, per_record=True)
            return e if per_record else _per_h_mean(e, va, h)

    with torch.no_grad():
        rigid_val = val_err(lambda x, i: torch.zeros(len(x), len(names), dtype=torch.float64))
    best_err = rigid_val.clone()
    it = range(steps)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="hybrid", leave=False)
    for step in it:
        opt.zero_grad()
        d = static[tr.heliostat_index] + scale * net(x_tr, tr.heliostat_index)
        r = metrics.normal_residuals(apply_deviations(kin_tr, d, names), tr, per_record=True)
        loss = (r * r).sum() / noise ** 2 + weight_decay * net.weight_norm().sum()
        loss.backward()
        opt.step()
        if (step + 1) % 10 == 0:
            err = val_err(net)
            better = err < best_err
            best.copy_rows(net, better)
            best_err = torch.where(better, err, best_err)
    # Fallback unless the net beats its own rigid body on validation by a clear (10 %) AND significant
    # paired gain on enough records: a gain on 2-6 records is mostly noise, and the net extrapolates in time.
    zero = lambda x, i: torch.zeros(len(x), len(names), dtype=torch.float64)  # noqa: E731
    use_net = torch.zeros(h, dtype=torch.bool)
    why = {}
    if len(va):
        gain = val_err(zero, True) - val_err(best, True)  # per record, rigid minus hybrid
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
    # Fallback heliostats: the rigid body refitted on every record they may see (as lm does).
    seen = RecordTable.concatenate([tr, fit_spots(va, fit_focal_spot)]) if len(va) else tr
    refit, _ = stone8_field_fit(nominal, seen, ok, field_prior=field_prior)
    static = torch.where(use_net.unsqueeze(-1), static, refit)
    static[~ok] = 0.0
    per_h = {}
    ids = list(train.heliostat_ids)
    for i, hid in enumerate(ids):
        if bool(ok[i]):
            per_h[hid] = {"uses_network": bool(use_net[i]), "fallback_reason": why.get(i),
                          "rigid_validation_mrad": float(rigid_val[i]) * 1e3 if math.isfinite(rigid_val[i]) else None,
                          "hybrid_validation_mrad": float(best_err[i]) * 1e3 if math.isfinite(best_err[i]) else None}
    networks = {hid: {"config": dict(best.config, kind="hybrid", names=list(names), scale=scale.tolist(),
                                     t0=float(t0[i]), span=float(span[i]), use_net=bool(use_net[i])),
                      "state": best.state_of(i)} for i, hid in enumerate(ids) if bool(ok[i])}
    extras = {"net": best, "scale": scale, "t0": t0, "span": span, "use_net": use_net, "per_heliostat": per_h, "networks": networks,
              "summary": {"heliostats_using_network": int((use_net & ok).sum()), "depth": depth, "hidden": hidden}}
    return HybridModel("hybrid", ids, nominal, names, static, ok, extras=extras)


def aim_hybrid(net_entry: dict, kin, sun: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Motor steps for one heliostat with its hybrid network: fixed point over steps -> deviations -> inverse.

    ``kin`` is the static calibrated kinematics (1 heliostat); network deviations are added on top.
    """
    from ..field import kinematics as K
    from ..io.records import RecordTable

    cfg = net_entry["config"]
    steps, _ = K.inverse(kin, target, sun, strict=False)
    if not cfg.get("use_net"):
        return steps
    net = BatchedMLP.from_state(cfg, net_entry["state"])
    scale = torch.tensor(cfg["scale"], dtype=torch.float64)
    import time

    now = time.time()
    z = torch.zeros(1, dtype=torch.float64)
    for _ in range(5):
        b = RecordTable(["h"], torch.zeros(1, dtype=torch.long), torch.zeros(1, dtype=torch.long), z, z, sun.reshape(1, 3),
                        steps.reshape(1, 2), target.reshape(1, 3), target.reshape(1, 3), target.reshape(1, 3),
                        target.reshape(1, 3), target.reshape(1, 3), torch.tensor([now], dtype=torch.float64),
                        torch.zeros(1, 5, dtype=torch.float64))
        with torch.no_grad():
            d = scale * net(features(b, kin, torch.tensor([cfg["t0"]], dtype=torch.float64),
                                     torch.tensor([cfg.get("span", SECONDS_PER_YEAR)], dtype=torch.float64)),
                            b.heliostat_index)
        k = apply_deviations(kin, d, cfg["names"])
        steps, _ = K.inverse(k, target, sun, strict=False)
    return steps
