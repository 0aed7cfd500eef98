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
from ..io.weather import read_dni_series
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


def prediction_energy(series: dict, plant, dni_model: float, every: str, weather: str | None) -> dict:
    """The year's energy on the target [kWh]: each instant's predicted power (made at the plant's DNI) scaled by
    the DNI of that instant (clear sky, or the weather file's nearest row within half its step; none: 0)."""
    times = pd.DatetimeIndex(pd.to_datetime(series["time"], utc=True))
    if weather is None:
        dni, source = clear_sky_dni(times, plant), "pvlib ineichen clear sky"
    else:
        w = read_dni_series(weather)
        at = pd.Series(w.dni, index=w.times).sort_index()
        near = at.reindex(times, method="nearest", tolerance=pd.Timedelta(hours=w.step_hours / 2))
        dni, source = near.fillna(0.0).to_numpy(), f"{weather} ({w.kind})"
    step_h = pd.Timedelta(every).total_seconds() / 3600.0
    power = np.asarray(series["power_w"], dtype=np.float64) * np.asarray(dni, dtype=np.float64) / max(dni_model, 1e-9)
    series["dni_w_m2"] = [float(v) for v in dni]
    return {"energy_kwh": float(power.sum() * step_h / 1e3), "dni_source": source, "model_dni_w_m2": dni_model,
            "rule": "sum over instants of power at the model DNI x (DNI of the instant / model DNI) x step"}


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
    energy = prediction_energy(series, plant, float(getattr(optics, "dni", plant.sun.dni)), s.every, s.weather)
    return scenario, {"heliostat": heliostat, "target": name, "year": s.year, "every": s.every,
                      "instants": len(series["time"]), "statistics": summarize(series), "series": series,
                      "optics": {"sunshape": optics.sunshape, "slope_error_rad": optics.slope_error},
                      "device": device, "energy": energy}
