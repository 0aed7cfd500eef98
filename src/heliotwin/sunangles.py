"""Sun direction from PAINT's sun angles and back: pure geometry, no ephemeris.

Kept apart from :mod:`heliotwin.sun` (which adds NREL's SPA through pvlib and re-exports these) so that what
only turns recorded angles into directions -- reading records, a daily update -- does not import pvlib and
pandas (a quarter of such a command's start-up).

Convention
----------
PAINT azimuth is measured from **south**, positive towards **east** (+90 deg = east, -90 deg = west);
elevation is above the horizon. The returned direction points from the plant *towards* the sun, ENU:
``(sin(az) cos(el), -cos(az) cos(el), sin(el))``.
"""
from __future__ import annotations

import math

import torch

from .errors import OutOfRangeError

__all__ = ["direction_from_paint_angles", "paint_angles_from_direction"]


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
