"""In-silico study: distance x training-image count table (the published protocol).

    python benchmarks/bench_insilico.py [--distances 25,50,100,200] [--images 1,2,4,8,16] [--seed 0] \
        [--json insilico.json]

Prints one row per cell: mean normal deviation [mrad], piston-free height RMS [mm], mean test L1 of the ideal
and learned surfaces and IMP = L1(ideal)/L1(learned) - 1 (see heliotwin.surfaces.insilico).
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import torch

from heliotwin.io.paint import load_paint
from heliotwin.surfaces.insilico import run_case
from heliotwin.surfaces.reconstruct import TrainSettings

PAINT = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "paint")


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--paint", default=PAINT)
    p.add_argument("--distances", default="25,50,100,200")
    p.add_argument("--images", default="1,2,4,8,16")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=TrainSettings.steps)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    plant = load_paint(a.paint, heliostats=["AA39"], with_records=False).plant
    rows = []
    print(f"{'dist':>5} {'imgs':>4} {'n_dev mrad':>10} {'h_rms mm':>9} {'L1 ideal':>9} {'L1 learn':>9} {'IMP %':>8} {'s':>6}")
    for d in (float(x) for x in a.distances.split(",")):
        for n in (int(x) for x in a.images.split(",")):
            r = run_case(plant, d, n, seed=a.seed, settings=TrainSettings(steps=a.steps))
            rows.append(r)
            li = sum(r["test_l1_ideal"]) / len(r["test_l1_ideal"])
            ll = sum(r["test_l1_learned"]) / len(r["test_l1_learned"])
            print(f"{d:5.0f} {n:4d} {r['normal_deviation_mrad']:10.3f} {r['height_rms_mm']:9.3f} {li:9.3f} {ll:9.3f} "
                  f"{100 * r['imp']:8.0f} {r['seconds']:6.1f}", flush=True)
    if a.json:
        with open(a.json, "w", encoding="utf-8") as fh:
            json.dump(rows, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
