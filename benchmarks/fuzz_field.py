"""Misuse campaign over the field commands: about a thousand bad inputs, and what each run did with them.

Commands: ``scenario from-layout``, ``field`` (one sun, ``--year``), ``aimpoints`` and the readers behind them
(layout CSV, TOML plant description, scenario file with its ``/learned`` group, ``--target`` maps). Cases:

* arguments: non-finite, absurd and unparsable suns, irradiance, times, years, steps, resolutions, peak limits;
* outputs onto inputs and onto each other, into missing folders;
* every TOML key set to NaN, inf, negative, zero, huge or mistyped values, and physically impossible plants
  (negative attenuation, receiver below ground, huge facet counts), binary and empty files;
* layouts with NUL bytes, overlapping pivots, heliostats 1e7 m away or in the tower, random byte damage;
* scenario files with one dataset or attribute set to NaN/inf/zero, truncated or deleted (plant and learned);
* FIFOs where a file is expected;
* with ``--subprocess`` (default on): ``--nproc`` above the heliostat count, SIGTERM during ``--nproc 2`` runs
  (must exit within 5 s with its workers) and during the writes.

Each run is judged on: a traceback, an "internal error" line, a hang, a silent bad result (exit 0 with a NaN,
a null or an out-of-range efficiency in its report, or an unmet peak limit), an input file modified, and
leftovers (files a failed run left, staging or temporary files, ``pytorch-errorfile-*``).

Usage (runs in-process against whatever ``heliotwin`` is importable; the lead's checkout or a worktree)::

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/fuzz_field.py [--cases 1000] [--seed 0] [--no-subprocess]
        [--show 20]

Prints the counts per category and the first ``--show`` bad cases; exit status 1 when any count is non-zero.
"""
from __future__ import annotations

import argparse
import contextlib
import glob
import hashlib
import io
import json
import math
import os
import random
import re
import resource
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
# the SolarPILOT reference case's plant, as the field tests and bench_field use it
from helpers.field import PLANT_TOML  # noqa: E402

#: TOML keys and the values each may be set to (TOML syntax).
TOML_KEYS = [("site", "latitude"), ("site", "longitude"), ("site", "altitude"), ("heliostat", "width"),
             ("heliostat", "height"), ("heliostat", "facets"), ("heliostat", "reflectivity"),
             ("heliostat", "slope_error_mrad"), ("heliostat", "focal_length"), ("receiver", "radius"),
             ("receiver", "height"), ("receiver", "center"), ("receiver", "opening_angle_deg"),
             ("receiver", "normal"), ("sun", "dni"), ("sun", "sigma_mrad"), ("sun", "csr"),
             ("atmosphere", "coefficients")]
BAD_TOML_VALUES = ["nan", "inf", "-inf", "-1.0", "0.0", "1e308", "-1e308", "\"text\"", "[]", "true", "1e-300",
                   "[nan, 0.0, 55.0]", "[0.0, 0.0, -10.0]", "[1000, 1000]", "[-0.5, 0.0, 0.0, 0.0]",
                   "[0.0, 5.0, 0.0, 0.0]"]
SPECIAL_TOMLS = {
    "negative-attenuation": ("coefficients = [0.006789, 0.1046, -0.0107, 0.002845]",
                             "coefficients = [-5.0, 0.0, 0.0, 0.0]"),
    "loss-above-one": ("coefficients = [0.006789, 0.1046, -0.0107, 0.002845]",
                       "coefficients = [0.0, 50.0, 0.0, 0.0]"),
    "receiver-below-ground": ("center = [0.0, 0.0, 55.0]", "center = [0.0, 0.0, -20.0]"),
    "receiver-at-ground": ("center = [0.0, 0.0, 55.0]", "center = [0.0, 0.0, 1.0]"),
    "huge-facets": ("facets = [1, 1]", "facets = [3000, 3000]"),
    "huge-mirror": ("width = 3.22", "width = 1e6"),
}


#: What one in-process case may take beyond what is loaded: address space, and bytes per file written.
MEMORY_BYTES = 6 * 2**30
CAMPAIGN_PID = os.getpid()
FILE_BYTES = 512 * 2**20


# ------------------------------------------------------------------------------------------------ helpers
def digest(path: Path) -> str | None:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def snapshot(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): (digest(p) if p.is_file() and not p.is_fifo() else "special")
            for p in folder.rglob("*") if not p.is_dir()}


def errorfiles() -> set:
    return set(glob.glob(os.path.join(tempfile.gettempdir(), "pytorch-errorfile-*")))


def dense_layout(rows: int, cols: int, spacing=(4.0, 3.6), first_row=30.0) -> list:
    out = []
    for r in range(rows):
        for c in range(cols):
            x = (c - (cols - 1) / 2) * spacing[0] + (0.5 * spacing[0] if r % 2 else 0.0)
            out.append((x, first_row + r * spacing[1], 0.0))
    return out


