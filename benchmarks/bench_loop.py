"""The whole loop on real data: PAINT -> calibrate -> reconstruct -> validate, through scenario files.

Measures what the issue "One plant, one loop" asks for, on ``../shared/data/paint``:

* the chain runs: ``calibrate -o a.h5``, ``reconstruct --scenario a.h5 -o b.h5``, ``validate --scenario b.h5``;
* ``validate --scenario`` reproduces, record by record, the test errors ``calibrate`` reported (largest
  absolute difference [mrad] over every test record of every calibrated heliostat);
* behaviour checks against the figures before the redesign: ``validate`` nominal median pointing error
  (34.60 mrad), ``calibrate lm`` chrono N=30 median over heliostats of the mean test error (0.969 mrad),
  AA39 ``reconstruct`` median learned test L1 on the nominal plant (0.146);
* the AA39 figure on the calibrated plant too (the chained run).

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_loop.py --out /tmp/loop [--paint ../shared/data/paint]

Writes ``<out>/loop.json`` (and every intermediate file); about 1-2 minutes on one core.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

from heliotwin.cli import main as heliotwin
from heliotwin.io.report import write_json

PAINT = Path(__file__).resolve().parents[2] / "shared" / "data" / "paint"
BEFORE = {"validate_nominal_median_mrad": 34.60, "lm_chrono_n30_median_of_mean_test_mrad": 0.969,
          "aa39_median_l1_learned": 0.146}


def _run(*argv) -> float:
    t0 = time.perf_counter()
    code = heliotwin([str(a) for a in argv])
    if code != 0:
        sys.exit(f"bench_loop: 'heliotwin {' '.join(map(str, argv))}' failed with exit code {code}")
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paint", default=str(PAINT))
    ap.add_argument("--out", required=True, help="folder for every file the chain writes")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    p = args.paint
    seconds = {
        "calibrate": _run("calibrate", "--paint", p, "--method", "lm", "--split", "chrono", "--train", "30",
                          "--test", "30", "--no-curve", "--json", out / "cal.json", "-o", out / "a.h5"),
        "reconstruct_on_calibrated": _run("reconstruct", "--paint", p, "--scenario", out / "a.h5", "--heliostat",
                                          "AA39", "--train-first", "3", "--quiet", "--json", out / "r-chain.json",
                                          "-o", out / "b.h5"),
        "validate_on_learned": _run("validate", "--paint", p, "--scenario", out / "b.h5", "--quiet",
                                    "--json", out / "v-chain.json"),
        "validate_nominal": _run("validate", "--paint", p, "--quiet", "--json", out / "v-nominal.json"),
        "reconstruct_on_nominal": _run("reconstruct", "--paint", p, "--heliostat", "AA39", "--train-first", "3",
                                       "--quiet", "--json", out / "r-nominal.json", "-o", out / "c.h5"),
    }
    cal = json.loads((out / "cal.json").read_text())
    chain = {r["record"]: r for r in json.loads((out / "v-chain.json").read_text())["records"]}
    nominal = json.loads((out / "v-nominal.json").read_text())
    tested = [t for t in cal["test_records"] if t["pointing_error_mrad"] is not None]
    diffs = [abs(chain[t["record"]]["pointing_error_mrad"] - t["pointing_error_mrad"]) for t in tested]
    r_chain = json.loads((out / "r-chain.json").read_text())
    r_nominal = json.loads((out / "r-nominal.json").read_text())
    result = {
        "paint": os.path.abspath(p),
        "test_records_compared": len(tested),
        "validate_vs_calibrate_max_abs_diff_mrad": max(diffs) if diffs else None,
        "calibrated_test_median_over_records_mrad": statistics.median(t["pointing_error_mrad"] for t in tested),
        "validate_nominal_median_mrad": nominal["overall"]["median_pointing_error_mrad"],
        "lm_chrono_n30_median_of_mean_test_mrad": cal["overall"]["median_of_mean_test_mrad"],
        "aa39_median_l1_learned": r_nominal["median_l1_learned"],
        "aa39_median_l1_ideal": r_nominal["median_l1_ideal"],
        "aa39_on_calibrated_plant_median_l1_learned": r_chain["median_l1_learned"],
        "aa39_on_calibrated_plant_median_l1_ideal": r_chain["median_l1_ideal"],
        "before": BEFORE, "seconds": seconds,
    }
    write_json(out / "loop.json", result)
    print(json.dumps({k: v for k, v in result.items() if k not in ("before", "paint")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
