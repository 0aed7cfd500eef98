"""The predicted pointing spread: the one number by which ``plan``, ``daily`` and the report say how uncertain a
calibrated heliostat's pointing is on a day, rank the heliostats that need a record, and show what a record gains.

Definition (:data:`DEFINITION`): for heliostat h and the planned day d,

    spread_h(d) = sqrt( mean_t tr(J_t Sigma_h(d) J_t^T) )   [mrad],

* ``Sigma_h(d)`` [P, P]: the calibration's Laplace posterior covariance of the heliostat's deviations, grown by
  the stored random walk of the axis offsets from the heliostat's state time to noon of d
  (:func:`heliotwin.calibrate.clock.grown_covariance`);
* ``J_t`` [3, P]: the derivative of the mirror normal w.r.t. the deviations when the heliostat aims the sun at
  the calibration target, at the reference sun positions t of the year from d on (:func:`reference_sun`: one
  every :data:`REFERENCE_EVERY`, so every time of day in turn, with the sun above :data:`MIN_ELEVATION_DEG`),
  the mean over the positions the heliostat can reach;
* so it is the root mean square, over the sun positions it will aim at, of the error of the mirror normal that
  the parameters' uncertainty predicts; a record's own noise comes on top and is not in it.

The same quantity after a record at sun position c (``Sigma^-1 + J_c^T J_c / s^2``, :func:`spread_after`) is what
a plan minimises (the I-optimal design of :mod:`heliotwin.calibrate.protocol.plan`), so "now -> after" is the
one number before and after. The mean over the reference positions is ``tr(Sigma M)`` with the heliostat's metric
``M = mean_t J_t^T J_t`` [P, P] (:func:`spread_metric`), computed once per heliostat.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import pandas as pd
import torch

from ..errors import HeliotwinError
from ..field import kinematics as K
from ..field.plant import Kinematics
from ..field.targets import PlanarTarget
from ..sun import daylight_window, direction_from_paint_angles
from .clock import grown_covariance
from .params import apply_deviations
from .scenario import KEY

__all__ = ["DEFINITION", "SHORT", "REFERENCE_EVERY", "MIN_ELEVATION_DEG", "Spread", "day_start", "reference_sun",
           "spread_metric", "spread_after", "predicted_spread", "normal_jacobians_many"]

#: Spacing of the reference sun positions over the year (25 h: every time of day in turn, about one a day).
REFERENCE_EVERY = "25h"
#: Lowest sun elevation of a reference sun position [deg] (fixed: the definition does not move with a plan's
#: --min-elevation, which only limits the candidate record times).
MIN_ELEVATION_DEG = 15.0
#: The definition in one line, printed in the headers of ``plan``, ``daily`` and the report.
DEFINITION = ("predicted pointing spread [mrad] = RMS error of the mirror normal that the calibration's posterior "
              "predicts over the sun positions of the year from the planned day on (one every 25 h, sun above "
              "15 deg, aiming at the calibration target), its random walk grown to that day's noon; record noise "
              "not included")
#: The short name used beside the numbers.
SHORT = "predicted pointing spread"
#: Heliostat x reference-position rows per batched Jacobian (memory ~ 1 kB each).
CHUNK_ROWS = 50_000


def day_start(day) -> pd.Timestamp:
    """The UTC midnight that starts ``day`` (a date, ISO text or a Timestamp; one-line error when unreadable)."""
    try:
        start = pd.Timestamp(day)
        start = (start.tz_localize("UTC") if start.tzinfo is None else start.tz_convert("UTC")).normalize()
    except (ValueError, TypeError):
        raise HeliotwinError(f"--day: cannot parse {day!r} (expected a UTC date, e.g. 2024-06-21)") from None
    return start


def reference_sun(site, start: pd.Timestamp) -> torch.Tensor:
    """Unit vectors towards the sun [T, 3] at the reference positions of the year from ``start`` (UTC) on."""
    _, az, el = daylight_window(start, start + pd.DateOffset(years=1), REFERENCE_EVERY, site.latitude_deg,
                                site.longitude_deg, site.altitude_m, MIN_ELEVATION_DEG)
    return direction_from_paint_angles(az, el)


def normal_jacobians_many(nominal: Kinematics, delta: torch.Tensor, names, aim_point: torch.Tensor,
                          sun: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Derivative of the mirror normal w.r.t. the deviations of K heliostats at once, at every sun position,
    when aiming the sun at ``aim_point``.

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
        d(unit normal) per unit deviation (per [rad] for angles, per [m] for lengths); zero where the sun
        position is not reachable.
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


def stored_nominal(cal: dict, rows: list) -> Kinematics:
    """The stored nominal kinematics of the calibrated heliostats ``rows`` (positions in ``cal["heliostats"]``)."""
    return Kinematics(**{f.name: torch.as_tensor(cal["nominal"][f.name])[rows] for f in fields(Kinematics)})


def calibration_target(scenario, cal: dict, target: str | None) -> str:
    """The planar calibration target the spread and a plan aim at (``target``, default the first by name),
    checking that the calibration ``cal`` stores a posterior (one-line errors otherwise)."""
    if not cal.get("posterior"):
        raise HeliotwinError(f"{scenario.path} [/learned/{KEY}/posterior]: no posterior stored (calibrate with "
                             "--method lm to get one)")
    planar = sorted(n for n, t in scenario.plant.targets.items() if isinstance(t, PlanarTarget))
    name = target or (planar[0] if planar else None)
    if name not in planar:
        raise HeliotwinError(f"target {name!r} is not a planar calibration target; known: {', '.join(planar)}")
    return name


def spread_metric(cal: dict, rows: list, aim_point: torch.Tensor, sun: torch.Tensor) -> torch.Tensor:
    """``M = mean_t J_t^T J_t`` [K, P, P] of the calibrated heliostats ``rows`` over the sun positions ``sun``
    [T, 3] (unit vectors) they can reach (zero for one that reaches none), in chunks of :data:`CHUNK_ROWS` rows;
    ``aim_point`` [3] ENU [m] (the calibration target's centre); ``J_t`` [3, P] the mirror normal's Jacobian
    [rad per unit of each deviation]."""
    names = list(cal["parameter_names"])
    delta = torch.as_tensor(cal["deviations"], dtype=torch.float64)
    p = delta.shape[-1]
    out = torch.zeros(len(rows), p, p, dtype=torch.float64)
    step = max(1, CHUNK_ROWS // max(1, len(sun)))
    for a in range(0, len(rows), step):
        part = list(rows[a:a + step])
        jac, ok = normal_jacobians_many(stored_nominal(cal, part), delta[part], names, aim_point, sun)
        out[a:a + len(part)] = torch.einsum("ktci,ktcj->kij", jac, jac) / ok.sum(1).clamp_min(1)[:, None, None]
    return out


def spread_after(covariance: torch.Tensor, metric: torch.Tensor, information: torch.Tensor | None = None
                 ) -> torch.Tensor:
    """The spread [mrad] of covariance ``covariance`` [..., P, P] updated by ``information`` [..., P, P] (a
    record's ``J^T J / s^2``; None: no record), over the heliostat's metric ``metric`` [..., P, P] (broadcast)."""
    if information is None:
        cov = covariance
    else:
        eye = torch.eye(covariance.shape[-1], dtype=torch.float64)
        lam = torch.linalg.solve(covariance, eye.expand_as(covariance))
        cov = torch.linalg.solve(lam + information, eye.expand_as(information))
    return 1e3 * torch.einsum("...ij,...ji->...", cov, metric).clamp_min(0.0).sqrt()


@dataclass(frozen=True)
class Spread:
    """The predicted pointing spread of calibrated heliostats on one day (module docstring).

    Attributes
    ----------
    ids : list of str
        K heliostat ids (the calibration's order, or the subset asked for).
    rows : list of int
        Their positions in the calibration's heliostats.
    day : str
        The planned day (UTC date, ISO).
    target : str
        The calibration target the reference positions aim at.
    spread_mrad : torch.Tensor, [K]
    covariance : torch.Tensor, [K, P, P]
        The posterior grown to the day's noon.
    metric : torch.Tensor, [K, P, P]
        ``mean_t J_t^T J_t`` over the reference positions.
    walk_days : torch.Tensor, [K]
        Days of random walk the covariance was grown by.
    """

    ids: list
    rows: list
    day: str
    target: str
    spread_mrad: torch.Tensor
    covariance: torch.Tensor
    metric: torch.Tensor
    walk_days: torch.Tensor

    def summary(self) -> dict:
        """Median and 95th percentile over the heliostats [mrad], the day and the definition (for reports)."""
        s = self.spread_mrad
        return {"day": self.day, "definition": DEFINITION,
                "median_mrad": float(s.median()) if len(s) else None,
                "p95_mrad": float(torch.quantile(s, 0.95)) if len(s) else None}


def predicted_spread(scenario, day, *, heliostats=None, target: str | None = None) -> Spread:
    """The predicted pointing spread (module docstring) of the scenario's calibrated heliostats on ``day``.

    Parameters
    ----------
    scenario : heliotwin.io.scenario.Scenario
        Calibrated with a stored posterior (``--method lm``).
    day : str or pandas.Timestamp
        The planned day (UTC date).
    heliostats : sequence of str, optional
        Only these (default: every calibrated heliostat); one that is not calibrated is a one-line error.
    target : str, optional
        Planar calibration target (default: the first by name).
    """
    cal = scenario.learned.get(KEY) or {}
    name = calibration_target(scenario, cal, target)
    ids = list(cal["heliostats"])
    if heliostats is None:
        rows = list(range(len(ids)))
    else:
        missing = [h for h in heliostats if h not in ids]
        if missing:
            raise HeliotwinError(f"{scenario.path}: heliostat {missing[0]} is not calibrated in this scenario")
        rows = [ids.index(h) for h in heliostats]
    start = day_start(day)
    names = list(cal["parameter_names"])
    cov, days = grown_covariance(cal, names, start.timestamp() + 43200.0)
    sun = reference_sun(scenario.plant.site, start)
    if len(sun) == 0:
        raise HeliotwinError(f"no sun position above {MIN_ELEVATION_DEG:g} deg in the year from {start.date()} at "
                             f"{scenario.plant.site.latitude_deg:g} deg latitude")
    idx = torch.tensor(rows, dtype=torch.long)
    metric = spread_metric(cal, rows, scenario.plant.targets[name].center, sun)
    cov = cov[idx]
    return Spread(ids=[ids[r] for r in rows], rows=rows, day=start.date().isoformat(), target=name,
                  spread_mrad=spread_after(cov, metric), covariance=cov, metric=metric, walk_days=days[idx])

