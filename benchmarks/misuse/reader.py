"""Misuse cases of the PAINT reader (issue 41 items 2, 4, 6, 7, 9 and the reader parts of 11): odd files in the
plant's folder, another plant's folder, the record index fooled by a restored rewrite or a forged segment, a full
``$TMPDIR`` under the read-ahead helper, the folder listed once per heliostat, a missing metadata CSV and a record
under the wrong heliostat. Each verdict is clean only when the fixed behaviour is seen."""
from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from fuzz_daily import SRC, Case, Verdict, heliotwin

META = Path("metadata") / "calibration-metadata.csv"


def _copy(ws, folder: Path, which: str = "base") -> Path:
    dst = folder / which
    shutil.copytree(ws.small[which], dst, symlinks=True)
    return dst


def _heliostats(paint: Path) -> list:
    return sorted(p.name for p in paint.iterdir() if p.is_dir() and len(p.name) == 4 and p.name[2:].isdigit())


def _update(ws, folder: Path, paint: Path, *extra, timeout: float = 60.0):
    return heliotwin("update", "--scenario", ws.small["cal"], "--paint", paint, "-o", folder / "x.h5", "--json",
                     folder / "x.json", *extra, cwd=folder, timeout=timeout)


def _dropped(folder: Path) -> dict:
    try:
        counts = json.loads((folder / "x.json").read_text()).get("counts", {})
    except (OSError, ValueError):
        return {}
    return counts.get("dropped_by_reason", {})


def _odd_record(make, want: str):
    """A record file made odd by ``make(path)``: ``update`` ends (no hang, no GBs) and drops it naming why."""
    def run(ws, folder):
        paint = _copy(ws, folder)
        odd = paint / _heliostats(paint)[0] / "Calibration" / "999990-calibration-properties.json"
        make(odd)
        r = _update(ws, folder, paint, timeout=60)
        if r.timed_out:
            return Verdict(False, "update hung on the odd record file (killed after 60 s)")
        reasons = _dropped(folder)
        ok = r.code == 0 and any(want in k for k in reasons)
        return Verdict(ok, f"exit {r.code}, dropped {reasons or 'nothing'}; {r.err.strip()[-160:]}")
    return run


def _odd_folder_file(where: str):
    """A folder file (metadata CSV, tower, properties) that is a FIFO: a one-line error naming it, no hang."""
    def run(ws, folder):
        paint = _copy(ws, folder)
        if where == "metadata":
            path = paint / META
        elif where == "tower":
            path = next(paint.glob("*tower-measurements.json"))
        else:
            hid = _heliostats(paint)[0]
            path = paint / hid / "Properties" / f"{hid}-heliostat-properties.json"
        path.unlink()
        os.mkfifo(path)
        r = _update(ws, folder, paint, timeout=60)
        if r.timed_out:
            return Verdict(False, f"update blocked on the FIFO {path.name} (killed after 60 s)")
        ok = r.one_line_error and path.name in r.err and "FIFO" in r.err and not (folder / "x.h5").exists()
        return Verdict(ok, f"exit {r.code}: {r.err.strip()[-200:]}")
    return run


def _rename_heliostats(src: Path, dst: Path, new_ids: list) -> Path:
    """``src`` copied to ``dst`` with its heliostats renamed to ``new_ids``: another plant whose ids match."""
    shutil.copytree(src, dst)
    names = dict(zip(_heliostats(dst), new_ids))
    for o, n in names.items():
        os.rename(dst / o, dst / f"tmp-{n}")
    for o, n in names.items():
        os.rename(dst / f"tmp-{n}", dst / n)
        os.rename(dst / n / "Properties" / f"{o}-heliostat-properties.json",
                  dst / n / "Properties" / f"{n}-heliostat-properties.json")
    for name in ("calibration-metadata.csv", "calibration-weather.csv"):
        path = dst / "metadata" / name
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            fields, rows = reader.fieldnames, list(reader)
        for row in rows:
            row["HeliostatId"] = names.get(row["HeliostatId"], row["HeliostatId"])
        with open(path, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fields)
            writer.writeheader()
            writer.writerows(rows)
    return dst


