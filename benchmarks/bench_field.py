"""The whole field: heliotwin against SolarPILOT, and the speed of the field model.

1. **Against SolarPILOT** on ``../shared/data/solarpilot-reference`` (500 heliostats, four suns): per sun, ours
   against theirs -- per-heliostat cosine and attenuation (max abs difference), field-average shading and
   blocking, intercept, total efficiency, receiver power and the peak flux on the same 48 x 20 grid. Also the
   whole-mirror blocking (SolarPILOT's reading) and the tower's shadow. SolarPILOT azimuths (clockwise from
   north) become heliotwin's PAINT azimuths as ``180 - az``.
2. **Blocking, brute force**: for the east sun, the heliostats where SolarPILOT reports no blocking but the
   ray-rectangle test finds some, with the all-pairs check of the worst one.
3. **Over a year**: the efficiency table and the hourly clear-sky annual energy for 2000 heliostats (time).
4. **The demo** (``heliotwin demo``'s :func:`heliotwin.workflows.demo.run_field_demo`): wall time per stage and
   its figures (field efficiency, peak before/after aim points, power ratio).
5. **The live loop** (what the plant recomputes every few minutes), each beside its reference in the same run:
   the field model on a dense 2000-heliostat block (``tests/helpers/field.dense_field(40, 50)``, ~20 %
   blocking at the south sun) -- building the plant from its layout plus one sun, and the field model alone --
   against SolarPILOT's own wall times on the same layout (``../shared/tools/solarpilot``, run as a separate
   program: building its field, ``assign_layout_wall_s``, plus one sun, ``wall_s``); the receiver power of the
   field model against its Monte-Carlo trace of the same samples; and the demo's aim-point stage
   (:func:`heliotwin.optimise.aimpoints.optimise_aimpoints` at the demo's instant and limit) for
   ``--live-heliostats`` heliostats.
6. **Speed** of one sun (shading + blocking + 48 x 20 map, and + 256 x 256 map) for generated radial-staggered
   fields of 50 to 10 000 heliostats, and the Monte-Carlo field model's rays per second (256 rays per flux
   sample, shading and blocking included in the time) up to 2000 heliostats; peak resident memory. Wall
   times depend on the machine and its load: the script records ``torch.get_num_threads()`` and the load
   average next to them.

Usage::

    OMP_NUM_THREADS=2 python benchmarks/bench_field.py --out /tmp/field [--sizes 50,500,2000,10000]
        [--year-heliostats 2000] [--demo-heliostats 2000] [--live-heliostats 2000]   # "" / 0: skip that part

Writes ``<out>/field.json`` and prints the tables.
"""
from __future__ import annotations

import argparse
import csv
import inspect
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from heliotwin.field.layout import plant_from_layout
from heliotwin.geometry import safe_normalize
from heliotwin.io.report import write_json
from heliotwin.raytrace.field import FieldSettings, field_optics, summary
from heliotwin.sun import direction_from_paint_angles

REF = Path(__file__).resolve().parents[2] / "shared" / "data" / "solarpilot-reference"
SOLARPILOT = Path(__file__).resolve().parents[2] / "shared" / "tools" / "solarpilot" / "solarpilot_reference.py"
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers.field import PLANT_TOML, brute_force_unoccluded, dense_field, write_layout  # noqa: E402


def _sun(solarpilot_az: float, el: float) -> torch.Tensor:
    return direction_from_paint_angles(torch.tensor(math.radians(180.0 - solarpilot_az), dtype=torch.float64),
                                       torch.tensor(math.radians(el), dtype=torch.float64))


