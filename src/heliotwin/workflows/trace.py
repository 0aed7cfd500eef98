"""The ``trace`` workflow: one PAINT calibration record traced with a plant, and what that plant is.

:func:`trace_record` traces a record (its sun, motor steps and target) with the dataset's plant and reports
powers, centroid and the measured spots; :func:`describe_plant` says which kinematics and surfaces a
scenario's plant has (nominal or calibrated, ideal or learned), for the reports of ``trace`` and ``validate``.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

import torch

from ..devices import resolve_device, to_device
from ..field import kinematics as kin_ops
from ..io.records import SOURCES
from ..progress import Stages
from ..scene import trace, world_surface
from .sizes import check_trace_sizes

__all__ = ["TraceSettings", "trace_record", "describe_plant"]


@dataclass
class TraceSettings:
    """How :func:`trace_record` traces (``heliotwin trace``'s defaults).

    Attributes
    ----------
    integrator : {"mc", "gaussian"}
    rays_per_point : int
        Monte-Carlo rays per mirror sample (``mc`` only).
    resolution : int
        Bitmap rows = columns over the whole target [pixels].
    samples : int
        Mirror samples per facet and direction.
    seed : int
        Seed of the ray generator.
    device : str
        Where to trace (``auto``: CUDA when present); the returned flux image is on the CPU.
    """

    integrator: str = "mc"
    rays_per_point: int = 100
    resolution: int = 256
    samples: int = 50
    seed: int = 0
    device: str = "auto"


def describe_plant(scenario) -> dict:
    """What a scenario's plant is: ``kinematics`` nominal or calibrated (method, heliostat count), ``surface``
    ideal or learned (for which heliostats), and the ``scenario`` file; None: the nominal PAINT plant.

    >>> describe_plant(None)
    {'kinematics': 'nominal', 'surface': 'ideal'}
    >>> from heliotwin.field.demo import demo_plant
    >>> from heliotwin.io.scenario import Scenario
    >>> learned = {"calibration": {"method": "lm", "heliostats": ["AM43", "AQ49"]}, "surfaces": {"AM43": {}}}
    >>> described = describe_plant(Scenario(demo_plant(2), learned=learned, path="calibrated.h5"))
    >>> described["kinematics"], described["surface"], described["scenario"].endswith("calibrated.h5")
    ('calibrated (lm) for 2 heliostats', 'learned for AM43', True)
    """
    if scenario is None:
        return {"kinematics": "nominal", "surface": "ideal"}
    cal = scenario.learned.get("calibration") or {}
    surfaces = sorted(scenario.learned.get("surfaces") or {})
    return {"scenario": os.path.abspath(scenario.path),
            "kinematics": f"calibrated ({cal.get('method')}) for {len(cal.get('heliostats', []))} heliostats"
            if cal else "nominal",
            "surface": f"learned for {', '.join(surfaces)}" if surfaces else "ideal"}


def trace_record(dataset, record_id: int, settings: TraceSettings | None = None, *, progress: bool = False):
    """Trace one calibration record (its sun, motor steps and target) with the dataset's plant.

    Parameters
    ----------
    dataset : heliotwin.io.paint.PaintDataset
    record_id : int
        PAINT record id (one of ``dataset.records.record_id``).
    settings : TraceSettings, optional
    progress : bool
        Say when the tracing starts and ends (:class:`heliotwin.progress.Stages`: a line each in a log).

    Returns
    -------
    flux : heliotwin.raytrace.flux.FluxImage
        Batch of one, bitmap [1, resolution, resolution] [W/m^2], on the CPU.
    report : dict
        Powers [W], centroid (ENU [m], WGS84 [deg], target-local [m]; ``None`` when no light reaches the
        target), sun angles [deg] (PAINT: azimuth 0 = south, +90 = east), the measured spots, optics.
    """
    settings = settings or TraceSettings()
    integrator, rays_per_point, resolution = settings.integrator, settings.rays_per_point, settings.resolution
    samples, seed = settings.samples, settings.seed
    plant = dataset.plant
    check_trace_sizes(resolution=resolution, samples=samples, facets=plant.field.facets.translation.shape[1],
                      rays_per_point=rays_per_point if integrator == "mc" else None)
    device = resolve_device(settings.device)
    row = dataset.record(int(record_id))
    kin, surfaces, target, row_on = to_device((plant.field.kinematics, plant.field.surfaces,
                                               plant.target(row.target[0]), row), device)
    t0 = time.perf_counter()
    stages = Stages(1, "heliotwin trace", enabled=progress)
    stages.start(f"tracing record {int(record_id)} ({integrator})")
    with torch.no_grad():
        pts, nrm, area, R, c = world_surface(kin, surfaces, row_on.heliostat_index, row_on.motor_steps,
                                             (samples, samples))
        flux = trace(pts, nrm, area, row_on.sun.to(pts), target, integrator=integrator,
                     resolution=(resolution, resolution), sun=plant.sun, rays_per_point=rays_per_point,
                     generator=torch.Generator(device=device).manual_seed(seed))
    seconds = time.perf_counter() - t0
    stages.step(f"tracing record {int(record_id)}")
    stages.close()
    # Reporting happens on the CPU, where the plant's site and targets live.
    flux, nrm, area, R, c = to_device((flux, nrm, area, R, c), "cpu")
    s = row.sun
    # No light on the target: there is no centroid (a zero image's "centroid" would be the target centre).
    lit = bool(flux.bitmap[0].sum() > 0) and float(flux.intercepted_power_w[0]) > 0
    centroid = flux.centroid_enu()[0] if lit else None
    lla = plant.site.to_wgs84(centroid) if lit else None
    cosines = (nrm[0].to(torch.float64) @ s[0]).clamp_min(0)
    spots = {src: row.focal_spots[0, k].tolist() for k, src in enumerate(SOURCES)
             if bool(torch.isfinite(row.focal_spots[0, k]).all())}
    report = {
        "heliostat": row.heliostat_ids[int(row.heliostat_index[0])], "record": int(row.record_id[0]),
        "target": row.target[0], "integrator": integrator, "device": str(device),
        "rays_per_point": rays_per_point if integrator == "mc" else None, "resolution": resolution,
        "sun_azimuth_deg": math.degrees(float(row.sun_azimuth[0])),
        "sun_elevation_deg": math.degrees(float(row.sun_elevation[0])),
        "motor_steps": row.motor_steps[0].tolist(),
        "centroid_enu_m": centroid.tolist() if lit else None,
        "centroid_wgs84": {"latitude_deg": float(lla[0]), "longitude_deg": float(lla[1]),
                           "altitude_m": float(lla[2])} if lit else None,
        "centroid_local_m": flux.centroid_local()[0].tolist() if lit else None,
        "measured_spot_enu_m": spots,
        "measured_flux_png": row.flux_png[0],
        "total_power_w": float(flux.total_power_w[0]), "intercepted_power_w": float(flux.intercepted_power_w[0]),
        "mirror_area_m2": float(area[0].sum()),
        "mean_incidence_cosine": float((cosines * area[0]).sum() / area[0].sum()),
        "dni_w_m2": plant.sun.dni, "reflectivity": plant.sun.reflectivity, "sunshape": plant.sun.sunshape,
        "slope_error_mrad": plant.sun.slope_error * 1e3, "seconds": seconds,
        "concentrator_enu_m": c[0].tolist(), "mirror_normal_enu": kin_ops.mirror_normal(R)[0].tolist(),
    }
    return flux, report
