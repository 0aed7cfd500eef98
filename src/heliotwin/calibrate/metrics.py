"""Pointing error and miss distance of a kinematic model on calibration records: the one home of both.

Pointing error of a record = angle between the model's mirror normal at the recorded motor steps and the
*measured* normal, the bisector of the direction to the sun and the direction from the concentrator to the
measured focal spot. The angle is :func:`heliotwin.geometry.angle_between` (``atan2(|a x b|, a . b)``):
``acos`` of a dot product loses half the digits near zero (an error of 0.1 mrad would be resolved to
~0.01 mrad only), and calibrated errors are ~1 mrad.

:func:`pointing_error` (kinematics with a heliostat axis + a :class:`~heliotwin.io.records.RecordTable`)
is what calibration, its report and validation all use; models whose normals do not come from rigid-body
kinematics (hybrid, MLP) go through :func:`pointing_error_of_normals`. :func:`record_jacobian` (the residuals
and their derivative w.r.t. the deviations of :mod:`.params`) is what the LM fit, the drift model and the
predictive intervals linearise.
"""
from __future__ import annotations

import torch

from ..field import kinematics as K
from ..field.actuators import steps_to_angle
from ..field.plant import Kinematics
from ..geometry import angle_between, ray_plane, reflect
from ..io.records import RecordTable
from .params import ACTUATOR_FIELDS, FIELD_OF, apply_deviations


def per_record_kinematics(kin: Kinematics, batch: RecordTable) -> Kinematics:
    """Kinematics with one entry per record (``kin`` has the batch's H heliostats)."""
    return kin.index(batch.heliostat_index)


def model_normals(kin: Kinematics, batch: RecordTable, *, per_record: bool = False):
    """Model mirror normal and concentrator at the recorded motor steps.

    Parameters
    ----------
    kin : Kinematics
        H heliostats (``per_record=False``) or R entries already indexed per record.
    batch : RecordTable
        R records.

    Returns
    -------
    normal : torch.Tensor, [R, 3]
        Unit mirror normal, ENU.
    concentrator : torch.Tensor, [R, 3]
        ENU [m].
    """
    k = kin if per_record else per_record_kinematics(kin, batch)
    R, c = K.forward(k, batch.motor_steps)
    return K.mirror_normal(R), c


def measured_normals(batch: RecordTable, concentrator: torch.Tensor) -> torch.Tensor:
    """Bisector of the sun direction and the direction concentrator -> measured focal spot, [R, 3]."""
    return K.bisector_normal(batch.sun, concentrator, batch.spot)


def normal_residuals(kin: Kinematics, batch: RecordTable, *, per_record: bool = False) -> torch.Tensor:
    """Model minus measured normal, [R, 3]; its norm equals the pointing error to second order (rad)."""
    n, c = model_normals(kin, batch, per_record=per_record)
    return n - measured_normals(batch, c)


