"""Sun position: direction vectors from PAINT angles (:mod:`heliotwin.sunangles`, re-exported here) or from
UTC time at the site (NREL's SPA as pvlib computes it: :mod:`heliotwin.sunspa`, pvlib's own NumPy SPA without
pvlib's package import; pvlib stays the reference in the tests).

Convention
----------
PAINT azimuth is measured from **south**, positive towards **east** (+90 deg = east, -90 deg = west);
elevation is above the horizon. The returned direction points from the plant *towards* the sun, ENU:
``(sin(az) cos(el), -cos(az) cos(el), sin(el))``.
Sunshapes (the angular radiance profile) live in :mod:`heliotwin.sunshape`.
"""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import torch

from .sunangles import direction_from_paint_angles, paint_angles_from_direction
from .sunspa import solar_position_numpy

__all__ = ["direction_from_paint_angles", "paint_angles_from_direction", "solar_position", "direction_from_time",
           "daylight_times"]


def solar_position(times, latitude_deg: float, longitude_deg: float, altitude_m: float = 0.0):
    """Apparent sun position by NREL's SPA, in PAINT's convention: the numbers of
    ``pvlib.solarposition.get_solarposition(times, lat, lon, altitude=altitude_m, method="nrel_numpy")``
    (pressure from the altitude by pvlib's ``alt2pres``, 12 degC, delta T 67 s, refraction at the horizon
    0.5667 deg), computed by :func:`heliotwin.sunspa.solar_position_numpy` without importing pvlib.

    Parameters
    ----------
    times : array-like of datetimes, pandas DatetimeIndex or ISO strings
        Instants [UTC] (naive values are taken as UTC).
    latitude_deg, longitude_deg : float
        Site [deg].
    altitude_m : float
        Site altitude [m].

    Returns
    -------
    azimuth, elevation : torch.Tensor, shape (T,), float64
        [rad]; azimuth 0 = south, +pi/2 = east; elevation is the refraction-corrected apparent one.
    """
    idx = pd.DatetimeIndex(pd.to_datetime(times, utc=True))
    unixtime = np.array((idx - pd.Timestamp("1970-01-01", tz="UTC")) / pd.Timedelta("1s"))
    pressure_pa = 100 * ((44331.514 - altitude_m) / 11880.516) ** (1 / 0.1902632)  # pvlib.atmosphere.alt2pres
    _, _, app_elevation, _, azimuth, _ = solar_position_numpy(
        unixtime, latitude_deg, longitude_deg, altitude_m, pressure_pa / 100, 12.0, 67.0, 0.5667, 4)
    # SPA azimuth is from north, clockwise (east = 90). PAINT: from south, east positive.
    az_north = np.deg2rad(np.asarray(azimuth, dtype=np.float64))
    az_paint = np.angle(np.exp(1j * (math.pi - az_north)))  # wrap to (-pi, pi]
    el = np.deg2rad(np.asarray(app_elevation, dtype=np.float64))
    return torch.as_tensor(az_paint), torch.as_tensor(el)


def direction_from_time(times, latitude_deg: float, longitude_deg: float, altitude_m: float = 0.0,
                        *, check_horizon: bool = True) -> torch.Tensor:
    """ENU unit vectors towards the sun at UTC ``times`` (T of them), shape (T, 3), float64, for a site at
    ``latitude_deg``, ``longitude_deg`` [deg] and ``altitude_m`` [m] (see :func:`solar_position`)."""
    az, el = solar_position(times, latitude_deg, longitude_deg, altitude_m)
    return direction_from_paint_angles(az, el, check_horizon=check_horizon)


def daylight_times(year: int, every: str, latitude_deg: float, longitude_deg: float, altitude_m: float = 0.0,
                   min_elevation_deg: float = 5.0):
    """UTC instants over a year, every ``every`` (pandas frequency like ``"30min"``), with the sun above
    ``min_elevation_deg``.

    Returns
    -------
    times : pandas.DatetimeIndex
        T instants [UTC].
    azimuth, elevation : torch.Tensor, shape (T,) [rad], PAINT convention.
    """
    return daylight_window(pd.Timestamp(f"{year}-01-01", tz="UTC"), pd.Timestamp(f"{year + 1}-01-01", tz="UTC"),
                           every, latitude_deg, longitude_deg, altitude_m, min_elevation_deg)


def daylight_window(start, end, every: str, latitude_deg: float, longitude_deg: float, altitude_m: float = 0.0,
                    min_elevation_deg: float = 5.0):
    """:func:`daylight_times` over ``[start, end)`` (UTC pandas Timestamps) instead of a calendar year: the
    instants of the plant's own next year, say. Latitude and longitude [deg], altitude [m], ``min_elevation_deg``
    [deg]; same returns (times, azimuth and elevation [rad], shape (T,))."""
    times = pd.date_range(start, end, freq=every, inclusive="left")
    az, el = solar_position(times, latitude_deg, longitude_deg, altitude_m)
    keep = el > math.radians(min_elevation_deg)
    return times[keep.numpy()], az[keep], el[keep]
