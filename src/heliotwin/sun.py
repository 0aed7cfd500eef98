"""Sun position: direction vectors from PAINT angles (:mod:`heliotwin.sunangles`, re-exported here) or from
UTC time at the site (pvlib SPA).

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
import pvlib
import torch

from .sunangles import direction_from_paint_angles, paint_angles_from_direction

__all__ = ["direction_from_paint_angles", "paint_angles_from_direction", "solar_position", "direction_from_time",
           "daylight_times"]


def solar_position(times, latitude_deg: float, longitude_deg: float, altitude_m: float = 0.0):
    """Apparent sun position by NREL's SPA (via pvlib), in PAINT's convention.

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
    sp = pvlib.solarposition.get_solarposition(idx, latitude_deg, longitude_deg, altitude=altitude_m,
                                               method="nrel_numpy")
    # pvlib azimuth is from north, clockwise (east = 90). PAINT: from south, east positive.
    az_north = np.deg2rad(sp["azimuth"].to_numpy())
    az_paint = np.angle(np.exp(1j * (math.pi - az_north)))  # wrap to (-pi, pi]
    el = np.deg2rad(sp["apparent_elevation"].to_numpy())
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
    times = pd.date_range(f"{year}-01-01", f"{year + 1}-01-01", freq=every, tz="UTC", inclusive="left")
    az, el = solar_position(times, latitude_deg, longitude_deg, altitude_m)
    keep = el > math.radians(min_elevation_deg)
    return times[keep.numpy()], az[keep], el[keep]