def record_jacobian(nominal_per_record: Kinematics, batch: RecordTable, delta_rec: torch.Tensor, names):
    """Residuals [R, 3] and their derivative w.r.t. each record's own parameters [R, 3, P].

    Analytic: the chain's derivatives by its coordinates (:func:`heliotwin.field.kinematics.pose_derivatives`),
    the actuators' by their parameters (element-wise, one reverse pass over [R, 2] angles) and the measured
    normal's by the concentrator it is seen from, chained per record. It equals the reverse-mode Jacobian of
    :func:`normal_residuals` (:func:`record_jacobian_autograd`) to rounding at ~4x less cost: this is what
    every least-squares iteration of the calibration evaluates.

    Parameters
    ----------
    nominal_per_record : Kinematics
        R entries, one per record (its heliostat's kinematics).
    batch : RecordTable
        R records (``motor_steps``, ``sun`` and ``spot`` are read).
    delta_rec : torch.Tensor, [R, P]
        Each record's heliostat's deviations (rad, m, relative; see :mod:`.params`).
    names : sequence of str, length P
        The deviations' names.

    Returns
    -------
    residuals : torch.Tensor, [R, 3]
        :func:`normal_residuals` (model minus measured normal), detached.
    jacobian : torch.Tensor, [R, 3, P]
        Per natural unit of each parameter (1/rad, 1/m, 1 per relative increment).
    """
    with torch.no_grad():
        kin = apply_deviations(nominal_per_record, delta_rec.detach(), names)
    fields = [FIELD_OF[n] for n in names]
    actuator = sorted({f for f, _ in fields if f in ACTUATOR_FIELDS})
    with torch.enable_grad():  # d theta_j / d (axis j's actuator parameters): element-wise, so one pass
        leaves = {f: getattr(kin, f).detach().clone().requires_grad_(True) for f in actuator}
        kwargs = {f: getattr(kin, f) for f in ACTUATOR_FIELDS} | leaves
        angles = steps_to_angle(torch.as_tensor(batch.motor_steps), clockwise=kin.clockwise, linear=kin.linear,
                                **kwargs)
        grads = dict(zip(actuator, torch.autograd.grad(angles.sum(), list(leaves.values())))) if actuator else {}
    coords = [("angle", (idx[0],)) if f in ACTUATOR_FIELDS else (f, idx) for f, idx in fields]
    with torch.no_grad():
        normal, conc, d_normal, d_conc = K.pose_derivatives(kin, angles.detach(), coords)
        measured, d_res = _bisector_and_residual_derivative(batch.sun, conc, batch.spot, d_normal, d_conc)
        scale = [torch.ones_like(angles[:, 0])] * len(names)
        for p, (f, idx) in enumerate(fields):
            if f in ACTUATOR_FIELDS:
                scale[p] = grads[f][:, idx[0]]
                if f == "increment":  # relative deviation: increment = nominal (1 + delta)
                    scale[p] = scale[p] * nominal_per_record.increment[:, idx[0]]
        return normal - measured, d_res * torch.stack(scale, -1).unsqueeze(1)


def _bisector_and_residual_derivative(sun, concentrator, spot, d_normal, d_concentrator):
    """The measured normal ``b = unit(s + unit(spot - c))`` (:func:`~heliotwin.field.kinematics.bisector_normal`)
    [R, 3] and the residual's derivative ``d_normal - (db/dc) d_concentrator`` [R, 3, C], with
    ``db/dc = -(I - b b^T) / |m| (I - u u^T) / |w|`` applied as two projections (no matrix products)."""
    w = spot - concentrator
    dw = torch.linalg.norm(w, dim=-1, keepdim=True).clamp_min(1e-300)
    u = w / dw
    m = sun + u
    dm = torch.linalg.norm(m, dim=-1, keepdim=True).clamp_min(1e-300)
    b = m / dm
    v = d_concentrator / dw.unsqueeze(-1)
    v = v - u.unsqueeze(-1) * (u.unsqueeze(-1) * v).sum(1, keepdim=True)
    v = (v - b.unsqueeze(-1) * (b.unsqueeze(-1) * v).sum(1, keepdim=True)) / dm.unsqueeze(-1)
    return b, d_normal + v


def record_jacobian_autograd(nominal_per_record: Kinematics, batch: RecordTable, delta_rec: torch.Tensor, names):
    """:func:`record_jacobian` by reverse-mode autograd (three passes, one per residual component): the
    reference the analytic one is tested against. Same arguments (``delta_rec`` [R, P]) and returns
    (residuals [R, 3], Jacobian [R, 3, P] per natural unit)."""
    d = delta_rec.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        r = normal_residuals(apply_deviations(nominal_per_record, d, names), batch, per_record=True)
        jac = [torch.autograd.grad(r[:, c].sum(), d, retain_graph=c < 2)[0] for c in range(3)]
    return r.detach(), torch.stack(jac, 1)


