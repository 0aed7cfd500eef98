"""The demos: the whole embedded field (:func:`run_field_demo`, ``heliotwin demo``) and the small traced
plant of earlier releases (:func:`run_demo`, ``heliotwin demo --classic``).

Both run on an embedded plant (:mod:`heliotwin.field.demo`) with no data and no network, and write their
figures, PNGs and ``summary.json`` into the folder they are given (the caller stages it).
"""
from __future__ import annotations

import csv
import math
import os
import time
from pathlib import Path

import pandas as pd
import torch
from tqdm.auto import tqdm

from ..devices import resolve_device, to_device
from ..errors import HeliotwinError
from ..field import kinematics as kin_ops
from ..field.demo import demo_field_plant, demo_plant
from ..io.images import to_png
from ..io.report import write_json
from ..io.scenario import next_scenario, provenance_entry, write_scenario
from ..optimise.aimpoints import AimSettings, optimise_aimpoints
from ..optimise.aimstate import KEY, aimpoint_state, instant_state
from ..plots import plot_demo, plot_field_demo
from ..progress import Stages
from ..raytrace.field import FACTORS, field_optics, per_heliostat_rows, summary
from ..raytrace.flux import FluxImage
from ..scene import trace, world_surface
from ..sun import direction_from_time, paint_angles_from_direction

__all__ = ["run_demo", "run_field_demo"]


def run_field_demo(out, *, num_heliostats: int = 2000, time_utc: str = "2023-03-20T11:30:00Z",
                   peak_limit_fraction: float = 0.75, iterations: int | None = None,
                   progress: bool = False, device: str = "cpu") -> dict:
    """The demo as the whole field: efficiency map, loss breakdown, receiver flux before/after aim points.

    On :func:`demo_field_plant` at ``time_utc``: the field model with exact shading and blocking
    (:func:`heliotwin.raytrace.field.field_optics`, Gaussian footprints on the 48 x 20 receiver map) at
    equator aiming, then :func:`heliotwin.optimise.aimpoints.optimise_aimpoints` for a peak limit of
    ``peak_limit_fraction`` times equator aiming's peak (re-judged with exact occlusion).

    Parameters
    ----------
    out : path
        Folder (created when missing) for ``field_efficiency.png`` (per-heliostat efficiency),
        ``losses.png`` (power-weighted loss breakdown), ``flux_equator.png`` and ``flux_optimised.png``
        (receiver maps [kW/m^2] on one scale) and ``flux_before_after.png`` (both side by side with the
        limit contour), ``heliostats.csv`` (per-heliostat factors, the ``field`` command's columns),
        ``plant.h5`` (the plant as a scenario with the optimised aim points, to go on from) and
        ``summary.json``.
    num_heliostats : int
    time_utc : str
        ISO time [UTC] of the sun position (pvlib at the Jülich reference); the sun must be up.
    peak_limit_fraction : float
        In (0, 1].
    iterations : int, optional
        Image-model steps per round of the aim-point optimiser (default: the optimiser's).
    progress : bool
        Progress over the stages (:class:`heliotwin.progress.Stages`: a bar on a terminal, a line per stage
        otherwise).
    device : str
        Where the field model and the aim points run (``auto``: CUDA when present); results on the CPU.

    Returns
    -------
    dict
        The summary (also written as JSON): the ``field`` command's report (``field.efficiency`` unweighted as
        SolarPILOT and power-weighted, ``receiver``: the field model's product, without the tower's shadow),
        ``losses`` (per stage of :data:`CHAIN`, the tower's shadow included: power-weighted fraction and [W]),
        ``chain`` (the receiver power [W] and efficiency with the tower's shadow, :func:`_chain`), ``aim_points``
        (limit, peaks before/after, violation, power ratio), ``seconds`` per stage.
    """
    if not 0.0 < float(peak_limit_fraction) <= 1.0:
        raise HeliotwinError(f"run_field_demo: peak_limit_fraction must be in (0, 1], got {peak_limit_fraction!r}")
    t_start = time.perf_counter()
    folder = Path(out)
    seconds = {}
    bar = Stages(4, "heliotwin demo", enabled=progress)
    bar.start(f"field model ({num_heliostats} heliostats)")
    plant, atm = demo_field_plant(num_heliostats)
    s = plant.site
    sun = direction_from_time(pd.DatetimeIndex([pd.Timestamp(time_utc)]), s.latitude_deg, s.longitude_deg,
                              s.altitude_m)[0]
    device = resolve_device(device)
    plant_cpu, plant, sun = plant, to_device(plant, device), sun.to(device)
    t0 = time.perf_counter()
    with torch.no_grad():
        equator = field_optics(plant, sun, atmosphere=atm)  # the aim points' exact model at equator aiming too
        before = to_device(equator, "cpu")
    seconds["field_model"] = time.perf_counter() - t0
    rep = summary(before, plant_cpu)
    bar.step("field model")
    bar.start("aim points")
    limit = float(peak_limit_fraction) * rep["receiver"]["peak_flux_w_m2"]
    t0 = time.perf_counter()
    knobs = AimSettings() if iterations is None else AimSettings(iterations=int(iterations))
    aimed = to_device(optimise_aimpoints(plant, sun, limit, knobs, atmosphere=atm, equator=equator), "cpu")
    seconds["aim_points"] = time.perf_counter() - t0
    bar.step("aim points")
    bar.start("figures and plant.h5")
    folder.mkdir(parents=True, exist_ok=True)
    rep["losses"] = _loss_breakdown(before)
    rep["chain"] = _chain(before)
    t0 = time.perf_counter()
    plot_field_demo(folder, plant_cpu, before, aimed, rep, limit, time_utc)
    _write_rows(folder / "heliostats.csv", per_heliostat_rows(before, plant_cpu))
    write_scenario(_demo_scenario(plant_cpu, atm, aimed, sun.cpu(), limit, time_utc, num_heliostats),
                   folder / "plant.h5")
    seconds["outputs"] = time.perf_counter() - t0
    bar.step("figures and plant.h5")
    bar.start("summary")
    seconds["total"] = time.perf_counter() - t_start
    rep.update({"plant": "embedded Jülich-like field (heliotwin.field.demo.demo_field_plant)", "time_utc": time_utc,
                "aim_points": {
                    "peak_limit_w_m2": limit, "equator_peak_w_m2": rep["receiver"]["peak_flux_w_m2"],
                    "optimised_peak_w_m2": aimed.peak_flux_w_m2, "violation": aimed.violation(limit),
                    "equator_power_w": rep["receiver"]["power_w"], "optimised_power_w": aimed.power_w,
                    "power_vs_equator": aimed.power_w / rep["receiver"]["power_w"], "iterations": aimed.iterations},
                "seconds": seconds,
                "files": ["field_efficiency.png", "losses.png", "flux_equator.png", "flux_optimised.png",
                          "flux_before_after.png", "heliostats.csv", "plant.h5", "summary.json"]})
    write_json(folder / "summary.json", rep)
    bar.step("summary")
    bar.close()
    return rep


