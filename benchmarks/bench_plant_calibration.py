"""Whole-plant calibration: wall time and peak memory of the default ``lm`` run at plant scale.

1. Synthetic plants (records simulated from known deviations, ``tests/helpers/calibrate.py``) of 100 / 500 /
   2,000 heliostats x 100 records, each calibrated by the default ``heliotwin calibrate --method lm``
   (chrono split, train 30, test 30) in a fresh process: wall time of the run, of its fit, peak RSS, and the
   growth exponent of the time in heliostats (log-log slope; 1 = linear).
2. ``--real``: the stored-settings routine run on the real PAINT folder: ``--learn-settings`` once on the
   archive (the routine heliostats excluded), then a routine run on them with ``--prior-from`` the scenario
   (``--settings stored``), timed.

Usage::

    python benchmarks/bench_plant_calibration.py [--sizes 100,500,2000] [--records 100] [--threads 2]
        [--real] [--paint ../shared/data/paint] [--json bench_plant.json]
"""
from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))
DEFAULT_PAINT = HERE.parents[1] / "shared" / "data" / "paint"


def one_plant(h: int, records: int, threads: int) -> dict:
    """Calibrate one synthetic plant in this process; returns its figures."""
    import torch
    from helpers.calibrate import synthetic_plant

    from heliotwin.calibrate.protocol.pipeline import RunConfig, run_calibration

    torch.set_num_threads(threads)
    ds, true = synthetic_plant(h, records, seed=0)
    cfg = RunConfig(paint="synthetic", method="lm", split="chrono", train=30, test=30, min_records=50)
    t0 = time.perf_counter()
    rep, model, _ = run_calibration(cfg, ds)
    seconds = time.perf_counter() - t0
    ov = rep["overall"]
    err = (model.delta - true)[:, :2].abs().median()
    return {"heliostats": h, "records": len(ds.records), "seconds": seconds, "fit_seconds": ov["fit_seconds"],
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "median_test_mrad": ov["median_of_mean_test_mrad"], "axis_offset_error_mrad": 1e3 * float(err),
            "interval_90_coverage": ov.get("interval_90_coverage")}


def growth_exponent(rows) -> float | None:
    """Least-squares slope of log(seconds) against log(heliostats)."""
    pts = [(math.log(r["heliostats"]), math.log(r["seconds"])) for r in rows if r.get("seconds")]
    if len(pts) < 2:
        return None
    mx, my = sum(p[0] for p in pts) / len(pts), sum(p[1] for p in pts) / len(pts)
    return sum((x - mx) * (y - my) for x, y in pts) / sum((x - mx) ** 2 for x, _ in pts)


def real_stored(paint: str, threads: int) -> dict:
    """Learn settings once on the archive (routine heliostats excluded), then time the routine run."""
    import tempfile

    import torch

    from heliotwin.calibrate.protocol.pipeline import RunConfig, run_calibration
    from heliotwin.calibrate.scenario import save_calibration
    from heliotwin.io.paint import load_paint

    torch.set_num_threads(threads)
    routine_ids = ["BH58", "BF41", "AK46", "BG23"]
    ds = load_paint(paint)
    t0 = time.perf_counter()
    learn = RunConfig(paint=paint, heliostats=["AK32", "BE36", "BF55", "BH60"], train=30, test=30,
                      learn_settings=True, prior_exclude=routine_ids)
    rep, model, _ = run_calibration(learn, ds)
    learn_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        sc = str(Path(tmp) / "plant.h5")
        save_calibration(sc, ds.plant, model, focal_spot="HeliOS", settings_choice=rep["settings_choice"])
        t0 = time.perf_counter()
        rep2, _, _ = run_calibration(RunConfig(paint=paint, heliostats=routine_ids, train=30, test=30,
                                               prior_from=sc, settings="stored"), load_paint(paint))
        routine_s = time.perf_counter() - t0
    return {"learn_seconds": learn_s, "routine_seconds_incl_read": routine_s,
            "chosen": rep["settings_choice"]["chosen"], "stored_used": rep2["settings_choice"]["used"],
            "routine_median_test_mrad": rep2["overall"]["median_of_mean_test_mrad"],
            "routine_interval_90_coverage_held_out": rep2["overall"].get("interval_90_coverage")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="100,500,2000")
    ap.add_argument("--records", type=int, default=100)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)  # one size, in this process (JSON on stdout)
    ap.add_argument("--real", action="store_true")
    ap.add_argument("--paint", default=str(DEFAULT_PAINT))
    ap.add_argument("--json", default="bench_plant_calibration.json")
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(one_plant(args.one, args.records, args.threads)))
        return 0
    rows = []
    for h in (int(x) for x in args.sizes.split(",")):
        out = subprocess.run([sys.executable, __file__, "--one", str(h), "--records", str(args.records),
                              "--threads", str(args.threads)], capture_output=True, text=True, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        print(f"{h:5d} heliostats x {args.records} records: {r['seconds']:.1f} s (fit {r['fit_seconds']:.1f} s), "
              f"peak RSS {r['peak_rss_mb']:.0f} MB, median test {r['median_test_mrad']:.3f} mrad", flush=True)
    result = {"plants": rows, "growth_exponent": growth_exponent(rows)}
    print(f"growth exponent of the wall time in heliostats: {result['growth_exponent']}")
    if args.real:
        result["real_stored_settings"] = real_stored(args.paint, args.threads)
        print(json.dumps(result["real_stored_settings"], indent=1))
    Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
