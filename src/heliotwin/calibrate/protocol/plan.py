"""Which record next: sun positions whose calibration record would shrink a heliostat's uncertainty most.

From the Laplace posterior of a calibration (:mod:`heliotwin.calibrate.uncertainty`, stored in
``/learned/calibration``): precision ``Lambda = Sigma^-1`` over the heliostat's P deviations and residual noise ``s``. A
new record at sun position c adds ``J_c^T J_c / s^2`` to ``Lambda`` (``J_c`` [3, P]: derivative of the mirror normal at
the motor steps that aim the sun at the calibration target). What a plant cares about is the error of the
normal over the sun positions it will aim at, so the objective is the mean predictive variance of the
normal over a reference set of sun positions (the year's daylight grid),

    V(Sigma) = mean_t tr(J_t Sigma J_t^T) = tr(Sigma M),  M = mean_t J_t^T J_t,

(an I-optimal design; Atkinson, Donev & Tobias, *Optimum Experimental Designs*, 2007, ch. 10). Records are
chosen greedily: each step adds the candidate with the smallest ``V`` after its update (all candidates in
one batched solve), then updates ``Lambda``.
"""
from __future__ import annotations

import math
from dataclasses import fields

import torch

from ...errors import HeliotwinError
from ...field import kinematics as K
from ...field.plant import Kinematics
from ...field.targets import PlanarTarget
from ...sun import daylight_times, direction_from_paint_angles
from ..params import apply_deviations
from ..scenario import KEY


