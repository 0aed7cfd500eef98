"""Questions asked of a calibrated plant: where to point a heliostat now (``heliotwin aim``) and which records
to take next (``heliotwin plan``).

Both read a scenario and learn nothing, so the scenario comes back unchanged (no provenance step); the
report is the answer. Inputs are checked here, once, with one-line errors that name the option.
"""
from __future__ import annotations

import datetime
import math
from dataclasses import dataclass

import pandas as pd

from ..calibrate.clock import planned_day
from ..calibrate.protocol.plan import plan as plan_records
from ..calibrate.scenario import aim as aim_heliostat
from ..calibrate.spread import day_start
from ..errors import HeliotwinError
from ..io.records import parse_time
from ..io.scenario import Scenario
from ..sun import daylight_times, daylight_window

__all__ = ["PlanSettings", "plan", "AimRequest", "aim", "aim_time"]


@dataclass(frozen=True)
class PlanSettings:
    """Options of ``heliotwin plan`` (same names and defaults).

    Attributes
    ----------
    year : int or None
        Year whose daylight sun positions are the candidates (None: the year from the plant's next day on).
    day : str or None
        The planned day (UTC date): the candidates are the year from it on and the predicted pointing spread is
        that day's (None: the plant's next day, :func:`heliotwin.calibrate.clock.planned_day`). Not with ``year``.
    every : str
        Candidate spacing (pandas frequency, e.g. ``"1h"``).
    count : int
        Records to propose.
    target : str or None
        Planar calibration target (None: the first by name).
    min_elevation : float
        Lowest sun elevation of a candidate [deg].
    sky : bool
        Also return the predictive spread at every candidate (``report["sky"]``, numpy arrays) for a sky map.
    """

    year: int | None = None
    day: str | None = None
    every: str = "1h"
    count: int = 5
    target: str | None = None
    min_elevation: float = 15.0
    sky: bool = False

    def __post_init__(self):
        # checked on construction, so bad settings are refused before any file is read
        if self.year is not None and (isinstance(self.year, bool) or not isinstance(self.year, int)
                                      or not 1900 <= self.year <= 2100):
            raise HeliotwinError(f"--year: expected a year in 1900..2100, got {self.year!r}")
        if self.day is not None:
            if self.year is not None:
                raise HeliotwinError("--day and --year: give one (the candidates are the year from --day on)")
            day_start(self.day)  # a one-line error for an unreadable day
        try:
            step = pd.Timedelta(self.every)
        except (ValueError, TypeError, OverflowError):
            raise HeliotwinError(f"--every: cannot parse {self.every!r} (e.g. 1h, 30min)") from None
        if not pd.Timedelta("1min") <= step <= pd.Timedelta("31D"):
            raise HeliotwinError(f"--every {self.every}: expected a time step between 1min and 31d")
        if step % pd.Timedelta("1D") == pd.Timedelta(0):
            raise HeliotwinError(f"--every {self.every}: a whole number of days puts every candidate at the same "
                                 "time of day; use hours or minutes (1h, 30min, 25h)")
        if isinstance(self.count, bool) or not isinstance(self.count, int) or not 1 <= self.count <= 1000:
            raise HeliotwinError(f"--count: expected 1..1000 records, got {self.count!r}")
        e = self.min_elevation
        if isinstance(e, bool) or not isinstance(e, (int, float)) or not math.isfinite(e) or not 0 <= e <= 89:
            raise HeliotwinError(f"--min-elevation: expected an elevation in [0, 89] deg, got {e!r}")


