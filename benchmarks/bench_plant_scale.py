"""The whole plant, continuously: wall time and peak memory of each stage against the number of heliostats.

For each size a simulated plant (``heliotwin simulate``: the demo field, ~100 records per heliostat over three
years) is written, then every stage runs in its own subprocess (so its peak memory is its own and a stage that
hangs is cut off by ``--timeout``):

* ``simulate`` -- draw the plant, write the PAINT folder and the truth
  (:func:`heliotwin.workflows.simulate.simulate`);
* ``read`` -- read the folder with no record cache (and write it): :func:`heliotwin.io.paint.load_paint`;
* ``read_cached`` -- read it again from the record cache;
* ``calibrate`` -- :func:`heliotwin.workflows.calibrate.calibrate` with default settings, scored against the truth.

Per stage and size: wall seconds, the peak resident memory of the stage's process and what it added over the
process after its imports [MiB]; per stage, the growth exponent ``b`` of ``seconds ~ heliostats^b`` (least
squares in log-log over the sizes that finished). A stage that fails or times out is recorded as such and not
run for larger sizes.

Adding a stage is one function: ``@stage("name")`` on ``def name(ctx) -> dict`` (``ctx``: ``size``, ``seed``,
``folder`` (the PAINT folder), ``truth`` (its truth scenario path), ``work`` (a folder for the stage's own
files)); return any JSON values to record next to the timing, and add it to ``--stages``.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_plant_scale.py --out /tmp/plant-scale \
        [--sizes 100 500 2000 10000] [--stages simulate read read_cached calibrate] [--timeout 600]

Writes ``<out>/plant_scale.json`` and ``<out>/plant_scale.md``; the simulated plants stay under ``<out>/size-N``
(``--keep`` not given: removed after their size). Deterministic inputs (``--seed``); wall times depend on the
machine and its load.

Measured on a busy 2-core machine (shared with seven other jobs; 1 thread; re-measure on an idle one):

=================================  ============  ============  ==========================
stage                              100 hel.      500 hel.      2000 hel. (202,676 rec.)
=================================  ============  ============  ==========================
simulate (draw + write folder)     4.4 s         15.6 s        2.5 s draw + 109 s write
read, no record cache              1.2 s         8.5 s         10.5 s (10.2 s writing it)
read_cached                        0.2 s         1.0 s         3.3 s
=================================  ============  ============  ==========================

The 2000-heliostat column was measured by hand (``heliotwin simulate --heliostats 2000 --records-per-month 3``,
then :func:`heliotwin.io.paint.load_paint` with ``cache=False`` / ``True``; the 100/500 columns are from before
the bracket-count shortcut of the JSON depth check); the reader before the record
cache and the batched parser took 28.0 s for 200 of those heliostats (18,869 records; ~300 s for the folder).
Drawing alone (:func:`heliotwin.simulate.simulate_plant`, no files): 100 / 500 / 2000 / 10000 heliostats in
2.7 / 2.9 / 8.6 / 36.5 s (9,685 / 47,604 / 189,789 / 871,800 records, peak RSS 400-960 MiB). ``calibrate`` with
default settings took 23 s for 20 heliostats and 98 s for 60 (growth exponent 1.3; 1.8 GB peak).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

#: Stage name -> function(ctx) -> dict; filled by :func:`stage`.
STAGES: dict = {}


def stage(name: str):
    """Register a stage under ``name`` (module docstring)."""
    def register(fn):
        STAGES[name] = fn
        return fn
    return register


@stage("simulate")
def simulate_stage(ctx: dict) -> dict:
    from heliotwin.io.scenario import write_scenario
    from heliotwin.workflows.simulate import SimulationSettings, simulate

    truth, report = simulate(SimulationSettings(heliostats=ctx["size"], seed=ctx["seed"]), ctx["folder"])
    write_scenario(truth, ctx["truth"])
    return {k: report[k] for k in ("records", "steps", "dropped_off_target", "months_at_capacity",
                                   "seconds_simulate", "seconds_write")}


@stage("read")
def read_stage(ctx: dict) -> dict:
    from heliotwin.io.paint import load_paint, record_cache_path

    ds = load_paint(ctx["folder"], cache=True)
    return {"records": len(ds.records), "cache_bytes": os.path.getsize(record_cache_path(ctx["folder"],
                                                                                        ds.plant.field.ids))}


@stage("read_cached")
def read_cached_stage(ctx: dict) -> dict:
    from heliotwin.io.paint import load_paint

    return {"records": len(load_paint(ctx["folder"], cache=True).records)}


@stage("calibrate")
def calibrate_stage(ctx: dict) -> dict:
    from heliotwin.io.scenario import load_scenario
    from heliotwin.simulate import score
    from heliotwin.workflows.calibrate import CalibrationSettings, calibrate

    scenario, report = calibrate(None, ctx["folder"], CalibrationSettings())
    out = {"calibrated": report["overall"].get("n_heliostats"),
           "median_of_mean_test_mrad": report["overall"].get("median_of_mean_test_mrad")}
    if scenario is not None:
        got = score(load_scenario(ctx["truth"]), scenario, flux=False)
        out["truth_pointing_median_mrad"] = got["pointing_mrad"]["median"]
        out["truth_pointing_p95_mrad"] = got["pointing_mrad"]["p95"]
    return out


# ------------------------------------------------------------------------------------------------ driver
def _child(args) -> None:
    """Run one stage in this process; print one JSON line with its result."""
    os.environ.setdefault("HELIOTWIN_CACHE_DIR", os.path.join(args.work, "cache"))
    import torch  # noqa: F401  (the imports every stage pays, outside its timing)

    import heliotwin.workflows.calibrate  # noqa: F401
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    ctx = {"size": args.size, "seed": args.seed, "folder": os.path.join(args.work, "plant"),
           "truth": os.path.join(args.work, "truth.h5"), "work": args.work}
    t0 = time.perf_counter()
    extra = STAGES[args.child](ctx)
    seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print("RESULT " + json.dumps({"seconds": seconds, "peak_mib": peak, "added_mib": peak - base, **extra}))


def run_stage(name: str, size: int, work: Path, seed: int, timeout: float) -> dict:
    """One stage in a subprocess: its result, or ``{"status": "timeout" | "failed", ...}``."""
    cmd = [sys.executable, os.path.abspath(__file__), "--child", name, "--size", str(size), "--seed", str(seed),
           "--work", str(work)]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"status": "timeout", "wall": time.perf_counter() - t0}
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        return {"status": "failed", "error": (proc.stderr.strip().splitlines() or ["?"])[-1][:300]}
    return {"status": "ok", **json.loads(lines[-1][len("RESULT "):])}


def growth(sizes, seconds) -> float | None:
    """Least-squares slope of log(seconds) against log(size) (None with fewer than two finished sizes)."""
    pts = [(s, t) for s, t in zip(sizes, seconds) if t is not None and t > 0]
    if len(pts) < 2:
        return None
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def markdown(results: dict, sizes, stages) -> str:
    lines = ["| stage | " + " | ".join(f"{s} heliostats" for s in sizes) + " | growth exponent |",
             "|---|" + "---|" * len(sizes) + "---|"]
    for name in stages:
        cells = []
        for s in sizes:
            r = results["stages"][name].get(str(s))
            if r is None:
                cells.append("-")
            elif r["status"] != "ok":
                cells.append(r["status"])
            else:
                cells.append(f"{r['seconds']:.1f} s, {r['peak_mib']:.0f} MiB")
        g = results["growth"].get(name)
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {'-' if g is None else f'{g:.2f}'} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="/tmp/plant-scale")
    p.add_argument("--sizes", type=int, nargs="+", default=[100, 500, 2000, 10000])
    p.add_argument("--stages", nargs="+", default=["simulate", "read", "read_cached", "calibrate"],
                   choices=sorted(STAGES))
    p.add_argument("--timeout", type=float, default=600.0, help="seconds per stage and size")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--keep", action="store_true", help="keep the simulated plants")
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--size", type=int, help=argparse.SUPPRESS)
    p.add_argument("--work", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        _child(args)
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"sizes": args.sizes, "stages": {s: {} for s in args.stages}, "growth": {},
               "threads": os.environ.get("OMP_NUM_THREADS"), "cpus": os.cpu_count()}
    stopped: set = set()
    for size in args.sizes:
        work = out / f"size-{size}"
        if work.exists():
            shutil.rmtree(work)
        work.mkdir()
        for name in args.stages:
            if name in stopped or ("simulate" in stopped and name != "simulate"):
                continue
            r = run_stage(name, size, work, args.seed, args.timeout)
            results["stages"][name][str(size)] = r
            if r["status"] != "ok":
                stopped.add(name)
            shown = f"{r['seconds']:.1f} s, peak {r['peak_mib']:.0f} MiB" if r["status"] == "ok" else r["status"]
            print(f"{size:>6} heliostats  {name:<12} {shown}", flush=True)
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    for name in args.stages:
        rows = results["stages"][name]
        results["growth"][name] = growth(args.sizes, [rows.get(str(s), {}).get("seconds") for s in args.sizes])
    (out / "plant_scale.json").write_text(json.dumps(results, indent=2, allow_nan=False, default=_nan_free))
    (out / "plant_scale.md").write_text(markdown(results, args.sizes, args.stages))
    print(markdown(results, args.sizes, args.stages))
    return 0


def _nan_free(x):
    return None if isinstance(x, float) and not math.isfinite(x) else str(x)


if __name__ == "__main__":
    sys.exit(main())