def against_solarpilot(out: Path, model: str = "exact") -> list[dict]:
    """Per sun, ours (occlusion ``model``: ``exact`` ray tests or ``solarpilot``'s analytic estimate) vs theirs."""
    toml = out / "plant.toml"
    toml.write_text(PLANT_TOML)
    plant, atm = plant_from_layout(REF / "layout-500.csv", toml)
    settings = FieldSettings(occlusion_model=model)
    table = []
    for ref in json.loads((REF / "field-results.json").read_text())["suns"]:
        az, el = ref["sun_azimuth_deg_from_north_clockwise"], ref["sun_elevation_deg"]
        key = f"az{az:.2f}_el{el:.2f}"
        t0 = time.perf_counter()
        with torch.no_grad():
            res = field_optics(plant, _sun(az, el), atmosphere=atm, settings=settings)
        seconds = time.perf_counter() - t0
        rep = summary(res, plant)
        rows = list(csv.DictReader(open(REF / f"per-heliostat_{key}.csv")))
        idx = torch.tensor([plant.field.ids.index(f"H{int(r['id']):04d}") for r in rows])
        col = {k: torch.tensor([float(r[k]) for r in rows], dtype=torch.float64)
               for k in ("cosine", "attenuation", "shading", "blocking")}
        e = rep["field"]["efficiency"]
        table.append({
            "sun": key, "occlusion_model": model, "solarpilot_azimuth_deg": az, "elevation_deg": el,
            "seconds": seconds,
            "cosine_max_abs_diff": float((res.cosine[idx] - col["cosine"]).abs().max()),
            "attenuation_max_abs_diff": float((res.attenuation[idx] - col["attenuation"]).abs().max()),
            "shading_per_heliostat_max_abs_diff": float((res.shading[idx] - col["shading"]).abs().max()),
            "blocking_per_heliostat_max_abs_diff": float((res.blocking[idx] - col["blocking"]).abs().max()),
            **{f"{k}_ours": e[k] for k in ("shading", "blocking", "intercept", "total")},
            **{f"{k}_solarpilot": ref[f"eff_{k}"] for k in ("shading", "blocking", "intercept", "total")},
            "blocking_whole_mirror_ours": e["blocking_whole_mirror"], "tower_shading_ours": e["tower_shading"],
            "power_kw_ours": rep["receiver"]["power_w"] / 1e3, "power_kw_solarpilot": ref["receiver_power_kw"],
            "peak_48x20_kw_m2_ours": rep["receiver"]["peak_flux_w_m2"] / 1e3,
            "peak_48x20_kw_m2_solarpilot": ref["peak_flux_kw_m2"]["48x20"],
        })
    return table


def _print_table(table: list[dict]) -> None:
    print("model      | sun                 | cos dmax | att dmax | shading ours/SP | blocking ours/SP | "
          "intercept ours/SP | total ours/SP   | power kW ours/SP | peak 48x20 kW/m2 ours/SP | "
          "per-helio max|d| shad/block")
    for t in table:
        print(f"{t['occlusion_model']:10s} | {t['sun']:19s} | {t['cosine_max_abs_diff']:.1e}  | "
              f"{t['attenuation_max_abs_diff']:.1e}  | "
              f"{t['shading_ours']:.4f}/{t['shading_solarpilot']:.4f}   | {t['blocking_ours']:.4f}/"
              f"{t['blocking_solarpilot']:.4f}    | {t['intercept_ours']:.4f}/{t['intercept_solarpilot']:.4f}     | "
              f"{t['total_ours']:.4f}/{t['total_solarpilot']:.4f} | {t['power_kw_ours']:.1f}/"
              f"{t['power_kw_solarpilot']:.1f}  | {t['peak_48x20_kw_m2_ours']:.1f}/"
              f"{t['peak_48x20_kw_m2_solarpilot']:.1f}             | "
              f"{t['shading_per_heliostat_max_abs_diff']:.4f}/{t['blocking_per_heliostat_max_abs_diff']:.4f}")


