"""The field model at one sun as a workflow, without an ephemeris: :func:`field` on a scenario's plant, the
run settings and their checks, and :func:`sun_from_angles` (PAINT angles to a sun direction).

Kept apart from :mod:`heliotwin.workflows.field` (which re-exports everything here and adds the sun at a UTC
time through pvlib, day and year sweeps, and weather files through pandas) so that ``heliotwin field`` at
given sun angles imports neither pvlib nor pandas (~0.7 s of such a command's start-up).
"""
from __future__ import annotations

import dataclasses
import math
import os
import time
from dataclasses import dataclass

import torch

from ..atmosphere import Atmosphere
from ..devices import to_device
from ..distributed import run_sharded
from ..errors import HeliotwinError
from ..optimise.aimstate import stored_aimpoints
from ..raytrace.field import FieldResult, FieldSettings, field_optics, summary
from ..sunangles import direction_from_paint_angles

__all__ = ["FieldRunSettings", "field", "flux_map_fields", "sun_from_angles", "check_irradiance",
           "check_map_resolution", "check_sun_angles", "MAX_MAP_CELLS", "MAX_DNI"]


@dataclass
class FieldRunSettings:
    """What :func:`field` runs (the ``field`` command's defaults).

    Attributes
    ----------
    resolution : (int, int)
        Receiver map ``(rows, cols)``.
    integrator : {"gaussian", "conv", "mc"}
    occlusion : {"exact", "solarpilot"}
    seed : int
        Monte-Carlo seed.
    aim : {"equator", "scenario"}
        Equator aiming, or the scenario's stored aim points for the nearest stored sun.
    dni : float, optional
        Direct normal irradiance [W/m^2] (default: the scenario's).
    nproc : int
        Local gloo processes to shard the heliostats over (1: none).
    device : str, optional
        Where the field model runs (None: where the plant is).
    """

    resolution: tuple[int, int] = (20, 48)
    integrator: str = "gaussian"
    occlusion: str = "exact"
    seed: int = 0
    aim: str = "equator"
    dni: float | None = None
    nproc: int = 1
    device: str | None = None

    def __post_init__(self):
        self.check()  # refused when made, before any file is read or output staged

    def check(self) -> None:
        """One-line :class:`HeliotwinError` for settings no run can use (:func:`field` checks them too)."""
        check_irradiance(self.dni)
        check_map_resolution(self.resolution)
        if isinstance(self.nproc, bool) or not isinstance(self.nproc, int) or self.nproc < 1:
            raise HeliotwinError(f"--nproc: expected a positive number of processes, got {self.nproc!r}")


#: Most receiver map cells of a run: beyond, the maps alone exceed the memory of a workstation.
MAX_MAP_CELLS = 4096 * 4096
#: Highest direct normal irradiance accepted [W/m^2] (the solar constant is 1361 W/m^2).
MAX_DNI = 1500.0


def check_irradiance(dni) -> None:
    """``dni`` [W/m^2] is None (the scenario's) or a finite value in [0, :data:`MAX_DNI`]; else one line."""
    if dni is None:
        return
    if isinstance(dni, bool) or not isinstance(dni, (int, float)) or not math.isfinite(dni) or \
            not 0.0 <= dni <= MAX_DNI:
        raise HeliotwinError(f"--dni: expected a direct normal irradiance in [0, {MAX_DNI:g}] W/m2, got {dni!r}")


def check_map_resolution(resolution) -> None:
    """``(rows, cols)`` of a receiver map: positive integers; too many cells is the out-of-memory error."""
    try:
        rows, cols = (int(v) for v in resolution)
        ok = all(not isinstance(v, bool) and int(v) == v for v in resolution)
    except (TypeError, ValueError):
        rows = cols = 0
        ok = False
    if not ok or rows < 1 or cols < 1:
        raise HeliotwinError(f"--resolution: expected two positive integers (rows, cols), got {resolution!r}")
    if rows * cols > MAX_MAP_CELLS:
        raise MemoryError(f"a {cols}x{rows} receiver map has more than {MAX_MAP_CELLS} cells")


