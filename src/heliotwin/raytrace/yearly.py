"""The field over a year: an efficiency table over sun positions and the annual optical energy.

Like SolarPILOT, the field model (:func:`heliotwin.raytrace.field.field_optics`, equator aiming) is evaluated
on a grid of sun positions (azimuth x elevation); the optical efficiency at any instant is interpolated
bilinearly in that table (periodic in azimuth). The annual optical energy is

    ``E = sum_t DNI_t * A * eta(sun_t) * dt``

over the daylight instants of a year (sun above 5 deg), with ``DNI_t`` from pvlib's Ineichen clear-sky model
at the plant's site (Linke turbidity from pvlib's climatology; Ineichen & Perez, Solar Energy 73 (2002)
151), ``A`` the mirror area and ``eta`` the field efficiency ``receiver power / (DNI A)``.

Shapes: table [E, Z] over E elevations and Z azimuths; angles in degrees only at this module's edges
(``*_deg`` names), PAINT azimuth convention (0 = south, +90 = east).
"""
from __future__ import annotations

import math
import time

import numpy as np
import pandas as pd
import pvlib
import torch

from ..atmosphere import Atmosphere
from ..devices import resolve_device, to_device
from ..field.facets import surface_points
from ..field.plant import Plant
from ..sun import daylight_times, direction_from_paint_angles
from .field import FACTORS, FieldSettings, field_optics

__all__ = ["efficiency_table", "interpolate_efficiency", "clear_sky_dni", "annual_energy"]

DEFAULT_AZIMUTHS_DEG = tuple(range(-180, 180, 15))
DEFAULT_ELEVATIONS_DEG = (5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 89.0)


def efficiency_table(plant: Plant, *, atmosphere: Atmosphere | None = None, azimuths_deg=DEFAULT_AZIMUTHS_DEG,
                     elevations_deg=DEFAULT_ELEVATIONS_DEG, settings: FieldSettings | None = None,
                     device=None) -> dict:
    """Field efficiency (and the unweighted factors) on a grid of sun positions.

    Parameters
    ----------
    plant : Plant
    atmosphere : Atmosphere, optional
    azimuths_deg, elevations_deg : sequences of float
        Grid [deg] (PAINT azimuth, increasing; elevations in (0, 90]).
    settings : FieldSettings, optional
        Default: the field model with a small map (the intercept does not depend on the map).
    device : str or torch.device, optional
        Where to trace (``"auto"``: CUDA when present); default: the plant's device. The table is NumPy.

    Returns
    -------
    dict
        ``azimuth_deg`` [Z], ``elevation_deg`` [E], ``efficiency`` [E, Z] (``receiver power / (DNI A)``),
        ``<factor>`` [E, Z] for every factor (unweighted means, SolarPILOT's table), ``seconds``.
    """
    settings = settings or FieldSettings(resolution=(4, 8))
    plant = _on_device(plant, device)
    dev = plant.field.kinematics.position.device
    az = [float(a) for a in azimuths_deg]
    el = [float(e) for e in elevations_deg]
    out = {"efficiency": np.zeros((len(el), len(az)))}
    out.update({name: np.zeros((len(el), len(az))) for name in FACTORS})
    t0 = time.perf_counter()
    for i, e in enumerate(el):
        for j, a in enumerate(az):
            sun = direction_from_paint_angles(torch.tensor(math.radians(a), dtype=torch.float64, device=dev),
                                              torch.tensor(math.radians(e), dtype=torch.float64, device=dev))
            with torch.no_grad():
                r = field_optics(plant, sun, atmosphere=atmosphere, settings=settings)
            out["efficiency"][i, j] = float((r.mirror_area * r.efficiency).sum() / r.mirror_area.sum())
            for name in FACTORS:
                out[name][i, j] = float(getattr(r, name).mean())
    return {"azimuth_deg": az, "elevation_deg": el, **out, "seconds": time.perf_counter() - t0}