def blocking_disagreement(out: Path) -> dict:
    """East sun: heliostats SolarPILOT calls unblocked but the ray test blocks, checked all-pairs, and the
    mechanism (:func:`mechanism`)."""
    toml = out / "plant.toml"
    plant, atm = plant_from_layout(REF / "layout-500.csv", toml)
    sun = _sun(97.5527, 36.7262)
    with torch.no_grad():
        res = field_optics(plant, sun, atmosphere=atm)
    rows = list(csv.DictReader(open(REF / "per-heliostat_az97.55_el36.73.csv")))
    theirs = {f"H{int(r['id']):04d}": float(r["blocking"]) for r in rows}
    ours = dict(zip(plant.field.ids, res.blocking.tolist()))
    missed = sorted((h for h in ours if theirs[h] >= 0.9999 and ours[h] < 0.99), key=lambda h: ours[h])
    worst = plant.field.ids.index(missed[0]) if missed else None
    check = None
    if worst is not None:
        from heliotwin.raytrace.field import tracked_mirror_samples
        from heliotwin.raytrace.occlusion import OccluderSet

        occ = OccluderSet(plant.field.kinematics.position, res.normal, plant.field.width, plant.field.height)
        pts, nrm, _ = tracked_mirror_samples(plant, res.normal, 16, torch.float64)
        refl = -sun + 2 * (nrm * sun).sum(-1, keepdim=True) * nrm
        free = brute_force_unoccluded(pts, refl, occ.center, occ.normal, occ.width_axis, occ.height_axis,
                                      plant.field.width, plant.field.height)[worst]
        check = {"heliostat": missed[0], "blocking_ours": ours[missed[0]], "blocking_solarpilot": theirs[missed[0]],
                 "all_pairs_blocked_fraction": 1.0 - float(free.mean())}
    return {"heliostats_unblocked_in_solarpilot_blocked_here": len(missed), "worst": check,
            "field_blocking_ours": float(res.blocking.mean()),
            "field_blocking_solarpilot": float(np.mean(list(theirs.values()))),
            "mechanism": mechanism(plant)}


_VARIANTS = ("solarpilot", "no_reach_test", "no_reach_test_independent", "no_reach_test_independent_no_corner_rule")


def mechanism(plant) -> dict:
    """Field-average shading and blocking per sun with SolarPILOT's estimate, then with its approximations
    removed one at a time: ``distance_cutoff=False`` (no reach test: SolarPILOT compares the 3-D pivot distance
    with an along-the-ray reach and so drops diagonal neighbours that do block), then also
    ``combine="independent"`` (overlapping pair losses not counted twice), then also ``corner_rule=False``."""
    from heliotwin.raytrace.field import equator_aim_points, tracking_normals
    from heliotwin.raytrace.occlusion import OccluderSet, occluder_candidates, solarpilot_interference

    pos = plant.field.kinematics.position.to(torch.float64)
    w, h = plant.field.width.to(torch.float64), plant.field.height.to(torch.float64)
    aim = equator_aim_points(plant.targets["receiver"], pos)
    out = {}
    for ref in json.loads((REF / "field-results.json").read_text())["suns"]:
        az, el = ref["sun_azimuth_deg_from_north_clockwise"], ref["sun_elevation_deg"]
        sun = _sun(az, el)
        n = tracking_normals(pos, aim, sun)
        occ = OccluderSet(pos, n, w, h)
        entry = {}
        for name, direction in (("shading", sun), ("blocking", safe_normalize(aim - pos))):
            idx, valid = occluder_candidates(occ, direction)
            for label, kw in (("solarpilot", {}), ("no_reach_test", {"distance_cutoff": False}),
                              ("no_reach_test_independent", {"distance_cutoff": False, "combine": "independent"}),
                              ("no_reach_test_independent_no_corner_rule",
                               {"distance_cutoff": False, "combine": "independent", "corner_rule": False})):
                entry[f"{name}_{label}"] = float(solarpilot_interference(pos, n, w, h, direction, idx, valid,
                                                                         **kw).mean())
        out[f"az{az:.2f}_el{el:.2f}"] = entry
    return out


def radial_staggered(n: int) -> np.ndarray:
    """The demo's radial-staggered northern field (:func:`heliotwin.field.demo.demo_field_positions`)."""
    from heliotwin.field.demo import demo_field_positions

    return demo_field_positions(n).numpy()


