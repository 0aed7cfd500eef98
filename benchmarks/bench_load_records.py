"""The reading behind ``report --paint`` / ``calibrate --scenario`` / ``trace`` / ``validate`` at plant scale:
:func:`heliotwin.io.scenario.load_records` on a simulated folder, timed, with its folder listings counted
(``os.listdir`` of the folder, ``os.scandir`` of Calibration folders) and the peak memory. Issue 41 item 9: it listed
the folder once per heliostat (498 s at 10,000 heliostats); linear now, so the listings are a constant and the
scans one per heliostat.

Usage (the folder and scenario are made once in ``--work``; time it on a quiet machine)::

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_load_records.py --heliostats 10000 --years 1 \\
        --work /tmp/bench-records [--json out.json]

and the whole command, on the same folder (its nominal plant as the scenario)::

    /usr/bin/time -v python -m heliotwin report --scenario /tmp/bench-records/n10000/plant.h5 \\
        --paint /tmp/bench-records/n10000/paint -o /tmp/bench-records/report.html

Prints heliostats, records, seconds, listings of the folder, scans of Calibration folders and peak RSS [MiB].
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import time
from pathlib import Path

from heliotwin.io import paint as P
from heliotwin.io import scenario as S
from heliotwin.simulate import SimulationSettings, simulate_plant, write_paint_folder


def prepare(work: Path, n: int, years: float, seed: int) -> tuple[Path, Path]:
    """The simulated folder and its nominal plant as a scenario (made once)."""
    d = work / f"n{n}"
    paint, scenario = d / "paint", d / "plant.h5"
    if not scenario.exists():
        d.mkdir(parents=True, exist_ok=True)
        if not paint.exists():
            write_paint_folder(simulate_plant(SimulationSettings(heliostats=n, seed=seed, years=years)), paint)
        S.save_scenario(P.load_paint(paint, with_records=False).plant, scenario)
    return paint, scenario


def measure(paint: Path, scenario: Path) -> dict:
    """One ``load_records(paint, scenario)``: seconds, listings of ``paint``, Calibration scans, records."""
    counts = {"listdir": 0, "scandir": 0}
    real_listdir, real_scandir = os.listdir, os.scandir
    root = os.path.abspath(paint)

    def listdir(path="."):
        counts["listdir"] += os.path.abspath(path) == root
        return real_listdir(path)

    def scandir(path="."):
        counts["scandir"] += str(path).endswith("Calibration")
        return real_scandir(path)
    os.listdir, os.scandir = listdir, scandir
    try:
        t0 = time.perf_counter()
        ds, sc = S.load_records(str(paint), str(scenario))
        seconds = time.perf_counter() - t0
    finally:
        os.listdir, os.scandir = real_listdir, real_scandir
    return {"heliostats": len(sc.plant.field.ids), "records": len(ds.records), "seconds": round(seconds, 2),
            "folder_listings": counts["listdir"], "calibration_scans": counts["scandir"],
            "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--heliostats", type=int, default=10000)
    ap.add_argument("--years", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--work", required=True, help="folder for the simulated plant (kept)")
    ap.add_argument("--json", help="write the result here")
    args = ap.parse_args(argv)
    paint, scenario = prepare(Path(args.work), args.heliostats, args.years, args.seed)
    out = measure(paint, scenario)
    print(" ".join(f"{k}={v}" for k, v in out.items()))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
