"""``hybrid``: rigid body with static parameters plus deviations predicted by a small SELU network.

Per record, the deviations are ``delta_static + scale * net(features)`` where

* ``delta_static`` is the rigid body: ``lm``'s Stone/Jülich fit (bagged, the run's field prior or the plant
  prior) on the same records the network trains on;
* ``features`` (7): motor steps normalised to the actuator range and encoded as sin/cos (4), the age
  (time since the heliostat's first training record over the span of its training records, clamped to
  [0, 1]: a record after the last training record is treated like the last one -- no extrapolation in
  wear) and the month as sin/cos (season; bounded by construction);
* ``scale`` makes one network unit ~ 10 mrad for angles/tilts, 1 m for translations, 1 % for increments;
* the network is 14 hidden layers x 2 neurons (as published; ``depth``/``hidden`` configurable), SELU, its
  output layer starts at zero (the hybrid starts exactly at its rigid body), trained ``steps`` Adam steps with
  weight decay (a fixed count: no step is chosen on the records that decide whether the network is kept).

Keep rule (:mod:`.keep`): per heliostat, ``lm`` and ``lm`` + network are both fitted on the training records
before each of two check blocks (the run's validation records: the latest ones in a chronological run, or,
without any, the latest 20 % of the training records; and as many records before them), and the network is
kept only where a one-sided Wilcoxon signed-rank test on the paired per-record errors of both blocks says it
helps (at least 6 records per block, p-values held to a 5 % false-discovery rate over the run's heliostats, a
positive mean gain in each block). A kept network is then
refitted on every record on top of ``lm`` fitted on every record; every other heliostat is exactly ``lm``. The report
gives each heliostat's evidence (``keep_test``: gain, p, its threshold, n, wins and losses).
"""
from __future__ import annotations

import math
import time

import torch

from ...errors import HeliotwinError
from ...field import kinematics as K
from ...io.records import RecordTable
from .. import metrics
from ..fitloop import early_stopping_fit, net_state
from ..inputs import FIT_FOCAL_SPOT, fit_spots, restrict
from ..model import Calibrated
from ..params import STONE8, apply_deviations, kinds
from . import keep
from .lm import fit_lm_method
from .nets import BatchedMLP

#: Physical size of one network output unit per kind (see module docstring).
OUTPUT_SCALE = {"angle": 0.01, "tilt": 0.01, "translation": 1.0, "actuator_length": 1.0, "increment": 0.01}
SECONDS_PER_YEAR = 365.25 * 86400.0
#: ``pretrain="fleet"``: weight of a network's squared weight change from the fleet's (per unit weight: one
#: record at 1 mrad costs 1), strong enough that ~30 records move a weight by ~0.1 at most.
FLEET_SHRINK = 1e3
#: ``pretrain`` options of the hybrid.
PRETRAIN = ("none", "fleet")


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


def _train_network(nominal, static, records: RecordTable, names, scale, *, seed, depth, hidden, steps, lr,
                   weight_decay, noise, progress, desc, fleet: RecordTable | None = None, shrink: float = 0.0):
    """The network on top of ``static`` [H, P] trained ``steps`` Adam steps on ``records`` (no early stopping: the
    keep rule's check records must not choose anything, :mod:`.keep`).

    ``fleet``: pretrain one network shared by every heliostat on these records first (every heliostat's residuals
    from its own rigid body ``static``), start each heliostat's network there and fine-tune it with
    ``shrink`` x (squared change of its weights from the shared ones) added to its loss.

    Returns ``(net, t0 [H] [s], span [H] [s])`` (the age feature's reference, from ``records``' times, or
    ``fleet``'s).
    """
    h, like = nominal.num_heliostats, nominal.position
    t0, span = training_times(records if fleet is None else fleet, h)
    gen = torch.Generator().manual_seed(int(seed))
    net = BatchedMLP(h, 7, len(names), hidden, depth, gen, zero_output=True, dtype=like.dtype).to(like.device)
    if not len(records) or steps <= 0:
        return net, t0, span
    anchor = None
    if fleet is not None and len(fleet):
        shared = BatchedMLP(1, 7, len(names), hidden, depth, gen, zero_output=True, dtype=like.dtype).to(like.device)
        pre = _HybridFit(nominal, static, names, scale, t0, span, fleet)
        zeros = torch.zeros_like(fleet.heliostat_index)
        opt = torch.optim.Adam(shared.parameters(), lr=lr)
        n_h = max(int((fleet.counts() > 0).sum()), 1)
        for _ in range(steps):  # one shared network: the loss per heliostat's records as in the fine-tuning
            opt.zero_grad()
            d = pre.static[fleet.heliostat_index] + pre.scale * shared(pre.x, zeros)
            r = metrics.normal_residuals(apply_deviations(pre.kin, d, names), fleet, per_record=True)
            loss = (r * r).sum() / noise ** 2 / n_h + weight_decay * shared.weight_norm().sum()
            loss.backward()
            opt.step()
        with torch.no_grad():
            for mine, theirs in zip(list(net.weights) + list(net.biases), list(shared.weights) + list(shared.biases)):
                mine.copy_(theirs.expand_as(mine))
        anchor = [p.detach().clone() for p in net.parameters()]
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    fit = _HybridFit(nominal, static, names, scale, t0, span, records)

    def step():
        opt.zero_grad()
        r = fit.residuals(net)
        loss = (r * r).sum() / noise ** 2
        if anchor is None:
            loss = loss + weight_decay * net.weight_norm().sum()
        else:  # strong shrinkage of each heliostat's network towards the fleet's
            loss = loss + shrink * sum(((p - p0) ** 2).sum() for p, p0 in zip(net.parameters(), anchor))
        loss.backward()
        opt.step()
        return loss

    # The shared loop (for --resume checkpoints) with nothing validated: every heliostat keeps its final state.
    log = early_stopping_fit(step, lambda: like.new_full((h,), float("inf")), net_state(net), steps,
                             validated=torch.zeros(h, dtype=torch.bool, device=like.device), check_every=steps,
                             progress=progress, desc=desc)
    return log.best, t0, span