def interpolate_efficiency(table: dict, azimuth: torch.Tensor, elevation: torch.Tensor,
                           key: str = "efficiency") -> torch.Tensor:
    """Bilinear interpolation in an :func:`efficiency_table` (periodic in azimuth, clamped in elevation).

    Parameters
    ----------
    table : dict
    azimuth, elevation : torch.Tensor, shape (T,)
        [rad], PAINT convention.

    Returns
    -------
    torch.Tensor, shape (T,), float64
    """
    az_grid = np.asarray(table["azimuth_deg"], dtype=np.float64)
    el_grid = np.asarray(table["elevation_deg"], dtype=np.float64)
    values = np.asarray(table[key], dtype=np.float64)
    # periodic azimuth: append the first column one turn later
    az_ext = np.concatenate((az_grid, az_grid[:1] + 360.0))
    val_ext = np.concatenate((values, values[:, :1]), axis=1)
    a = (np.rad2deg(azimuth.detach().cpu().numpy()) - az_grid[0]) % 360.0 + az_grid[0]
    e = np.clip(np.rad2deg(elevation.detach().cpu().numpy()), el_grid[0], el_grid[-1])
    j = np.clip(np.searchsorted(az_ext, a, side="right") - 1, 0, len(az_ext) - 2)
    i = np.clip(np.searchsorted(el_grid, e, side="right") - 1, 0, max(len(el_grid) - 2, 0))
    if len(el_grid) == 1:
        wa = (a - az_ext[j]) / (az_ext[j + 1] - az_ext[j])
        return torch.as_tensor((1 - wa) * val_ext[0, j] + wa * val_ext[0, j + 1])
    wa = (a - az_ext[j]) / (az_ext[j + 1] - az_ext[j])
    we = (e - el_grid[i]) / (el_grid[i + 1] - el_grid[i])
    v = ((1 - we) * ((1 - wa) * val_ext[i, j] + wa * val_ext[i, j + 1])
         + we * ((1 - wa) * val_ext[i + 1, j] + wa * val_ext[i + 1, j + 1]))
    return torch.as_tensor(v)


def clear_sky_dni(times, plant: Plant) -> np.ndarray:
    """pvlib Ineichen clear-sky DNI [W/m^2] at the plant's site for UTC ``times`` (pandas DatetimeIndex)."""
    s = plant.site
    loc = pvlib.location.Location(s.latitude_deg, s.longitude_deg, altitude=s.altitude_m)
    return loc.get_clearsky(times, model="ineichen")["dni"].to_numpy()


def annual_energy(plant: Plant, year: int, every: str = "1h", *, atmosphere: Atmosphere | None = None,
                  table: dict | None = None, device=None) -> dict:
    """Annual optical energy on the receiver under clear-sky DNI.

    Parameters
    ----------
    plant : Plant
    year : int
    every : str
        pandas frequency of the instants (``"1h"``, ``"30min"``); each instant stands for that interval.
    atmosphere : Atmosphere, optional
    table : dict, optional
        From :func:`efficiency_table` (computed when missing).
    device : str or torch.device, optional
        Where :func:`efficiency_table` traces (default: the plant's device).

    Returns
    -------
    dict
        ``annual_optical_energy_mwh``, ``annual_dni_energy_on_mirrors_mwh`` (DNI x area), ``mean_efficiency``
        (DNI-weighted), ``instants``, ``mirror_area_m2``, ``table`` (lists), ``seconds``.
    """
    t0 = time.perf_counter()
    table = table or efficiency_table(plant, atmosphere=atmosphere, device=device)
    s = plant.site
    times, az, el = daylight_times(int(year), every, s.latitude_deg, s.longitude_deg, s.altitude_m)
    dni = clear_sky_dni(times, plant)
    eta = interpolate_efficiency(table, az, el).numpy()
    hours = pd.Timedelta(every).total_seconds() / 3600.0
    area = _mirror_area(plant)
    e_mirror = float((dni * area).sum() * hours) / 1e6
    e_rx = float((dni * area * eta).sum() * hours) / 1e6
    return {"year": int(year), "every": every, "instants": int(len(times)), "mirror_area_m2": area,
            "annual_dni_energy_on_mirrors_mwh": e_mirror, "annual_optical_energy_mwh": e_rx,
            "mean_efficiency": e_rx / e_mirror if e_mirror > 0 else None,
            "table": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in table.items()},
            "seconds": time.perf_counter() - t0}


def _on_device(plant: Plant, device) -> Plant:
    """``plant`` on ``device`` (None: where it is; ``"auto"``: CUDA when present)."""
    if device is None:
        return plant
    return to_device(plant, resolve_device(device))


def _mirror_area(plant: Plant) -> float:
    """Total mirror area [m^2] (the sampled facet areas, as the field model uses them)."""
    return float(surface_points(plant.field.surfaces, (4, 4))[2].sum())
