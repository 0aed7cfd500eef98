"""``mlp``: per-axis networks from (sun, aim) to motor steps, pretrained on the heliostat's own rigid body.

Why the steps are predicted *on top of the plant's geometry*: one motor increment moves the normal by about
0.1-0.4 mrad and the actuator range is ~10^4-10^5 increments, so a network that outputs the steps as a
fraction of the range needs a relative precision of ~10^-5 to be useful. A small net trained for a few
hundred steps reaches ~10^-2 (hundreds of mrad: what the first version of this method measured on real
records, 412 mrad after pretraining). The geometry of the plant's nominal kinematics (the ``base``: nominal,
or the plant prior's mean when one is given) already gets the steps right to some tens of increments, so
the network predicts the rest, in increments, scaled to its spread: a relative precision of ~10^-2 of that
spread is then ~0.1 increments.

Per heliostat and motor axis one network (SELU, LeCun-normal initialisation, :class:`~.nets.BatchedMLP`).

* Inputs (5), standardised with the pretraining samples' mean and spread per heliostat: unit sun vector (3)
  and the base's motor steps for (sun, aim) as a fraction of the actuator range (2) (they encode the aim).
* Output: that axis' motor steps minus the base's [increments] = an affine function of the inputs (least
  squares on the pretraining samples: a skip connection that carries most of a rigid body's correction,
  e.g. an increment scale is linear in the steps) + the network's output in units of what the affine part
  leaves (its spread, at least :data:`MIN_OUTPUT_SCALE` increments).
* Loss: Huber on the step error in increments (:data:`HUBER_INCREMENTS`).

Training:

1. *rigid body*: the Stone/Jülich-8 LM fit on the training records (field prior of the run, or the plant
   prior), as the hybrid's pre-alignment;
2. *pretraining* on samples simulated by that rigid body over the whole sun range: a year of sun positions
   (:func:`heliotwin.sun.daylight_times`, every ``every``) with aim points spread over the heliostat's
   training spots (+-10 m in the target plane: the other targets of the tower face too), motor steps from
   the rigid body's inverse; Adam with a cosine schedule, full batch, then L-BFGS. After pretraining the
   network reproduces its rigid body (tested: its validation error is within a small tolerance of the rigid
   body's);
3. *fine-tuning* on the real training records (aim = fitted focal spot, target = recorded steps) with a
   small learning rate in ``cycles`` training cycles with growing data (cycle c uses the earliest c/C of each
   heliostat's training records), early-stopped on validation;
4. *fallback*: a heliostat keeps its network only where, on its validation records (inside ``--train``), the
   network beats the rigid body by 10 % and significantly (paired gain per record above :data:`SIGNIFICANCE`
   standard errors on at least :data:`MIN_VALIDATION` records); otherwise it uses exactly ``lm`` (on train +
   validation).

Pointing error of a record: the network predicts steps for the measured spot; the pointing error is the
angle between the measured normal and the measured normal moved by the rigid body's normal change from the
recorded to the predicted steps (first order in the step error; the rigid body supplies only the local
Jacobian, not the answer).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from ...field import kinematics as K
from ...io.records import RecordTable
from ...site import Site
from ...sun import daylight_times, direction_from_paint_angles
from .. import metrics
from ..fitloop import State, early_stopping_fit
from ..inputs import FIT_FOCAL_SPOT, fit_spots, restrict, trainable
from ..model import Calibrated
from ..params import STONE8, apply_deviations, read_deviations
from .lm import fit_lm_method, stone8_field_fit, stone8_plant_fit
from .nets import BatchedMLP

#: Inputs per network: sun (3), base steps as a fraction of the range (2).
N_INPUTS = 5
#: Smallest output unit [increments] (a heliostat whose rigid body equals the base still gets a usable scale).
MIN_OUTPUT_SCALE = 0.5
#: Huber transition of the step loss [increments]: quadratic within a few increments, linear for outliers.
HUBER_INCREMENTS = 2.0
#: Fewest validation records to trust a gain, and the paired gain's significance [standard errors].
MIN_VALIDATION = 4
SIGNIFICANCE = 2.0
#: The network must also beat the rigid body's mean validation error by 10 %.
FALLBACK_MARGIN = 0.9


def _inputs(sun: torch.Tensor, aim: torch.Tensor, reference: torch.Tensor, base_fraction: torch.Tensor) -> torch.Tensor:
    """Raw network inputs [R, 5]: ``sun`` [R, 3] unit and ``base_fraction`` [R, 2] (the base's steps for the
    aim as a fraction of the actuator range). ``aim`` [R, 3] and ``reference`` [3] or [R, 3] ENU [m] are not
    inputs: the base's steps already encode the aim, and an aim offset would make the network extrapolate
    whenever a record uses another target than the training records (a rigid body's step correction depends
    on the wanted normal, i.e. the base's steps, not on where the target is)."""
    return torch.cat([sun, base_fraction], -1)


def _normalised_steps(kin, steps: torch.Tensor) -> torch.Tensor:
    """Motor steps [R, 2] as a fraction of each actuator's range (kinematics indexed per record)."""
    return (steps - kin.min_steps) / (kin.max_steps - kin.min_steps)


def _base_steps(base, hidx: torch.Tensor, aim: torch.Tensor, sun: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The base kinematics' motor steps [R, 2] for (aim [R, 3], sun [R, 3]) and their range fraction [R, 2]."""
    k = base.index(hidx)
    steps, _ = K.inverse(k, aim, sun, strict=False)
    return steps, _normalised_steps(k, steps)


def _pad(hidx: torch.Tensor, h: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows [H, N] into a record axis grouped by heliostat (N = most records of one heliostat) and their mask."""
    counts = torch.bincount(hidx, minlength=h)
    n = max(int(counts.max()) if len(hidx) else 0, 1)
    order = torch.argsort(hidx, stable=True)
    start = torch.cumsum(counts, 0) - counts
    pos = torch.arange(len(hidx), device=hidx.device) - start[hidx[order]]
    rows = torch.zeros(h, n, dtype=torch.long, device=hidx.device)
    mask = torch.zeros(h, n, dtype=torch.bool, device=hidx.device)
    rows[hidx[order], pos] = order
    mask[hidx[order], pos] = True
    return rows, mask


class StepNetworks:
    """Per-heliostat, per-axis networks with their input standardisation and output scale.

    ``x_mean``/``x_std`` [H, 5]; ``linear`` [H, 6, 2] [increments]: the affine part (least squares on the
    standardised inputs and 1, a skip connection around the network); ``y_scale`` [H, 2] [increments]: the
    network's output unit (the spread of what the affine part leaves); ``net`` has 2H rows (heliostat h,
    axis a at row 2h + a).
    """

    def __init__(self, net: BatchedMLP, x_mean, x_std, linear, y_scale):
        self.net, self.x_mean, self.x_std, self.linear, self.y_scale = net, x_mean, x_std, linear, y_scale

    def with_net(self, net: BatchedMLP) -> "StepNetworks":
        return StepNetworks(net, self.x_mean, self.x_std, self.linear, self.y_scale)

    def increments(self, x_raw: torch.Tensor, hidx: torch.Tensor, net: BatchedMLP | None = None) -> torch.Tensor:
        """Predicted steps minus base steps [R, 2] [increments] for raw inputs ``x_raw`` [R, 5]."""
        net = self.net if net is None else net
        h = len(self.x_mean)
        x = (x_raw - self.x_mean[hidx]) / self.x_std[hidx]
        rows, mask = _pad(hidx, h)
        dense = net.dense(x[rows].repeat_interleave(2, 0))  # [2H, N, 1]
        y = dense.reshape(h, 2, -1).transpose(1, 2)  # [H, N, 2]
        out = x.new_zeros(len(x), 2)
        out = out.index_put((rows[mask],), y[mask])
        affine = (torch.cat([x, torch.ones_like(x[:, :1])], -1).unsqueeze(1) @ self.linear[hidx]).squeeze(1)
        return affine + out * self.y_scale[hidx]


def _standardisation(x: torch.Tensor, y: torch.Tensor, hidx: torch.Tensor, h: int):
    """Per-heliostat input mean/spread [H, 5], affine part [H, 6, 2] and output unit [H, 2] of the pretraining
    samples (see :class:`StepNetworks`)."""
    x_mean, x_std = x.new_zeros(h, x.shape[1]), x.new_ones(h, x.shape[1])
    linear, y_scale = y.new_zeros(h, x.shape[1] + 1, 2), y.new_full((h, 2), MIN_OUTPUT_SCALE)
    for i in range(h):  # heliostats (tens), once per fit
        m = hidx == i
        if int(m.sum()) < 2:
            continue
        x_mean[i], x_std[i] = x[m].mean(0), x[m].std(0).clamp_min(1e-6)
        xa = torch.cat([(x[m] - x_mean[i]) / x_std[i], torch.ones_like(x[m][:, :1])], -1)
        linear[i] = torch.linalg.lstsq(xa, y[m]).solution
        y_scale[i] = (y[m] - xa @ linear[i]).std(0).clamp_min(MIN_OUTPUT_SCALE)
    return x_mean, x_std, linear, y_scale


def _simulate(rigid, train: RecordTable, site, every: str, year: int, gen: torch.Generator):
    """Simulated (heliostat, sun, aim, steps) from the rigid body over a year of sun positions.

    Returns ``hidx`` [S], ``sun`` [S, 3], ``aim`` [S, 3] ENU [m], ``steps`` [S, 2] (reachable samples only).
    """
    _, az, el = daylight_times(year, every, site.latitude_deg, site.longitude_deg, site.altitude_m,
                               min_elevation_deg=8.0)
    sun = direction_from_paint_angles(az, el).to(train.spot)
    dev = train.spot.device
    rows = []
    for i in range(rigid.num_heliostats):  # heliostats (tens), once per fit
        m = train.heliostat_index == i
        if not bool(m.any()):
            continue
        # Aim points: the heliostat's training spots, jittered by +-10 m in the target plane (CPU draws: the
        # same samples on any device).
        spots, right, up = train.spot[m], train.plane_right[m], train.plane_up[m]
        pick = torch.randint(len(spots), (len(sun),), generator=gen).to(dev)
        jit = ((torch.rand(len(sun), 2, generator=gen, dtype=torch.float64) - 0.5) * 20.0).to(spots)
        aim = spots[pick] + jit[:, :1] * right[pick] + jit[:, 1:] * up[pick]
        steps, ok = K.inverse(rigid.index([i] * len(sun)), aim, sun, strict=False)
        ok = ok & torch.isfinite(steps).all(-1)
        rows.append((torch.full((int(ok.sum()),), i, dtype=torch.long, device=dev), sun[ok], aim[ok], steps[ok]))
    return [torch.cat(c) for c in zip(*rows)]


def _huber(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Huber loss on step errors [increments], summed over axes, mean over records."""
    return torch.nn.functional.huber_loss(pred, target, delta=HUBER_INCREMENTS, reduction="none").sum(-1).mean()


def _pretrain(nets: StepNetworks, x, hidx, y, steps: int, lr: float, polish: int) -> float:
    """Pretraining on the simulated samples (full batch): Adam with a cosine schedule over ``steps``, then
    ``polish`` L-BFGS iterations; returns the final RMS step error [increments].

    The loss is the mean squared error in output units (each heliostat weighted by its own sample count): the
    rigid body is smooth and noise-free, so precision, not robustness, is what pretraining needs.
    """
    h = len(nets.x_mean)
    w = (1.0 / torch.bincount(hidx, minlength=h).clamp_min(1).to(x))[hidx]
    def loss_fn():
        return ((((nets.increments(x, hidx) - y) / nets.y_scale[hidx]) ** 2).sum(-1) * w).sum()

    opt = torch.optim.Adam(nets.net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(steps, 1))
    for _ in range(steps):
        opt.zero_grad()
        loss_fn().backward()
        opt.step()
        sched.step()
    if polish:
        lbfgs = torch.optim.LBFGS(nets.net.parameters(), lr=1.0, max_iter=polish, history_size=50,
                                  line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-15)

        def closure():
            lbfgs.zero_grad()
            loss = loss_fn()
            loss.backward()
            return loss

        lbfgs.step(closure)
    with torch.no_grad():
        return float(((nets.increments(x, hidx) - y) ** 2).sum(-1).mean().sqrt())


class MLPModel(Calibrated):
    """Calibrated MLP: predicted steps for (sun, spot); errors via the rigid body's local Jacobian."""

    def predict_steps(self, batch: RecordTable, use_all: bool = False) -> torch.Tensor:
        """Network motor steps [R, 2] for the records' (sun, measured spot)."""
        nets, ref, base = self.extras["nets"], self.extras["reference"], self.extras["base"]
        with torch.no_grad():
            b_steps, frac = _base_steps(base, batch.heliostat_index, batch.spot, batch.sun)
            x = _inputs(batch.sun, batch.spot, ref[batch.heliostat_index], frac)
            return b_steps + nets.increments(x, batch.heliostat_index)

    def normals(self, batch: RecordTable):
        rigid = self.kinematics
        with torch.no_grad():
            n_rec, c = metrics.model_normals(rigid, batch)
            pred = batch.subset(torch.arange(len(batch), device=batch.spot.device))
            pred.motor_steps = self.predict_steps(batch)
            n_pred, _ = metrics.model_normals(rigid, pred)
            measured = metrics.measured_normals(batch, c)
            n = measured + (n_pred - n_rec)
            n = n / torch.linalg.norm(n, dim=-1, keepdim=True)
            # Heliostats whose MLP did not beat the rigid body on validation use the rigid body (fallback).
            use = self.extras.get("use_net")
            if use is not None:
                n = torch.where(use[batch.heliostat_index].unsqueeze(-1), n, n_rec)
            return n, c


@dataclass(frozen=True)
class MLPSettings:
    """Settings of the ``mlp`` method (:func:`fit_mlp_method`; each field is also one of its keywords).

    Attributes
    ----------
    hidden, depth : int
        Width and number of hidden layers of each axis' network.
    every : str
        Spacing of the simulated sun positions of the pretraining year (e.g. ``"3h"``).
    year : int
        The pretraining year.
    pretrain_steps, finetune_steps : int
        Optimiser steps on the simulated samples, then on the real training records (all cycles together).
    lr : float
        Pretraining learning rate (Adam).
    finetune_lr : float
        Fine-tuning learning rate (Adamax): small, the network starts at its rigid body.
    cycles : int
        Fine-tuning cycles with growing data.
    field_prior : bool
        The rigid body's field prior (without a plant prior).
    fit_focal_spot : str or None
        Centroid source the rigid body and the fine-tuning train on.
    site : Site or None
        Where the sun positions are computed (default: :class:`~heliotwin.site.Site`'s).
    """

    hidden: int = 32
    depth: int = 2
    every: str = "3h"
    year: int = 2023
    pretrain_steps: int = 500
    polish_steps: int = 100
    finetune_steps: int = 300
    lr: float = 1e-2
    finetune_lr: float = 1e-3
    cycles: int = 3
    field_prior: bool = True
    fit_focal_spot: str | None = FIT_FOCAL_SPOT
    site: Site | None = None


def _rigid_fit(nominal, batch, ok, s: MLPSettings, plant_prior):
    """The Stone/Jülich-8 deviations [H, 8] of the rigid body on ``batch`` (plant prior or field prior)."""
    if plant_prior is not None:
        return stone8_plant_fit(nominal, batch, plant_prior)
    return stone8_field_fit(nominal, batch, ok, field_prior=s.field_prior)[0]


def _growing(train: RecordTable, cycles: int) -> list[torch.Tensor]:
    """Record masks [R] of the training cycles: cycle c keeps the earliest ceil(c/C n_h) records of each
    heliostat (records without a time sort last, in their order)."""
    t = torch.where(torch.isfinite(train.time), train.time, torch.full_like(train.time, float("inf")))
    rank = torch.zeros(len(train), dtype=torch.long, device=train.spot.device)
    counts = train.counts()
    for i in range(train.num_heliostats):  # heliostats (tens), once per fit
        rows = train.of(i).to(rank.device)
        rank[rows[torch.argsort(t[rows], stable=True)]] = torch.arange(len(rows), device=rank.device)
    n = counts[train.heliostat_index].to(torch.float64)
    return [rank < torch.ceil(n * c / cycles) for c in range(1, cycles + 1)]


def _keep_network(err_rigid: torch.Tensor, err_net: torch.Tensor, hidx: torch.Tensor, h: int):
    """Which heliostats keep their network (see module docstring) and why the others do not."""
    use = torch.zeros(h, dtype=torch.bool, device=hidx.device)
    why = {}
    gain = err_rigid - err_net
    for i in range(h):  # heliostats (tens), once per fit
        g = gain[hidx == i]
        if len(g) < MIN_VALIDATION:
            why[i] = f"{len(g)} validation records < {MIN_VALIDATION}"
            continue
        se = float(g.std()) / math.sqrt(len(g))
        if float(g.mean()) > SIGNIFICANCE * se and float(err_net[hidx == i].mean()) < FALLBACK_MARGIN * float(
                err_rigid[hidx == i].mean()):
            use[i] = True
        else:
            why[i] = f"validation gain {float(g.mean()) * 1e3:.3f} mrad not above {SIGNIFICANCE} x {se * 1e3:.3f}"
    return use, why


def fit_mlp_method(nominal, train, validation, *, seed: int = 0, progress: bool = False,
                   settings: MLPSettings | None = None, plant_prior=None, **options) -> MLPModel:
    """``mlp``: per-heliostat, per-axis networks from (sun, aim) to motor steps (see module docstring).

    ``settings`` (:class:`MLPSettings`, default its defaults) and/or its fields by keyword (``options``,
    replacing ``settings``'s); ``plant_prior`` (:class:`~heliotwin.calibrate.priors.PlantPrior`): the rigid
    body's prior and the base's mean. The networks follow the nominal kinematics' dtype and device; every
    random draw takes ``seed``.
    """
    s = replace(settings or MLPSettings(), **options)
    h, like = nominal.num_heliostats, nominal.position
    ok = trainable(train)
    tr = fit_spots(restrict(train, ok), s.fit_focal_spot)
    va = restrict(validation, ok) if validation is not None else train.subset([])
    delta = _rigid_fit(nominal, tr, ok, s, plant_prior).to(like)
    delta[~ok] = 0.0
    rigid = apply_deviations(nominal, delta, STONE8)
    base = nominal if plant_prior is None else apply_deviations(
        nominal, plant_prior.mean.to(like).expand(h, len(STONE8)), STONE8)
    gen = torch.Generator().manual_seed(int(seed))
    reference = like.new_zeros(h, 3)
    for i in range(h):  # heliostats (tens): the first training target's centre
        rows = tr.of(i)
        if len(rows):
            reference[i] = tr.plane_center[rows[0]]
    # 1. pretraining samples from the rigid body, standardised per heliostat
    hidx, sun, aim, steps = _simulate(rigid, tr, s.site or Site(), s.every, s.year, gen)
    b_steps, frac = _base_steps(base, hidx, aim, sun)
    x_sim, y_sim = _inputs(sun, aim, reference[hidx], frac), steps - b_steps
    fine = torch.isfinite(x_sim).all(-1) & torch.isfinite(y_sim).all(-1)
    hidx, x_sim, y_sim = hidx[fine], x_sim[fine], y_sim[fine]
    net = BatchedMLP(2 * h, N_INPUTS, 1, s.hidden, s.depth, gen, dtype=like.dtype).to(like.device)
    nets = StepNetworks(net, *_standardisation(x_sim, y_sim, hidx, h))
    pretrain_rms = _pretrain(nets, x_sim, hidx, y_sim, s.pretrain_steps, s.lr, s.polish_steps)
    model = MLPModel("mlp", list(train.heliostat_ids), nominal, STONE8, delta, ok,
                     extras={"nets": nets, "reference": reference, "base": base,
                             "use_net": torch.ones(h, dtype=torch.bool, device=like.device)})
    # 2. fine-tuning on the training records in cycles with growing data; early stopping on validation
    b_tr, f_tr = _base_steps(base, tr.heliostat_index, tr.spot, tr.sun)
    x_tr, y_tr = _inputs(tr.sun, tr.spot, reference[tr.heliostat_index], f_tr), tr.motor_steps - b_tr
    good = torch.isfinite(x_tr).all(-1) & torch.isfinite(y_tr).all(-1)
    cycles = [m & good for m in _growing(tr, max(1, s.cycles))]
    per_cycle = max(1, s.finetune_steps // len(cycles))
    opt = torch.optim.Adamax(net.parameters(), lr=s.finetune_lr)
    counter = [0]

    def step():
        m = cycles[min(counter[0] // per_cycle, len(cycles) - 1)]
        counter[0] += 1
        opt.zero_grad()
        loss = _huber(nets.increments(x_tr[m], tr.heliostat_index[m]), y_tr[m])
        loss.backward()
        opt.step()
        return loss

    def errors(net_rows=None, use=True):
        model.extras["use_net"] = torch.full((h,), use, dtype=torch.bool, device=like.device)
        if net_rows is not None:
            model.extras["nets"] = nets.with_net(net_rows)
        try:
            return model.pointing_error(va)
        finally:
            model.extras["nets"] = nets

    def val_err():
        if not len(va):
            return like.new_full((h,), float("inf"))
        return metrics.per_heliostat_mean(errors(), va.heliostat_index, h)

    rigid_val = val_err_of(errors(use=False), va, h, like)
    pretrain_val = val_err()
    state = State(lambda: _copy_net(net), lambda best, rows: best.copy_rows(net, rows.repeat_interleave(2)))
    log = early_stopping_fit(step, val_err, state, len(cycles) * per_cycle, validated=va.counts() > 0,
                             check_every=10, progress=progress, desc="mlp finetune")
    best, best_err = log.best, log.best_error
    nets = nets.with_net(best)
    # 3. fallback: the network only where validation says it helps; elsewhere the rigid body refitted on
    # every record the method may see (as lm does)
    if len(va):
        use_net, why = _keep_network(errors(use=False), errors(best), va.heliostat_index, h)
    else:
        use_net, why = torch.zeros(h, dtype=torch.bool, device=like.device), {}
    # (exactly lm: bagged, on train + validation; an unbagged refit alone loses ~0.05-0.2 mrad to lm)
    refit = fit_lm_method(nominal, train, validation, seed=seed, plant_prior=plant_prior, field_prior=s.field_prior,
                          fit_focal_spot=s.fit_focal_spot).delta.to(like)
    delta = torch.where(use_net.unsqueeze(-1), delta, refit)
    delta[~ok] = 0.0
    model = MLPModel("mlp", list(train.heliostat_ids), nominal, STONE8, delta, ok,
                     extras={"nets": nets, "reference": reference, "base": base, "use_net": use_net})
    _describe(model, ok, use_net, why, pretrain_val, best_err, rigid_val, len(hidx), s)
    model.extras["summary"]["pretraining_rms_increments"] = pretrain_rms
    return model


def val_err_of(err: torch.Tensor, va: RecordTable, h: int, like: torch.Tensor) -> torch.Tensor:
    """Per-heliostat mean [H] of per-record errors on ``va`` (inf without validation records)."""
    if not len(va):
        return like.new_full((h,), float("inf"))
    return metrics.per_heliostat_mean(err, va.heliostat_index, h)


def _copy_net(net: BatchedMLP) -> BatchedMLP:
    out = BatchedMLP(len(net.weights[0]), net.config["n_in"], net.config["n_out"], net.config["hidden"],
                     net.config["depth"], torch.Generator().manual_seed(0), dtype=net.weights[0].dtype)
    out = out.to(net.weights[0].device)
    out.load_state_dict(net.state_dict())
    return out


def _describe(model, ok, use_net, why, pretrain_err, best_err, rigid_val, samples: int, s: MLPSettings) -> None:
    """Per-heliostat report, stored networks and summary of a fitted MLP model (into ``model.extras``)."""
    def mrad(x):
        return float(x) * 1e3 if math.isfinite(x) else None

    ids = model.heliostat_ids
    nets, ref, base = model.extras["nets"], model.extras["reference"], model.extras["base"]
    base_dev = read_deviations(base, model.kinematics, STONE8)
    model.extras["per_heliostat"] = {hid: {"validation_after_pretraining_mrad": mrad(pretrain_err[i]),
                                           "validation_after_finetuning_mrad": mrad(best_err[i]),
                                           "rigid_validation_mrad": mrad(rigid_val[i]),
                                           "uses_network": bool(use_net[i]), "fallback_reason": why.get(i)}
                                     for i, hid in enumerate(ids) if bool(ok[i])}
    networks = {}
    for i, hid in enumerate(ids):
        if not bool(ok[i]):
            continue
        cfg = dict(nets.net.config, kind="mlp", reference=ref[i].tolist(), use_net=bool(use_net[i]),
                   x_mean=nets.x_mean[i].tolist(), x_std=nets.x_std[i].tolist(), linear=nets.linear[i].tolist(),
                   y_scale=nets.y_scale[i].tolist(), base_deviations=base_dev[i].tolist(), base_names=list(STONE8))
        state = {f"{k}_axis{a}": v for a in (0, 1) for k, v in nets.net.state_of(2 * i + a).items()}
        networks[hid] = {"config": cfg, "state": state}
    model.extras["networks"] = networks
    model.extras["summary"] = {"pretraining_samples": samples, "hidden": s.hidden, "depth": s.depth,
                               "cycles": s.cycles, "heliostats_using_network": int((use_net & ok).sum())}


def aim_mlp(net_entry: dict, kin, sun: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Motor steps [1, 2] straight from a stored MLP (``kin``: the heliostat's calibrated kinematics, 1 row;
    ``sun`` [3] unit, ``target`` [3] ENU [m])."""
    cfg = net_entry["config"]
    if not cfg.get("use_net", True):
        return K.inverse(kin, target, sun, strict=False)[0]
    f64 = dict(dtype=torch.float64)
    states = [{k[:-len(f"_axis{a}")]: v for k, v in net_entry["state"].items() if k.endswith(f"_axis{a}")}
              for a in (0, 1)]
    net = BatchedMLP.from_states(cfg, states)
    base = apply_deviations(kin, torch.tensor([cfg["base_deviations"]], **f64), cfg["base_names"])
    nets = StepNetworks(net, torch.tensor([cfg["x_mean"]], **f64), torch.tensor([cfg["x_std"]], **f64),
                        torch.tensor([cfg["linear"]], **f64), torch.tensor([cfg["y_scale"]], **f64))
    sun, target = sun.reshape(1, 3).double(), target.reshape(1, 3).double()
    hidx = torch.zeros(1, dtype=torch.long)
    with torch.no_grad():
        b_steps, frac = _base_steps(base, hidx, target, sun)
        x = _inputs(sun, target, torch.tensor([cfg["reference"]], **f64), frac)
        return b_steps + nets.increments(x, hidx)
