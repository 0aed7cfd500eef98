"""Sun position: direction vectors from PAINT angles or from UTC time at the site (pvlib SPA).

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

from .errors import OutOfRangeError


def direction_from_paint_angles(azimuth, elevation, *, check_horizon: bool = True) -> torch.Tensor:
    """Unit vector towards the sun from PAINT angles.

    Parameters
    ----------
    azimuth : tensor-like, shape (...)
        Sun azimuth [rad], 0 = south, +pi/2 = east.
    elevation : tensor-like, shape (...)
        Sun elevation above the horizon [rad].
    check_horizon : bool
        Raise :class:`~heliotwin.errors.OutOfRangeError` when any elevation is <= 0.

    Returns
    -------
    torch.Tensor, shape (..., 3), float64
        ENU unit vector towards the sun.
    """
    az = torch.as_tensor(azimuth, dtype=torch.float64)
    el = torch.as_tensor(elevation, dtype=torch.float64)
    if check_horizon and bool((el <= 0).any()):
        bad = float(el.min())
        raise OutOfRangeError(f"sun elevation {math.degrees(bad):.3f} deg is at or below the horizon")
    ce = torch.cos(el)
    return torch.stack((torch.sin(az) * ce, -torch.cos(az) * ce, torch.sin(el)), dim=-1)


def paint_angles_from_direction(direction) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of :func:`direction_from_paint_angles`.

    Parameters
    ----------
    direction : tensor-like, shape (..., 3)
        ENU vector towards the sun (need not be unit).

    Returns
    -------
    azimuth, elevation : torch.Tensor, shape (...)
        [rad], PAINT convention (0 = south, +pi/2 = east).
    """
    d = torch.as_tensor(direction, dtype=torch.float64)
    horizontal = torch.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)
    return torch.atan2(d[..., 0], -d[..., 1]), torch.atan2(d[..., 2], horizontal)


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
