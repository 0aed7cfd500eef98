"""How the per-heliostat year tables' sun-position grid was chosen: interpolation against the direct sum.

For small generated fields (:func:`heliotwin.optimise.testbed.generated_plant`: radial field, full cylinder,
vertical flat and tilted flat receivers), the field model is evaluated directly at every daylight hour of a
clear-sky year (pvlib Ineichen at the plant's site), and the per-heliostat energy of that year is compared with
the table interpolation (:mod:`heliotwin.raytrace.annual`) for candidate grids, all of them subsets of one fine
grid evaluated once: per heliostat the relative error of its annual energy (median, p95) and the field total's.
The issue's limits: median <= 1 %, p95 <= 3 %, field <= 0.3 %.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/year_grid_choice.py --heliostats 60 --out /tmp/yg [--every 1h]

Writes ``<out>/grid_choice.json`` and prints one line per field and grid.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from heliotwin.optimise.testbed import generated_plant
from heliotwin.raytrace import annual as A
from heliotwin.raytrace.field import equator_aim_points, field_optics, reuse_mirror_samples
from heliotwin.raytrace.yearly import clear_sky_dni
from heliotwin.sun import daylight_times, direction_from_paint_angles

FINE_EL = (1.0, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.5, 8.0, 10.0, 12.5, 13.0, 15.0, 16.0, 20.0, 25.0, 30.0, 37.5, 40.0,
           45.0, 50.0, 55.0, 60.0, 65.0, 70.0, 77.5, 80.0, 89.0, 90.0)
#: Tables' variants: ``table`` interpolates the efficiency itself; ``exact-cosine`` interpolates the efficiency over
#: the cosine (shading x blocking x attenuation x intercept x reflectance) and multiplies each hour's exact cosine.
VARIANTS = ("table", "exact-cosine")
CANDIDATES = {
    "az15_old-el": (15.0, (5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 89.0)),
    "az15_dense-low": (15.0, A.DEFAULT_GRID.elevations_deg),
    "az10_dense-low": (10.0, A.DEFAULT_GRID.elevations_deg),
    "az5_dense-low": (5.0, A.DEFAULT_GRID.elevations_deg),
    "az10_sparse-low": (10.0, (1.0, 3.0, 6.0, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0, 77.5, 90.0)),
    "az10_mid": (10.0, (1.0, 2.5, 4.0, 6.0, 8.0, 10.0, 13.0, 16.0, 20.0, 25.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0,
                        90.0)),
    "az20_dense-low": (20.0, A.DEFAULT_GRID.elevations_deg),
    "az30_dense-low": (30.0, A.DEFAULT_GRID.elevations_deg),
    "az20_mid-low": (20.0, (1.0, 2.5, 4.0, 6.0, 8.0, 10.0, 13.0, 16.0, 20.0, 25.0, 30.0, 40.0, 50.0, 60.0, 70.0,
                            80.0, 90.0)),
    "az30_sparse": (30.0, (1.0, 2.5, 4.0, 6.0, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0, 77.5, 90.0)),
    "az20_sparse": (20.0, (1.0, 2.5, 4.0, 6.0, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0, 77.5, 90.0)),
}


def run(receiver: str, heliostats: int, every: str, year: int = 2023) -> dict:
    plant, atm = generated_plant("radial", heliostats, receiver)
    s = plant.site
    times, az, el = daylight_times(year, every, s.latitude_deg, s.longitude_deg, s.altitude_m, min_elevation_deg=0.0)
    dni = torch.as_tensor(clear_sky_dni(times, plant))
    keep = dni > 0
    az, el, dni = az[keep], el[keep], dni[keep]
    hours = float(np.timedelta64(1, "h") / np.timedelta64(1, "h"))
    settings = A.TABLE_SETTINGS
    aim = equator_aim_points(plant.targets["receiver"], plant.field.kinematics.position.to(torch.float64))
    t0 = time.perf_counter()
    suns = direction_from_paint_angles(az, el).reshape(-1, 3)
    direct, cosine = [], []
    with torch.no_grad(), reuse_mirror_samples():
        for k in range(suns.shape[0]):
            r = field_optics(plant, suns[k], atmosphere=atm, aim=aim, settings=settings)
            direct.append(r.efficiency.double())
            cosine.append(r.cosine.double())
    direct, cosine = torch.stack(direct, -1), torch.stack(cosine, -1)  # [H, T]
    t_direct = time.perf_counter() - t0
    e_direct = (direct * dni).sum(-1) * hours
    fine = A.TableGrid(5.0, FINE_EL)
    idx, w = A.bilinear_weights(fine, az, el)
    nodes_needed = set()
    grids = {name: A.TableGrid(step, els) for name, (step, els) in CANDIDATES.items()}
    for g in grids.values():
        i, ww = A.bilinear_weights(g, az, el)
        for n in A.needed_nodes(i, ww, dni).tolist():
            z = g.shape[1]
            e_deg, a_deg = g.elevations_deg[n // z], g.azimuths_deg[n % z]
            nodes_needed.add(FINE_EL.index(e_deg) * fine.shape[1] + int(round((a_deg + 180.0) / 5.0)))
    nodes = torch.tensor(sorted(nodes_needed))
    t0 = time.perf_counter()
    tables = A.heliostat_tables(plant, fine.suns(nodes), aim, atmosphere=atm)
    tab, tab_cos = tables["efficiency"], tables["cosine"]
    t_tables = time.perf_counter() - t0
    lookup = {int(n): k for k, n in enumerate(nodes.tolist())}
    out = {"receiver": receiver, "heliostats": heliostats, "hours": int(len(dni)), "direct_s": t_direct,
           "fine_nodes": int(nodes.numel()), "tables_s": t_tables, "grids": {}}
    for name, g in grids.items():
        i, ww = A.bilinear_weights(g, az, el)
        gn = A.needed_nodes(i, ww, dni)
        z = g.shape[1]
        cols = [lookup[FINE_EL.index(g.elevations_deg[n // z]) * fine.shape[1] + int(round((g.azimuths_deg[n % z]
                                                                                             + 180.0) / 5.0))]
                for n in gn.tolist()]
        for variant in VARIANTS:
            if variant == "table":
                e_int = tab[:, cols] @ A.node_weights(i, ww, dni * hours, gn)
            else:  # the year's sums: each hour's exact cosine times the interpolated rest
                rest = tab[:, cols] / tab_cos[:, cols].clamp_min(1e-12)
                e_int = A.hourly_sums(rest, cosine, A.node_columns(gn, i, ww), ww, dni * hours)
            rel = ((e_int - e_direct).abs() / e_direct.clamp_min(1e-30))
            key = f"{name}/{variant}"
            out["grids"][key] = {"nodes": int(gn.numel()), "median_error": float(rel.median()),
                                 "p95_error": float(torch.quantile(rel, 0.95)),
                                 "field_error": float(abs(e_int.sum() - e_direct.sum()) / e_direct.sum())}
            r = out["grids"][key]
            print(f"{receiver:12s} {key:30s} nodes {r['nodes']:4d}  median {100 * r['median_error']:.3f} %  p95 "
                  f"{100 * r['p95_error']:.3f} %  field {100 * r['field_error']:.3f} %", flush=True)
    return out


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--heliostats", type=int, default=60)
    p.add_argument("--every", default="1h")
    p.add_argument("--receivers", default="cylinder,flat,tilted-flat")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    res = [run(r, a.heliostats, a.every) for r in a.receivers.split(",")]
    Path(a.out).mkdir(parents=True, exist_ok=True)
    (Path(a.out) / "grid_choice.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
