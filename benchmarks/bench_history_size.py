"""Bytes the update history adds to a scenario per plant-year: daily ``update`` calls on a simulated plant.

A simulated plant (``--heliostats``, the demo field, ``--years`` of records) is calibrated on every record before
its last ``--days`` days (:func:`heliotwin.workflows.calibrate.calibrate`, trained on all), then updated once per
day with that day's records (:func:`bench_plant_loop.daily_updates`); the scenario after the last day is written
(:func:`heliotwin.io.scenario.write_scenario`). Reported: the history's rows, its datasets' bytes on disk
(``/learned/assimilation/history``, h5py's storage size), the whole file's growth over the calibrated one, bytes
per history row, and both scaled to a plant-year of ``--plant`` heliostats (rows per heliostat-year from the
simulated plant's own record rate).

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_history_size.py --out /tmp/history-size [--heliostats 200]
        [--days 30] [--plant 2000] [--keep]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile

import h5py
from bench_plant_loop import DAY, daily_updates, records_between

from heliotwin.io.paint import load_paint
from heliotwin.io.scenario import write_scenario
from heliotwin.workflows.calibrate import CalibrationSettings, calibrate
from heliotwin.workflows.simulate import SimulationSettings, simulate

YEAR = 365.25 * DAY


def history_bytes(path) -> tuple[int, int]:
    """(rows, bytes on disk) of ``/learned/assimilation/history`` in the scenario file ``path``."""
    with h5py.File(path, "r") as h5:
        g = h5["learned/assimilation/history"]
        return int(g["heliostat"].shape[0]), sum(int(g[k].id.get_storage_size()) for k in g)


def measure(heliostats: int, days: int, plant: int, seed: int, work: str) -> dict:
    truth, _ = simulate(SimulationSettings(heliostats=heliostats, years=1.0 + days / 365.25, seed=seed),
                        os.path.join(work, "plant"))
    ds = load_paint(os.path.join(work, "plant"))
    end = float(truth.learned["simulation"]["end_time"].reshape(-1)[0])
    cutoff = end - days * DAY
    calibrated, _ = calibrate(None, records_between(ds, -math.inf, cutoff),
                              CalibrationSettings(train=10 ** 6, min_records=20))
    write_scenario(calibrated, os.path.join(work, "calibrated.h5"))
    updated, loop = daily_updates(calibrated, ds, cutoff, days)
    write_scenario(updated, os.path.join(work, "updated.h5"))
    rows, stored = history_bytes(os.path.join(work, "updated.h5"))
    growth = os.path.getsize(os.path.join(work, "updated.h5")) - os.path.getsize(os.path.join(work, "calibrated.h5"))
    per_year = YEAR / (days * DAY) * plant / heliostats  # rows of this run -> rows of a plant-year
    return {"heliostats": heliostats, "days": days, "updates": len(loop["days"]), "rows": rows,
            "history_bytes": stored, "file_growth_bytes": growth, "bytes_per_row": stored / max(rows, 1),
            "plant": plant, "history_mb_per_plant_year": stored * per_year / 1e6,
            "file_growth_mb_per_plant_year": growth * per_year / 1e6}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="/tmp/history-size")
    p.add_argument("--heliostats", type=int, default=200)
    p.add_argument("--days", type=int, default=30)
    p.add_argument("--plant", type=int, default=2000, help="heliostats of the plant the figures are scaled to")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--keep", action="store_true", help="keep the plant and scenarios under <out>/work")
    args = p.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    if args.keep:
        work = os.path.join(args.out, "work")
        shutil.rmtree(work, ignore_errors=True)
        os.makedirs(work)
        r = measure(args.heliostats, args.days, args.plant, args.seed, work)
    else:
        with tempfile.TemporaryDirectory(dir=args.out) as work:
            r = measure(args.heliostats, args.days, args.plant, args.seed, work)
    with open(os.path.join(args.out, "history_size.json"), "w") as fh:
        json.dump(r, fh, indent=2)
    print(json.dumps(r, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