def fit_hybrid_method(nominal, train, validation, *, seed=0, progress=False, field_prior=True, depth=14, hidden=2,
                      steps=400, lr=3e-3, weight_decay=1e-3, noise=1e-3, fit_focal_spot=FIT_FOCAL_SPOT,
                      plant_prior=None, level=keep.LEVEL, min_check=keep.MIN_CHECK, pretrain="none",
                      shrink=FLEET_SHRINK) -> HybridModel:
    """``hybrid``: ``lm``'s rigid body plus a small network per heliostat where it earns its place (module docstring).

    ``plant_prior`` (:class:`~heliotwin.calibrate.priors.PlantPrior`): the rigid body's prior instead of the run's
    field prior. ``level``/``min_check``: the keep rule's (:mod:`.keep`). ``pretrain="fleet"``: each network starts
    from one pretrained on every heliostat's training records (residuals from its own ``lm``) and is fine-tuned
    with ``shrink`` towards it (:func:`_train_network`); the keep rule decides as for ``"none"``. The network
    follows the nominal kinematics' dtype and device; every random draw takes ``seed``.
    """
    if pretrain not in PRETRAIN:
        raise HeliotwinError(f"hybrid: pretrain must be one of {', '.join(PRETRAIN)}, got {pretrain!r}")
    like = nominal.position
    names = STONE8
    scale = torch.tensor([OUTPUT_SCALE[k] for k in kinds(names)], dtype=like.dtype, device=like.device)
    lm_opts = dict(seed=seed, plant_prior=plant_prior, field_prior=field_prior, fit_focal_spot=fit_focal_spot)
    net_opts = dict(seed=seed, depth=depth, hidden=hidden, steps=steps, lr=lr, weight_decay=weight_decay,
                    noise=noise, progress=progress)
    # The fallback, and the base of a kept network: exactly lm on every record the method may see.
    rigid, seen, folds, testable = keep.rigid_and_folds(nominal, train, validation, lm_opts, min_check)
    ok = rigid.ok
    fold_errors = []
    for a, v in folds:
        # per block: both candidates on the records before it only, their errors on it
        va = restrict(v, testable)
        if not bool(testable.any()):
            fold_errors.append((like.new_zeros(0), like.new_zeros(0), va.heliostat_index))
            continue
        base = fit_lm_method(nominal, a, None, **lm_opts).delta.to(like)
        fleet = fit_spots(a, fit_focal_spot) if pretrain == "fleet" else None
        cand, t0, span = _train_network(nominal, base, fit_spots(restrict(a, testable), fit_focal_spot), names,
                                        scale, desc="hybrid (keep check)", fleet=fleet, shrink=shrink, **net_opts)
        fit_va = _HybridFit(nominal, base, names, scale, t0, span, va)
        fold_errors.append((fit_va.errors(None), fit_va.errors(cand), va.heliostat_index))
    use_net, evidence = keep.keep_decision(fold_errors, folds, testable, level=level, min_check=min_check)
    # 3. a kept network is refitted on every record, on top of lm's rigid body of the same records
    static = rigid.delta.to(like).clone()
    static[~ok] = 0.0
    fleet = fit_spots(restrict(seen, ok), fit_focal_spot) if pretrain == "fleet" else None
    net, t0, span = _train_network(nominal, static, fit_spots(restrict(seen, use_net), fit_focal_spot), names, scale,
                                   desc="hybrid", fleet=fleet, shrink=shrink,
                                   **dict(net_opts, steps=steps if bool(use_net.any()) else 0))
    ids = list(train.heliostat_ids)
    per_h = {hid: {"uses_network": bool(use_net[i]), "fallback_reason": evidence[i]["reason"],
                   "rigid_validation_mrad": evidence[i]["rigid_check_mrad"],
                   "hybrid_validation_mrad": evidence[i]["network_check_mrad"], "keep_test": evidence[i]}
             for i, hid in enumerate(ids) if bool(ok[i])}
    networks = {hid: {"config": dict(net.config, kind="hybrid", names=list(names), scale=scale.tolist(),
                                     t0=float(t0[i]), span=float(span[i]), use_net=bool(use_net[i])),
                      "state": net.state_of(i)} for i, hid in enumerate(ids) if bool(ok[i])}
    extras = {"net": net, "scale": scale, "t0": t0, "span": span, "use_net": use_net, "per_heliostat": per_h,
                   "networks": networks,
                   "summary": dict(rigid.extras.get("summary", {}), heliostats_using_network=int((use_net & ok).sum()),
                                   depth=depth, hidden=hidden, pretrain=pretrain,
                                   keep_rule={"test": "one-sided Wilcoxon signed-rank on paired validation errors, "
                                                      "Benjamini-Hochberg over the heliostats",
                                              "level": level, "min_check": min_check,
                                              "check_fraction_without_validation": keep.CHECK_FRACTION})}
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