def check_sun_angles(azimuth_deg, elevation_deg) -> None:
    """PAINT sun angles [deg]: finite, azimuth within +-360, elevation above the horizon and at most 90."""
    for name, v, lo, hi in (("--sun-azimuth", azimuth_deg, -360.0, 360.0),
                            ("--sun-elevation", elevation_deg, -90.0, 90.0)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
            raise HeliotwinError(f"{name}: expected a finite angle in [{lo:g}, {hi:g}] deg, got {v!r}")
    if elevation_deg <= 0:
        raise HeliotwinError(f"--sun-elevation: the sun is below the horizon ({elevation_deg} deg)")


def sun_from_angles(azimuth_deg, elevation_deg) -> torch.Tensor:
    """The sun direction [3] (ENU, float64, unit, towards the sun) from PAINT angles [deg] (0 = south, +90 =
    east), checked by :func:`check_sun_angles`.

    >>> [round(x, 3) for x in sun_from_angles(0.0, 30.0).tolist()]
    [0.0, -0.866, 0.5]
    """
    check_sun_angles(azimuth_deg, elevation_deg)
    return direction_from_paint_angles(torch.tensor(math.radians(azimuth_deg), dtype=torch.float64),
                                       torch.tensor(math.radians(elevation_deg), dtype=torch.float64))


def field(scenario, sun: torch.Tensor, settings: FieldRunSettings | None = None) -> tuple[dict, FieldResult]:
    """The field model on the scenario's plant at one sun.

    Parameters
    ----------
    scenario : heliotwin.io.scenario.Scenario
        Plant, atmosphere (``extras``) and, for ``settings.aim == "scenario"``, stored aim points.
    sun : torch.Tensor, [3]
        Unit vector towards the sun (ENU), e.g. from :func:`sun_direction_at`.
    settings : FieldRunSettings, optional

    Returns
    -------
    report : dict
        :func:`heliotwin.raytrace.field.summary` plus ``scenario`` (its file), ``aim``, ``integrator``,
        ``occlusion``, ``resolution``, ``seconds`` and ``seconds_field_model`` [s].
    result : FieldResult
        Per-heliostat factors [H] and the receiver map [rows, cols] [W/m^2].
    """
    t0 = time.perf_counter()
    settings = settings or FieldRunSettings()
    plant = scenario.plant
    settings.check()
    if not len(plant.field.ids):  # the model's [H, ...] reshapes have nothing to infer a size from
        raise HeliotwinError(f"{getattr(scenario, 'path', None) or 'the scenario'}: the plant has no heliostats; "
                             f"nothing to evaluate")
    if settings.dni is not None:
        plant = dataclasses.replace(plant, sun=dataclasses.replace(plant.sun, dni=float(settings.dni)))
    if settings.device is not None:
        plant = to_device(plant, settings.device)
    sun = sun.to(plant.field.kinematics.position.device)
    aim = stored_aimpoints(scenario, sun) if settings.aim == "scenario" else None
    model = FieldSettings(resolution=settings.resolution, integrator=settings.integrator, seed=settings.seed,
                          occlusion_model=settings.occlusion)
    t1 = time.perf_counter()
    kwargs = dict(atmosphere=Atmosphere.from_extras(scenario.extras), aim=aim, settings=model)
    nproc = min(settings.nproc, len(plant.field.ids))  # at most one process per heliostat
    if nproc > 1:
        result = run_sharded(plant, sun, nproc, **kwargs)
    else:
        with torch.no_grad():
            result = field_optics(plant, sun, **kwargs)
    seconds_model = time.perf_counter() - t1
    report = summary(result, plant)
    report["receiver"].update(flux_map_fields(result))
    report.update({"scenario": os.path.abspath(scenario.path) if scenario.path else None, "aim": settings.aim,
                   "integrator": settings.integrator, "occlusion": settings.occlusion,
                   "resolution": {"cols": settings.resolution[1], "rows": settings.resolution[0]},
                   "seconds": time.perf_counter() - t0, "seconds_field_model": seconds_model})
    return report, result


def flux_map_fields(result: FieldResult) -> dict:
    """The receiver map for a JSON report: ``flux_map_w_m2`` [rows][cols] (row 0 = top) and
    ``flux_map_extent_m`` ``[arc_min, arc_max, height_min, height_max]`` (the same numbers as ``--flux-csv``)."""
    return {"flux_map_w_m2": result.flux.detach().cpu().to(torch.float64).tolist(),
            "flux_map_extent_m": [float(v) for v in result.extent.detach().cpu()]}
