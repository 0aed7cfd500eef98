"""Which record next: sun positions whose calibration record would shrink a heliostat's uncertainty most.

From the Laplace posterior of a calibration (:mod:`heliotwin.calibrate.uncertainty`, stored in
``/learned/calibration``): precision ``Lambda = Sigma^-1`` over the heliostat's P deviations and residual noise ``s``. A
new record at sun position c adds ``J_c^T J_c / s^2`` to ``Lambda`` (``J_c`` [3, P]: derivative of the mirror normal at
the motor steps that aim the sun at the calibration target). What a plant cares about is the error of the
normal over the sun positions it will aim at, so the objective is the mean predictive variance of the
normal over the reference sun positions of the year from the planned day on, whose root is the predicted pointing
spread (:mod:`heliotwin.calibrate.spread`: the one definition ``plan``, ``daily`` and the report print),

    V(Sigma) = mean_t tr(J_t Sigma J_t^T) = tr(Sigma M),  M = mean_t J_t^T J_t,

(an I-optimal design; Atkinson, Donev & Tobias, *Optimum Experimental Designs*, 2007, ch. 10). Records are
chosen greedily: each step adds the candidate with the smallest ``V`` after its update (all candidates in
one batched solve), then updates ``Lambda``.
"""
from __future__ import annotations

import math

import pandas as pd
import torch

from ...errors import HeliotwinError
from ...field.plant import Kinematics
from ...sun import daylight_times, daylight_window, direction_from_paint_angles, solar_position
from ..scenario import KEY
from ..spread import (
    DEFINITION,
    REFERENCE_EVERY,
    calibration_target,
    day_start,
    normal_jacobians_many,
    predicted_spread,
    spread_after,
    stored_nominal,
)

