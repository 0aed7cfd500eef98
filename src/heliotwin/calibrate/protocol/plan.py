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

import pandas as pd
import torch

from ...errors import HeliotwinError
from ...field import kinematics as K
from ...field.plant import Kinematics
from ...field.targets import PlanarTarget
from ...sun import daylight_times, daylight_window, direction_from_paint_angles, solar_position
from ..clock import OFFSET_NAMES, grown_covariance
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
    jac, ok = normal_jacobians_many(nominal, delta.reshape(1, -1), names, aim_point, sun)
    return jac[0][ok[0]], ok[0]


def _posterior_and_target(scenario, cal: dict, target: str | None) -> str:
    """The planar calibration target a plan aims at (``target``, default the first by name), checking that the
    calibration ``cal`` stores a posterior (one-line errors otherwise)."""
    if not cal.get("posterior"):
        raise HeliotwinError(f"{scenario.path} [/learned/{KEY}/posterior]: no posterior stored (calibrate with "
                             "--method lm to get one)")
    planar = sorted(n for n, t in scenario.plant.targets.items() if isinstance(t, PlanarTarget))
    name = target or (planar[0] if planar else None)
    if name not in planar:
        raise HeliotwinError(f"target {name!r} is not a planar calibration target; known: {', '.join(planar)}")
    return name


