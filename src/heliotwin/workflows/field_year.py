"""The ``field --year`` workflow: the field's efficiency table over sun positions and its annual optical energy,
under pvlib's clear sky or a DNI file (:func:`field_year`, :func:`weather_energy`).

Apart from :mod:`heliotwin.workflows.field` (one sun, the sun's positions) so that only a command that sweeps a
year imports what a year needs (pvlib's clear-sky model, weather files through pandas).
"""
from __future__ import annotations

import os
import time

import numpy as np
import pandas as pd

from ..atmosphere import Atmosphere
from ..errors import HeliotwinError
from ..field.facets import surface_points
from ..io.weather import weather_checks, weather_for_year
from ..raytrace.yearly import DEFAULT_ELEVATIONS_DEG, annual_energy, efficiency_table, interpolate_efficiency
from ..sun import solar_position
from .field import _day_unit, _step, _text

__all__ = ["field_year", "weather_energy"]


def weather_energy(plant, series, table: dict, year: int | None = None) -> dict:
    """Optical energy on the receiver under a DNI time series (:func:`heliotwin.io.weather.read_dni_series`).

    The series is placed in ``year`` by :func:`heliotwin.io.weather.weather_for_year` (the one rule of every
    ``--weather``: its rows in that year, or a typical year moved into it; gaps, repeats and the coverage
    stated). Every row with the sun up contributes ``DNI x mirror area x efficiency(sun) x its hours``
    (efficiency interpolated in ``table``, :func:`heliotwin.raytrace.yearly.interpolate_efficiency`).

    Returns
    -------
    dict
        ``optical_energy_mwh`` and ``dni_energy_on_mirrors_mwh`` over the hours the file covers, the same as
        ``annual_optical_energy_mwh`` / ``annual_dni_energy_on_mirrors_mwh`` when it covers the year (else
        those are None), ``annual``, ``coverage``, ``assumptions``, ``mean_efficiency`` (DNI-weighted),
        ``instants`` (sun up), ``step_hours``, ``dni_source`` (file, kind, rows used and not, year moved),
        ``mirror_area_m2``, ``table``; and what :func:`heliotwin.io.weather.weather_checks` states:
        ``time_convention``, ``weather_site`` (the file's site, or None), ``site_offset_km`` (from the plant's,
        or None), ``dni_share_below_horizon`` (of the file's DNI energy; <= 0.005 for a correct reading) and
        ``warnings`` (one-line texts, e.g. the file's site more than 50 km from the plant's; the CLI prints them).
    """
    if year is None:  # the file's own (middle) year
        year = int(series.times.year[len(series.times) // 2])
    wy = weather_for_year(series, int(year))
    s = plant.site
    az, el = solar_position(wy.times, s.latitude_deg, s.longitude_deg, s.altitude_m)
    up = (el > 0).numpy()
    checks = weather_checks(wy, series, s, elevation=el.numpy())
    eta = interpolate_efficiency(table, az[up], el[up]).numpy()
    area = _mirror_area(plant)
    e_mirror = float((wy.dni[up] * area * wy.hours[up]).sum()) / 1e6
    e_rx = float((wy.dni[up] * area * eta * wy.hours[up]).sum()) / 1e6
    if e_mirror <= 0.0:
        raise HeliotwinError(f"{os.path.basename(series.path)}: no direct sun in {year} while the sun is up (every "
                             "daytime DNI is 0): no energy to report")
    return {"year": int(year), "instants": int(up.sum()), "step_hours": wy.step_hours,
            "mirror_area_m2": area, "optical_energy_mwh": e_rx, "dni_energy_on_mirrors_mwh": e_mirror,
            "annual": wy.annual, "annual_dni_energy_on_mirrors_mwh": e_mirror if wy.annual else None,
            "annual_optical_energy_mwh": e_rx if wy.annual else None, "mean_efficiency": e_rx / e_mirror,
            "coverage": wy.coverage, "assumptions": wy.assumptions, **checks,
            "dni_source": {**wy.source, "file": os.path.abspath(series.path), "rows_dropped": series.dropped},
            "table": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in table.items()}}


def _mirror_area(plant) -> float:
    """Total mirror area [m^2]: the sampled facet areas, as the field model and the clear-sky energy use them."""
    return float(surface_points(plant.field.surfaces, (4, 4))[2].sum())


def field_year(scenario, year: int, every: str = "1h", *, azimuth_step_deg: float = 15.0, weather=None) -> dict:
    """The efficiency table over sun positions and the clear-sky annual optical energy (equator aiming).

    Parameters
    ----------
    scenario : heliotwin.io.scenario.Scenario
    year : int
    every : str
        pandas frequency of the instants (``"1h"``, ``"30min"``).
    azimuth_step_deg : float
        Azimuth step [deg] of the efficiency table, in (0, 180].
    weather : heliotwin.io.weather.DniSeries, optional
        Measured or typical-year DNI (``field --weather CSV``) instead of pvlib's clear sky
        (:func:`weather_energy`; ``every`` is then the file's own step).

    Returns
    -------
    dict
        :func:`heliotwin.raytrace.yearly.annual_energy`'s (or :func:`weather_energy`'s) report plus
        ``scenario``, ``aim``, ``dni_model`` and ``seconds`` [s].
    """
    t0 = time.perf_counter()
    if isinstance(year, bool) or not isinstance(year, int) or not 1900 <= year <= 2100:
        raise HeliotwinError(f"--year: expected a year in 1900..2100, got {year!r}")
    step = _step(every)
    if step > pd.Timedelta("366D"):
        raise HeliotwinError(f"--every {_text(step)}: longer than the year")
    if step % pd.Timedelta("1D") == pd.Timedelta(0):
        raise HeliotwinError(f"--every {_text(step)}: a whole number of days puts every instant at the same time "
                             "of day (e.g. all at night); use hours or minutes (1h, 30min, 25h)")
    atm = Atmosphere.from_extras(scenario.extras)
    az_step = float(azimuth_step_deg)
    if not 0 < az_step <= 180:
        raise HeliotwinError(f"--table-azimuth-step: expected (0, 180] deg, got {az_step}")
    table = efficiency_table(scenario.plant, atmosphere=atm, azimuths_deg=np.arange(-180.0, 180.0, az_step),
                             elevations_deg=DEFAULT_ELEVATIONS_DEG)
    if weather is not None:
        report = weather_energy(scenario.plant, weather, table, year)
        dni_model = f"measured/typical-year DNI from {os.path.basename(weather.path)} ({weather.kind})"
    else:
        report = annual_energy(scenario.plant, year, _day_unit(every), atmosphere=atm, table=table)
        dni_model = "pvlib ineichen clear sky"
    if not report.get("instants"):
        raise HeliotwinError(f"--year {year} --every {every}: no instant with the sun above the horizon")
    report.update({"scenario": os.path.abspath(scenario.path) if scenario.path else None, "aim": "equator",
                   "dni_model": dni_model, "seconds": time.perf_counter() - t0})
    return report