__all__ = ["normal_jacobians", "normal_jacobians_many", "greedy_design", "plan", "plant_plan", "RANKED_BY",
           "REFERENCE_EVERY"]


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
    jac, ok = normal_jacobians_many(nominal, delta.reshape(1, -1), names, aim_point, sun)
    return jac[0][ok[0]], ok[0]


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
    reference : torch.Tensor, [T, 3, P] or [P, P]
        Normal Jacobians of the sun positions the objective averages over, or their metric ``mean_t J_t^T J_t``
        (:func:`heliotwin.calibrate.spread.spread_metric`).

    Returns
    -------
    chosen : list of int (indices into candidates)
    rms : list of float, length count + 1
        ``sqrt(V)`` [rad] before and after each choice.
    """
    if reference.dim() == 2:
        m = reference.double()
    else:
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
         min_elevation_deg: float = 15.0, sky: bool = False, since=None) -> dict:
    """Sun positions (times of ``year``) whose records would shrink ``heliostat_id``'s predicted pointing spread
    (:mod:`heliotwin.calibrate.spread`) most.

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
        Lowest sun elevation of a candidate [deg].
    sky : bool
        Also return the predictive error of the normal at every candidate time.
    since : pandas.Timestamp, optional
        Candidates over the year from this UTC day on (the plant's own next year) instead of ``year``; the spread
        is the one of that day (else of January 1 of ``year``).

    Returns
    -------
    dict
        ``proposals`` (list of {time (UTC ISO), sun_azimuth_deg, sun_elevation_deg, spread_after_mrad: the
        predicted pointing spread after this and the earlier proposals' records}), ``spread_now_mrad`` (the
        predicted pointing spread on ``spread_day``), ``spread_day``, ``spread_definition``, ``target``,
        ``candidates``. With ``sky`` also ``sky``: numpy arrays over the C reachable candidate times,
        ``sun_azimuth_deg`` [C], ``sun_elevation_deg`` [C] (PAINT: 0 = south, +90 = east) and ``std_now_mrad``
        [C] (``sqrt(tr(J Sigma J^T))``: the predicted error of the normal there, the covariance grown to the
        spread's day), for :func:`heliotwin.calibrate.report.plot_plan`.
    """
    cal = scenario.learned.get(KEY) or {}
    if heliostat_id not in (cal.get("heliostats") or []):
        raise HeliotwinError(f"{scenario.path}: heliostat {heliostat_id} is not calibrated in this scenario")
    name = calibration_target(scenario, cal, target)
    plant = scenario.plant
    spread_day = day_start(since if since is not None else f"{int(year)}-01-01")
    sp = predicted_spread(scenario, spread_day, heliostats=[heliostat_id], target=name)
    j = sp.rows[0]
    names = list(cal["parameter_names"])
    nominal = stored_nominal(cal, [j])
    delta = torch.as_tensor(cal["deviations"], dtype=torch.float64)[j]
    cov = sp.covariance[0]
    noise = float(torch.as_tensor(cal["posterior"]["noise_rad"], dtype=torch.float64)[j])
    site = plant.site
    if since is None:
        times, az, el = daylight_times(year, every, site.latitude_deg, site.longitude_deg, site.altitude_m,
                                       min_elevation_deg)
    else:
        times, az, el = daylight_window(spread_day, spread_day + pd.DateOffset(years=1), every, site.latitude_deg,
                                        site.longitude_deg, site.altitude_m, min_elevation_deg)
    sun = direction_from_paint_angles(az, el)
    jac, ok = normal_jacobians(nominal, delta, names, plant.targets[name].center, sun)
    if len(jac) == 0:
        raise HeliotwinError(f"{heliostat_id} cannot aim at {name} at any daylight time of {year}")
    chosen, rms = greedy_design(torch.linalg.inv(cov), noise, jac, sp.metric[0], count)
    keep = ok.nonzero().flatten()
    proposals = [{"time": times[int(keep[k])].isoformat(), "sun_azimuth_deg": math.degrees(float(az[keep[k]])),
                  "sun_elevation_deg": math.degrees(float(el[keep[k]])), "spread_after_mrad": 1e3 * rms[i + 1]}
                 for i, k in enumerate(chosen)]
    ans = {"heliostat": heliostat_id, "target": name, "year": int(year), "candidates": int(len(jac)),
           "spread_now_mrad": float(sp.spread_mrad[0]), "spread_day": sp.day, "spread_definition": DEFINITION,
           "proposals": proposals}
    if sky:
        std = torch.einsum("tci,ij,tcj->t", jac, cov, jac).clamp_min(0.0).sqrt()
        ans["sky"] = {"sun_azimuth_deg": torch.rad2deg(az[keep]).numpy(),
                      "sun_elevation_deg": torch.rad2deg(el[keep]).numpy(), "std_now_mrad": 1e3 * std.numpy()}
    return ans


# ------------------------------------------------------------------------------------------ the plant's day
#: What a plant plan ranks by (printed with it).
RANKED_BY = "open and new step alarms first, then the largest predicted pointing spread on the day"


def plant_plan(scenario, *, day: str, slots: int = 20, every: str = "30min", target: str | None = None,
               min_elevation_deg: float = 15.0, urgent=()) -> dict:
    """Tomorrow's calibration plan for the plant: which heliostats to record on ``day`` and at which sun
    position, one heliostat at a time on the calibration target.

    Heliostats are ranked (:data:`RANKED_BY`: ``urgent`` ones first, e.g. those with a step alarm; then by their
    predicted pointing spread on that day, :func:`heliotwin.calibrate.spread.predicted_spread`, largest first);
    each of the ``slots`` first gets the candidate time of ``day`` (every ``every``, sun above
    ``min_elevation_deg``) whose record shrinks that spread most (the I-optimal choice of :func:`plan`, one
    record; all heliostats in one batched solve), at most ``ceil(slots / candidates)`` heliostats per time.

    Returns
    -------
    dict
        ``day``, ``target``, ``candidates`` (times of the day), ``heliostats`` (calibrated), ``slots``,
        ``ranked_by``, ``spread_definition``, ``spread_mrad`` {heliostat: spread on the day}, ``proposals`` (per
        planned heliostat in priority order: ``heliostat``, ``time`` UTC ISO, ``sun_azimuth_deg``,
        ``sun_elevation_deg`` (PAINT: 0 = south, +90 = east), ``reason``, ``spread_now_mrad``,
        ``spread_after_mrad``), the spread's median and 95th percentile over the plant [mrad] and, when fewer
        than ``slots`` are planned, ``why_fewer``.
    """
    cal = scenario.learned.get(KEY) or {}
    name = calibration_target(scenario, cal, target)
    plant = scenario.plant
    urgent = set(urgent)
    start = day_start(day)
    ids, names = list(cal["heliostats"]), list(cal["parameter_names"])
    sp = predicted_spread(scenario, start, target=name)
    spread = sp.spread_mrad
    order = sorted(range(len(ids)), key=lambda h: (ids[h] not in urgent, -float(spread[h])))
    chosen = order[:max(0, int(slots))]
    site = plant.site
    stamps = pd.date_range(start, start + pd.Timedelta("1D"), freq=every, inclusive="left")
    az, el = solar_position(stamps, site.latitude_deg, site.longitude_deg, site.altitude_m)
    up = el > math.radians(min_elevation_deg)
    stamps, az, el = stamps[up.numpy()], az[up], el[up]
    summary = sp.summary()
    out = {"day": sp.day, "target": name, "candidates": int(len(stamps)), "heliostats": len(ids),
           "slots": int(slots), "ranked_by": RANKED_BY, "spread_definition": DEFINITION,
           "median_spread_mrad": summary["median_mrad"], "p95_spread_mrad": summary["p95_mrad"],
           "spread_mrad": {h: float(v) for h, v in zip(ids, spread)}, "proposals": []}
    if not chosen or not len(stamps):
        out["why_fewer"] = ("no candidate time with the sun above the minimum elevation" if not len(stamps)
                            else "no calibrated heliostat" if not ids else "no slots asked for")
        return out
    idx = torch.tensor(chosen)
    nominal = stored_nominal(cal, chosen)
    delta = torch.as_tensor(cal["deviations"], dtype=torch.float64)[idx]
    noise = torch.as_tensor(cal["posterior"]["noise_rad"], dtype=torch.float64)[idx].clamp_min(1e-6)
    cand, cand_ok = normal_jacobians_many(nominal, delta, names, plant.targets[name].center,
                                          direction_from_paint_angles(az, el))
    info = torch.einsum("ktci,ktcj->ktij", cand, cand) / noise[:, None, None, None] ** 2
    after = spread_after(sp.covariance[idx][:, None], sp.metric[idx][:, None], info)  # [K, C] [mrad]
    after = torch.where(cand_ok, after, torch.full_like(after, math.inf))
    per_time = math.ceil(len(chosen) / len(stamps))
    load = [0] * len(stamps)
    for j, h in enumerate(chosen):  # priority order; K <= slots heliostats, bookkeeping only
        free = torch.tensor([c < per_time for c in load])
        v = torch.where(free, after[j], torch.full_like(after[j], math.inf))
        c = int(torch.argmin(v))
        if not math.isfinite(float(v[c])):
            continue  # cannot reach the target at any free time of the day
        load[c] += 1
        out["proposals"].append({
            "heliostat": ids[h], "time": stamps[c].isoformat(), "sun_azimuth_deg": math.degrees(float(az[c])),
            "sun_elevation_deg": math.degrees(float(el[c])),
            "reason": "step alarm" if ids[h] in urgent else "largest predicted pointing spread",
            "spread_now_mrad": float(spread[h]), "spread_after_mrad": float(v[c])})
    fewer = []
    if len(ids) < int(slots):
        fewer.append(f"the plant has {len(ids)} calibrated heliostat(s), one record each")
    if len(out["proposals"]) < len(chosen):
        fewer.append(f"{len(chosen) - len(out['proposals'])} heliostat(s) cannot reach the target at a free time")
    if fewer:
        out["why_fewer"] = "; ".join(fewer)
    return out