def another_plants_folder(ws, folder):
    """``simulate --seed 2`` (another layout), its heliostats named as the calibrated plant's: refused in one line
    naming a Properties file (before: 119 records assimilated, step alarms, exit 0)."""
    r = heliotwin("simulate", "--heliostats", 12, "--years", 1, "--seed", 2, "--out", folder / "seed2", cwd=folder,
                  timeout=300)
    if r.code != 0:
        return Verdict(False, f"simulate failed: {r.err.strip()[-200:]}")
    other = _rename_heliostats(folder / "seed2", folder / "other", _heliostats(ws.small["base"]))
    r = _update(ws, folder, other)
    ok = (r.one_line_error and "another plant's folder" in r.err and "-heliostat-properties.json" in r.err
          and not (folder / "x.h5").exists())
    return Verdict(ok, f"exit {r.code}: {r.err.strip()[-220:] or r.out.strip()[:160]}")


def moved_seen_record(ws, folder):
    """A record the plant saw under one heliostat now under another (left out by id before): refused naming it."""
    paint = _copy(ws, folder, "old")
    a, b = _heliostats(paint)[:2]
    rec = sorted((paint / a / "Calibration").glob("*-calibration-properties.json"))[0]
    shutil.move(rec, paint / b / "Calibration" / rec.name)
    r = _update(ws, folder, paint)
    ok = r.one_line_error and rec.name in r.err and f"under {a}" in r.err
    return Verdict(ok, f"exit {r.code}: {r.err.strip()[-200:] or r.out.strip()[:160]}")


def _records_of(folder: Path) -> list:
    return sorted(folder.glob("*/Calibration/*-calibration-properties.json"))


def restored_rewrite(ws, folder):
    """A new record rewritten with the same size and its mtime restored (``touch -d``), read with the record index:
    the indexed run agrees with the run without it (before: served stale)."""
    paint = _copy(ws, folder)
    env = {"HELIOTWIN_CACHE": "1", "HELIOTWIN_CACHE_DIR": str(folder / "cache")}
    first = heliotwin("update", "--scenario", ws.small["cal"], "--paint", paint, "-o", folder / "a.h5", cwd=folder,
                      env=env)
    if first.code != 0:
        return Verdict(False, f"first update failed: {first.err.strip()[-200:]}")
    # the latest record of the folder (not seen by the plant): a step of 2,000 motor steps in its axis 1
    meta = list(csv.DictReader(open(paint / META, newline="")))
    last = meta[-1]
    path = paint / last["HeliostatId"] / "Calibration" / f"{last['Id']}-calibration-properties.json"
    st = path.stat()
    text = path.read_text()
    data = json.loads(text)
    steps = int(data["motor_position"]["axis_1_motor_position"])
    other = steps + 2000 if len(str(steps + 2000)) == len(str(steps)) else steps - 2000
    new = text.replace(f": {steps},", f": {other},", 1)
    if len(new) != len(text) or new == text:
        return Verdict(False, "case could not rewrite the record with the same size")
    path.write_text(new)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    indexed = heliotwin("update", "--scenario", ws.small["cal"], "--paint", paint, "-o", folder / "b.h5", "--json",
                        folder / "b.json", cwd=folder, env=env)
    plain = heliotwin("update", "--scenario", ws.small["cal"], "--paint", paint, "-o", folder / "c.h5", "--json",
                      folder / "c.json", cwd=folder, env={"HELIOTWIN_CACHE": "0"})
    try:
        b, c = (json.loads((folder / n).read_text()) for n in ("b.json", "c.json"))
    except (OSError, ValueError):
        return Verdict(False, f"exit {indexed.code}/{plain.code}: {indexed.err.strip()[-160:]}")
    same = b.get("alarms") == c.get("alarms") and b.get("overall") == c.get("overall")
    return Verdict(same, f"indexed: {len(b.get('alarms', []))} alarm(s), {b['overall']}; without index: "
                         f"{len(c.get('alarms', []))} alarm(s), {c['overall']}")


