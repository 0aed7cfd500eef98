"""Misuse campaign over the daily loop (issue 41, "safe to schedule, all of it"): every finding of the campaign as a
reproducible case with its expected verdict.

The cases live in ``benchmarks/misuse/*.py`` (one module per area: ``reader`` -- odd files in the plant's folder,
another plant's folder, the record index; ``outputs`` -- outputs against inputs, symlinked plants, the lock,
arguments and datasets; ``loop`` -- what the day's report claims: standby, ``--confidence``, alarms, the plant's
clock). Each module defines ``CASES``, a list of :class:`Case`. A case builds what it needs from the shared
:class:`Workspace` (the issue's setup: ``base`` = ``simulate --heliostats 12 --years 1 --seed 1``, ``old`` = its
records before 2021-09-01, ``calold.h5`` = ``calibrate --paint old --min-records 10 --train 1000000``; the same at
300 heliostats, ``--seed 3``, with ``--big``), runs the command as a user would (a subprocess with a time limit: a
hang is a verdict, not a stuck campaign) and returns a :class:`Verdict`: ``clean`` or not, and what it saw.

Usage::

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/fuzz_daily.py [--big] [--only NAME ...] [--area reader ...]
        [--json misuse.json] [--work DIR]

Prints one line per case (area, name, severity, verdict, seconds, what it saw) and a summary; exit status 1 when
any case is not clean.
"""
from __future__ import annotations

import argparse
import csv
import importlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

HERE = Path(__file__).resolve().parent
SRC = HERE.parent / "src"
AREAS = ("reader", "outputs", "loop")


@dataclass(frozen=True)
class Verdict:
    """A case's outcome: ``clean`` (the expected behaviour was seen) and a one-line ``detail``."""

    clean: bool
    detail: str


@dataclass(frozen=True)
class Case:
    """One misuse case: ``run(workspace, folder) -> Verdict`` in a fresh ``folder`` [pathlib.Path].

    ``expected`` says in words what a clean run does (refused in one line naming X, exit 3, ...); ``severity`` is
    ``high``, ``medium`` or ``low`` as in the issue; ``big`` cases need the 300-heliostat plant (``--big``)."""

    name: str
    severity: str
    expected: str
    run: Callable
    big: bool = False


@dataclass
class Result:
    """What one command did: exit status, output, wall time [s], and whether it hit the time limit."""

    code: int | None
    out: str
    err: str
    seconds: float
    timed_out: bool = False

    @property
    def one_line_error(self) -> bool:
        """Exit 2 with exactly one ``heliotwin: error:`` line on stderr."""
        lines = [ln for ln in self.err.strip().splitlines() if ln.strip()]
        return self.code == 2 and len(lines) == 1 and lines[0].startswith("heliotwin: error: ")


def heliotwin(*argv, cwd, timeout: float = 120.0, env: dict | None = None, stdin=subprocess.DEVNULL) -> Result:
    """Run ``heliotwin ARGV`` as a user would (``python -m heliotwin`` of this checkout), killed after ``timeout``."""
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")]),
                   "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1"), **(env or {})}
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "heliotwin", *map(str, argv)], cwd=cwd, env=environment,
                            stdin=stdin, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
        return Result(proc.returncode, out, err, time.perf_counter() - t0)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, 9)
        out, err = proc.communicate()
        return Result(None, out, err, time.perf_counter() - t0, timed_out=True)


