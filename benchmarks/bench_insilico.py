"""In-silico study: distance x training-image count table (the published protocol).

    python benchmarks/bench_insilico.py [--distances 25,50,100,200] [--images 1,2,4,8,16] [--seeds 0] \
        [--window aim|centred] [--steps 1500] [--grid 1e-5,3e-5,1e-4,3e-4] [--cv last|loo] [--threads 2] \
        [--json insilico.json] [--markdown insilico.md]

Prints one row per cell: mean normal deviation [mrad], piston-free height RMS [mm], mean test L1 of the ideal
and learned surfaces and IMP = L1(ideal)/L1(learned) - 1 (see heliotwin.surfaces.insilico), the Laplacian
weight chosen on the held-out latest training image, loss evaluations and seconds; then the same table as
markdown. Settings: :func:`heliotwin.surfaces.insilico.insilico_settings` (the surface learner's one settings
class with L-BFGS + blur continuation, L2 loss; gauge-fixed), 7x7 degree-3 facets, 32x32 samples per facet,
64x64 px 6 m windows fixed on the aim point (known kinematics; ``--window centred`` for spot-centred ones), 5 test
images per cell. With several ``--seeds`` each cell is run per seed and the markdown table also gives the mean
over seeds.

Model mismatch (``--mismatch``): :func:`heliotwin.surfaces.mismatch.run_mismatch_case` per distance and seed --
truth rendered with a Gaussian sun (2.8 mrad) + 1.2 mrad slope error, a camera saturating at 80 % of the
true max and cutting below 5 %; the learner (:mod:`heliotwin.surfaces.generalise`) assumes a Buie sun and
estimates cut and saturation itself. Spot-centred windows, ``--images`` training (first value) and 10 test
images. Prints median test L1 (ideal vs learned), training images worse than the ideal, test images
improved with a Wilson 95 % interval, the largest edge ridge and normal deviation from the truth.

    python benchmarks/bench_insilico.py --mismatch --distances 50 --images 4 --seeds 0 --json mismatch.json

``--halo K`` gives training image K a broad diffuse halo (half its power spread by an 8 px Gaussian): an
inconsistent image that the outlier rule should drop.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch

from heliotwin.io.paint import load_paint
from heliotwin.surfaces.insilico import LAPLACIAN_GRID, insilico_settings, run_case
from heliotwin.surfaces.mismatch import run_mismatch_case

PAINT = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "paint")


def markdown(rows) -> str:
    out = ["| distance [m] | images | seed | normal dev. [mrad] | height RMS [mm] | L1 ideal | L1 learned | IMP [%] | "
           "Laplacian | evals | s |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        li = sum(r["test_l1_ideal"]) / len(r["test_l1_ideal"])
        ll = sum(r["test_l1_learned"]) / len(r["test_l1_learned"])
        out.append(f"| {r['distance_m']:.0f} | {r['train_images']} | {r['seed']} | {r['normal_deviation_mrad']:.3f} | "
                   f"{r['height_rms_mm']:.3f} | {li:.3f} | {ll:.4f} | {100 * r['imp']:.0f} | {r['laplacian']:g} | "
                   f"{r['loss_evaluations']} | {r['seconds']:.1f} |")
    return "\n".join(out)


def mean_over_seeds(rows) -> str:
    """Markdown: per cell the mean over seeds of normal deviation, height RMS and IMP."""
    cells: dict = {}
    for r in rows:
        cells.setdefault((r["distance_m"], r["train_images"]), []).append(r)
    out = ["| distance [m] | images | seeds | mean normal dev. [mrad] | max | mean height RMS [mm] | min IMP [%] |",
           "|---:|---:|---:|---:|---:|---:|---:|"]
    for (d, n), rs in cells.items():
        nd = [r["normal_deviation_mrad"] for r in rs]
        out.append(f"| {d:.0f} | {n} | {len(rs)} | {sum(nd) / len(nd):.3f} | {max(nd):.3f} | "
                   f"{sum(r['height_rms_mm'] for r in rs) / len(rs):.3f} | {100 * min(r['imp'] for r in rs):.0f} |")
    return "\n".join(out)


def mismatch(a) -> int:
    plant = load_paint(a.paint, heliostats=["AA39"], with_records=False).plant
    n = int(a.images.split(",")[0])
    rows = []
    for d in (float(x) for x in a.distances.split(",")):
        for seed in (int(x) for x in a.seeds.split(",")):
            r = run_mismatch_case(plant, d, n, 10, seed, halo=a.halo)
            rows.append(r)
            lo, hi = r["test_improved_wilson95"]
            rec = r["recovery"]
            print(f"{d:5.0f} m seed {seed}: median test L1 ideal {r['median_l1_ideal']:.4f} -> learned "
                  f"{r['median_l1_learned']:.4f} (raw {r['median_l1_ideal_raw']:.4f} -> "
                  f"{r['median_l1_learned_raw']:.4f}); training worse than ideal "
                  f"{r['train_worse_than_ideal']}/{n}; test improved {r['test_improved']}/"
                  f"{r['test_images']} (Wilson 95 % [{lo:.2f}, {hi:.2f}]); max edge ridge "
                  f"{r['edge_ridge']['edge_max_mrad']:.2f} mrad; normal dev. from truth ideal "
                  f"{rec['ideal']['normal_deviation_mrad']:.2f} -> learned "
                  f"{rec['learned']['normal_deviation_mrad']:.2f} mrad; slope error "
                  f"{1e3 * r['optics_used']['slope_error_rad']:.1f} mrad; blur {r['blur_mode']}; "
                  f"dropped {[x['record'] for x in r['dropped']]}; alpha {r['acceptance']['alpha']}; "
                  f"{r['seconds']:.0f} s", flush=True)
    if a.json:
        with open(a.json, "w", encoding="utf-8") as fh:
            json.dump({"mismatch": True, "rows": rows}, fh, indent=1)
    return 0


def main(argv=None) -> int:
    default = insilico_settings()
    p = argparse.ArgumentParser()
    p.add_argument("--paint", default=PAINT)
    p.add_argument("--distances", default="25,50,100,200")
    p.add_argument("--images", default="1,2,4,8,16")
    p.add_argument("--seeds", default="0", help="comma-separated seeds (each cell is run once per seed)")
    p.add_argument("--window", default="aim", choices=("aim", "centred"),
                   help="windows fixed on the aim point (known kinematics) or centred on each spot")
    p.add_argument("--steps", type=int, default=default.steps, help="cap on loss evaluations per fit")
    p.add_argument("--grid", default=",".join(f"{w:g}" for w in LAPLACIAN_GRID),
                   help="Laplacian weights tried on the held-out training image")
    p.add_argument("--cv", default="last", choices=("last", "loo"),
                   help="Laplacian-weight validation: latest training image held out, or leave-one-out over all")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json")
    p.add_argument("--markdown")
    p.add_argument("--mismatch", action="store_true", help="the model-mismatch study (see the module docstring)")
    p.add_argument("--halo", type=int, help="--mismatch: give this training image a broad halo (inconsistent)")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    if a.mismatch:
        return mismatch(a)
    plant = load_paint(a.paint, heliostats=["AA39"], with_records=False).plant
    settings = insilico_settings(steps=a.steps)
    grid = tuple(float(x) for x in a.grid.split(",") if x)
    rows = []
    t0 = time.perf_counter()
    print(f"{'dist':>5} {'imgs':>4} {'seed':>4} {'n_dev mrad':>10} {'h_rms mm':>9} {'L1 ideal':>9} {'L1 learn':>9} "
          f"{'IMP %':>8} {'lap':>6} {'evals':>5} {'s':>6}")
    for d in (float(x) for x in a.distances.split(",")):
        for n in (int(x) for x in a.images.split(",")):
            for seed in (int(x) for x in a.seeds.split(",")):
                r = run_case(plant, d, n, seed=seed, settings=settings, window=a.window, laplacian_grid=grid,
                             laplacian_cv=a.cv)
                rows.append(r)
                li = sum(r["test_l1_ideal"]) / len(r["test_l1_ideal"])
                ll = sum(r["test_l1_learned"]) / len(r["test_l1_learned"])
                print(f"{d:5.0f} {n:4d} {seed:4d} {r['normal_deviation_mrad']:10.3f} {r['height_rms_mm']:9.3f} "
                      f"{li:9.3f} {ll:9.4f} {100 * r['imp']:8.0f} {r['laplacian']:6g} {r['loss_evaluations']:5d} "
                      f"{r['seconds']:6.1f}", flush=True)
    table = markdown(rows) + "\n\n" + mean_over_seeds(rows)
    print()
    print(table)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s on {a.threads} thread(s); window {a.window}; "
          f"settings {settings.as_dict()}; Laplacian grid {list(grid)} ({a.cv})")
    if a.json:
        with open(a.json, "w", encoding="utf-8") as fh:
            json.dump({"settings": settings.as_dict(), "laplacian_grid": list(grid), "laplacian_cv": a.cv,
                       "seeds": a.seeds, "window": a.window, "rows": rows}, fh, indent=2)
    if a.markdown:
        with open(a.markdown, "w", encoding="utf-8") as fh:
            fh.write(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