def speed(out: Path, sizes: list[int]) -> list[dict]:
    toml = out / "plant.toml"
    sun = _sun(180.0, 39.8)
    rows = []
    for n in sizes:
        layout = out / f"layout-{n}.csv"
        xyz = radial_staggered(n)
        layout.write_text("x,y,z\n" + "\n".join(",".join(f"{v:.4f}" for v in p) for p in xyz) + "\n")
        plant, atm = plant_from_layout(layout, toml)
        entry = {"heliostats": n}
        for name, res in (("48x20", (20, 48)), ("256x256", (256, 256))):
            with torch.no_grad():
                field_optics(plant, sun, atmosphere=atm, settings=FieldSettings(resolution=res))  # warm-up
                times = []
                for _ in range(3):
                    t0 = time.perf_counter()
                    r = field_optics(plant, sun, atmosphere=atm, settings=FieldSettings(resolution=res))
                    times.append(time.perf_counter() - t0)
            entry[f"seconds_{name}"] = min(times)
            entry[f"total_efficiency_{name}"] = float(r.efficiency.mean())
        if n <= 2000:  # Monte Carlo with shading and blocking: rays per second of the whole field model
            mc = FieldSettings(integrator="mc", rays_per_point=256)
            with torch.no_grad():
                field_optics(plant, sun, atmosphere=atm, settings=mc)
                t0 = time.perf_counter()
                field_optics(plant, sun, atmosphere=atm, settings=mc)
                dt = time.perf_counter() - t0
            rays = n * plant.field.facets.translation.shape[1] * mc.flux_samples ** 2 * mc.rays_per_point
            entry.update(mc_rays=rays, mc_seconds=dt, mc_rays_per_s=rays / dt)
        rows.append(entry)
        mc_text = f", Monte Carlo {entry['mc_rays_per_s'] / 1e6:.1f} M rays/s" if "mc_rays" in entry else ""
        print(f"  {n:6d} heliostats: {entry['seconds_48x20']:.3f} s (48x20), {entry['seconds_256x256']:.3f} s "
              f"(256x256){mc_text}", flush=True)
    return rows


def solarpilot_seconds(layout: Path, out: Path, az: float = 180.0, el: float = 39.8, repeats: int = 2) -> dict | None:
    """SolarPILOT's own wall times (CoPilot, Hermite model, equator aiming, 48 x 20 map) for one sun on
    ``layout``, the fastest of ``repeats`` runs of the separate program; None when it is not installed."""
    if not SOLARPILOT.exists():
        return None
    best = None
    for _ in range(repeats):
        js = out / "solarpilot-live.json"
        subprocess.run([sys.executable, str(SOLARPILOT), "--engine", "copilot", "--aim", "simple", "--layout",
                        str(layout), "--sun", str(az), str(el), "--flux-nx", "48", "--flux-ny", "20", "--json",
                        str(js)], check=True, stdout=subprocess.DEVNULL)
        cp = json.loads(js.read_text())["copilot"]
        r = cp["results"][0]
        entry = {"build_s": cp["assign_layout_wall_s"], "sun_s": r["wall_s"],
                 "total_s": cp["assign_layout_wall_s"] + r["wall_s"], "eff_total": r["eff_total"],
                 "eff_blocking": r["eff_blocking"], "eff_shading": r["eff_shading"]}
        best = entry if best is None or entry["total_s"] < best["total_s"] else best
    return best