def records_before(src: Path, dst: Path, date: str) -> Path:
    """A copy of PAINT folder ``src`` at ``dst`` holding only the records before ``date`` (ISO, UTC): the record
    files dated later and their metadata rows are left out (tower, properties and truth are copied)."""
    shutil.copytree(src, dst)
    meta = dst / "metadata" / "calibration-metadata.csv"
    with open(meta, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        names, rows = reader.fieldnames, list(reader)
    keep = [r for r in rows if r["DateTime"][:10] < date]
    drop = {r["Id"] for r in rows} - {r["Id"] for r in keep}
    for rec in dst.glob("*/Calibration/*-calibration-properties.json"):
        if rec.name.split("-")[0] in drop:
            rec.unlink()
    with open(meta, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, names)
        writer.writeheader()
        writer.writerows(keep)
    return dst


class Workspace:
    """The campaign's shared inputs, built once in ``root`` on first use (cases copy, never modify them)."""

    def __init__(self, root: Path):
        self.root = root
        self._made: dict = {}

    def _plant(self, n: int, seed: int) -> dict:
        key = (n, seed)
        if key not in self._made:
            d = self.root / f"plant{n}"
            d.mkdir(parents=True, exist_ok=True)
            base, old, cal = d / "base", d / "old", d / "calold.h5"
            if not cal.exists():
                for p in (base, old):
                    shutil.rmtree(p, ignore_errors=True)
                r = heliotwin("simulate", "--heliostats", n, "--years", 1, "--seed", seed, "--out", base, cwd=d,
                              timeout=600)
                assert r.code == 0, r.err
                records_before(base, old, "2021-09-01")
                r = heliotwin("calibrate", "--paint", old, "--min-records", 10, "--train", 1000000, "-o", cal,
                              "--quiet", cwd=d, timeout=1800)
                assert r.code == 0, r.err
            self._made[key] = {"base": base, "old": old, "cal": cal}
        return self._made[key]

    @property
    def small(self) -> dict:
        """``{"base", "old", "cal"}`` of the 12-heliostat plant (paths; copy before changing)."""
        return self._plant(12, 1)

    @property
    def big(self) -> dict:
        """The same for the 300-heliostat plant."""
        return self._plant(300, 3)


def load_cases(areas=AREAS) -> list:
    """Every case of the named areas' modules (``benchmarks/misuse/<area>.py``), as ``(area, Case)``."""
    sys.path.insert(0, str(HERE))
    found = []
    for area in areas:
        try:
            module = importlib.import_module(f"misuse.{area}")
        except ModuleNotFoundError as exc:
            if exc.name != f"misuse.{area}":
                raise
            continue
        found += [(area, c) for c in module.CASES]
    return found


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--big", action="store_true", help="also the cases on the 300-heliostat plant")
    ap.add_argument("--area", action="append", choices=AREAS, help="only these areas (repeatable)")
    ap.add_argument("--only", action="append", help="only cases whose name contains this (repeatable)")
    ap.add_argument("--json", help="write every case's verdict here")
    ap.add_argument("--work", help="keep the workspace here (default: a temporary folder, removed)")
    args = ap.parse_args(argv)
    cases = [(a, c) for a, c in load_cases(args.area or AREAS) if args.big or not c.big]
    if args.only:
        cases = [(a, c) for a, c in cases if any(o in c.name for o in args.only)]
    root = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="fuzz-daily-"))
    root.mkdir(parents=True, exist_ok=True)
    ws = Workspace(root)
    rows = []
    try:
        for i, (area, case) in enumerate(cases):
            folder = root / "cases" / f"{i:03d}-{case.name}"
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            t0 = time.perf_counter()
            try:
                v = case.run(ws, folder)
            except Exception as exc:  # a broken case is a finding too, not the end of the campaign
                v = Verdict(False, f"case raised {type(exc).__name__}: {exc}")
            row = {"area": area, "case": case.name, "severity": case.severity, "expected": case.expected,
                   "clean": v.clean, "detail": v.detail, "seconds": round(time.perf_counter() - t0, 2)}
            rows.append(row)
            print(f"{area:8s} {case.name:44s} {case.severity:6s} {'clean' if v.clean else 'NOT CLEAN':9s} "
                  f"{row['seconds']:7.1f} s  {v.detail}", flush=True)
    finally:
        if not args.work:
            shutil.rmtree(root, ignore_errors=True)
    bad = [r for r in rows if not r["clean"]]
    print(f"{len(rows)} cases: {len(rows) - len(bad)} clean, {len(bad)} not clean")
    if args.json:
        Path(args.json).write_text(json.dumps({"cases": rows, "clean": len(rows) - len(bad), "not_clean": len(bad)},
                                              indent=1) + "\n")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