def normal_jacobians(nominal: Kinematics, delta: torch.Tensor, names, aim_point: torch.Tensor,
                     sun: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Derivative of the mirror normal w.r.t. the deviations when aiming the sun at ``aim_point``.

    Parameters
    ----------
    nominal : Kinematics
        One heliostat.
    delta : torch.Tensor, [P]
    aim_point : torch.Tensor, [3]
        ENU [m].
    sun : torch.Tensor, [T, 3]
        Unit vectors towards the sun.

    Returns
    -------
    jacobian : torch.Tensor, [Tr, 3, P]
        At the Tr reachable sun positions only; d(unit normal) per unit deviation (per [rad] for angles, per
        [m] for lengths).
    reachable : torch.Tensor, [T], bool
    """
    t = len(sun)
    kin_t = nominal.index([0] * t)
    d = delta.double().reshape(1, -1).expand(t, -1).clone()
    cal = apply_deviations(kin_t, d, names)
    steps, ok = K.inverse(cal, aim_point.double().reshape(1, 3).expand(t, 3), sun.double(), strict=False)
    ok = ok & ((steps >= cal.min_steps) & (steps <= cal.max_steps)).all(-1) & torch.isfinite(steps).all(-1)
    d = d.requires_grad_(True)
    rot, _ = K.forward(apply_deviations(kin_t, d, names), steps.detach())
    n = K.mirror_normal(rot)
    jac = torch.stack([torch.autograd.grad(n[:, c].sum(), d, retain_graph=c < 2)[0] for c in range(3)], 1)
    return jac[ok].detach(), ok


def greedy_design(precision: torch.Tensor, noise: float, candidates: torch.Tensor, reference: torch.Tensor,
                  count: int) -> tuple[list, list]:
    """Greedy I-optimal choice of ``count`` candidates.

    Parameters
    ----------
    precision : torch.Tensor, [P, P]
        Current posterior precision.
    noise : float
        Residual noise per component [rad].
    candidates : torch.Tensor, [C, 3, P]
        Normal Jacobians of the candidate records.
    reference : torch.Tensor, [T, 3, P]
        Normal Jacobians of the sun positions the objective averages over.

    Returns
    -------
    chosen : list of int (indices into candidates)
    rms : list of float, length count + 1
        ``sqrt(V)`` [rad] before and after each choice.
    """
    m = torch.einsum("tci,tcj->ij", reference, reference) / max(1, len(reference))
    info = torch.einsum("kci,kcj->kij", candidates, candidates) / noise ** 2  # [C, P, P]
    lam = precision.double().clone()
    eye = torch.eye(lam.shape[0], dtype=torch.float64)
    rms = [math.sqrt(max(0.0, float(torch.trace(torch.linalg.solve(lam, eye) @ m))))]
    chosen: list = []
    for _ in range(count):
        cov = torch.linalg.solve(lam + info, eye.expand_as(info))
        v = torch.einsum("kij,ji->k", cov, m)
        if chosen:
            v[chosen] = float("inf")  # one record per sun position and time
        k = int(torch.argmin(v))
        chosen.append(k)
        lam = lam + info[k]
        rms.append(math.sqrt(max(0.0, float(v[k]))))
    return chosen, rms


def plan(scenario, heliostat_id: str, *, year: int, every: str = "1h", count: int = 5, target: str | None = None,
         min_elevation_deg: float = 15.0, sky: bool = False) -> dict:
    """Sun positions (times of ``year``) whose records would shrink ``heliostat_id``'s uncertainty most.

    Parameters
    ----------
    scenario : heliotwin.io.scenario.Scenario
        Calibrated with a stored posterior (``--method lm``).
    heliostat_id : str
    year : int
    every : str
        Spacing of the candidate times (a pandas frequency, e.g. ``"1h"``).
    count : int
        Sun positions to propose.
    target : str, optional
        Planar calibration target to aim at (default: the first by name).
    min_elevation_deg : float
        Lowest sun elevation considered [deg].
    sky : bool
        Also return the predictive spread over every candidate time.

    Returns
    -------
    dict
        ``proposals`` (list of {time (UTC ISO), sun_azimuth_deg, sun_elevation_deg, rms_after_mrad}),
        ``rms_now_mrad`` (root mean predictive variance of the normal over the year's sun positions, from
        the parameters alone; the per-record noise comes on top), ``target``, ``candidates``. With ``sky``
        also ``sky``: numpy arrays over the C reachable candidate times, ``sun_azimuth_deg`` [C],
        ``sun_elevation_deg`` [C] and ``std_now_mrad`` [C] (``sqrt(tr(J Sigma J^T))``: the predictive spread
        of the normal there; its mean square is ``rms_now_mrad`` squared), for
        :func:`heliotwin.calibrate.report.plot_plan`.
    """
    cal = scenario.learned.get(KEY) or {}
    if heliostat_id not in (cal.get("heliostats") or []):
        raise HeliotwinError(f"{scenario.path}: heliostat {heliostat_id} is not calibrated in this scenario")
    if not cal.get("posterior"):
        raise HeliotwinError(f"{scenario.path} [/learned/{KEY}/posterior]: no posterior stored (calibrate with "
                             "--method lm to get one)")
    plant = scenario.plant
    planar = sorted(n for n, t in plant.targets.items() if isinstance(t, PlanarTarget))
    name = target or (planar[0] if planar else None)
    if name not in planar:
        raise HeliotwinError(f"target {name!r} is not a planar calibration target; known: {', '.join(planar)}")
    j = list(cal["heliostats"]).index(heliostat_id)
    names = list(cal["parameter_names"])
    nominal = Kinematics(**{f.name: torch.as_tensor(cal["nominal"][f.name])[j:j + 1] for f in fields(Kinematics)})
    delta = torch.as_tensor(cal["deviations"], dtype=torch.float64)[j]
    cov = torch.as_tensor(cal["posterior"]["covariance"], dtype=torch.float64)[j]
    noise = float(torch.as_tensor(cal["posterior"]["noise_rad"], dtype=torch.float64)[j])
    site = plant.site
    times, az, el = daylight_times(year, every, site.latitude_deg, site.longitude_deg, site.altitude_m,
                                   min_elevation_deg)
    sun = direction_from_paint_angles(az, el)
    jac, ok = normal_jacobians(nominal, delta, names, plant.targets[name].center, sun)
    if len(jac) == 0:
        raise HeliotwinError(f"{heliostat_id} cannot aim at {name} at any daylight time of {year}")
    chosen, rms = greedy_design(torch.linalg.inv(cov), noise, jac, jac, count)
    keep = ok.nonzero().flatten()
    proposals = [{"time": times[int(keep[k])].isoformat(), "sun_azimuth_deg": math.degrees(float(az[keep[k]])),
                  "sun_elevation_deg": math.degrees(float(el[keep[k]])), "rms_after_mrad": 1e3 * rms[i + 1]}
                 for i, k in enumerate(chosen)]
    ans = {"heliostat": heliostat_id, "target": name, "year": int(year), "candidates": int(len(jac)),
           "rms_now_mrad": 1e3 * rms[0], "proposals": proposals}
    if sky:
        std = torch.einsum("tci,ij,tcj->t", jac, cov, jac).clamp_min(0.0).sqrt()
        ans["sky"] = {"sun_azimuth_deg": torch.rad2deg(az[keep]).numpy(),
                      "sun_elevation_deg": torch.rad2deg(el[keep]).numpy(), "std_now_mrad": 1e3 * std.numpy()}
    return ans
