"""How close a learned plant is to the truth of a simulated one: pointing, surfaces and the receiver flux.

:func:`score` compares any scenario (calibrated, updated, reconstructed) with the truth scenario that
``heliotwin simulate`` wrote, over the heliostats both hold:

* **pointing error** [mrad] at new sun positions: the learned model computes the motor steps that put the
  sun's reflection on an aim point; the *true* heliostat at those steps has some mirror normal; the error is
  its angle to the normal that would have hit the aim point (so the truth scores exactly 0);
* **surface normal error** [mrad]: area-weighted RMS angle between the learned and the true surface normals
  of each heliostat, at the same parameter samples of each facet (any NURBS nets);
* **receiver flux**: the flux map the learned twin predicts (learned plant, intended aim points) against the
  one the true plant delivers (true plant, aimed by the learned model), as a relative L1 difference.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from .errors import HeliotwinError
from .field import kinematics as K
from .field.facets import surface_points
from .field.update import select_heliostats
from .geometry import angle_between
from .raytrace.field import FieldSettings, equator_aim_points, field_optics
from .sun import daylight_times, direction_from_paint_angles

#: Year whose daylight supplies the scoring sun positions (any year: the sun's path repeats).
SCORE_YEAR = 2030

#: Key under a truth scenario's ``/learned`` of what the simulator drew (:mod:`heliotwin.simulate.writer`).
TRUTH_KEY = "simulation"


def truth_missing(truth) -> list[str]:
    """What ``truth`` (a :class:`~heliotwin.io.scenario.Scenario`) lacks to be a ``heliotwin simulate`` truth:
    the simulated history ``/learned/simulation``, the true kinematics (``/learned/calibration`` with method
    ``truth``) and the ``simulate`` provenance step; empty when it is one."""
    learned = truth.learned or {}
    cal = learned.get("calibration") or {}
    missing = []
    if not learned.get(TRUTH_KEY):
        missing.append(f"/learned/{TRUTH_KEY} (the simulated history)")
    if cal.get("method") != "truth":
        got = f"method {cal.get('method')!r}" if cal else "none"
        missing.append(f"/learned/calibration of method 'truth' (the true kinematics; found {got})")
    if not any(p.get("step") == "simulate" for p in truth.provenance):
        steps = ", ".join(str(p.get("step")) for p in truth.provenance) or "none"
        missing.append(f"a 'simulate' provenance step (steps: {steps})")
    return missing


def check_truth(truth) -> None:
    """Refuse a scenario that is not a ``heliotwin simulate`` truth, naming what it lacks (:func:`truth_missing`).

    Raises
    ------
    HeliotwinError
        One line: ``score --truth FILE: not a 'heliotwin simulate' truth; it lacks ...``.
    """
    missing = truth_missing(truth)
    if missing:
        raise HeliotwinError(f"score --truth {truth.path or '(in memory)'}: not a 'heliotwin simulate' truth; it lacks "
                             + "; ".join(missing) + " (score compares a learned plant with the truth that "
                             "'heliotwin simulate' wrote)")


def score_suns(site, count: int, seed: int, min_elevation_deg: float = 15.0) -> torch.Tensor:
    """``count`` sun directions [S, 3] (ENU unit vectors) drawn from a year's hourly daylight above
    ``min_elevation_deg`` [deg] by a seeded generator (S = ``count``, or fewer when the year has fewer hours)."""
    _, az, el = daylight_times(SCORE_YEAR, "1h", site.latitude_deg, site.longitude_deg, site.altitude_m,
                               min_elevation_deg=min_elevation_deg)
    pick = np.sort(np.random.default_rng(seed).choice(len(az), size=min(count, len(az)), replace=False))
    return direction_from_paint_angles(az[pick], el[pick])


def aim_points(plant) -> torch.Tensor:
    """Aim points [H, 3] ENU [m]: the receiver's equator facing each heliostat, else the first planar target's
    centre."""
    if "receiver" in plant.targets:
        return equator_aim_points(plant.targets["receiver"], plant.field.kinematics.position)
    planar = [t for t in plant.targets.values() if t.kind == "planar"]
    if not planar:
        raise HeliotwinError("score: the plant has neither a receiver nor a planar target to aim at")
    return planar[0].center.expand(len(plant.field.ids), 3)


def pointing_errors(true_kin, learned_kin, aim: torch.Tensor, suns: torch.Tensor):
    """Pointing error [S, H] [rad] of heliostats aimed by ``learned_kin`` but moving as ``true_kin``, the
    actual central-ray direction [S, H, 3] and the true concentrators [S, H, 3], plus [S, H] bool reachable.

    Parameters
    ----------
    true_kin, learned_kin : Kinematics
        H heliostats each (same order).
    aim : torch.Tensor, [H, 3]
        ENU [m].
    suns : torch.Tensor, [S, 3]
        Unit vectors towards the sun.
    """
    s = suns.unsqueeze(1).expand(-1, aim.shape[0], 3)
    steps, reachable = K.inverse(learned_kin, aim.expand(s.shape), s, strict=False)
    rot, conc = K.forward(true_kin, steps)
    normal = K.mirror_normal(rot)
    wanted = K.bisector_normal(s, conc, aim.expand(s.shape))
    ray = s - 2.0 * (s * normal).sum(-1, keepdim=True) * normal
    return angle_between(normal, wanted), -ray, conc, reachable


def _stats(values: torch.Tensor) -> dict:
    v = values[torch.isfinite(values)]
    if not len(v):
        return {"median": None, "p95": None, "mean": None, "max": None}
    return {"median": float(v.median()), "p95": float(torch.quantile(v, 0.95)), "mean": float(v.mean()),
            "max": float(v.max())}


def surface_errors(true_surfaces, learned_surfaces, samples=(8, 8)) -> torch.Tensor | None:
    """Area-weighted RMS normal angle [H] [rad] between two heliostat surface sets, compared at the same
    parameter samples of each facet (so nets of other sizes or degrees compare too); None when the heliostat or
    facet counts differ."""
    a, b = true_surfaces.control_points, learned_surfaces.control_points
    if a.shape[:2] != b.shape[:2]:
        return None
    _, nt, area = surface_points(true_surfaces, samples)
    _, nl, _ = surface_points(learned_surfaces, samples)
    ang = angle_between(nt, nl.to(nt))
    return torch.sqrt((area * ang ** 2).sum(-1) / area.sum(-1))


#: Heliostats named in :func:`score`'s ``worst_heliostats``.
WORST = 5


def score(truth, learned, *, suns: int = 16, seed: int = 0, flux: bool = True,
          flux_resolution: tuple = (20, 48)) -> dict:
    """Compare a learned scenario with the truth of a simulated plant (module docstring).

    Parameters
    ----------
    truth, learned : heliotwin.io.scenario.Scenario
        Same site; the learned plant's heliostats are scored where the truth has them. ``truth`` must be
        what ``heliotwin simulate`` wrote (:func:`check_truth`: else a one-line ``HeliotwinError``).
    suns : int
        Sun positions for the pointing error.
    seed : int
        Draws the sun positions.
    flux : bool
        Also compare receiver flux maps at the first sun (needs a ``receiver`` target): relative L1 [1] and
        power ratio [1].
    flux_resolution : tuple of int
        ``(rows, cols)`` of the compared maps.

    Returns
    -------
    dict
        ``heliostats`` (scored), ``missing`` (truth heliostats the learned plant lacks), ``suns``,
        ``pointing_mrad`` {median, p95, mean, max} over heliostats x suns, ``pointing_per_heliostat_mrad``
        {median, p95, ...} of each heliostat's median, ``unreachable`` (pairs left out), ``surface_mrad``
        (or None), ``flux`` {relative_l1, power_ratio} (or None), ``worst_heliostats`` (the :data:`WORST`
        largest per-heliostat medians: ``heliostat``, ``median_mrad``).
    """
    check_truth(truth)
    tp, lp = truth.plant, learned.plant
    ids = [h for h in tp.field.ids if h in set(lp.field.ids)]
    if not ids:
        raise HeliotwinError("score: the learned scenario shares no heliostat with the truth")
    tp, lp = select_heliostats(tp, ids), select_heliostats(lp, ids)
    sun = score_suns(tp.site, suns, seed)
    aim = aim_points(tp)
    tk = tp.field.kinematics
    lk = lp.field.kinematics.to(dtype=tk.position.dtype)
    with torch.no_grad():
        err, ray, conc, ok = pointing_errors(tk, lk, aim, sun)
    err = torch.where(ok, err, torch.full_like(err, float("nan")))
    per_heliostat = torch.nanmedian(err, 0).values
    report = {"heliostats": len(ids), "missing": len(truth.plant.field.ids) - len(ids), "suns": int(sun.shape[0]),
              "pointing_mrad": {k: (None if v is None else 1e3 * v) for k, v in _stats(err.flatten()).items()},
              "pointing_per_heliostat_mrad": {k: (None if v is None else 1e3 * v)
                                              for k, v in _stats(per_heliostat).items()},
              "unreachable": int((~ok).sum())}
    # the heliostats that set the tail, named (a p95 alone tells an operator nothing to act on)
    order = torch.argsort(torch.nan_to_num(per_heliostat, nan=-1.0), descending=True)[:WORST]
    report["worst_heliostats"] = [{"heliostat": ids[i], "median_mrad": 1e3 * float(per_heliostat[i])}
                                  for i in order.tolist() if math.isfinite(float(per_heliostat[i]))]
    surf = surface_errors(tp.field.surfaces, lp.field.surfaces)
    report["surface_mrad"] = None if surf is None else {k: (None if v is None else 1e3 * v)
                                                        for k, v in _stats(surf).items()}
    report["flux"] = _flux(tp, lp, sun[0], aim, ray[0], conc[0], ok[0], flux_resolution) if flux else None
    return report


def _flux(tp, lp, sun, aim, ray, conc, ok, resolution) -> dict | None:
    """Predicted (learned plant, intended aim) vs delivered (true plant, the aim point its actual central ray
    reaches at the intended slant range) receiver flux at one sun."""
    if "receiver" not in tp.targets:
        return None
    dist = torch.linalg.vector_norm(aim - conc, dim=-1, keepdim=True)
    actual = torch.where(ok.unsqueeze(-1), conc + ray * dist, aim)
    settings = FieldSettings(resolution=tuple(resolution))
    with torch.no_grad():
        predicted = field_optics(lp, sun, aim=aim, settings=settings).flux.double()
        delivered = field_optics(tp, sun, aim=actual, settings=settings).flux.double()
    total = float(delivered.sum())
    if not math.isfinite(total) or total <= 0:
        return None
    return {"relative_l1": float((predicted - delivered).abs().sum()) / total,
            "power_ratio": float(predicted.sum()) / total, "peak_delivered_w_m2": float(delivered.max()),
            "peak_predicted_w_m2": float(predicted.max())}