def _nominal(cal: dict, rows: list) -> Kinematics:
    """The stored nominal kinematics of the calibrated heliostats ``rows`` (positions in ``cal["heliostats"]``)."""
    return Kinematics(**{f.name: torch.as_tensor(cal["nominal"][f.name])[rows] for f in fields(Kinematics)})


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
         min_elevation_deg: float = 15.0, sky: bool = False, since=None) -> dict:
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
    since : pandas.Timestamp, optional
        Candidates over the year from this UTC instant on (the plant's own next year) instead of ``year``.

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
    name = _posterior_and_target(scenario, cal, target)
    plant = scenario.plant
    j = list(cal["heliostats"]).index(heliostat_id)
    names = list(cal["parameter_names"])
    nominal = _nominal(cal, [j])
    delta = torch.as_tensor(cal["deviations"], dtype=torch.float64)[j]
    cov = torch.as_tensor(cal["posterior"]["covariance"], dtype=torch.float64)[j]
    noise = float(torch.as_tensor(cal["posterior"]["noise_rad"], dtype=torch.float64)[j])
    site = plant.site
    if since is None:
        times, az, el = daylight_times(year, every, site.latitude_deg, site.longitude_deg, site.altitude_m,
                                       min_elevation_deg)
    else:
        times, az, el = daylight_window(since, since + pd.DateOffset(years=1), every, site.latitude_deg,
                                        site.longitude_deg, site.altitude_m, min_elevation_deg)
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


# ------------------------------------------------------------------------------------------ the plant's day
#: Spacing of the reference sun positions over the year that a plant plan's objective averages over (25 h: every
#: time of day in turn, about one a day).
REFERENCE_EVERY = "25h"


def normal_jacobians_many(nominal: Kinematics, delta: torch.Tensor, names, aim_point: torch.Tensor,
                          sun: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`normal_jacobians` of K heliostats at once, at every sun position.

    Parameters
    ----------
    nominal : Kinematics
        K heliostats.
    delta : torch.Tensor, [K, P]
    aim_point : torch.Tensor, [3]
        ENU [m].
    sun : torch.Tensor, [T, 3]

    Returns
    -------
    jacobian : torch.Tensor, [K, T, 3, P]
        d(unit normal) per unit deviation; zero where the sun position is not reachable.
    reachable : torch.Tensor, [K, T], bool
    """
    k, t = delta.shape[0], len(sun)
    rows = torch.arange(k).repeat_interleave(t)
    kin = nominal.index(rows.tolist())
    d = delta.double()[rows].clone()
    cal = apply_deviations(kin, d, names)
    s = sun.double().repeat(k, 1)
    steps, ok = K.inverse(cal, aim_point.double().reshape(1, 3).expand(k * t, 3), s, strict=False)
    ok = ok & ((steps >= cal.min_steps) & (steps <= cal.max_steps)).all(-1) & torch.isfinite(steps).all(-1)
    steps = torch.where(ok[:, None], steps, cal.min_steps)  # a reachable stand-in keeps the gradient finite
    d = d.requires_grad_(True)
    rot, _ = K.forward(apply_deviations(kin, d, names), steps.detach())
    n = K.mirror_normal(rot)
    jac = torch.stack([torch.autograd.grad(n[:, c].sum(), d, retain_graph=c < 2)[0] for c in range(3)], 1)
    jac = torch.where(ok[:, None, None], jac.detach(), torch.zeros((), dtype=jac.dtype))
    return jac.reshape(k, t, 3, -1), ok.reshape(k, t)


def _spread_now(cal: dict, names: list, day_s: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Each calibrated heliostat's predicted pointing spread on the planned day [rad] (root of the summed
    variances of its axis offsets, the random walk grown to the day's noon from the state's time:
    :func:`heliotwin.calibrate.clock.grown_covariance`) and the posterior covariance [H, P, P] at that day."""
    cov, _ = grown_covariance(cal, names, day_s + 43200.0)
    drift = cal.get("drift") or {}
    offset_names = [n for n in drift.get("names") or OFFSET_NAMES if n in names]
    cols = torch.tensor([names.index(n) for n in offset_names], dtype=torch.long)
    spread = cov[:, cols, cols].sum(-1).clamp_min(0.0).sqrt()
    return spread, cov


def plant_plan(scenario, *, day: str, slots: int = 20, every: str = "30min", target: str | None = None,
               min_elevation_deg: float = 15.0, urgent=()) -> dict:
    """Tomorrow's calibration plan for the plant: which heliostats to record on ``day`` and at which sun
    position, one heliostat at a time on the calibration target.

    Heliostats are ranked (``urgent`` ones first, e.g. those that raised a step alarm; then by their predicted
    pointing spread on that day, :func:`_spread_now`); each of the ``slots`` most in need gets the candidate
    time of ``day`` (every ``every``, sun above ``min_elevation_deg``) whose record shrinks its mean predictive
    variance of the mirror normal over the year's sun positions most (the I-optimal choice of :func:`plan`, one
    record; all heliostats in one batched solve), at most ``ceil(slots / candidates)`` heliostats per time.

    Returns
    -------
    dict
        ``day``, ``target``, ``candidates`` (times of the day), ``heliostats`` (ranked), ``proposals`` (per
        planned heliostat in priority order: ``heliostat``, ``time`` UTC ISO, ``sun_azimuth_deg``,
        ``sun_elevation_deg``, ``reason``, ``spread_now_mrad``, ``rms_now_mrad``, ``rms_after_mrad``), and the
        spread's median and 95th percentile over the plant [mrad].
    """
    cal = scenario.learned.get(KEY) or {}
    name = _posterior_and_target(scenario, cal, target)
    plant = scenario.plant
    urgent = set(urgent)
    try:
        start = pd.Timestamp(day)
        start = (start.tz_localize("UTC") if start.tzinfo is None else start.tz_convert("UTC")).normalize()
    except (ValueError, TypeError):
        raise HeliotwinError(f"--day: cannot parse {day!r} (expected a UTC date, e.g. 2024-06-21)") from None
    ids, names = list(cal["heliostats"]), list(cal["parameter_names"])
    spread, cov = _spread_now(cal, names, start.timestamp())
    order = sorted(range(len(ids)), key=lambda h: (ids[h] not in urgent, -float(spread[h])))
    chosen = order[:max(0, int(slots))]
    site = plant.site
    stamps = pd.date_range(start, start + pd.Timedelta("1D"), freq=every, inclusive="left")
    az, el = solar_position(stamps, site.latitude_deg, site.longitude_deg, site.altitude_m)
    up = el > math.radians(min_elevation_deg)
    stamps, az, el = stamps[up.numpy()], az[up], el[up]
    out = {"day": start.date().isoformat(), "target": name, "candidates": int(len(stamps)), "heliostats": len(ids),
           "median_spread_mrad": 1e3 * float(spread.median()) if len(ids) else None,
           "p95_spread_mrad": 1e3 * float(torch.quantile(spread, 0.95)) if len(ids) else None, "proposals": []}
    out["slots"] = int(slots)
    if not chosen or not len(stamps):
        out["why_fewer"] = ("no candidate time with the sun above the minimum elevation" if not len(stamps)
                            else "no calibrated heliostat" if not ids else "no slots asked for")
        return out
    idx = torch.tensor(chosen)
    nominal = _nominal(cal, chosen)
    delta = torch.as_tensor(cal["deviations"], dtype=torch.float64)[idx]
    noise = torch.as_tensor(cal["posterior"]["noise_rad"], dtype=torch.float64)[idx].clamp_min(1e-6)
    aim_point = plant.targets[name].center
    _, raz, rel = daylight_times(start.year, REFERENCE_EVERY, site.latitude_deg, site.longitude_deg, site.altitude_m,
                                 min_elevation_deg)
    ref, ref_ok = normal_jacobians_many(nominal, delta, names, aim_point, direction_from_paint_angles(raz, rel))
    cand, cand_ok = normal_jacobians_many(nominal, delta, names, aim_point, direction_from_paint_angles(az, el))
    m = torch.einsum("ktci,ktcj->kij", ref, ref) / ref_ok.sum(1).clamp_min(1)[:, None, None]
    lam = torch.linalg.inv(cov[idx])
    info = torch.einsum("ktci,ktcj->ktij", cand, cand) / noise[:, None, None, None] ** 2
    eye = torch.eye(lam.shape[-1], dtype=torch.float64)
    after = torch.einsum("ktij,kji->kt", torch.linalg.solve(lam[:, None] + info, eye), m).clamp_min(0.0)
    now = torch.einsum("kij,kji->k", torch.linalg.solve(lam, eye.expand_as(lam)), m).clamp_min(0.0)
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
            "spread_now_mrad": 1e3 * float(spread[h]), "rms_now_mrad": 1e3 * math.sqrt(float(now[j])),
            "rms_after_mrad": 1e3 * math.sqrt(float(after[j, c]))})
    fewer = []
    if len(ids) < int(slots):
        fewer.append(f"the plant has {len(ids)} calibrated heliostat(s), one record each")
    if len(out["proposals"]) < len(chosen):
        fewer.append(f"{len(chosen) - len(out['proposals'])} heliostat(s) cannot reach the target at a free time")
    if fewer:
        out["why_fewer"] = "; ".join(fewer)
    return out
