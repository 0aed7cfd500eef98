"""The operator's walk-through of issue 42, run again as commands: a simulated plant whose PAINT folder grows a
day at a time (``simulate --until`` / ``--extend``), calibrated once, then for a few days ``daily``, ``report``,
``score`` and ``scenario export`` as a new user would run them, and for each finding of the issue what was
observed (a table and a JSON).

Usage::

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_operator_day.py [--heliostats 300] [--years 2]
        [--days 3] [--seed 3] [--work DIR] [--json operator-day.json]

A quick try: ``--heliostats 30 --days 3``. The checks are written against the issue's target behaviour (what a
plant would act on); each reads the commands' JSON reports and files where it can (the report page's map is
read from its HTML). ``ok`` says whether the target was seen; exit status 1 when any check is not ok.

Findings checked (issue 42's list):

* ``nominal_named`` -- no heliostat silently left nominal: calibrate's JSON names every nominal heliostat;
* ``alarms_persist`` -- an alarm stays open over a rerun of ``daily`` with no new record (exit 3 while open);
* ``planned_day`` -- ``daily`` without ``--day`` plans the day after the plant's latest record, not the wall
  clock's tomorrow; with ``--day`` it plans that day;
* ``map_values`` -- every calibrated heliostat has a value on the report's map ("no value" only for nominal ones);
* ``export_aim`` -- ``scenario export --solarpilot`` writes the stored optimised aim points;
* ``spread_consistent`` -- the plan's spread is the one the report prints, the ranking by what is printed;
* ``folder_grows`` -- the folder grew a day at a time (``simulation.json`` says how far it reaches).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd

HERE = Path(__file__).resolve().parent
SRC = HERE.parent / "src"


def heliotwin(*argv, cwd: Path, log: list, ok=(0, 3)) -> subprocess.CompletedProcess:
    """Run ``heliotwin ARGV`` as a process in ``cwd``; record the command, exit status and seconds."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")]))
    env.setdefault("OMP_NUM_THREADS", "1")
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "heliotwin", *map(str, argv)], cwd=cwd, env=env, capture_output=True,
                       text=True)
    log.append({"command": "heliotwin " + " ".join(map(str, argv)), "code": p.returncode,
                "seconds": round(time.perf_counter() - t0, 2)})
    if p.returncode not in ok:
        log[-1]["stderr"] = p.stderr.strip()[-500:]
    return p


def find(obj, key: str) -> list:
    """Every value under a key containing ``key`` anywhere in a JSON document."""
    out = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            if key in str(k):
                out.append(v)
            out.extend(find(v, key))
    elif isinstance(obj, list):
        for v in obj:
            out.extend(find(v, key))
    return out


