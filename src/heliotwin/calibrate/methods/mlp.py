"""``mlp``: the thesis' per-axis MLP that maps (sun, aim offset) directly to motor steps.

Per heliostat and axis one network (inputs: unit sun vector (3) and the aim point's east/up offset from
the tower reference (the first planar target's centre) / 10 m; output: that axis' motor steps normalised
to the actuator range); SELU, Huber loss, AdaMax. Training:

1. *pretraining* on records simulated by the ``gradient``-fitted rigid body: sun positions over a year
   (:func:`heliotwin.sun.daylight_times`, every ``every``) with aim points spread over the heliostat's
   training targets, motor steps from the rigid body's inverse;
2. *fine-tuning* on the real training records (aim = measured focal spot), early-stopped on validation.

Pointing error of a record: the network predicts steps for the measured spot; the pointing error is the
angle between the measured normal and the measured normal moved by the rigid body's normal change from
the recorded to the predicted steps (first order in the step error; the rigid body supplies only the
local Jacobian, not the answer).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from tqdm import tqdm

from ...field import kinematics as K
from ...io.records import RecordTable
from ...site import Site
from ...sun import daylight_times, direction_from_paint_angles
from .. import metrics
from ..fitloop import early_stopping_fit, net_state
from ..inputs import trainable
from ..model import Calibrated
from .gradient import fit_gradient_method
from .nets import BatchedMLP


def _inputs(sun: torch.Tensor, aim: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    off = (aim - reference) / 10.0
    return torch.cat([sun, off[:, [0, 2]]], -1)


class MLPModel(Calibrated):
    """Calibrated MLP: predicted steps for (sun, spot); errors via the rigid body's local Jacobian."""

    def predict_steps(self, batch: RecordTable) -> torch.Tensor:
        net, ref = self.extras["net"], self.extras["reference"]
        k = self.nominal.index(batch.heliostat_index)
        with torch.no_grad():
            y = net(_inputs(batch.sun, batch.spot, ref), batch.heliostat_index)
        return k.min_steps + y * (k.max_steps - k.min_steps)

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
            # Heliostats whose MLP lost to the rigid body on validation use the rigid body (fallback).
            use = self.extras.get("use_net")
            if use is not None:
                n = torch.where(use[batch.heliostat_index].unsqueeze(-1), n, n_rec)
            return n, c


def _simulate(rigid_model: Calibrated, train: RecordTable, site, every: str, year: int, gen: torch.Generator):
    """Simulated (sun, aim, steps) per heliostat from the rigid body over a year of sun positions."""
    _, az, el = daylight_times(year, every, site.latitude_deg, site.longitude_deg, site.altitude_m,
                               min_elevation_deg=8.0)
    sun = direction_from_paint_angles(az, el).to(train.spot)
    kin = rigid_model.kinematics
    # Draws in float64 on the CPU generator (one seed, the same draws for any dtype/device), then moved.
    dev = train.spot.device
    h = kin.num_heliostats
    rows = []
    for i in range(h):
        m = train.heliostat_index == i
        if not bool(m.any()):
            continue
        # Aim points: the heliostat's measured training spots, jittered by +-1 m in the target plane.
        spots, right, up = train.spot[m], train.plane_right[m], train.plane_up[m]
        pick = torch.randint(len(spots), (len(sun),), generator=gen).to(dev)
        jit = ((torch.rand(len(sun), 2, generator=gen, dtype=torch.float64) - 0.5) * 2.0).to(spots)
        aim = spots[pick] + jit[:, :1] * right[pick] + jit[:, 1:] * up[pick]
        steps, ok = K.inverse(kin.index([i] * len(sun)), aim, sun, strict=False)
        ok = ok & torch.isfinite(steps).all(-1)
        rows.append((torch.full((int(ok.sum()),), i, dtype=torch.long, device=dev), sun[ok], aim[ok], steps[ok]))
    return [torch.cat(c) for c in zip(*rows)]


