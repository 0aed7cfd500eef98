"""Benchmark of the calibration methods on the real PAINT records.

1. Every method for ``--train 10`` and ``--train 30`` (split chrono, ``--test 30``) on the heliostats with
   >= 50 records: median over heliostats of each heliostat's mean test error [mrad].
2. MSc experiments: error vs training size (10, 20, 40, 60, 100 where available) for the rigid body
   (``gradient``) and the ``hybrid``; test error vs mean train-to-test sun distance for the isolation and
   the chronological split.

Usage::

    python benchmarks/bench_calibration.py [--paint ../shared/data/paint] [--json bench.json]
        [--methods lm,gradient,hybrid,mlp,images] [--skip-msc] [--threads 2]

3. Speed: ``lm`` + ``gradient`` fit time over all heliostats (goal < 60 s on 2 cores), printed at the end;
   the wall-clock figures live here, never in the tests.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

DEFAULT_PAINT = Path(__file__).resolve().parents[2] / "shared" / "data" / "paint"


def main(argv=None) -> int:
    from heliotwin.calibrate.protocol.pipeline import RunConfig, run_calibration
    from heliotwin.calibrate.report import plot_training_size
    from heliotwin.io.paint import load_paint
    from heliotwin.io.report import write_json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paint", default=str(DEFAULT_PAINT))
    ap.add_argument("--json", default="bench_calibration.json")
    ap.add_argument("--methods", default="lm,gradient,hybrid,mlp,images")
    ap.add_argument("--skip-msc", action="store_true")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (the speed goal is for 2 cores)")
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    ds = load_paint(args.paint)
    base = RunConfig(paint=args.paint, split="chrono", test=30, min_records=50)
    out = {"table": {}, "msc": {}}
    t0 = time.perf_counter()
    rows = []
    for method in args.methods.split(","):
        for n in (10, 30):
            rep, _, _ = run_calibration(replace(base, method=method, train=n), ds)
            ov = rep["overall"]
            per_h = {h: r.get("mean_test_mrad") for h, r in rep["heliostats"].items() if r.get("status") == "ok"}
            out["table"][f"{method}/N={n}"] = {"overall": ov, "per_heliostat_mean_test_mrad": per_h}
            rows.append((method, n, ov["median_of_mean_test_mrad"], ov["mean_of_mean_test_mrad"],
                         ov["nominal_median_of_mean_test_mrad"],
                         ov["fit_seconds"], ov["n_heliostats"]))
            info = ov.get("method_info") or {}
            extra = ""
            if "heliostats_using_network" in info:
                extra = f", network kept for {info['heliostats_using_network']}/{ov['n_heliostats']} heliostats"
            if "image_records_train" in info:
                extra = f", {info['image_records_train']} training records with images"
            print(f"{method:9s} N={n:3d}: median {ov['median_of_mean_test_mrad']:.3f} mrad  "
                  f"mean {ov['mean_of_mean_test_mrad']:.3f}  (nominal {ov['nominal_median_of_mean_test_mrad']:.2f}), "
                  f"fit {ov['fit_seconds']:.1f} s, "
                  f"{ov['n_heliostats']} heliostats{extra}", flush=True)
    print("\n| method | N=10 median [mrad] | N=30 median [mrad] | N=10 mean | N=30 mean | fit s (N=10 / N=30) |")
    print("|---|---|---|---|---|---|")
    for method in args.methods.split(","):
        r10 = next(r for r in rows if r[0] == method and r[1] == 10)
        r30 = next(r for r in rows if r[0] == method and r[1] == 30)
        print(f"| {method} | {r10[2]:.2f} | {r30[2]:.2f} | {r10[3]:.2f} | {r30[3]:.2f} | {r10[5]:.1f} / {r30[5]:.1f} |")
    print(f"| nominal | {rows[0][4]:.2f} | {rows[0][4]:.2f} | - | - | - |")
    speed = {n: sum(r[5] for r in rows if r[0] in ("lm", "gradient") and r[1] == n) for n in (10, 30)}
    if {"lm", "gradient"} <= set(args.methods.split(",")):
        print(f"speed: lm + gradient fit over all heliostats: {speed[10]:.1f} s (N=10), {speed[30]:.1f} s (N=30) "
              f"with {args.threads} threads (goal < 60 s)")
        out["speed_lm_gradient_seconds"] = speed
    if not args.skip_msc:
        curves = {}
        for method in ("gradient", "hybrid"):
            pts = []
            for n in (10, 20, 40, 60, 100):
                rep, _, _ = run_calibration(replace(base, method=method, train=n), ds)
                ov = rep["overall"]
                pts.append((n, ov["median_of_mean_test_mrad"]))
                print(f"size curve {method:9s} N={n:3d}: median {ov['median_of_mean_test_mrad']:.3f} mrad "
                      f"({ov['n_heliostats']} heliostats)", flush=True)
            curves[method] = pts
        out["msc"]["training_size"] = curves
        plot_training_size(os.path.splitext(args.json)[0] + "-training-size.png", curves,
                           "chrono, --test 30: rigid body (gradient) vs hybrid")
        dist = {}
        for split in ("chrono", "isolation"):
            rep, _, _ = run_calibration(replace(base, method="lm", train=30, split=split), ds)
            per = {h: {"mean_test_mrad": r["mean_test_mrad"],
                       "mean_train_test_distance_rad": r["split"]["mean_train_test_distance_rad"]}
                   for h, r in rep["heliostats"].items() if r.get("status") == "ok"}
            dist[split] = {"median_of_mean_test_mrad": rep["overall"]["median_of_mean_test_mrad"],
                           "mean_of_mean_train_test_distance_rad":
                               rep["overall"]["mean_of_mean_train_test_distance_rad"],
                           "heliostats": per}
            print(f"distance {split:9s}: median test {rep['overall']['median_of_mean_test_mrad']:.3f} mrad, "
                  f"mean train-test distance {rep['overall']['mean_of_mean_train_test_distance_rad']:.3f} rad",
                  flush=True)
        out["msc"]["distance"] = dist
    out["seconds"] = time.perf_counter() - t0
    write_json(args.json, out)
    print(f"wrote {args.json} ({out['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
