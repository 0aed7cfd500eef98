"""The predict workflow: a year of flux from one heliostat with a learned surface.

:func:`predict` is the one entry (``heliotwin predict`` calls it): ``Scenario × heliostat × PredictionSettings →
(Scenario, report)``. It reads the learned surface (:func:`heliotwin.surfaces.state.learned_surface`) and runs
:func:`heliotwin.surfaces.predict.yearly_flux`; it learns nothing, so the scenario comes back unchanged.

Units: metres, radians; flux [W/m^2], power [W].
"""
from __future__ import annotations

from dataclasses import dataclass

from ..devices import resolve_device, to_device
from ..errors import HeliotwinError
from ..io.scenario import Scenario
from ..surfaces.predict import summarize, yearly_flux
from ..surfaces.state import KEY, learned_surface

__all__ = ["PredictionSettings", "predict", "learned_heliostat"]


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
    """

    year: int = 2023
    every: str = "30min"
    target: str | None = None
    device: str = "auto"


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
    series = yearly_flux(kin, target, site, surfaces, ideal, item["optics"], year=s.year, every=s.every,
                         progress=progress)
    optics = item["optics"]
    return scenario, {"heliostat": heliostat, "target": name, "year": s.year, "every": s.every,
                      "instants": len(series["time"]), "statistics": summarize(series), "series": series,
                      "optics": {"sunshape": optics.sunshape, "slope_error_rad": optics.slope_error},
                      "device": device}
