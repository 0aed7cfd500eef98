"""The main job on the embedded default plant: aim the field at the receiver, trace, report.

Used by ``heliotwin demo``; runs with no data and no network.
"""
from __future__ import annotations

import math
import os

import torch
from tqdm.auto import tqdm

from .field import kinematics as kin_ops
from .field.demo import demo_plant
from .raytrace.flux import FluxImage, to_png
from .scene import trace, world_surface
from .sun import direction_from_time, paint_angles_from_direction


def run_demo(out: str, *, num_heliostats: int = 48, integrator: str = "mc", rays_per_point: int = 64,
             resolution: int = 256, seed: int = 0, time_utc: str = "2023-03-20T11:30:00Z",
             samples: tuple[int, int] = (20, 20), chunk: int = 8, progress: bool = True, device="cpu") -> dict:
    """Trace the demo plant at ``time_utc`` with every heliostat aimed at the receiver's apex.

    Writes into ``out``: ``receiver-flux.png`` (unrolled cylinder, PAINT orientation: left = east),
    ``calibration-spot.png`` (the first heliostat on the lower calibration target, as in a camera-target
    calibration), ``field.png`` (layout coloured by cosine efficiency, flux maps in kW/m²) and
    ``summary.json``. ``device`` (``"cpu"``, ``"cuda"``, ``"auto"`` = CUDA when present) is where the
    tracing runs; images, plots and numbers are made on the CPU.

    Returns
    -------
    dict
        The summary (also written to ``out/summary.json``).
    """
    from .devices import resolve_device, to_device
    from .io.report import write_json
    from .plots import plot_demo

    device = resolve_device(device)
    os.makedirs(out, exist_ok=True)
    plant_cpu = demo_plant(num_heliostats, seed)
    plant = to_device(plant_cpu, device) if device != "cpu" else plant_cpu
    site, fld, kin = plant.site, plant.field, plant.field.kinematics
    sun_dir = direction_from_time([time_utc], *site.reference)[0].to(kin.position.device)
    az, el = paint_angles_from_direction(sun_dir)
    receiver = plant.target("receiver")
    h = len(fld.ids)
    aim = receiver.center.expand(h, 3)
    steps, reachable = kin_ops.inverse(kin, aim, sun_dir.expand(h, 3), strict=False)
    idx = torch.nonzero(reachable).flatten()
    gen = torch.Generator(device=device).manual_seed(seed)
    bitmap = torch.zeros(resolution, resolution, device=device)
    total, intercepted, per_heliostat = 0.0, 0.0, []
    bar = tqdm(total=len(idx), desc="demo: tracing field", unit="heliostat", disable=not progress)
    extent = None
    with torch.no_grad():
        for start in range(0, len(idx), chunk):
            sel = idx[start:start + chunk]
            pts, nrm, area, R, c = world_surface(kin, fld.surfaces, sel, steps[sel], samples)
            s = sun_dir.to(pts).expand(len(sel), 3)
            flux = trace(pts, nrm, area, s, receiver, integrator=integrator, resolution=(resolution, resolution),
                         sun=plant.sun, rays_per_point=rays_per_point, generator=gen)
            bitmap += flux.bitmap.sum(0)
            extent = flux.extent[:1]
            cos = (nrm.to(torch.float64) @ sun_dir).clamp_min(0)
            for j, hi in enumerate(sel.tolist()):
                per_heliostat.append({
                    "heliostat": fld.ids[hi], "position_enu_m": kin.position[hi].tolist(),
                    "motor_steps": steps[hi].tolist(),
                    "cosine_efficiency": float((cos[j] * area[j]).sum() / area[j].sum()),
                    "reflected_power_w": float(flux.total_power_w[j]),
                    "intercepted_power_w": float(flux.intercepted_power_w[j]),
                })
            total += float(flux.total_power_w.sum())
            intercepted += float(flux.intercepted_power_w.sum())
            bar.update(len(sel))
    bar.close()
    bitmap = bitmap.cpu()
    receiver_flux = to_device(FluxImage(bitmap[None], receiver, extent), "cpu")
    to_png(bitmap, os.path.join(out, "receiver-flux.png"))

    # One heliostat on the lower calibration target, as the camera-target calibration photographs it.
    cal = plant.target("solar_tower_juelich_lower")
    first = int(idx[0]) if len(idx) else 0
    cal_steps, _ = kin_ops.inverse(kin.index(first), cal.center[None], sun_dir[None], strict=False)
    with torch.no_grad():
        pts, nrm, area, _, _ = world_surface(kin, fld.surfaces, [first], cal_steps, samples)
        spot = trace(pts, nrm, area, sun_dir.to(pts)[None], cal, integrator=integrator,
                     resolution=(resolution, resolution),
                     sun=plant.sun, rays_per_point=rays_per_point, generator=gen)
    spot = to_device(spot, "cpu")
    cal = to_device(cal, "cpu")
    to_png(spot.bitmap[0], os.path.join(out, "calibration-spot.png"))
    plot_demo(plant_cpu, per_heliostat, receiver_flux, spot, os.path.join(out, "field.png"))
    peak = float(bitmap.max())
    summary = {
        "plant": "embedded Jülich-like demo plant", "time_utc": time_utc,
        "sun_azimuth_deg": math.degrees(float(az)), "sun_elevation_deg": math.degrees(float(el)),
        "dni_w_m2": plant.sun.dni, "sunshape": plant.sun.sunshape, "slope_error_mrad": plant.sun.slope_error * 1e3,
        "reflectivity": plant.sun.reflectivity, "integrator": integrator,
        "rays_per_point": rays_per_point if integrator == "mc" else None,
        "surface_samples_per_facet": samples[0] * samples[1],
        "heliostats": h, "heliostats_traced": int(len(idx)), "heliostats_unreachable": [fld.ids[i] for i in
                                                                                      torch.nonzero(~reachable).flatten().tolist()],
        "total_power_w": total,
        "receiver": {"intercepted_power_w": intercepted, "intercept_factor": intercepted / total if total else None,
                     "peak_flux_w_m2": peak, "centroid_enu_m": receiver_flux.centroid_enu()[0].tolist(),
                     "png": "receiver-flux.png"},
        "calibration_spot": {"heliostat": fld.ids[first], "target": cal.name,
                             "centroid_enu_m": spot.centroid_enu()[0].tolist(),
                             "centroid_wgs84": site.to_wgs84(spot.centroid_enu()[0]).tolist(),
                             "aim_point_enu_m": cal.center.tolist(), "png": "calibration-spot.png"},
        "per_heliostat": per_heliostat,
        "plots": ["field.png"],
    }
    write_json(os.path.join(out, "summary.json"), summary)
    return summary