def forged_index_segment(ws, folder):
    """An index segment whose record ids are stored as text: ignored (every record still has its time)."""
    code = r"""
import os, sys, numpy as np
from heliotwin.io import paint as P, record_index as RI
root = sys.argv[1]
P.load_paint(root, cache=True)
entries, segments = RI.read_entries(root)
forged = dict(entries); forged["record_id"] = entries["record_id"].astype("U")
for s in segments: os.remove(s)
np.savez(os.path.join(RI.index_dir(root), "seg-00000000000000000001-1-forged.npz"), version=np.array(RI.INDEX_VERSION),
         **forged)
ds = P.load_paint(root, cache=True)
plain = P.load_paint(root, cache=False)
print(int(ds.records.time.isnan().sum()), int(plain.records.time.isnan().sum()), len(ds.records), len(plain.records))
"""
    paint = _copy(ws, folder)
    for f in _records_of(paint):  # settled files: the index takes them
        os.utime(f, (1.6e9, 1.6e9))
    env = {**os.environ, "PYTHONPATH": str(SRC), "HELIOTWIN_CACHE_DIR": str(folder / "cache")}
    p = subprocess.run([sys.executable, "-c", code, str(paint)], capture_output=True, text=True, env=env, timeout=120)
    try:
        a, b, n, m = map(int, p.stdout.split())
    except ValueError:
        return Verdict(False, f"exit {p.returncode}: {p.stderr.strip()[-200:]}")
    return Verdict(p.returncode == 0 and a == b and n == m, f"without a time: indexed {a}, plain {b}; records {n}/{m}")


def full_tmpdir(ws, folder):
    """The read-ahead helper's list file failing ENOSPC (a full ``$TMPDIR``): ``update`` is not stopped (before:
    "[Errno 28] No space left on device"); the helper is forced to run on this small folder."""
    code = r"""
import errno, runpy, sys, tempfile
real = tempfile.mkstemp
def full(*a, **k):  # the read-ahead's list file only: the outputs' staging must still work
    if str(k.get("prefix", a[1] if len(a) > 1 else "")).startswith("heliotwin-read-ahead"):
        raise OSError(errno.ENOSPC, "No space left on device")
    return real(*a, **k)
tempfile.mkstemp = full
from heliotwin.io import readahead
readahead.READ_AHEAD_MIN_FILES = 1
from heliotwin.io import paint
import functools
orig = paint.read_ahead
paint.read_ahead = functools.partial(orig, min_files=1)
sys.argv = ["heliotwin"] + sys.argv[1:]
runpy.run_module("heliotwin", run_name="__main__")
"""
    paint = _copy(ws, folder)
    env = {**os.environ, "PYTHONPATH": str(SRC), "HELIOTWIN_READ_AHEAD": "1", "OMP_NUM_THREADS": "1"}
    p = subprocess.run([sys.executable, "-c", code, "update", "--scenario", str(ws.small["cal"]), "--paint", str(paint),
                        "-o", str(folder / "x.h5")], capture_output=True, text=True, env=env, timeout=120, cwd=folder)
    ok = p.returncode == 0 and (folder / "x.h5").exists()
    return Verdict(ok, f"exit {p.returncode}: {(p.stderr.strip() or p.stdout.strip())[-200:]}")


def listing_once(ws, folder):
    """``report --paint``'s reading (``load_records`` on a scenario) lists the folder a fixed number of times, not
    once per heliostat (before: 1 + 12 at 12 heliostats, 10,001 at 10,000)."""
    code = r"""
import os, sys
from heliotwin.io import paint as P, scenario as S
calls = [0]
real = os.listdir
def counting(path="."):
    if os.path.abspath(path) == os.path.abspath(sys.argv[1]):
        calls[0] += 1
    return real(path)
os.listdir = counting
ds, sc = S.load_records(sys.argv[1], sys.argv[2])
print(calls[0], len(sc.plant.field.ids))
"""
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    p = subprocess.run([sys.executable, "-c", code, str(ws.small["base"]), str(ws.small["cal"])], capture_output=True,
                       text=True, env=env, timeout=120)
    try:
        calls, n = map(int, p.stdout.split())
    except ValueError:
        return Verdict(False, f"exit {p.returncode}: {p.stderr.strip()[-200:]}")
    return Verdict(calls <= 2, f"folder listed {calls} time(s) for {n} heliostats")


