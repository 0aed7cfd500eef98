"""The whole plant, continuously: wall time and peak memory of each stage against the number of heliostats.

For each size a simulated plant (``heliotwin simulate``: the demo field, ~100 records per heliostat over three
years) is written, then every stage runs in its own subprocess (so its peak memory is its own and a stage that
hangs is cut off by ``--timeout``):

* ``simulate`` -- draw the plant, write the PAINT folder and the truth
  (:func:`heliotwin.workflows.simulate.simulate`);
* ``read`` -- read the folder with no record cache (and write it): :func:`heliotwin.io.paint.load_paint`;
* ``read_cached`` -- read it again from the record cache;
* ``calibrate`` -- :func:`heliotwin.workflows.calibrate.calibrate` with default settings, scored against the truth
  (its scenario is kept for ``update``);
* ``calibrate_nproc2`` -- the same with ``nproc=2`` (two local processes); fails unless its pointing against the
  truth equals the one-process result's (the ``calibrate`` stage's scenario, else a one-process run here) to
  1e-9 mrad; timed: the nproc=2 call (``worker_peak_mib``: the largest worker's peak memory);
* ``update`` -- the last day's records assimilated by :func:`heliotwin.workflows.update.update` into a scenario
  calibrated on the records before that day (the ``calibrate`` stage's: chronological, its earliest records;
  else one made here, outside the timing); the stage fails if the calibration saw any of the day's records.
  Timed: the update call;
* ``reconstruct`` -- :func:`heliotwin.workflows.reconstruct_plant.reconstruct_plant` (``heliotwin reconstruct
  --heliostats``) on ``--sample`` heliostats that have simulated images (``--images K`` makes the simulate stage
  draw them, 3 training + 7 test each), in ``--nproc`` worker processes; timed: the run's wall seconds per
  heliostat (``seconds``; with ``--nproc 2`` and ``OMP_NUM_THREADS=1`` that is the figure on 2 cores), also each
  heliostat's own seconds in its process and the largest worker's peak memory (``worker_peak_mib``);
  ``--reconstruct-steps``: the step budget (default: the learner's, 300);
* ``aimpoints`` -- :func:`heliotwin.workflows.aimpoints.aimpoints` (default settings) on the truth plant for one
  sun (2024-06-01 11:00 UTC), the peak limit 0.8 x the equator-aimed peak; timed: the aimpoints call.

A stage that returns ``seconds`` is timed by that (its measured call); ``wall_seconds`` is the whole stage.

Per stage and size: wall seconds, the peak resident memory of the stage's process and what it added over the
process after its imports [MiB]; per stage, the growth exponent ``b`` of ``seconds ~ heliostats^b`` (least
squares in log-log over the sizes that finished). A stage that fails or times out is recorded as such and not
run for larger sizes.

Adding a stage is one function: ``@stage("name")`` on ``def name(ctx) -> dict`` (``ctx``: ``size``, ``seed``,
``folder`` (the PAINT folder), ``truth`` (its truth scenario path), ``work`` (a folder for the stage's own
files)); return any JSON values to record next to the timing, and add it to ``--stages``.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_plant_scale.py --out /tmp/plant-scale \
        [--sizes 100 500 2000 10000] [--stages simulate read read_cached calibrate calibrate_nproc2] [--timeout 600]
    OMP_NUM_THREADS=1 python benchmarks/bench_plant_scale.py --out /tmp/plant-loop-stages --sizes 100 500 2000 \
        --stages simulate calibrate update aimpoints reconstruct --images 2 --sample 2 --reconstruct-steps 60
    OMP_NUM_THREADS=1 python benchmarks/bench_plant_scale.py --out /tmp/plant-reconstruct --sizes 20 \
        --stages simulate reconstruct --images 4 --sample 4 --nproc 2      # seconds per heliostat on 2 cores

Writes ``<out>/plant_scale.json`` and ``<out>/plant_scale.md``; the simulated plants stay under ``<out>/size-N``
(``--keep`` not given: removed after their size). Deterministic inputs (``--seed``); wall times depend on the
machine and its load.

Measured 2026-11-26 on the idle 2-core machine (torch's default 2 threads; reconstruct one thread per worker)::

    python benchmarks/bench_plant_scale.py --out D --sizes 100 500 2000 10000 --stages simulate read \
        read_cached calibrate calibrate_nproc2 update aimpoints reconstruct --images 4 --sample 4 --nproc 2 --keep

Seconds (a stage's measured call) and the peak resident memory of its process:

================  ================  ================  =================  =================  ========
stage             100 hel.          500 hel.          2000 hel.          10000 hel.         exponent
================  ================  ================  =================  =================  ========
simulate          0.9 s, 488 MiB    2.4 s, 580 MiB    8.6 s, 752 MiB     50.2 s, 1833 MiB   0.88
read              0.4 s, 429 MiB    2.5 s, 548 MiB    10.5 s, 943 MiB    55.9 s, 2791 MiB   1.07
read_cached       0.1 s, 415 MiB    0.4 s, 478 MiB    2.0 s, 725 MiB     11.0 s, 1924 MiB   1.03
calibrate         3.2 s, 541 MiB    13.0 s, 717 MiB   44.3 s, 1308 MiB   231.5 s, 4758 MiB  0.92
calibrate_nproc2  7.9 s, 448 MiB    19.6 s, 584 MiB   67.5 s, 1116 MiB   356.2 s, 3676 MiB  0.83
update (one day)  0.02 s            0.02 s            0.06 s             0.53 s             0.73
aimpoints         1.9 s, 468 MiB    3.8 s, 631 MiB    15.2 s, 1139 MiB   94.5 s, 3276 MiB   0.86
reconstruct       12.6 s, 595 MiB   12.2 s, 603 MiB   14.2 s, 1210 MiB   23.2 s, 4149 MiB   0.13
================  ================  ================  =================  =================  ========

Records: 9,685 / 47,604 / 189,789 / 871,800. Calibrate's pointing against the truth at new suns, median / p95:
0.62 / 2.37, 0.56 / 2.25, 0.51 / 2.21, 0.54 / 3.04 mrad (10,000: 9,578 heliostats calibrated; the demo field
grown to 10,000 sends 47,718 simulated records off the target, which the simulator drops). ``calibrate_nproc2``
equals one process to 0.0 mrad but is slower on one 2-core machine: one process already uses both cores through
torch's threads, and the process group costs seconds to start (it is meant for several machines, via torchrun).
``reconstruct``: wall seconds per heliostat of 4 sampled heliostats over 2 workers (one heliostat took 20.7-22.7 s
in its process); at 10,000 the parent's listing of the folder's 871,800 records adds ~45 s to the run, and its
4.1 GiB peak is the parent's (a worker's peak: 0.6-1.9 GiB).

2026-11-28, after ``reconstruct`` learned from every centred image (10 per simulated heliostat, 3-fold
cross-validation over mini-batches) instead of the latest 3: ``--sizes 100 --stages simulate reconstruct --images 4
--sample 4 --nproc 2``: 14.7 s per heliostat over 2 workers (27.4 s per heliostat in its one-thread process),
median cross-validated L1 0.430 (ideal) -> 0.321 (learned).
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

    truth, report = simulate(SimulationSettings(heliostats=ctx["size"], seed=ctx["seed"], images=ctx["images"]),
                             ctx["folder"])
    write_scenario(truth, ctx["truth"])
    return {k: report[k] for k in ("records", "steps", "dropped_off_target", "months_at_capacity",
                                   "seconds_simulate", "seconds_write")}


@stage("read")
def read_stage(ctx: dict) -> dict:
    from heliotwin.io.paint import load_paint
    from heliotwin.io.record_index import index_dir

    ds = load_paint(ctx["folder"], cache=True)
    where = index_dir(ctx["folder"])
    return {"records": len(ds.records), "cache_bytes": sum(os.path.getsize(os.path.join(where, f))
                                                           for f in os.listdir(where))}


@stage("read_cached")
def read_cached_stage(ctx: dict) -> dict:
    from heliotwin.io.paint import load_paint

    return {"records": len(load_paint(ctx["folder"], cache=True).records)}


@stage("calibrate")
def calibrate_stage(ctx: dict) -> dict:
    from heliotwin.io.scenario import load_scenario, write_scenario
    from heliotwin.simulate import score
    from heliotwin.workflows.calibrate import CalibrationSettings, calibrate

    scenario, report = calibrate(None, ctx["folder"], CalibrationSettings())
    out = {"calibrated": report["overall"].get("n_heliostats"),
           "median_of_mean_test_mrad": report["overall"].get("median_of_mean_test_mrad")}
    if scenario is not None:
        write_scenario(scenario, os.path.join(ctx["work"], "calibrated.h5"))  # the update stage starts from it
        got = score(load_scenario(ctx["truth"]), scenario, flux=False)
        out["truth_pointing_median_mrad"] = got["pointing_mrad"]["median"]
        out["truth_pointing_p95_mrad"] = got["pointing_mrad"]["p95"]
    return out


@stage("calibrate_nproc2")
def calibrate_nproc2_stage(ctx: dict) -> dict:
    """The calibrate stage's workflow with ``nproc=2`` (two local gloo processes), timed, checked against the
    one-process result: the calibrate stage's scenario when it ran before (its time is that stage's), else a
    one-process run here (timed: ``seconds_nproc1``). Their pointing against the truth (median, p95, mean, max
    over heliostats x suns) must agree to 1e-9 mrad."""
    from heliotwin.io.paint import load_paint
    from heliotwin.io.scenario import load_scenario
    from heliotwin.simulate import score
    from heliotwin.workflows.calibrate import CalibrationSettings, calibrate

    dataset = load_paint(ctx["folder"], cache=True)  # the records the calibrate stage fits
    t0 = time.perf_counter()
    two, _ = calibrate(None, dataset, CalibrationSettings(nproc=2))
    out = {"seconds": time.perf_counter() - t0,
           "worker_peak_mib": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}  # largest rank
    path = os.path.join(ctx["work"], "calibrated.h5")
    if os.path.exists(path):
        one = load_scenario(path)
    else:
        t0 = time.perf_counter()
        one, _ = calibrate(None, dataset, CalibrationSettings())
        out["seconds_nproc1"] = time.perf_counter() - t0
    truth = load_scenario(ctx["truth"])
    got = [score(truth, sc, flux=False)["pointing_mrad"] for sc in (two, one)]
    diff = max(abs(got[0][k] - got[1][k]) for k in ("median", "p95", "mean", "max"))
    if not diff <= 1e-9:
        raise RuntimeError(f"calibrate_nproc2: nproc=2 and one process differ by {diff:g} mrad against the truth")
    return {**out, "truth_pointing_median_mrad": got[0]["median"], "max_difference_mrad": diff}


@stage("update")
def update_stage(ctx: dict) -> dict:
    from bench_plant_loop import DAY, records_between

    from heliotwin.io.paint import load_paint
    from heliotwin.io.scenario import load_scenario, write_scenario
    from heliotwin.workflows.calibrate import CalibrationSettings, calibrate
    from heliotwin.workflows.update import seen_record_ids, update

    ds = load_paint(ctx["folder"], cache=True)
    t = ds.records.time.double()
    last_day = float(t[t.isfinite()].max()) - DAY
    path = os.path.join(ctx["work"], "calibrated.h5")  # the calibrate stage's (chrono: its earliest records)
    if not os.path.exists(path):
        write_scenario(calibrate(None, records_between(ds, -math.inf, last_day), CalibrationSettings()).scenario, path)
    calibrated = load_scenario(path)
    day = records_between(ds, last_day, math.inf).records
    if seen_record_ids(calibrated) & set(day.record_id.tolist()):
        raise RuntimeError("update stage: the calibration saw records of the last day")
    t0 = time.perf_counter()
    _, report = update(calibrated, day)
    return {"seconds": time.perf_counter() - t0, "records": report["counts"]["new"],
            "heliostats_updated": report["heliostats_updated"], "alarms": report["overall"]["alarms"]}


@stage("reconstruct")
def reconstruct_stage(ctx: dict) -> dict:
    from bench_plant_loop import image_heliostats

    from heliotwin.workflows.reconstruct import ReconstructionSettings
    from heliotwin.workflows.reconstruct_plant import reconstruct_plant

    chosen = image_heliostats(ctx["folder"])[:ctx["sample"]]
    if not chosen:
        raise RuntimeError("reconstruct stage: no heliostat has images (simulate with --images K)")
    settings = ReconstructionSettings(steps=ctx["reconstruct_steps"], device="cpu")
    t0 = time.perf_counter()
    _, report = reconstruct_plant(None, ctx["folder"], chosen, settings, nproc=ctx["nproc"], progress=False)
    seconds = time.perf_counter() - t0
    s = report["summary"]
    if s["learned"] != len(chosen):
        raise RuntimeError(f"reconstruct stage: {s['learned']} of {len(chosen)} heliostats learned "
                           f"({[r.get('reason') for r in report['heliostats'] if r['status'] != 'learned']})")
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    workers = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024  # the largest finished worker
    return {"seconds": seconds / len(chosen), "seconds_all": seconds, "heliostats": chosen, "nproc": ctx["nproc"],
            "seconds_per_heliostat_in_its_process": s["seconds_per_heliostat"],
            # the table's peak: the largest process of the stage (a worker's, with --nproc > 1)
            "peak_mib": max(own, workers) if ctx["nproc"] > 1 else own, "worker_peak_mib": workers,
            "median_test_l1_ideal": s["median_test_l1_ideal"], "median_test_l1_learned": s["median_test_l1_learned"]}


@stage("aimpoints")
def aimpoints_stage(ctx: dict) -> dict:
    from heliotwin.io.scenario import load_scenario
    from heliotwin.workflows.aimpoints import AimpointSettings, aimpoints
    from heliotwin.workflows.field import FieldRunSettings, field, sun_direction_at

    plant = load_scenario(ctx["truth"])
    sun = sun_direction_at(plant.plant, time_utc="2024-06-01T11:00:00")
    equator, _ = field(plant, sun, FieldRunSettings())
    limit = 0.8 * equator["receiver"]["peak_flux_w_m2"]  # binding: the equator's peak is over it
    t0 = time.perf_counter()
    _, report = aimpoints(plant, [("sun", sun)], AimpointSettings(peak_limit_w_m2=limit))
    return {"seconds": time.perf_counter() - t0, "seconds_field_equator": equator["seconds"],
            "peak_limit_w_m2": limit, "power_w": report["optimised"].get("power_w"),
            "peak_flux_w_m2": report["optimised"].get("peak_flux_w_m2")}


# ------------------------------------------------------------------------------------------------ driver
def _child(args) -> None:
    """Run one stage in this process; print one JSON line with its result."""
    os.environ.setdefault("HELIOTWIN_CACHE_DIR", os.path.join(args.work, "cache"))
    import torch  # noqa: F401  (the imports every stage pays, outside its timing)

    import heliotwin.workflows.calibrate  # noqa: F401
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    ctx = {"size": args.size, "seed": args.seed, "folder": os.path.join(args.work, "plant"),
           "truth": os.path.join(args.work, "truth.h5"), "work": args.work, "images": args.images,
           "sample": args.sample, "reconstruct_steps": args.reconstruct_steps, "nproc": args.nproc}
    t0 = time.perf_counter()
    extra = STAGES[args.child](ctx)
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print("RESULT " + json.dumps({"seconds": wall, "wall_seconds": wall, "peak_mib": peak, "added_mib": peak - base,
                                  **extra}))


def run_stage(name: str, size: int, work: Path, seed: int, timeout: float, options: tuple = ()) -> dict:
    """One stage in a subprocess: its result, or ``{"status": "timeout" | "failed", ...}``; ``options``: more
    command-line words for the child (``--images``, ``--sample``, ``--nproc``, ``--reconstruct-steps``)."""
    cmd = [sys.executable, os.path.abspath(__file__), "--child", name, "--size", str(size), "--seed", str(seed),
           "--work", str(work), *options]
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
    p.add_argument("--stages", nargs="+", default=["simulate", "read", "read_cached", "calibrate", "calibrate_nproc2"],
                   choices=sorted(STAGES))
    p.add_argument("--timeout", type=float, default=600.0, help="seconds per stage and size")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--keep", action="store_true", help="keep the simulated plants")
    p.add_argument("--images", type=int, default=0,
                   help="heliostats the simulate stage gives flux-centred images (the reconstruct stage needs some)")
    p.add_argument("--sample", type=int, default=2, help="heliostats the reconstruct stage reconstructs")
    p.add_argument("--reconstruct-steps", type=int, default=None, help="reconstruct's step budget (default its own)")
    p.add_argument("--nproc", type=int, default=1, help="reconstruct's worker processes")
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
    options = ("--images", str(args.images), "--sample", str(args.sample), "--nproc", str(args.nproc),
               *(("--reconstruct-steps", str(args.reconstruct_steps)) if args.reconstruct_steps else ()))
    for size in args.sizes:
        work = out / f"size-{size}"
        if work.exists():
            shutil.rmtree(work)
        work.mkdir()
        for name in args.stages:
            if name in stopped or ("simulate" in stopped and name != "simulate"):
                continue
            r = run_stage(name, size, work, args.seed, args.timeout, options)
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
