"""The ``field`` workflow at one sun, and the sun positions asked for.

:func:`field` runs the field model (:func:`heliotwin.raytrace.field.field_optics`, optionally sharded over
local processes) on a scenario's plant at one sun, with equator aiming or the scenario's stored aim points
(:func:`heliotwin.optimise.aimstate.stored_aimpoints`); it lives in :mod:`heliotwin.workflows.field_one_sun`
(no ephemeris, no pandas) and is re-exported here. :func:`sun_direction_at` and :func:`sun_instants` turn the
user's times or angles into sun directions (the ``field`` and ``aimpoints`` commands' ``--time``, ``--day``,
``--sun-azimuth``). The year (``field --year``: the efficiency table over sun positions and the clear-sky
annual optical energy) is :mod:`heliotwin.workflows.field_year`. Nothing here learns anything, so nothing
returns a new scenario.

Four heliostats of the demo plant under a southern sun, a coarse receiver map; the power-weighted factors
chain to the field's efficiency, receiver power over DNI times mirror area:

>>> from heliotwin.field.demo import demo_plant
>>> from heliotwin.io.scenario import Scenario
>>> plant = demo_plant(4)
>>> sun = sun_direction_at(plant, azimuth_deg=0.0, elevation_deg=30.0)
>>> report, result = field(Scenario(plant), sun, FieldRunSettings(resolution=(8, 16)))
>>> tuple(result.flux.shape), tuple(result.power_w.shape)
((8, 16), (4,))
>>> total = report["field"]["efficiency_power_weighted"]["total"]
>>> abs(report["receiver"]["power_w"] / (report["dni_w_m2"] * report["mirror_area_m2"]) - total) < 1e-9
True
>>> 0.5 < total < 1.0
True
"""
from __future__ import annotations

import math
import re

import pandas as pd
import torch

from ..errors import HeliotwinError
from ..sun import direction_from_time
from .field_one_sun import (
    MAX_DNI,
    MAX_MAP_CELLS,
    FieldRunSettings,
    check_irradiance,
    check_map_resolution,
    check_sun_angles,
    field,
    flux_map_fields,
    sun_from_angles,
)

__all__ = ["FieldRunSettings", "field", "flux_map_fields", "sun_direction_at", "sun_from_angles",
           "sun_instants", "check_irradiance", "check_map_resolution", "check_sun_angles", "MAX_MAP_CELLS", "MAX_DNI"]