def layout_text(xyz, ids=None) -> str:
    lines = ["# x east, y north, z up [m]", "id,x,y,z" if ids else "x,y,z"]
    for i, p in enumerate(xyz):
        lines.append((f"{ids[i]}," if ids else "") + ",".join(repr(float(v)) for v in p))
    return "\n".join(lines) + "\n"


def _vm_bytes() -> int:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def run_inprocess(argv, timeout: float = 60.0, fifo: Path | None = None) -> tuple:
    """(exit status or 'hang'/'traceback', stdout, stderr) of ``heliotwin argv`` in a forked copy of this process.

    The fork has torch imported already (cheap to start), its own memory (a run that exhausts it cannot take
    the campaign along), at most :data:`MEMORY_BYTES` more address space and :data:`FILE_BYTES` per file
    written, and is killed when it does not end within ``timeout`` s (a hang).
    """
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: run, report, exit without running the parent's cleanups
        os.close(read_end)
        code, out, err = "traceback", io.StringIO(), io.StringIO()
        try:
            resource.setrlimit(resource.RLIMIT_AS, (_vm_bytes() + MEMORY_BYTES,) * 2)
            resource.setrlimit(resource.RLIMIT_FSIZE, (FILE_BYTES,) * 2)
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead
            from heliotwin.cli import main

            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                code = main([str(a) for a in argv])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 2
        except BaseException as exc:  # noqa: BLE001 -- what escaped the command line's safety net
            err.write(f"Traceback (escaped): {type(exc).__name__}: {' '.join(str(exc).split())}\n")
        with contextlib.suppress(BaseException):
            data = json.dumps([code, out.getvalue()[-20000:], err.getvalue()[-20000:]]).encode()
            with os.fdopen(write_end, "wb") as fh:
                fh.write(data)
        os._exit(0)
    os.close(write_end)
    chunks, deadline = [], time.monotonic() + timeout
    with os.fdopen(read_end, "rb") as fh:
        os.set_blocking(fh.fileno(), False)
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            ready, _, _ = select.select([fh], [], [], min(left, 1.0))
            if ready:
                block = fh.read()
                if not block:
                    break
                chunks.append(block)
    if time.monotonic() >= deadline:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        return "hang", "", ""
    _, status = os.waitpid(pid, 0)
    try:
        code, out, err = json.loads(b"".join(chunks).decode())
    except ValueError:
        return "traceback", "", f"Traceback: the run died ({os.waitstatus_to_exitcode(status)})"
    return code, out, err