def missing_metadata(ws, folder):
    """No ``metadata/calibration-metadata.csv``: ``update`` refuses in one line naming it (before: exit 0)."""
    paint = _copy(ws, folder)
    (paint / META).unlink()
    r = _update(ws, folder, paint)
    ok = r.one_line_error and "calibration-metadata.csv" in r.err and not (folder / "x.h5").exists()
    return Verdict(ok, f"exit {r.code}: {r.err.strip()[-200:] or r.out.strip()[:160]}")


def report_missing_metadata(ws, folder):
    """``report --paint`` without the metadata CSV (the records' times are what ``--paint`` is for): one line naming
    it, no page (before: exit 0, "0 records planned for -")."""
    paint = _copy(ws, folder)
    (paint / META).unlink()
    r = heliotwin("report", "--scenario", ws.small["cal"], "--paint", paint, "-o", folder / "r.html", "--no-flux",
                  cwd=folder, timeout=120)
    ok = r.one_line_error and "calibration-metadata.csv" in r.err and not (folder / "r.html").exists()
    return Verdict(ok, f"exit {r.code}: {r.err.strip()[-200:] or r.out.strip()[:160]}")


def wrong_heliostat(ws, folder):
    """A new record whose metadata row names another heliostat than its folder: dropped, named (before: taken)."""
    paint = _copy(ws, folder)
    with open(paint / META, newline="") as fh:
        reader = csv.DictReader(fh)
        fields, rows = reader.fieldnames, list(reader)
    ids = _heliostats(paint)
    rows[-1]["HeliostatId"] = next(h for h in ids if h != rows[-1]["HeliostatId"])
    with open(paint / META, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fields)
        writer.writeheader()
        writer.writerows(rows)
    r = _update(ws, folder, paint)
    reasons = _dropped(folder)
    ok = r.code == 0 and any(k.startswith("HeliostatId") for k in reasons)
    return Verdict(ok, f"exit {r.code}, dropped {reasons or 'nothing'}")


def _symlink_to(target):
    return lambda p: os.symlink(target, p)


def _huge(p):
    with open(p, "wb") as fh:
        fh.truncate(5 * 2**30)


CASES = [
    Case("record-fifo", "high", "a FIFO record file is dropped, named (no hang under the lock)",
         _odd_record(os.mkfifo, "not a regular file")),
    Case("record-symlink-dev-zero", "high", "a record symlinked to /dev/zero is dropped, named (no 4 GB read)",
         _odd_record(_symlink_to("/dev/zero"), "not a regular file")),
    Case("record-huge", "high", "a 5 GiB (sparse) record file is dropped as too large",
         _odd_record(_huge, "too large")),
    Case("record-dangling-symlink", "medium", "a dangling symlink as a record is dropped, named",
         _odd_record(_symlink_to("/nonexistent/record.json"), "not a regular file")),
    Case("metadata-fifo", "high", "a FIFO metadata CSV: one-line error naming it, no hang",
         _odd_folder_file("metadata")),
    Case("tower-fifo", "high", "a FIFO tower file: one-line error naming it", _odd_folder_file("tower")),
    Case("properties-fifo", "high", "a FIFO properties file: one-line error naming it",
         _odd_folder_file("properties")),
    Case("another-plants-folder", "high", "another plant's folder (ids matching): refused naming heliostat and file",
         another_plants_folder),
    Case("seen-record-under-another-heliostat", "high", "a seen record moved to another heliostat: refused naming it",
         moved_seen_record),
    Case("index-restored-rewrite", "medium", "a same-size rewrite with restored mtime is re-read (index = no index)",
         restored_rewrite),
    Case("index-forged-segment", "medium", "a segment with record ids as text is ignored", forged_index_segment),
    Case("readahead-full-tmpdir", "medium", "ENOSPC in tempfile does not stop update", full_tmpdir),
    Case("report-paint-listing", "medium", "load_records lists the folder a fixed number of times", listing_once),
    Case("missing-metadata-csv", "medium", "update without the metadata CSV: one-line error naming it",
         missing_metadata),
    Case("report-missing-metadata-csv", "medium", "report --paint without the metadata CSV: one-line error naming it",
         report_missing_metadata),
    Case("heliostat-id-contradicts-folder", "medium", "a record whose HeliostatId is another: dropped, named",
         wrong_heliostat),
]