def _text(step: pd.Timedelta) -> str:
    """A time step as a user writes it: ``31d``, ``7h``, ``90min``."""
    minutes = int(step.total_seconds() // 60)
    for unit, size in (("d", 1440), ("h", 60)):
        if minutes % size == 0:
            return f"{minutes // size}{unit}"
    return f"{minutes}min"


def _day_unit(every):
    """``every`` with pandas' day unit spelled ``D`` (``1d`` -> ``1D``): pandas deprecates the lower-case alias."""
    return re.sub(r"(?<=\d)\s*d(?![a-z])", "D", every) if isinstance(every, str) else every


def _step(every: str, flag: str = "--every") -> pd.Timedelta:
    """A positive time step from pandas text (``"1h"``, ``"30min"``); one line when it is not one."""
    try:
        step = pd.Timedelta(_day_unit(every))
    except (ValueError, TypeError, OverflowError):
        raise HeliotwinError(f"{flag}: cannot parse {every!r} (e.g. 1h, 30min)") from None
    if step < pd.Timedelta("1min"):
        raise HeliotwinError(f"{flag}: expected a time step of at least 1min, got {every!r}")
    return step


def sun_direction_at(plant, *, time_utc: str | None = None, azimuth_deg: float | None = None,
                     elevation_deg: float | None = None) -> torch.Tensor:
    """The sun direction at a UTC time (pvlib at the plant's site) or from PAINT angles.

    Parameters
    ----------
    plant : Plant
    time_utc : str, optional
        ISO time [UTC] (naive: UTC); takes precedence over the angles.
    azimuth_deg, elevation_deg : float, optional
        PAINT convention [deg] (0 = south, +90 = east).

    Returns
    -------
    torch.Tensor, [3], float64
        Unit vector towards the sun (ENU).

    Raises
    ------
    HeliotwinError
        Unparsable time, or the sun below the horizon.

    Examples
    --------
    PAINT's azimuth 0 is south: a sun 30 deg above the southern horizon lies south (-y) and up (+z):

    >>> from heliotwin.field.demo import demo_plant
    >>> [round(x, 3) for x in sun_direction_at(demo_plant(1), azimuth_deg=0.0, elevation_deg=30.0).tolist()]
    [0.0, -0.866, 0.5]
    >>> sun_direction_at(demo_plant(1), azimuth_deg=0.0, elevation_deg=-1.0)
    Traceback (most recent call last):
    ...
    heliotwin.errors.HeliotwinError: --sun-elevation: the sun is below the horizon (-1.0 deg)
    """
    if time_utc is not None:
        try:
            stamp = pd.Timestamp(time_utc)
            if pd.isna(stamp):
                raise ValueError(time_utc)
        except (ValueError, TypeError, OverflowError):
            raise HeliotwinError(f"--time: cannot parse {time_utc!r} (expected ISO UTC, e.g. 2023-06-21T12:00Z)") \
                from None
        if not 1900 <= stamp.year <= 2100:  # read, but not a time the solar position model covers
            raise HeliotwinError(f"--time: {time_utc!r} is out of range (expected a time in the years 1900..2100)")
        if stamp.tzinfo is None:
            stamp = stamp.tz_localize("UTC")
        s = plant.site
        d = direction_from_time(pd.DatetimeIndex([stamp]), s.latitude_deg, s.longitude_deg, s.altitude_m,
                                check_horizon=False)
        d = torch.as_tensor(d, dtype=torch.float64).reshape(3)
        if float(d[2]) <= 0:
            raise HeliotwinError(f"--time: the sun is below the horizon at {time_utc} "
                                 f"(elevation {math.degrees(math.asin(float(d[2]))):.1f} deg)")
        return d
    return sun_from_angles(azimuth_deg, elevation_deg)


def sun_instants(plant, *, times: str | None = None, day: str | None = None, every: str = "1h",
                 azimuth_deg: float | None = None,
                 elevation_deg: float | None = None) -> list[tuple[str, torch.Tensor]]:
    """``(label, sun direction [3])`` of every instant asked for: the daylight instants of ``day`` every
    ``every`` (sun above 10 deg), the comma-separated UTC ``times``, or one sun from PAINT angles [deg]."""
    if day is not None:
        try:
            start = pd.Timestamp(day)
            if pd.isna(start):
                raise ValueError(day)
        except (ValueError, TypeError, OverflowError):
            raise HeliotwinError(f"--day: cannot parse {day!r} (expected a UTC date, e.g. 2023-06-21)") from None
        if not 1900 <= start.year <= 2100:
            raise HeliotwinError(f"--day: {day!r} is out of range (expected a day in the years 1900..2100)")
        step = _step(every)
        if step > pd.Timedelta("1D"):
            raise HeliotwinError(f"--every {_text(step)}: longer than the day of --day (at most 1d: one instant)")
        start = start.tz_localize("UTC") if start.tzinfo is None else start
        stamps = pd.date_range(start.normalize(), start.normalize() + pd.Timedelta("1D"), freq=step, inclusive="left")
        s = plant.site
        d = direction_from_time(stamps, s.latitude_deg, s.longitude_deg, s.altitude_m, check_horizon=False)
        keep = [(t.isoformat(), torch.as_tensor(v, dtype=torch.float64)) for t, v in zip(stamps, d)
                if math.degrees(math.asin(float(v[2]))) > 10.0]
        if not keep:
            raise HeliotwinError(f"--day: the sun stays below 10 deg elevation on {day}")
        return keep
    if times is not None:
        out = [(text, sun_direction_at(plant, time_utc=text)) for text in [t.strip() for t in times.split(",")
                                                                            if t.strip()]]
        if not out:
            raise HeliotwinError("--time: no instant given")
        return out
    return [(f"azimuth {azimuth_deg} deg, elevation {elevation_deg} deg",
             sun_direction_at(plant, azimuth_deg=azimuth_deg, elevation_deg=elevation_deg))]