def _pretrain(net, x_sim, hidx, y_sim, steps: int, lr: float, huber, progress: bool) -> None:
    """Pretraining on the simulated records: AdaMax with a cosine schedule over ``steps``."""
    opt = torch.optim.Adamax(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    it = range(steps)
    if progress:
        it = tqdm(it, desc="mlp pretrain", leave=False)
    for _ in it:
        opt.zero_grad()
        loss = huber(net(x_sim, hidx), y_sim)
        loss.backward()
        opt.step()
        sched.step()


def _normalised_steps(kin, steps: torch.Tensor) -> torch.Tensor:
    """Motor steps [R, 2] as a fraction of each actuator's range (kinematics indexed per record)."""
    return (steps - kin.min_steps) / (kin.max_steps - kin.min_steps)


@dataclass(frozen=True)
class MLPSettings:
    """Settings of the ``mlp`` method (:func:`fit_mlp_method`; each field is also one of its keywords).

    Attributes
    ----------
    hidden, depth : int
        Width and number of hidden layers of each heliostat's network.
    every : str
        Spacing of the simulated sun positions of the pretraining year (e.g. ``"6h"``).
    year : int
        The pretraining year.
    pretrain_steps, finetune_steps : int
        Optimiser steps on the simulated records, then on the real training records (early stopping).
    lr : float
        Pretraining learning rate (fine-tuning: a fifth of it).
    site : Site or None
        Where the sun positions are computed (default: :class:`~heliotwin.site.Site`'s).
    rigid_options : dict or None
        Keywords of the ``gradient`` fit of the rigid body (pretraining data and fallback).
    """

    hidden: int = 32
    depth: int = 2
    every: str = "6h"
    year: int = 2023
    pretrain_steps: int = 500
    finetune_steps: int = 300
    lr: float = 1e-2
    site: Site | None = None
    rigid_options: dict | None = None


def fit_mlp_method(nominal, train, validation, *, seed: int = 0, progress: bool = False,
                   settings: MLPSettings | None = None, **options) -> MLPModel:
    """``mlp``: per-heliostat networks from (sun, aim) to motor steps (see module docstring).

    ``settings`` (:class:`MLPSettings`, default its defaults) and/or its fields by keyword (``options``,
    replacing ``settings``'s). The networks follow the nominal kinematics' dtype and device; every random draw
    takes ``seed``.
    """
    s = replace(settings or MLPSettings(), **options)
    hidden, depth, lr = s.hidden, s.depth, s.lr
    h, like = nominal.num_heliostats, nominal.position
    rigid = fit_gradient_method(nominal, train, validation, seed=seed, progress=progress, **(s.rigid_options or {}))
    ok = rigid.ok & trainable(train)
    gen = torch.Generator().manual_seed(int(seed))
    reference = train.plane_center[0] if len(train) else like.new_zeros(3)
    hidx, sun, aim, steps = _simulate(rigid, train, s.site or Site(), s.every, s.year, gen)
    net = BatchedMLP(h, 5, 2, hidden, depth, gen, dtype=like.dtype).to(like.device)
    huber = torch.nn.HuberLoss(delta=0.01)
    _pretrain(net, _inputs(sun, aim, reference), hidx, _normalised_steps(nominal.index(hidx), steps),
              s.pretrain_steps, lr, huber, progress)
    # Fine-tune on the real training records; early stopping on validation (state per heliostat).
    x_tr = _inputs(train.sun, train.spot, reference)
    y_tr = _normalised_steps(nominal.index(train.heliostat_index), train.motor_steps)
    model = MLPModel("mlp", list(train.heliostat_ids), nominal, rigid.names, rigid.delta, ok,
                     corrections=rigid.corrections, extras={"net": net, "reference": reference})
    has_val = validation is not None and len(validation) > 0

    def val_err(m=model):
        if not has_val:
            return like.new_full((h,), float("inf"))
        return metrics.per_heliostat_mean(m.pointing_error(validation), validation.heliostat_index, h)

    opt = torch.optim.Adamax(net.parameters(), lr=lr / 5)

    def step():
        opt.zero_grad()
        loss = huber(net(x_tr, train.heliostat_index), y_tr)
        loss.backward()
        opt.step()
        return loss

    pretrain_err = val_err()
    validated = validation.counts() > 0 if has_val else torch.zeros(h, dtype=torch.bool, device=like.device)
    log = early_stopping_fit(step, val_err, net_state(net), s.finetune_steps, validated=validated, check_every=10,
                             progress=progress, desc="mlp finetune")
    best, best_err = log.best, log.best_error
    model.extras["net"] = best
    # Fallback: the rigid body wherever the MLP is not better on validation (the report tells which).
    use_net = best_err < val_err(rigid)
    model.extras["use_net"] = use_net
    _describe(model, best, ok, use_net, pretrain_err, best_err, val_err(rigid), reference, len(hidx))
    return model


def _describe(model, best, ok, use_net, pretrain_err, best_err, rigid_val, reference, samples: int) -> None:
    """Per-heliostat report, stored networks and summary of a fitted MLP model (into ``model.extras``)."""
    def mrad(x):
        return float(x) * 1e3 if math.isfinite(x) else None

    ids = model.heliostat_ids
    model.extras["per_heliostat"] = {hid: {"validation_after_pretraining_mrad": mrad(pretrain_err[i]),
                                           "validation_after_finetuning_mrad": mrad(best_err[i]),
                                           "rigid_validation_mrad": mrad(rigid_val[i]),
                                           "uses_network": bool(use_net[i])}
                                     for i, hid in enumerate(ids) if bool(ok[i])}
    model.extras["networks"] = {hid: {"config": dict(best.config, kind="mlp", reference=reference.tolist(),
                                                     use_net=bool(use_net[i])),
                                      "state": best.state_of(i)} for i, hid in enumerate(ids) if bool(ok[i])}
    model.extras["summary"] = {"pretraining_samples": samples, "hidden": best.config["hidden"],
                               "depth": best.config["depth"], "heliostats_using_network": int((use_net & ok).sum())}


def aim_mlp(net_entry: dict, kin, sun: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Motor steps straight from a stored MLP (one heliostat)."""
    cfg = net_entry["config"]
    if not cfg.get("use_net", True):
        return K.inverse(kin, target, sun, strict=False)[0]
    net = BatchedMLP.from_state(cfg, net_entry["state"])
    ref = torch.tensor(cfg["reference"], dtype=torch.float64)
    with torch.no_grad():
        y = net(_inputs(sun.reshape(1, 3), target.reshape(1, 3), ref), torch.zeros(1, dtype=torch.long))
    return kin.min_steps + y * (kin.max_steps - kin.min_steps)