def _demo_scenario(plant, atmosphere, aimed, sun, limit: float, time_utc: str, num_heliostats: int):
    """The demo's plant as a scenario a user can go on from (``field --scenario plant.h5 --aim scenario``,
    ``aimpoints``, ``scenario export``): the atmosphere in ``/extras``, the optimised aim points of the demo's
    instant in ``/learned/aimpoints``, one provenance step naming the command."""
    entry = instant_state(plant, time_utc, aimed.aim.cpu(), sun, power_w=aimed.power_w,
                          peak_flux_w_m2=aimed.peak_flux_w_m2)
    learned = {KEY: aimpoint_state({"i000": entry}, peak_limit_w_m2=limit)}
    step = provenance_entry("demo", command=f"heliotwin demo --heliostats {num_heliostats} --time {time_utc}",
                            plant="heliotwin.field.demo.demo_field_plant", instants=[time_utc],
                            peak_limit_w_m2=limit)
    scenario = next_scenario(None, plant, learned=learned, step=step,
                             metadata={"created_by_command": "heliotwin demo"})
    scenario.extras = atmosphere.to_extras()
    return scenario


#: The demo's loss chain: the field model's factors with the tower's shadow after the heliostats' own shading.
#: The field model's product (``field.efficiency``, ``receiver.power_w``, the receiver maps) leaves the tower's
#: shadow out and reports it apart (:mod:`heliotwin.raytrace.field`, for comparing with SolarPILOT's factors);
#: the demo's waterfall and its MW on the receiver (``chain``) count it.
CHAIN = FACTORS[:2] + ("tower_shading",) + FACTORS[2:]


def _loss_breakdown(result) -> dict:
    """Per stage of :data:`CHAIN` (cosine, shading, the tower's shadow, blocking, attenuation, intercept,
    reflectance): the power [W] lost at that stage and its ``fraction`` of DNI x mirror area [1] (both add up to
    DNI x area - the chain's power), and ``own_fraction``: the factor's own loss, 1 - factor, power-weighted over
    what reaches the stage [1]."""
    stage = result.dni * result.mirror_area.to(torch.float64)
    total = max(float(stage.sum()), 1e-30)  # DNI x mirror area [W]: every fraction is of it, so they add up
    out = {}
    for name in CHAIN:
        f = getattr(result, name).to(torch.float64)
        lost = float((stage * (1.0 - f)).sum())
        out[name] = {"fraction": lost / total, "power_w": lost,
                     "own_fraction": lost / max(float(stage.sum()), 1e-30)}
        stage = stage * f
    return out


def _chain(result) -> dict:
    """The demo's chain at equator aiming (:data:`CHAIN`): its power on the receiver [W] and efficiency [1] with the
    tower's shadow, the tower's power-weighted unshaded fraction and what the field model's figures leave out."""
    area = result.dni * result.mirror_area.to(torch.float64)
    with_tower = area * result.efficiency.to(torch.float64) * result.tower_shading.to(torch.float64)
    power = float(with_tower.sum())
    without = float((area * result.efficiency.to(torch.float64)).sum())
    return {"stages": list(CHAIN), "power_w": power, "efficiency": power / max(float(area.sum()), 1e-30),
            "tower_shading_power_weighted": power / max(without, 1e-30),
            "tower_shading_unweighted_mean": float(result.tower_shading.mean()),
            "note": "the demo's chain counts the tower's shadow; the field model's efficiency, receiver power and "
                    "receiver maps leave it out (reported apart as tower_shading, for comparing with SolarPILOT)"}


def _write_rows(path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def run_demo(out: str, *, num_heliostats: int = 48, integrator: str = "mc", rays_per_point: int = 64,
             resolution: int = 256, seed: int = 0, time_utc: str = "2023-03-20T11:30:00Z",
             samples: tuple[int, int] = (20, 20), chunk: int = 8, progress: bool = True, device="cpu") -> dict:
    """Trace the demo plant at ``time_utc`` (an ISO time [UTC]) with every heliostat aimed at the receiver's apex.

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