def live(out: Path, aim_heliostats: int, repeats: int = 3) -> dict:
    """The live loop's field model on the dense 2000-heliostat block beside SolarPILOT, its receiver power
    against the Monte-Carlo trace, and the demo's aim-point stage (section 5 of the module docstring)."""
    import pandas as pd

    from heliotwin.field.demo import demo_field_plant
    from heliotwin.optimise.aimpoints import AimSettings, optimise_aimpoints
    from heliotwin.sun import direction_from_time
    from heliotwin.workflows.demo import run_field_demo

    out.mkdir(parents=True, exist_ok=True)
    (out / "plant.toml").write_text(PLANT_TOML)
    layout = write_layout(out, dense_field(40, 50), name="layout-dense-2000.csv")
    sun = _sun(180.0, 39.8)
    build, model = [], []
    for _ in range(repeats + 1):  # the first is a warm-up
        t0 = time.perf_counter()
        plant, atm = plant_from_layout(layout, out / "plant.toml")
        t1 = time.perf_counter()
        with torch.no_grad():
            res = field_optics(plant, sun, atmosphere=atm)
        rep = summary(res, plant)
        build.append(t1 - t0)
        model.append(time.perf_counter() - t1)
    build, model = min(build[1:]), min(model[1:])
    with torch.no_grad():
        mc = field_optics(plant, sun, atmosphere=atm, settings=FieldSettings(integrator="mc", rays_per_point=64))
    power = rep["receiver"]["power_w"]
    mc_power = float(mc.flux.sum()) * mc.pixel_area
    e = rep["field"]["efficiency"]
    entry = {"heliostats": len(plant.field.ids), "layout": "dense_field(40, 50)", "field_model_s": model,
             "build_plus_field_model_s": build + model, "total_efficiency": e["total"],
             "blocking": e["blocking"], "shading": e["shading"], "power_w": power,
             "monte_carlo_map_power_w": mc_power, "monte_carlo_relative_difference": mc_power / power - 1.0,
             "solarpilot": solarpilot_seconds(layout, out)}
    sp = entry["solarpilot"]
    sp_text = (f"SolarPILOT {sp['total_s']:.3f} s (build {sp['build_s']:.3f} s + sun {sp['sun_s']:.3f} s), "
               f"total {sp['eff_total']:.4f}" if sp else "SolarPILOT not found")
    print(f"  live field ({entry['heliostats']} heliostats, dense, blocking {1 - e['blocking']:.1%}): heliotwin "
          f"{build + model:.3f} s (build {build:.3f} s + field model {model:.3f} s), total {e['total']:.4f}; "
          f"{sp_text}; Monte-Carlo map power {entry['monte_carlo_relative_difference']:+.2%}", flush=True)
    if aim_heliostats:
        defaults = inspect.signature(run_field_demo).parameters
        plant, atm = demo_field_plant(aim_heliostats)
        s = plant.site
        when = pd.DatetimeIndex([pd.Timestamp(defaults["time_utc"].default)])
        demo_sun = direction_from_time(when, s.latitude_deg, s.longitude_deg, s.altitude_m)[0]
        with torch.no_grad():
            before = field_optics(plant, demo_sun, atmosphere=atm)
        limit = float(defaults["peak_limit_fraction"].default) * float(before.flux.max())
        t0 = time.perf_counter()
        aimed = optimise_aimpoints(plant, demo_sun, limit, AimSettings(), atmosphere=atm, equator=before)
        entry["aim_points"] = {"heliostats": aim_heliostats, "seconds": time.perf_counter() - t0,
                               "equator_peak_w_m2": float(before.flux.max()), "peak_limit_w_m2": limit,
                               "optimised_peak_w_m2": aimed.peak_flux_w_m2, "optimised_power_w": aimed.power_w,
                               "rounds": len(aimed.history)}
        a = entry["aim_points"]
        print(f"  live aim points ({aim_heliostats} heliostats, the demo's stage): {a['seconds']:.2f} s, peak "
              f"{a['equator_peak_w_m2'] / 1e3:.0f} -> {a['optimised_peak_w_m2'] / 1e3:.0f} kW/m2 (limit "
              f"{limit / 1e3:.0f}), {a['rounds']} exact checks after calibration", flush=True)
    return entry