def pointing_error_of_normals(normal: torch.Tensor, concentrator: torch.Tensor, batch: RecordTable) -> torch.Tensor:
    """Pointing error per record [rad], [R], of model normals [R, 3] at concentrators [R, 3] (ENU, m)."""
    return angle_between(normal, measured_normals(batch, concentrator))


def pointing_error(kin: Kinematics, batch: RecordTable, *, per_record: bool = False) -> torch.Tensor:
    """Pointing error per record [rad], shape [R].

    Parameters
    ----------
    kin : Kinematics
        The batch's H heliostats (``batch.heliostat_index`` indexes them), or R entries already indexed
        per record (``per_record=True``).
    batch : RecordTable
        R records; the measured normal uses ``batch.spot``.
    """
    n, c = model_normals(kin, batch, per_record=per_record)
    return pointing_error_of_normals(n, c, batch)


def predicted_spot(normal: torch.Tensor, concentrator: torch.Tensor, batch: RecordTable) -> torch.Tensor:
    """Where the reflected central ray meets the record's target plane, ENU [R, 3].

    A ray parallel to the plane (never the case for a heliostat aiming at its target) gives NaN; the caller
    reports that record rather than averaging it.
    """
    reflected = reflect(-batch.sun, normal)
    t, _ = ray_plane(concentrator, reflected, batch.plane_center, batch.plane_normal)
    parallel = (reflected * batch.plane_normal).sum(-1).abs() <= 1e-12  # ray_plane's t = 0 there: not a spot
    t = torch.where(parallel, torch.full_like(t, float("nan")), t)
    return concentrator + t.unsqueeze(-1) * reflected


def miss_distance(kin: Kinematics, batch: RecordTable, *, per_record: bool = False) -> torch.Tensor:
    """In-plane distance [m] between predicted and measured spot on the target plane, [R].

    The measured spot is compared in the plane's (right, up) coordinates, so a centroid a few cm behind
    the plane (multi-focus tower) does not add its depth to the miss.
    """
    n, c = model_normals(kin, batch, per_record=per_record)
    return miss_distance_of_normals(n, c, batch)


def miss_distance_of_normals(normal: torch.Tensor, concentrator: torch.Tensor, batch: RecordTable) -> torch.Tensor:
    """:func:`miss_distance` [m], [R], of model normals [R, 3] at concentrators [R, 3] (ENU, m)."""
    d = predicted_spot(normal, concentrator, batch) - batch.spot
    return torch.sqrt(((d * batch.plane_right).sum(-1)) ** 2 + ((d * batch.plane_up).sum(-1)) ** 2)


def per_heliostat_mean(values: torch.Tensor, heliostat_index: torch.Tensor, num_heliostats: int) -> torch.Tensor:
    """Mean of per-record ``values`` [R] per heliostat, [H]; ``inf`` for a heliostat without records.

    ``inf`` (not NaN) so that an early-stopping comparison ``error < best`` is simply False there.
    """
    s = values.new_zeros(num_heliostats).index_add_(0, heliostat_index, values)
    c = torch.bincount(heliostat_index, minlength=num_heliostats)
    return torch.where(c > 0, s / c.clamp_min(1), torch.full_like(s, float("inf")))


def summarize(errors_rad: torch.Tensor, miss_m: torch.Tensor | None = None) -> dict:
    """Median/mean/max [mrad] (and median miss [m]) of one heliostat's records; NaN-free or ``None``.

    ``errors_rad`` (R,) pointing errors [rad]; ``miss_m`` (R,) focal-spot misses [m], optional.
    """
    e = errors_rad.detach().double() * 1e3
    if e.numel() == 0:
        return {"n": 0, "median_mrad": None, "mean_mrad": None, "max_mrad": None, "median_miss_m": None}
    out = {"n": int(e.numel()), "median_mrad": float(e.quantile(0.5)), "mean_mrad": float(e.mean()),
           "max_mrad": float(e.max())}
    if miss_m is not None:
        out["median_miss_m"] = float(miss_m.detach().double().quantile(0.5))
    return out