def load(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def latest_record_day(folder: Path) -> str:
    with open(folder / "metadata" / "calibration-metadata.csv", newline="", encoding="utf-8") as fh:
        last = max(r["DateTime"] for r in csv.DictReader(fh))
    return str(pd.Timestamp(last).normalize().date())


def export_aims(path: Path) -> list:
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    return [[float(r[f"{a}_aimpoint"]) for a in "xyz"] for r in rows]


def run(args) -> dict:
    work = Path(args.work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    plant = work / "plant"
    log: list = []
    checks: dict = {}
    start = pd.Timestamp("2021-01-01", tz="UTC")
    cut = (start + pd.Timedelta(days=365.25 * args.years)).normalize() - pd.Timedelta(days=1)
    if not plant.exists():
        heliotwin("simulate", "--heliostats", args.heliostats, "--years", args.years + (args.days + 10) / 365.25,
                  "--seed", args.seed, "--until", cut.date(), "--out", plant, cwd=work, log=log, ok=(0,))
    cal = heliotwin("calibrate", "--paint", plant, "-o", "a.h5", "--json", "cal.json", cwd=work, log=log)
    cal_json = load(work / "cal.json") or {}
    nominal = find(cal_json, "nominal_heliostats") + find(cal_json, "uncalibrated")
    named = [v for v in nominal if isinstance(v, list) and v and all(isinstance(x, str) for x in v)]
    checks["nominal_named"] = {"ok": bool(named) or "nominal" not in cal.stdout + cal.stderr,
                               "observed": f"calibrate exit {cal.returncode}; nominal heliostats named in JSON: "
                                           f"{named[0][:5] if named else 'none'}"}
    # the plant keeps its aim points and their limit: 'aimpoints --in-place' once, as daily's advice says
    noon = f"{(cut + pd.Timedelta(days=1)).date()}T11:30:00Z"
    heliotwin("aimpoints", "--scenario", "a.h5", "-o", "a.h5", "--in-place", "--time", noon, "--peak-limit",
              args.peak_limit, "--no-baselines", "--json", "aim.json", cwd=work, log=log)
    days, alarm_runs, planned, aims_ok, spreads, maps = [], [], [], [], [], []
    for d in range(args.days):
        grow = heliotwin("simulate", "--extend", plant, "--days", 1, cwd=work, log=log, ok=(0,))
        next_day = (pd.Timestamp(latest_record_day(plant)) + pd.Timedelta(days=1)).date()
        use_day = d > 0  # the first day without --day: the plant's own clock
        argv = ["daily", "--plant", "a.h5", "--paint", plant, "--json", f"day{d}.json"]
        p = heliotwin(*argv, *(["--day", next_day] if use_day else []), cwd=work, log=log)
        rep = load(work / f"day{d}.json") or {}
        days.append({"day": d, "grow": grow.stdout.strip()[-120:], "daily_code": p.returncode})
        said = [str(v) for v in find(rep, "day") if isinstance(v, str)]
        planned.append({"expected": str(next_day), "said": said[:3], "with_day": use_day,
                        "ok": any(str(next_day) in s for s in said)})
        open_alarms = find(rep, "open_alarms")
        again = heliotwin(*argv[:-1], f"day{d}-again.json", *(["--day", next_day] if use_day else []), cwd=work,
                          log=log)
        rep2 = load(work / f"day{d}-again.json") or {}
        n_open = [len(v) for v in open_alarms if isinstance(v, list)]
        n_open2 = [len(v) for v in find(rep2, "open_alarms") if isinstance(v, list)]
        alarm_runs.append({"open": n_open, "open_on_rerun": n_open2, "rerun_code": again.returncode,
                           "ok": (not n_open or not n_open[0]) or (n_open2 == n_open and again.returncode == 3)})
        spreads.append(find(rep, "spread")[:10])
        heliotwin("report", "--scenario", "a.h5", "--paint", plant, "-o", f"report{d}.html", cwd=work, log=log)
        html = (work / f"report{d}.html").read_text(errors="replace") if (work / f"report{d}.html").exists() else ""
        maps.append({"no_value": html.count("no value"), "nominal": html.count("nominal")})
        heliotwin("score", "--truth", plant / "truth.h5", "--scenario", "a.h5", "--no-flux", "--json",
                  f"score{d}.json", cwd=work, log=log)
        ex = heliotwin("scenario", "export", "a.h5", "--solarpilot", f"export{d}.csv", cwd=work, log=log)
        if (work / f"export{d}.csv").exists():
            got = export_aims(work / f"export{d}.csv")
            said_stored = "stored optimised" in ex.stdout
            aims_ok.append({"said": ex.stdout.strip()[-100:], "ok": said_stored,
                            "spread_of_aims_m": round(max(a[0] for a in got) - min(a[0] for a in got), 3)})
    score = load(work / f"score{args.days - 1}.json") or {}
    worst = find(score, "worst")
    checks["alarms_persist"] = {"ok": all(a["ok"] for a in alarm_runs), "observed": alarm_runs}
    checks["planned_day"] = {"ok": all(p["ok"] for p in planned), "observed": planned}
    checks["map_values"] = {"ok": all(m["no_value"] == 0 for m in maps), "observed": maps}
    checks["export_aim"] = {"ok": bool(aims_ok) and all(a["ok"] for a in aims_ok), "observed": aims_ok}
    # the ranking by what is printed: the plan's spreads, in its order, do not increase
    ranked = [[float(x) for x in sp if isinstance(x, (int, float))] for sp in spreads]
    checks["spread_consistent"] = {"ok": all(r == sorted(r, reverse=True) for r in ranked), "observed": spreads}
    checks["score_names_worst"] = {"ok": bool(worst), "observed": worst[:1] or "no heliostat named"}
    grown = load(plant / "simulation.json") or {}
    reached = (pd.Timestamp(grown["until"], tz="UTC") - cut).days if grown.get("until") else None
    checks["folder_grows"] = {"ok": reached == args.days, "observed": f"simulation.json until {grown.get('until')}: "
                                                                        f"{reached} day(s) appended to {cut.date()}"}
    return {"settings": vars(args), "checks": checks, "days": days, "commands": log}


def table(result: dict) -> str:
    lines = [f"{'finding':<20} {'ok':<4} observed"]
    for name, c in result["checks"].items():
        lines.append(f"{name:<20} {'yes' if c['ok'] else 'NO':<4} {json.dumps(c['observed'])[:150]}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--heliostats", type=int, default=300)
    ap.add_argument("--years", type=float, default=2.0)
    ap.add_argument("--days", type=int, default=3)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--work", default="/tmp/operator-day")
    ap.add_argument("--peak-limit", type=float, default=650000.0, help="aimpoints' limit [W/m2]")
    ap.add_argument("--json", help="write the observations as JSON")
    args = ap.parse_args(argv)
    result = run(args)
    print(table(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2, default=str))
    return 0 if all(c["ok"] for c in result["checks"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