def plan(scenario: Scenario, heliostat: str, settings: PlanSettings = PlanSettings(), *,
         now: datetime.datetime | None = None) -> tuple[Scenario, dict]:
    """The sun positions whose calibration records would shrink ``heliostat``'s pointing uncertainty most.

    Without ``settings.year`` the candidates are the year from the plant's next day on
    (:func:`heliotwin.calibrate.clock.planned_day`: tomorrow by the wall clock ``now``, or the day after the
    plant's latest record when that is days behind), so that no proposal lies in the plant's past.

    Returns
    -------
    scenario : Scenario
        Unchanged.
    report : dict
        :func:`heliotwin.calibrate.protocol.plan.plan`'s answer (the predicted pointing spread on the day,
        :mod:`heliotwin.calibrate.spread`, and proposals with UTC times, sun angles [deg] and the spread after
        each [mrad]); without ``settings.year`` also ``candidates_from`` (the first day and why).
    """
    since = clock = None
    if settings.year is None:
        day, why = planned_day(scenario.learned, settings.day, now)
        since, clock = day_start(day), {"day": day, "why": why}
    site = scenario.plant.site
    if since is None:
        times, _, _ = daylight_times(settings.year, settings.every, site.latitude_deg, site.longitude_deg,
                                     site.altitude_m, settings.min_elevation)
    else:
        times, _, _ = daylight_window(since, since + pd.DateOffset(years=1), settings.every, site.latitude_deg,
                                      site.longitude_deg, site.altitude_m, settings.min_elevation)
    year = settings.year or since.year
    if len(times) == 0:
        raise HeliotwinError(f"plan: no candidate time in {year} every {settings.every} with the sun above "
                             f"{settings.min_elevation:g} deg at {site.latitude_deg:g} deg latitude")
    report = plan_records(scenario, heliostat, year=year, every=settings.every, count=settings.count,
                          target=settings.target, min_elevation_deg=settings.min_elevation, sky=settings.sky,
                          since=since)
    if clock:
        report["candidates_from"] = clock
    return scenario, report


@dataclass(frozen=True)
class AimRequest:
    """One ``heliotwin aim`` question.

    Attributes
    ----------
    sun_azimuth, sun_elevation : float
        [deg], PAINT convention (azimuth 0 = south, +90 = east); the sun must be above the horizon.
    aim_point : sequence of 3 float
        ENU [m].
    time : str or None
        UTC ISO time of the aim (drift models predict the offset then); None: the latest training time.

    Examples
    --------
    A question is checked when it is made, before any scenario is read:

    >>> AimRequest(sun_azimuth=10.0, sun_elevation=40.0, aim_point=(0.0, 0.0, 50.0)).time is None
    True
    >>> AimRequest(sun_azimuth=10.0, sun_elevation=-5.0, aim_point=(0.0, 0.0, 50.0))
    Traceback (most recent call last):
    ...
    heliotwin.errors.HeliotwinError: --sun-elevation -5.0 deg: the sun must be above the horizon
    """

    sun_azimuth: float
    sun_elevation: float
    aim_point: tuple
    time: str | None = None

    def __post_init__(self):
        # checked on construction, so a bad question is refused before any file is read
        _check(self)


def aim_time(text: str | None) -> float | None:
    """``--time``: UTC ISO text -> POSIX time [s] (None when not given; one-line error when unparsable)."""
    if text is None:
        return None
    try:
        t = parse_time(text)
    except ValueError:
        t = math.nan
    if not math.isfinite(t):
        raise HeliotwinError(f"--time must be a UTC ISO time (e.g. 2023-05-01T12:00:00Z), got {text!r}")
    return t


def _check(request: AimRequest) -> tuple[list, float | None]:
    point = list(request.aim_point)
    if len(point) != 3 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in point):
        raise HeliotwinError(f"--aim needs three finite numbers E,N,U, got {request.aim_point!r}")
    if not (0.0 < request.sun_elevation <= 90.0):
        raise HeliotwinError(f"--sun-elevation {request.sun_elevation} deg: the sun must be above the horizon")
    if not math.isfinite(request.sun_azimuth):
        raise HeliotwinError("--sun-azimuth must be finite")
    return point, aim_time(request.time)


def aim(scenario: Scenario, heliostat: str, request: AimRequest) -> tuple[Scenario, dict]:
    """Motor steps that put the sun's reflection on the aim point with the scenario's (calibrated) plant.

    Returns
    -------
    scenario : Scenario
        Unchanged.
    report : dict
        :func:`heliotwin.calibrate.scenario.aim`'s answer: ``motor_steps`` [2], ``reachable``, ``method`` and,
        for a rigid-body calibration with a posterior, the expected error and its 90 % interval [mrad].
    """
    point, t = list(request.aim_point), aim_time(request.time)
    report = aim_heliostat(scenario, heliostat, math.radians(request.sun_azimuth),
                           math.radians(request.sun_elevation), point, time=t)
    return scenario, report