def run_subprocess(argv, cwd: Path, timeout: float = 300.0) -> tuple:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    try:
        p = subprocess.run([sys.executable, "-m", "heliotwin", *map(str, argv)], cwd=cwd, env=env,
                           capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return "hang", "", ""
    return p.returncode, p.stdout, p.stderr


# ------------------------------------------------------------------------------------------------ judging
EFFICIENCY_KEYS = {"cosine", "shading", "blocking", "attenuation", "intercept", "reflectance", "total",
                   "efficiency", "mean_efficiency", "tower_shading"}


def bad_values(obj, path="") -> list:
    """Nulls, non-finite numbers and efficiencies outside [0, 1] in a report."""
    found = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            found += bad_values(v, f"{path}.{k}")
            if k in EFFICIENCY_KEYS and isinstance(v, (int, float)) and not isinstance(v, bool) \
                    and not -1e-9 <= v <= 1 + 1e-9:
                found.append(f"{path}.{k}={v}")
            if k == "limit_met" and v is False and ".optimised" in f"{path}.{k}":
                found.append(f"{path}.{k}=false")
            if k in ("power_w", "peak_flux_w_m2") and isinstance(v, (int, float)) and v < 0:
                found.append(f"{path}.{k}={v}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            found += bad_values(v, f"{path}[{i}]")
    elif obj is None and not path.endswith((".scenario", ".target_mismatch", "final_margin",
                                          "learned.aimpoints.peak_limit_w_m2")):  # show: no aim points stored
        found.append(f"{path}=null")
    elif isinstance(obj, float) and not math.isfinite(obj):
        found.append(f"{path}={obj}")
    return found


def judge_outputs(outputs: list) -> list:
    found = []
    for p in outputs:
        p = Path(p)
        if p.suffix == ".json" and p.is_file():
            try:
                found += [f"{p.name}{b}" for b in bad_values(json.loads(p.read_text()))][:3]
            except ValueError as exc:
                found.append(f"{p.name}: not JSON ({exc})")
        elif p.suffix == ".csv" and p.is_file():
            text = p.read_bytes().decode("utf-8", "replace").lower()
            if "nan" in text or "inf" in text:
                found.append(f"{p.name}: NaN/inf in the CSV")
    return found


class Campaign:
    def __init__(self, root: Path, show: int):
        self.root, self.show = root, show
        self.counts = {k: 0 for k in ("cases", "tracebacks", "internal_errors", "hangs", "silent_bad_results",
                                      "inputs_modified", "leftovers")}
        self.bad: list = []
        self.n = 0

    def report(self, summary: str) -> int:
        """Print which heliotwin ran, ``summary``, the first ``show`` bad cases and the counts; the exit status
        (1 when any count but ``cases`` is non-zero)."""
        import heliotwin

        print(f"heliotwin {heliotwin.__version__} from {Path(heliotwin.__file__).parent}; {summary}")
        for line in self.bad[:self.show]:
            print("  " + line)
        if len(self.bad) > self.show:
            print(f"  ... {len(self.bad) - self.show} more")
        print(" ".join(f"{k}={v}" for k, v in self.counts.items()))
        return 1 if any(v for k, v in self.counts.items() if k != "cases") else 0

    def case(self, name: str, argv, *, inputs: dict, outputs=(), fifo: str | None = None, subprocess_: bool = False,
             timeout: float = 90.0, followup=None):
        """Run one case in a fresh folder holding ``inputs`` ({name: bytes or Path to copy or 'fifo'})."""
        self.n += 1
        d = self.root / f"c{self.n:04d}"
        d.mkdir()
        for fname, src in inputs.items():
            if src == "fifo":
                os.mkfifo(d / fname)
            elif isinstance(src, bytes):
                (d / fname).write_bytes(src)
            else:
                shutil.copyfile(src, d / fname)
        before = snapshot(d)
        efiles = errorfiles()
        argv = [str(a).replace("{d}", str(d)) for a in argv]
        outs = [str(o).replace("{d}", str(d)) for o in outputs]
        t0 = time.perf_counter()
        if subprocess_:
            code, out, err = run_subprocess(argv, d, timeout)
        else:
            with _chdir(d):
                code, out, err = run_inprocess(argv, timeout, fifo=d / fifo if fifo else None)
        if os.getpid() != CAMPAIGN_PID:  # a forked case that came back here must not run the campaign twice
            os._exit(70)
        if self.n % 100 == 0:
            print(f"  {self.n} cases", flush=True)
        self.judge(name, argv, code, out, err, d, before, outs, efiles, time.perf_counter() - t0)
        if followup and code == 0:
            followup(d)

    def judge(self, name, argv, code, out, err, d, before, outs, efiles, seconds):
        self.counts["cases"] += 1
        problems = []
        if code == "traceback" or "Traceback" in err:
            problems.append(("tracebacks", err.strip().splitlines()[-1] if err.strip() else "traceback"))
        if "internal error" in err:
            problems.append(("internal_errors", err.strip().splitlines()[-1]))
        if code == "hang":
            problems.append(("hangs", f"no end within the time limit ({seconds:.0f} s)"))
        if code == 0:
            silent = judge_outputs(outs)
            if re.search(r"\b-?nan\b", out.lower()):  # a word: "provenance" holds no NaN
                silent.append("NaN on the console")
            if silent:
                problems.append(("silent_bad_results", "; ".join(silent[:3])))
        after = snapshot(d)
        changed = [k for k, v in before.items() if after.get(k) != v]
        if changed:
            problems.append(("inputs_modified", ", ".join(changed)))
        declared = {Path(o).resolve().relative_to(d.resolve()).as_posix() for o in outs
                    if Path(o).resolve().is_relative_to(d.resolve())}
        wrote = code in (0, 3)  # 3: aimpoints could not hold the peak limit, said so, and wrote its best
        new = [k for k in after if k not in before and (not wrote or not any(
            k == o or k.startswith(o + "/") for o in declared))]
        new_errorfiles = errorfiles() - efiles
        if new or new_errorfiles:
            problems.append(("leftovers", ", ".join(sorted(new)[:4] + sorted(new_errorfiles)[:2])))
            for f in new_errorfiles:
                with contextlib.suppress(OSError):
                    os.remove(f)
        for kind, what in problems:
            self.counts[kind] += 1
            self.bad.append(f"[{kind}] {name}: exit {code}: {what[:220]}")


@contextlib.contextmanager
def _chdir(d):
    old = os.getcwd()
    os.chdir(d)
    try:
        yield
    finally:
        os.chdir(old)


# ----------------------------------------------------------------------------------------------- the cases
def build_base(root: Path) -> dict:
    """A 6-heliostat field (layout, TOML, scenario) and the same scenario with learned aim points."""
    from heliotwin.cli import main

    base = root / "base"
    base.mkdir()
    xyz = dense_layout(2, 3)
    (base / "layout.csv").write_text(layout_text(xyz, [f"h{i}" for i in range(len(xyz))]))
    (base / "plant.toml").write_text(PLANT_TOML)
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["scenario", "from-layout", str(base / "layout.csv"), "--config", str(base / "plant.toml"),
                     "-o", str(base / "p.h5")]) == 0
        assert main(["aimpoints", "--scenario", str(base / "p.h5"), "--time", "2023-06-21T10:00Z,2023-06-21T13:00Z",
                     "--peak-limit", "1e6", "--resolution", "8x4", "--iterations", "3", "--no-baselines",
                     "-o", str(base / "a.h5"), "--json", str(base / "a.json"), "--quiet"]) == 0
    return {"layout": base / "layout.csv", "toml": base / "plant.toml", "scenario": base / "p.h5",
            "aimed": base / "a.h5", "xyz": xyz}


FIELD = ["--resolution", "8x4", "--quiet"]
AIM = ["--resolution", "8x4", "--iterations", "3", "--no-baselines", "--quiet"]


def field_case(c: Campaign, base, name, extra, scenario="p.h5", src=None, outputs=None, **kw):
    outs = outputs if outputs is not None else ["{d}/f.json"]
    c.case(name, ["field", "--scenario", scenario, "--json", "f.json", *FIELD, *extra],
           inputs={scenario: src or base["scenario"]}, outputs=outs, **kw)


def aim_case(c: Campaign, base, name, extra, inputs=None, **kw):
    c.case(name, ["aimpoints", "--scenario", "p.h5", "-o", "o.h5", "--json", "o.json", *AIM, *extra],
           inputs=inputs or {"p.h5": base["scenario"]}, outputs=["{d}/o.h5", "{d}/o.json"], **kw)


def argument_cases(c: Campaign, base):
    angles = ["nan", "inf", "-inf", "1e308", "-1e308", "720", "-400", "10"]
    elevations = ["nan", "inf", "-inf", "0", "-5", "90", "90.0001", "1e308", "40"]
    for az in angles:
        for el in elevations:
            field_case(c, base, f"field sun {az}/{el}", [f"--sun-azimuth={az}", f"--sun-elevation={el}"])
    for dni in ["nan", "inf", "-1", "1e30", "0", "1e-300", "x"]:
        field_case(c, base, f"field --dni {dni}", ["--sun-azimuth", "10", "--sun-elevation", "40", f"--dni={dni}"])
    for t in ["2023-06-21T12:00Z", "2023-06-21T00:00Z", "garbage", "", "9999-01-01", "2023-13-40", "nan", "1e308",
              "2023-06-21T12:00+25:00"]:
        field_case(c, base, f"field --time {t!r}", [f"--time={t}"])
    for year in ["0", "-1", "2023", "99999", "1899", "x"]:
        for every in ["1h", "31d", "0min", "-1h", "x", "1d", "400d", "7h"]:
            field_case(c, base, f"field --year {year} --every {every}",
                       ["--year", year, f"--every={every}", "--table-azimuth-step", "90"])
    for step in ["0", "-15", "nan", "inf", "1e-9", "200"]:
        field_case(c, base, f"field --table-azimuth-step {step}",
                   ["--year", "2023", "--every", "7h", f"--table-azimuth-step={step}"])
    for res in ["0x0", "1x1", "100000x100000", "10000000x1", "x", "48x20x3", "-1x5", "99999999999x99999999999"]:
        field_case(c, base, f"field --resolution {res}", ["--sun-azimuth", "10", "--sun-elevation", "40",
                                                          f"--resolution={res}"])
    for seed in ["-1", "1e3", "99999999999999999999999"]:
        field_case(c, base, f"field --seed {seed}", ["--sun-azimuth", "10", "--sun-elevation", "40",
                                                     "--integrator", "mc", f"--seed={seed}"])
    for n in ["0", "-1", "x"]:
        field_case(c, base, f"field --nproc {n}", ["--sun-azimuth", "10", "--sun-elevation", "40", f"--nproc={n}"])
    field_case(c, base, "field --aim scenario without aim points", ["--sun-azimuth", "10", "--sun-elevation", "40",
                                                                     "--aim", "scenario"])
    field_case(c, base, "field --aim scenario", ["--sun-azimuth", "10", "--sun-elevation", "40", "--aim",
                                                 "scenario"], src=base["aimed"])
    # aimpoints
    for limit in ["nan", "inf", "-1", "0", "1", "1e308", "x"]:
        aim_case(c, base, f"aimpoints --peak-limit {limit}", ["--sun-azimuth", "10", "--sun-elevation", "40",
                                                              f"--peak-limit={limit}"])
    for az, el in [("nan", "40"), ("10", "nan"), ("1e308", "40"), ("10", "inf"), ("10", "-3")]:
        aim_case(c, base, f"aimpoints sun {az}/{el}", [f"--sun-azimuth={az}", f"--sun-elevation={el}",
                                                       "--peak-limit", "1e6"])
    for day, every in [("2023-06-21", "0min"), ("2023-06-21", "31d"), ("2023-06-21", "x"), ("x", "1h"),
                       ("2023-12-21", "1d"), ("2023-06-21", "-1h"), ("0", "1h"), ("2023-06-21", "0h")]:
        aim_case(c, base, f"aimpoints --day {day} --every {every}", [f"--day={day}", f"--every={every}",
                                                                     "--peak-limit", "1e6"], timeout=240)
    for times in [",", "garbage", "2023-06-21T00:00Z", ",,2023-06-21T12:00Z,x"]:
        aim_case(c, base, f"aimpoints --time {times!r}", [f"--time={times}", "--peak-limit", "1e6"])
    for it in ["0", "-1", "1e9"]:
        aim_case(c, base, f"aimpoints --iterations {it}", ["--sun-azimuth", "10", "--sun-elevation", "40",
                                                           "--peak-limit", "1e6", f"--iterations={it}"])
    for res in ["0x0", "100000x100000", "1x1"]:
        aim_case(c, base, f"aimpoints --resolution {res}", ["--sun-azimuth", "10", "--sun-elevation", "40",
                                                            "--peak-limit", "1e6", f"--resolution={res}"])
    targets = {"nan.csv": b"nan,nan\nnan,nan\n", "empty.csv": b"", "shape.csv": b"1,2,3\n",
               "neg.csv": ("\n".join(",".join(["-1"] * 8) for _ in range(4)) + "\n").encode(),
               "zero.csv": ("\n".join(",".join(["0"] * 8) for _ in range(4)) + "\n").encode(),
               "bin.npy": b"\x93NUMPY\x01\x00garbage", "text.csv": b"a,b\nc,d\n"}
    for tname, data in targets.items():
        aim_case(c, base, f"aimpoints --target {tname}", ["--sun-azimuth", "10", "--sun-elevation", "40",
                                                          "--peak-limit", "1e6", "--target", tname],
                 inputs={"p.h5": base["scenario"], tname: data})
    aim_case(c, base, "aimpoints --target missing", ["--sun-azimuth", "10", "--sun-elevation", "40",
                                                     "--peak-limit", "1e6", "--target", "nope.csv"])


def output_cases(c: Campaign, base):
    sun = ["--sun-azimuth", "10", "--sun-elevation", "40"]
    for flags, outs in [
        (["--json", "p.h5"], ["{d}/p.h5"]), (["--per-heliostat", "p.h5"], ["{d}/f.json", "{d}/p.h5"]),
        (["--flux", "p.h5"], ["{d}/f.json", "{d}/p.h5"]), (["--per-heliostat", "f.json"], ["{d}/f.json"]),
        (["--flux", "f.json"], ["{d}/f.json"]), (["--per-heliostat", "nofolder/x.csv"], ["{d}/f.json"]),
        (["--flux", "."], ["{d}/f.json"]), (["--json", "nofolder/f.json"], []),
        (["--per-heliostat", "h.csv", "--flux", "h.csv"], ["{d}/f.json", "{d}/h.csv"]),
        (["--per-heliostat", "./p.h5"], ["{d}/f.json", "{d}/p.h5"]),
    ]:
        c.case(f"field outputs {' '.join(flags)}", ["field", "--scenario", "p.h5", "--json", "f.json", *FIELD, *sun,
                                                     *flags],
               inputs={"p.h5": base["scenario"]}, outputs=outs)
    c.case("field --year --json onto the scenario", ["field", "--scenario", "p.h5", "--year", "2023", "--every",
                                                     "7h", "--table-azimuth-step", "90", "--json", "p.h5"],
           inputs={"p.h5": base["scenario"]}, outputs=["{d}/p.h5"])
    for flags in (["-o", "p.h5"], ["--json", "p.h5"], ["-o", "same.h5", "--json", "same.h5"], ["--flux", "p.h5"],
                  ["--flux", "o.json"]):
        c.case(f"aimpoints outputs {' '.join(flags)}",
               ["aimpoints", "--scenario", "p.h5", "-o", "o.h5", "--json", "o.json", *AIM, *sun, "--peak-limit",
                "1e6", *flags], inputs={"p.h5": base["scenario"]}, outputs=["{d}/o.h5", "{d}/o.json"])
    for out in ["layout.csv", "plant.toml", "./layout.csv", "nofolder/x.h5", "."]:
        c.case(f"from-layout -o {out}", ["scenario", "from-layout", "layout.csv", "--config", "plant.toml", "-o", out],
               inputs={"layout.csv": base["layout"], "plant.toml": base["toml"]}, outputs=["{d}/" + out])


def plant_case(c: Campaign, base, name, layout: bytes, toml: bytes, sun=("10", "40")):
    def then_field(d):
        c.case(f"{name} -> field", ["field", "--scenario", str(d / "x.h5"), "--json", "f.json", *FIELD,
                                    "--sun-azimuth", sun[0], "--sun-elevation", sun[1]],
               inputs={}, outputs=["{d}/f.json"])

    c.case(name, ["scenario", "from-layout", "layout.csv", "--config", "plant.toml", "-o", "x.h5"],
           inputs={"layout.csv": layout, "plant.toml": toml}, outputs=["{d}/x.h5"], followup=then_field)


def toml_cases(c: Campaign, base):
    layout = base["layout"].read_bytes()
    for section, key in TOML_KEYS:
        for value in BAD_TOML_VALUES:
            text = _set_toml(PLANT_TOML, section, key, value)
            plant_case(c, base, f"toml [{section}.{key}] = {value}", layout, text.encode())
    for name, (old, new) in SPECIAL_TOMLS.items():
        plant_case(c, base, f"toml {name}", layout, PLANT_TOML.replace(old, new).encode())
    for name, data in {"binary": bytes(range(256)) * 4, "empty": b"", "nul": b"[site]\x00\n", "latin1": "[é]".encode(
            "latin-1"), "deep": b"a=" + b"[" * 5000 + b"]" * 5000}.items():
        plant_case(c, base, f"toml {name}", layout, data)


def _set_toml(text: str, section: str, key: str, value: str) -> str:
    lines, out, current, done = text.splitlines(), [], None, False
    for line in lines:
        if line.startswith("["):
            if current == section and not done:
                out.append(f"{key} = {value}")
                done = True
            current = line.strip("[]")
        elif current == section and line.split("=")[0].strip() == key:
            line, done = f"{key} = {value}", True
        out.append(line)
    if not done:
        out.append(f"{key} = {value}") if current == section else out.extend([f"[{section}]", f"{key} = {value}"])
    return "\n".join(out) + "\n"


def layout_cases(c: Campaign, base, rng: random.Random, n_random: int):
    toml = PLANT_TOML.encode()
    xyz = base["xyz"]
    ids = [f"h{i}" for i in range(len(xyz))]
    special = {
        "nul-id": layout_text(xyz, ["h\x00"] + ids[1:]),
        "two-on-one-pivot": layout_text(xyz + [xyz[0]], ids + ["dup"]),
        "overlapping": layout_text(xyz + [(xyz[0][0] + 0.5, xyz[0][1], 0.0)], ids + ["near"]),
        "far-1e7": layout_text(xyz + [(0.0, 1e7, 0.0)], ids + ["far"]),
        "far-1e300": layout_text(xyz + [(0.0, 1e300, 0.0)], ids + ["far"]),
        "in-tower": layout_text(xyz + [(0.0, 0.0, 0.0)], ids + ["tower"]),
        "above-receiver": layout_text(xyz + [(0.0, 40.0, 500.0)], ids + ["high"]),
        "underground": layout_text(xyz + [(0.0, 40.0, -500.0)], ids + ["deep"]),
        "one": layout_text(xyz[:1], ids[:1]),
        "empty-id": layout_text(xyz, [""] + ids[1:]),
        "header-only": "x,y,z\n",
        "binary": bytes(range(256)).decode("latin-1"),
    }
    for name, text in special.items():
        plant_case(c, base, f"layout {name}", text.encode("utf-8", "surrogatepass"), toml)
    plant_case(c, base, "layout huge (300000 heliostats)", _huge_layout(300_000), toml)
    text = base["layout"].read_bytes()
    chunks = [b"\x00", b"\xff", b",", b"\n", b"nan", b"inf", b"-", b"1e308", b"\"", b"#", b"x", b"9" * 400]
    for k in range(n_random):
        data = bytearray(text)
        for _ in range(rng.randint(1, 4)):
            i = rng.randrange(len(data))
            if rng.random() < 0.5:
                data[i:i + rng.randint(0, 3)] = rng.choice(chunks)
            else:
                del data[i:i + rng.randint(1, 5)]
        plant_case(c, base, f"layout random damage #{k}", bytes(data), toml)


def _huge_layout(n: int) -> bytes:
    side = int(math.ceil(math.sqrt(n)))
    i = np.arange(n)
    x, y = (i % side) * 5.0 - side * 2.5, 40.0 + (i // side) * 5.0
    return ("x,y,z\n" + "\n".join(f"{a:.1f},{b:.1f},0" for a, b in zip(x, y)) + "\n").encode()


def scenario_cases(c: Campaign, base, rng: random.Random, limit: int):
    """One HDF5 object of the (aimed) scenario damaged, then ``field`` (with ``--aim scenario`` on aimed ones)."""
    for src, aim in ((base["scenario"], "equator"), (base["aimed"], "scenario")):
        names = []
        with h5py.File(src, "r") as h5:
            h5.visititems(lambda n, o: names.append((n, isinstance(o, h5py.Dataset))))
            attrs = [(n, a) for n, _ in names for a in h5[n].attrs if a not in ("type",)]
        mutations = []
        for n, is_data in names:
            if not is_data:
                mutations.append((n, None, "delete"))
                continue
            for how in ("nan", "inf", "zero", "huge", "truncate", "delete", "one-nan", "scalar", "string"):
                mutations.append((n, None, how))
        for n, a in attrs:
            for how in ("nan", "zero", "negative", "string"):
                mutations.append((n, a, how))
        rng.shuffle(mutations)
        for n, a, how in mutations[:limit]:
            data = _damaged(src, n, a, how)
            if data is None:
                continue
            field_case(c, base, f"scenario {Path(src).name} {n}{'@' + a if a else ''} {how}",
                       ["--sun-azimuth", "10", "--sun-elevation", "40", "--aim", aim], src=data)
            if aim == "scenario" and "learned" in n:
                c.case(f"aimpoints on {Path(src).name} {n} {how}",
                       ["aimpoints", "--scenario", "p.h5", "-o", "o.h5", "--json", "o.json", *AIM, "--sun-azimuth",
                        "10", "--sun-elevation", "40", "--peak-limit", "1e6"],
                       inputs={"p.h5": data}, outputs=["{d}/o.h5", "{d}/o.json"])


def _damaged(src: Path, name: str, attr: str | None, how: str) -> bytes | None:
    with tempfile.TemporaryDirectory() as tmp:
        dst = Path(tmp) / "x.h5"
        shutil.copyfile(src, dst)
        with h5py.File(dst, "r+") as h5:
            obj = h5[name]
            if attr is not None:
                v = obj.attrs[attr]
                if isinstance(v, (bytes, str)) and how != "string":
                    return None
                obj.attrs[attr] = {"nan": np.nan, "zero": 0.0, "negative": -1.0, "string": "x"}[how]
            elif how == "delete":
                del h5[name]
            else:
                data = obj[()]
                if not isinstance(data, np.ndarray) or data.dtype.kind not in "biuf":
                    if how != "delete":
                        return None
                attrs = dict(obj.attrs)
                arr = np.asarray(data, dtype=np.float64)
                if how == "nan":
                    arr = np.full_like(arr, np.nan)
                elif how == "inf":
                    arr = np.full_like(arr, np.inf)
                elif how == "zero":
                    arr = np.zeros_like(arr)
                elif how == "huge":
                    arr = np.full_like(arr, 1e300)
                elif how == "truncate":
                    arr = arr.reshape(-1)[:-1] if arr.size else arr
                elif how == "one-nan":
                    if arr.size == 0:
                        return None
                    arr = arr.copy()
                    arr.reshape(-1)[0] = np.nan
                elif how == "scalar":
                    arr = np.float64(1.0)
                del h5[name]
                if how == "string":
                    h5[name] = "x"
                else:
                    h5[name] = arr.astype(data.dtype) if data.dtype.kind == "f" or how in ("zero",) else arr
                for k, v in attrs.items():
                    h5[name].attrs[k] = v
        return dst.read_bytes()


def fifo_cases(c: Campaign, base):
    sun = ["--sun-azimuth", "10", "--sun-elevation", "40"]
    c.case("fifo layout", ["scenario", "from-layout", "layout.csv", "--config", "plant.toml", "-o", "x.h5"],
           inputs={"layout.csv": "fifo", "plant.toml": base["toml"]}, outputs=["{d}/x.h5"], fifo="layout.csv",
           timeout=20)
    c.case("fifo toml", ["scenario", "from-layout", "layout.csv", "--config", "plant.toml", "-o", "x.h5"],
           inputs={"layout.csv": base["layout"], "plant.toml": "fifo"}, outputs=["{d}/x.h5"], fifo="plant.toml",
           timeout=20)
    c.case("fifo scenario", ["field", "--scenario", "p.h5", "--json", "f.json", *FIELD, *sun],
           inputs={"p.h5": "fifo"}, outputs=["{d}/f.json"], fifo="p.h5", timeout=20)
    c.case("fifo target", ["aimpoints", "--scenario", "p.h5", "-o", "o.h5", "--json", "o.json", *AIM, *sun,
                           "--peak-limit", "1e6", "--target", "t.csv"],
           inputs={"p.h5": base["scenario"], "t.csv": "fifo"}, outputs=["{d}/o.h5", "{d}/o.json"], fifo="t.csv",
           timeout=20)


def subprocess_cases(c: Campaign, base):
    sun = ["--sun-azimuth", "10", "--sun-elevation", "40"]
    c.case("field --nproc 7 > 6 heliostats", ["field", "--scenario", "p.h5", "--json", "f.json", *FIELD, *sun,
                                              "--nproc", "7"],
           inputs={"p.h5": base["scenario"]}, outputs=["{d}/f.json"], subprocess_=True, timeout=300)
    c.case("aimpoints --nproc 9 > 6 heliostats", ["aimpoints", "--scenario", "p.h5", "-o", "o.h5", "--json", "o.json",
                                                  *AIM, *sun, "--peak-limit", "1e6", "--nproc", "9"],
           inputs={"p.h5": base["scenario"]}, outputs=["{d}/o.h5", "{d}/o.json"], subprocess_=True, timeout=300)
    for name, argv, outs in [
        ("SIGTERM field --nproc 2", ["field", "--scenario", "p.h5", "--json", "f.json", "--resolution", "8x4", *sun,
                                     "--nproc", "2", "--integrator", "mc"], ["{d}/f.json"]),
        ("SIGTERM aimpoints --nproc 2", ["aimpoints", "--scenario", "p.h5", "-o", "o.h5", "--json", "o.json",
                                         "--resolution", "8x4", "--iterations", "100000", "--no-baselines", *sun,
                                         "--peak-limit", "1e6", "--nproc", "2"], ["{d}/o.h5", "{d}/o.json"])]:
        sigterm_case(c, base, name, argv, outs)


def children(pid: int) -> list:
    try:
        out = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True).stdout
    except OSError:
        return []
    return [int(x) for x in out.split()]


def sigterm_case(c: Campaign, base, name, argv, outs):
    """SIGTERM once the workers run; the command must end, with its workers, within 5 s."""
    c.n += 1
    d = c.root / f"c{c.n:04d}"
    d.mkdir()
    shutil.copyfile(base["scenario"], d / "p.h5")
    before, efiles = snapshot(d), errorfiles()
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "heliotwin", *argv], cwd=d, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    t_end = time.time() + 240
    workers = []
    while time.time() < t_end and proc.poll() is None:  # spawned workers: a resource tracker and two ranks
        workers = [w for k in children(proc.pid) for w in [k, *children(k)]]
        if len(workers) >= 3:
            time.sleep(3.0)
            break
        time.sleep(0.2)
    workers = [w for k in children(proc.pid) for w in [k, *children(k)]]
    proc.send_signal(signal.SIGTERM)
    t0 = time.time()
    try:
        out, err = proc.communicate(timeout=30)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        proc.kill()
        for w in workers:  # orphaned workers hold the command's pipes open
            with contextlib.suppress(OSError):
                os.kill(w, signal.SIGKILL)
        out, err = proc.communicate()
        code = "hang"
    seconds = time.time() - t0
    deadline = time.time() + 5.0  # the workers end with the command, within 5 s
    while time.time() < deadline and any(_not_zombie(w) for w in workers):
        time.sleep(0.1)
    alive = [w for w in workers if _not_zombie(w)]
    print(f"  {name}: exit {code} {seconds:.1f} s after SIGTERM; workers alive 5 s later: {len(alive)}", flush=True)
    if code != "hang" and (seconds > 5.0 or alive):
        err += f"\n(ended after {seconds:.1f} s; workers alive: {alive})"
        code = "hang"
    for w in alive:
        with contextlib.suppress(OSError):
            os.kill(w, signal.SIGKILL)
    c.judge(name, argv, code, out, err, d, before, outs, efiles, seconds)


def _not_zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=1000, help="about how many cases (default %(default)s)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-subprocess", action="store_true", help="skip the subprocess cases (nproc, SIGTERM)")
    ap.add_argument("--show", type=int, default=25, help="bad cases to list (default %(default)s)")
    args = ap.parse_args(argv)

    rng = random.Random(args.seed)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fuzz-field-") as tmp:
        root = Path(tmp)
        base = build_base(root)
        c = Campaign(root, args.show)
        argument_cases(c, base)
        output_cases(c, base)
        fifo_cases(c, base)
        toml_cases(c, base)
        fixed = c.counts["cases"]
        print(f"{fixed} argument, output, FIFO and TOML cases: {time.perf_counter() - t0:.0f} s", flush=True)
        room = max(0, args.cases - fixed - 420)
        layout_cases(c, base, rng, n_random=max(20, room // 3))
        scenario_cases(c, base, rng, limit=max(60, (args.cases - c.counts["cases"]) // 2))
        if not args.no_subprocess:
            subprocess_cases(c, base)
    return c.report(f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    sys.exit(main())