def yearly(out: Path, n: int) -> dict:
    """The yearly table (24 azimuths x 11 elevations) and the 2023 hourly clear-sky energy for ``n`` heliostats."""
    from heliotwin.raytrace.yearly import annual_energy

    layout = out / f"layout-{n}.csv"
    layout.write_text("x,y,z\n" + "\n".join(",".join(f"{v:.4f}" for v in p) for p in radial_staggered(n)) + "\n")
    plant, atm = plant_from_layout(layout, out / "plant.toml")
    rep = annual_energy(plant, 2023, "1h", atmosphere=atm)
    rep.pop("table")
    rep["heliostats"] = n
    print(f"  yearly ({n} heliostats): {rep['seconds']:.1f} s, {rep['annual_optical_energy_mwh']:.0f} MWh", flush=True)
    return rep


def demo(out: Path, n: int) -> dict:
    """``heliotwin demo``'s run on ``n`` heliostats: seconds per stage and the headline figures."""
    from heliotwin.workflows.demo import run_field_demo

    t0 = time.perf_counter()
    rep = run_field_demo(out / "demo", num_heliostats=n)
    entry = {"heliostats": n, "wall_seconds": time.perf_counter() - t0, "seconds": rep["seconds"],
             "field_efficiency_power_weighted": rep["field"]["efficiency_power_weighted"],
             "aim_points": rep["aim_points"], "receiver_power_w": rep["receiver"]["power_w"]}
    a = rep["aim_points"]
    print(f"  demo ({n} heliostats): {entry['wall_seconds']:.1f} s (field {rep['seconds']['field_model']:.1f} s, "
          f"aim points {rep['seconds']['aim_points']:.1f} s); efficiency "
          f"{entry['field_efficiency_power_weighted']['total']:.3f}; peak {a['equator_peak_w_m2'] / 1e3:.0f} -> "
          f"{a['optimised_peak_w_m2'] / 1e3:.0f} kW/m2 (limit {a['peak_limit_w_m2'] / 1e3:.0f}) at "
          f"{a['power_vs_equator']:.4f} of the power", flush=True)
    return entry


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--sizes", default="50,500,2000,10000", help="empty or 0: skip the speed runs")
    ap.add_argument("--year-heliostats", type=int, default=2000, help="0: skip the yearly run")
    ap.add_argument("--demo-heliostats", type=int, default=2000, help="0: skip the demo run")
    ap.add_argument("--live-heliostats", type=int, default=2000,
                    help="aim-point stage size of the live-loop run (dense field vs SolarPILOT); 0: skip it")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {"threads": torch.get_num_threads(), "load_average": os.getloadavg()}
    table = against_solarpilot(out, "exact") + against_solarpilot(out, "solarpilot")
    _print_table(table)
    report["against_solarpilot"] = table
    report["east_sun_blocking"] = blocking_disagreement(out)
    mech = report["east_sun_blocking"].pop("mechanism")
    print("east sun blocking:", json.dumps(report["east_sun_blocking"]))
    report["east_sun_blocking"]["mechanism"] = mech
    exact = {t["sun"]: t for t in table if t["occlusion_model"] == "exact"}
    print("mechanism (field averages): SolarPILOT's estimate -> without its reach test -> and overlaps not summed "
          "-> and no corner rule || exact ray test (blocking: of the whole mirror, and of the lit part)")
    for key, m in mech.items():
        sh = " -> ".join(f"{m['shading_' + v]:.4f}" for v in _VARIANTS)
        bl = " -> ".join(f"{m['blocking_' + v]:.4f}" for v in _VARIANTS)
        e = exact[key]
        print(f"  {key:19s} shading {sh} || {e['shading_ours']:.4f};  blocking {bl} || "
              f"{e['blocking_whole_mirror_ours']:.4f}, {e['blocking_ours']:.4f}")
    if args.live_heliostats:
        report["live"] = live(out, args.live_heliostats)
    sizes = [int(s) for s in args.sizes.split(",") if s.strip() and int(s) > 0]  # "" or 0: skip
    if sizes:
        report["speed"] = speed(out, sizes)
    if args.demo_heliostats:
        report["demo"] = demo(out, args.demo_heliostats)
    if args.year_heliostats:
        report["yearly"] = yearly(out, args.year_heliostats)
    report["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak resident memory {report['peak_rss_mb']:.0f} MB")
    write_json(out / "field.json", report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
