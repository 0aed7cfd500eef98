"""Real AA39: train on its 3 earliest centred images, test on the other 7 (wraps the CLI).

    python benchmarks/bench_reconstruct_aa39.py [--out DIR]

Writes DIR/aa39-report.json (+ plots) and DIR/aa39-learned.h5 (the plant with AA39's learned surface, a
scenario file) and prints the per-image table.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

from heliotwin.cli import main as cli

PAINT = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "paint")


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--paint", default=PAINT)
    p.add_argument("--heliostat", default="AA39")
    p.add_argument("--out", default=".")
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    rep = os.path.join(a.out, f"{a.heliostat.lower()}-report.json")
    rc = cli(["reconstruct", "--paint", a.paint, "--heliostat", a.heliostat, "--train-first", "3", "-o",
              os.path.join(a.out, f"{a.heliostat.lower()}-learned.h5"), "--json", rep, "--threads", str(a.threads),
              "--quiet"])
    if rc:
        return rc
    r = json.load(open(rep, encoding="utf-8"))
    print(f"{'record':>8} {'L1 ideal':>9} {'L1 learn':>9} {'IMP %':>7} {'L1 sharp-sun ideal':>19} {'L1 MC learn':>11}")
    for t in r["test"]:
        mc = t.get("l1_learned_mc")  # strict JSON: absent or null when not evaluated
        print(f"{t['record']:8d} {t['l1_ideal']:9.3f} {t['l1_learned']:9.3f} {100 * t['imp']:7.0f} "
              f"{t['l1_ideal_sharp_sun']:19.3f} {'-' if mc is None else format(mc, '.3f'):>11}")
    print(f"median L1 ideal {r['median_l1_ideal']:.3f} -> learned {r['median_l1_learned']:.3f}; median IMP "
          f"{100 * r['median_imp']:+.0f} % (vs sharp-sun ideal {100 * r['median_imp_vs_sharp_sun']:+.0f} %); "
          f"below ideal on all: {r['learned_below_ideal_on_all']}; "
          f"slope error {1e3 * r['optics']['slope_error_rad']:.2f} mrad; fit {r['fit_seconds']:.1f} s, "
          f"total {r['seconds']:.1f} s on {r['torch_threads']} threads")
    return 0


if __name__ == "__main__":
    sys.exit(main())
