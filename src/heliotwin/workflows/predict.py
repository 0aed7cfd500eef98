"""The predict workflow: a year of flux from one heliostat with a learned surface.

:func:`predict` is the one entry (``heliotwin predict`` calls it): ``Scenario × heliostat × PredictionSettings →
(Scenario, report)``. It reads the learned surface (:func:`heliotwin.surfaces.state.learned_surface`) and runs
:func:`heliotwin.surfaces.predict.yearly_flux`; it learns nothing, so the scenario comes back unchanged.

Units: metres, radians; flux [W/m^2], power [W].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from ..devices import resolve_device, to_device
from ..errors import HeliotwinError
from ..io.scenario import Scenario
from ..io.weather import ANNUAL_FRACTION, read_dni_series, weather_checks, weather_for_year
from ..raytrace.yearly import clear_sky_dni
from ..surfaces.predict import YearSampling, summarize, yearly_flux
from ..surfaces.state import KEY, learned_surface

__all__ = ["PredictionSettings", "predict", "learned_heliostat", "prediction_energy"]


@dataclass
class PredictionSettings:
    """Settings of :func:`predict` (defaults: the command line's).

    Attributes
    ----------
    year : int
    every : str
        Time step between daylight instants (pandas frequency, e.g. ``"30min"``).
    target : str, optional
        Target name (default: the one the training images were taken on).
    device : {"auto", "cpu", "cuda"}
    weather : str, optional
        A DNI time series CSV (:func:`heliotwin.io.weather.read_dni_series`) for the energy figure; default:
        pvlib's clear sky at the plant's site.
    """

    year: int = 2023
    every: str = "30min"
    target: str | None = None
    device: str = "auto"
    weather: str | None = None


def prediction_energy(series: dict, plant, dni_model: float, every: str, weather: str | None,
                      year: int | None = None) -> dict:
    """The year's energy on the target [kWh]: each instant's predicted power (made at the plant's DNI) scaled by
    the DNI of that instant (clear sky, or the weather file placed in ``year`` by
    :func:`heliotwin.io.weather.weather_for_year`, the same rule as ``field --year --weather``: the row whose
    interval holds the instant; an instant in a gap of the file counts no energy and the coverage says so).

    ``series``: ``time`` (ISO, UTC) and ``power_w`` per instant (T); gets ``dni_w_m2`` (NaN in a gap).
    ``year``: default the instants' year. Returns ``energy_kwh`` over the instants with a DNI, ``annual``,
    ``coverage`` and ``assumptions`` (with a file), ``dni_source``, ``model_dni_w_m2``, ``rule``; with a file also
    :func:`heliotwin.io.weather.weather_checks`' ``time_convention``, ``weather_site``, ``site_offset_km``,
    ``dni_share_below_horizon`` and ``warnings`` (the same as ``field --year --weather`` states).
    """
    times = pd.DatetimeIndex(pd.to_datetime(series["time"], utc=True))
    out = {}
    if weather is None:
        dni, source = clear_sky_dni(times, plant), "pvlib ineichen clear sky"
    else:
        w = read_dni_series(weather)
        year = int(times.year[len(times) // 2]) if year is None else int(year)
        wy = weather_for_year(w, year)
        dni, source = wy.dni_at(times), f"{weather} ({w.kind})"
        have = np.isfinite(dni)
        if not have.any():
            raise HeliotwinError(f"{weather}: no row within half its step ({wy.step_hours:g} h) of any of the "
                                 f"{len(times)} instants in {year}")
        annual = wy.annual and float(have.mean()) >= ANNUAL_FRACTION
        assumptions = list(wy.assumptions)
        if wy.annual and not annual:
            assumptions.append(f"{int(have.sum())} of the {len(times)} instants have a DNI in the file: the energy "
                               "is theirs, not annual")
        out = {"annual": annual, "assumptions": assumptions, **weather_checks(wy, w, plant.site),
               "coverage": {**wy.coverage, "instants_with_dni": int(have.sum()), "instants": int(len(times))}}
    step_h = pd.Timedelta(every).total_seconds() / 3600.0
    dni = np.asarray(dni, dtype=np.float64)
    power = np.asarray(series["power_w"], dtype=np.float64) * np.nan_to_num(dni) / max(dni_model, 1e-9)
    series["dni_w_m2"] = [float(v) for v in dni]
    return {"energy_kwh": float(power.sum() * step_h / 1e3), "dni_source": source, "model_dni_w_m2": dni_model,
            **out, "rule": "sum over instants of power at the model DNI x (DNI of the instant / model DNI) x step; "
                           "instants in a gap of the weather file count nothing"}


def learned_heliostat(scenario: Scenario, heliostat: str | None = None) -> str:
    """``heliostat``, or the scenario's only learned surface when None (one line when there is not exactly one)."""
    if heliostat is not None:
        return heliostat
    learned = sorted(scenario.learned.get(KEY) or {})
    if len(learned) != 1:
        raise HeliotwinError(f"{scenario.path}: {len(learned)} learned surfaces ({', '.join(learned) or 'none'}); "
                             f"choose one with --heliostat")
    return learned[0]


def predict(scenario: Scenario, heliostat: str | None = None, settings: PredictionSettings | None = None, *,
            progress: bool = True) -> tuple[Scenario, dict]:
    """The yearly flux prediction of ``heliostat`` (default: the scenario's only learned surface).

    Returns
    -------
    scenario : Scenario
        Unchanged.
    report : dict
        JSON-ready: ``heliostat``, ``target``, ``year``, ``every``, ``instants`` (T), ``statistics`` over the
        year, ``series`` (lists of length T, see :func:`~heliotwin.surfaces.predict.yearly_flux`), ``optics``,
        ``device``.
    """
    s = settings or PredictionSettings()
    heliostat = learned_heliostat(scenario, heliostat)
    item = learned_surface(scenario, heliostat)
    plant = scenario.plant
    name = s.target or item["target"]
    target = plant.target(name)
    site = (plant.site.latitude_deg, plant.site.longitude_deg, plant.site.altitude_m)
    kin = plant.field.kinematics.index([plant.field.index_of(heliostat)])
    surfaces, ideal = item["surfaces"], item["ideal"]
    device = resolve_device(s.device)
    if device != "cpu":
        kin, target, surfaces, ideal = to_device((kin, target, surfaces, ideal), device)
    series = yearly_flux(kin, target, site, surfaces, ideal, item["optics"],
                         when=YearSampling(year=s.year, every=s.every), progress=progress)
    optics = item["optics"]
    energy = prediction_energy(series, plant, float(getattr(optics, "dni", plant.sun.dni)), s.every, s.weather,
                               s.year)
    return scenario, {"heliostat": heliostat, "target": name, "year": s.year, "every": s.every,
                      "instants": len(series["time"]), "statistics": summarize(series), "series": series,
                      "optics": {"sunshape": optics.sunshape, "slope_error_rad": optics.slope_error},
                      "device": device, "energy": energy}
