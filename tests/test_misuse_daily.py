"""Misuse of the daily loop (issue 30, "safe to schedule"): zone-named or malformed dates, a record dated in the
future, an absurd sun azimuth, a full disk while writing the plant, and two commands updating one plant.

Each case ends in a clear refusal naming the file and field, a counted and named skip, or correct behaviour."""
from __future__ import annotations

import csv
import json
import math
import multiprocessing
import os
import signal
import subprocess
import sys
from datetime import datetime, timezone

import pytest
from helpers.cli import assert_one_line_error

from heliotwin.errors import HeliotwinError, InputFileError
from heliotwin.io.lock import FileStamp, check_unchanged, file_stamp, lock_path, plant_lock
from heliotwin.io.paint import (
    find_tower_file,
    list_heliostats,
    load_paint,
    read_calibration_record,
    read_metadata,
    read_tower,
)
from heliotwin.io.records import build_record_table, parse_time, raw_from_records
from heliotwin.simulate import SimulationSettings, simulate_plant, write_paint_folder

META = os.path.join("metadata", "calibration-metadata.csv")


@pytest.fixture(scope="module")
def sim():
    """3 heliostats, a few weeks of records in 2021 (simulated, deterministic)."""
    return simulate_plant(SimulationSettings(heliostats=3, seed=30, years=0.1, records_per_month=8))


@pytest.fixture()
def folder(sim, tmp_path):
    """A fresh PAINT folder of ``sim`` that the test may corrupt."""
    return write_paint_folder(sim, tmp_path / "plant")


def _rows(folder):
    with open(os.path.join(folder, META), newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        return reader.fieldnames, list(reader)


def _set_datetime(folder, index: int, text: str) -> int:
    """Write ``text`` as the DateTime of the metadata CSV's row ``index``; return that row's record id."""
    names, rows = _rows(folder)
    rows[index]["DateTime"] = text
    with open(os.path.join(folder, META), "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, names)
        writer.writeheader()
        writer.writerows(rows)
    return int(rows[index]["Id"])


def _record_file(folder, record_id: int) -> str:
    for h in list_heliostats(folder):
        path = os.path.join(folder, h, "Calibration", f"{record_id}-calibration-properties.json")
        if os.path.exists(path):
            return path
    raise AssertionError(f"no file of record {record_id}")


def _edit_record(folder, record_id: int, **fields) -> str:
    path = _record_file(folder, record_id)
    with open(path, encoding="utf-8") as fh:
        data = json.load(fh)
    data.update(fields)
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(data, fh)
    return path


def _raw_one_by_one(folder, paths=None):
    """The folder's records (or those of ``paths``) through the reference reader, with the metadata's times."""
    site, targets = read_tower(find_tower_file(folder))
    times, _ = read_metadata(folder)
    records = []
    for h in list_heliostats(folder):
        calibration = os.path.join(folder, h, "Calibration")
        for name in sorted(os.listdir(calibration)):
            path = os.path.join(calibration, name)
            if name.endswith("-calibration-properties.json") and (paths is None or path in paths):
                records.append(read_calibration_record(path, site, h, known_targets=targets))
                records[-1].datetime = times.get(records[-1].record_id)
    return raw_from_records(records)


def _skip_of(ds, record_id: int) -> dict:
    hits = [s for s in ds.skipped if s["record_id"] == record_id]
    assert len(hits) == 1, ds.skipped
    return hits[0]


# ------------------------------------------------------------------------------------------------ 1. dates
def test_parse_time_accepts_iso_utc_and_refuses_zone_names_and_text():
    t = datetime(2023, 5, 1, 10, tzinfo=timezone.utc).timestamp()
    for text in ("2023-05-01T10:00:00Z", "2023-05-01 10:00:00+00:00", "2023-05-01T12:00:00+02:00",
                 "2023-05-01 10:00:00", "2023-05-01 10:00:00 UTC", "2023-05-01T10:00:00 GMT", " 2023-05-01T10:00 "):
        assert parse_time(text) == t, text
    assert math.isnan(parse_time("")) and math.isnan(parse_time(None)) and math.isnan(parse_time("  "))
    for text, needle in (("2023-05-01 10:00:00 CEST", "CEST"), ("2023-05-01 10:00:00 CET", "CET"),
                         ("yesterday", "ISO 8601"), ("2023-13-01 10:00", "ISO 8601"), ("nan", "ISO 8601"),
                         ("2023-05-01 10:00:00+02:00 UTC", "both")):
        with pytest.raises(ValueError, match=needle):
            parse_time(text)


@pytest.mark.parametrize("text, needle", [("2023-05-01 10:00:00 CEST", "CEST"), ("yesterday", "yesterday")])
def test_a_zone_named_or_malformed_date_names_file_line_and_field(folder, text, needle):
    _set_datetime(folder, 1, text)  # the CSV's line 3
    with pytest.raises(InputFileError) as info:
        read_metadata(folder)
    message = str(info.value)
    assert len(message.splitlines()) == 1
    assert os.path.join(folder, META) in message and "line 3" in message and "DateTime" in message
    assert needle in message
    with pytest.raises(InputFileError, match="DateTime"):  # the whole reader, fast path and cache alike
        load_paint(folder)


def test_an_empty_date_is_a_record_without_time(folder, sim):
    rid = _set_datetime(folder, 0, "")
    ds = load_paint(folder)
    assert len(ds.records) == len(sim.records) and not ds.skipped
    row = ds.records.index_of(rid)
    assert math.isnan(float(ds.records.time[row]))
    assert int(ds.records.time.isnan().sum()) == 1


def test_a_record_object_with_a_zone_named_date_names_its_file(folder):
    """Records built in code (not from the CSV) meet the same rule when they are judged."""
    raw = _raw_one_by_one(folder)
    plant = load_paint(folder, with_records=False).plant
    site, targets = read_tower(find_tower_file(folder))
    path = raw.path[0]
    record = read_calibration_record(path, site, raw.heliostat_ids[int(raw.heliostat_index[0])], targets)
    record.datetime = "2023-05-01 10:00:00 CEST"
    with pytest.raises(InputFileError) as info:
        build_record_table(plant, [record])
    assert str(info.value).startswith(f"{path} [DateTime]: ") and "CEST" in str(info.value)


# ------------------------------------------------------------------------------------------ 2. the future
def test_a_record_dated_2099_is_dropped_with_a_named_reason(folder, sim):
    rid = _set_datetime(folder, 2, "2099-06-01T10:00:00Z")
    ds = load_paint(folder)  # "now" = the time of reading
    assert rid not in ds.records.record_id.tolist()
    assert len(ds.records) == len(sim.records) - 1
    skip = _skip_of(ds, rid)
    assert skip["field"] == "DateTime" and "2099-06-01T10:00:00Z is in the future" in skip["reason"]
    assert skip["path"] == _record_file(folder, rid)
    assert float(ds.records.time.max()) < datetime(2022, 1, 1, tzinfo=timezone.utc).timestamp()


def test_the_reading_time_is_injectable(folder):
    """A record a few hours ahead of the reading time is kept (clock skew); one more than a day ahead is not."""
    plant = load_paint(folder, with_records=False).plant
    raw = _raw_one_by_one(folder)
    last = float(raw.time.max())
    latest = int(raw.record_id[raw.time.argmax()])
    kept, skipped = build_record_table(plant, raw, now=last - 3600.0)
    assert latest in kept.record_id.tolist() and not skipped
    kept, skipped = build_record_table(plant, raw, now=datetime.fromtimestamp(last - 2 * 86400.0, timezone.utc))
    ahead = {int(r) for r, t in zip(raw.record_id, raw.time) if float(t) > last - 86400.0}
    assert latest in ahead and latest not in kept.record_id.tolist()
    assert {s["record_id"] for s in skipped} == ahead
    assert all(s["field"] == "DateTime" and "is in the future" in s["reason"] for s in skipped)
    assert len(kept) + len(skipped) == len(raw)
    ds = load_paint(folder, now=last - 2 * 86400.0)  # the reader passes it on
    assert {s["record_id"] for s in ds.skipped} == ahead and len(ds.records) == len(kept)
    with pytest.raises(HeliotwinError, match="now"):
        build_record_table(plant, raw, now="tomorrow")


# ----------------------------------------------------------------------------------------- 3. sun angles
@pytest.mark.parametrize("azimuth", [1e300, 400.0, -361.0])
def test_an_absurd_sun_azimuth_is_dropped_naming_the_field(folder, sim, azimuth):
    rid = int(sim.records.record_id[1])
    path = _edit_record(folder, rid, sun_azimuth=azimuth)
    ds = load_paint(folder)  # the fast path
    assert rid not in ds.records.record_id.tolist() and len(ds.records) == len(sim.records) - 1
    skip = _skip_of(ds, rid)
    assert skip["field"] == "sun_azimuth" and "sun_azimuth" in skip["reason"] and skip["path"] == path
    # The reference reader (one record at a time) gives the same record the same verdict.
    table, skipped = build_record_table(ds.plant, _raw_one_by_one(folder, [path]))
    assert len(table) == 0 and [(s["record_id"], s["field"]) for s in skipped] == [(rid, "sun_azimuth")]


def test_a_full_turn_of_azimuth_is_still_a_sun(folder, sim):
    rid = int(sim.records.record_id[1])
    _edit_record(folder, rid, sun_azimuth=-360.0)
    ds = load_paint(folder)
    assert rid in ds.records.record_id.tolist() and not ds.skipped


# ------------------------------------------------------------------------------------------ 4. full disk
_UNDER_LIMIT = """
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write gets EFBIG instead of the process being killed
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]), resource.RLIM_INFINITY))
from heliotwin.cli import main
sys.exit(main(sys.argv[2:]))
"""


def test_a_full_disk_leaves_the_plant_untouched_with_one_line(folder, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    plant = out / "plant.h5"
    argv = ["scenario", "from-paint", "--paint", str(folder), "-o", str(plant), "--quiet"]
    first = subprocess.run([sys.executable, "-c", _UNDER_LIMIT, str(2**40), *argv], capture_output=True, text=True,
                           timeout=300)
    assert first.returncode == 0, first.stderr
    before = plant.read_bytes()
    limit = len(before) // 2
    again = subprocess.run([sys.executable, "-c", _UNDER_LIMIT, str(limit), *argv], capture_output=True, text=True,
                           timeout=300)
    assert again.returncode == 2, (again.returncode, again.stderr)  # a user-facing error, not a crash (-11)
    assert_one_line_error(again.returncode, again.stderr, str(plant), "File too large")
    assert "Traceback" not in again.stderr and ".heliotwin-" not in again.stderr
    assert plant.read_bytes() == before
    assert sorted(os.listdir(out)) == ["plant.h5"]  # no temporary file, no staging folder


def test_save_scenario_turns_a_write_error_into_one_line(tmp_path, monkeypatch):
    """ENOSPC from the write itself (no real full disk needed): the existing file and its folder as they were."""
    import builtins

    from heliotwin.field.demo import demo_field_plant
    from heliotwin.io.scenario import load_scenario, save_scenario

    plant, _ = demo_field_plant(4)
    path = tmp_path / "plant.h5"
    save_scenario(plant, path, metadata={"day": 1})
    before = path.read_bytes()
    real_open = builtins.open

    class Full:
        def __init__(self, fh):
            self.fh = fh

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.fh.close()

        def write(self, data):
            raise OSError(28, "No space left on device")

    def full_open(file, mode="r", *args, **kwargs):
        fh = real_open(file, mode, *args, **kwargs)
        return Full(fh) if "w" in mode and os.path.basename(str(file)).startswith(".tmp-") else fh

    monkeypatch.setattr(builtins, "open", full_open)
    with pytest.raises(InputFileError) as info:
        save_scenario(plant, path, metadata={"day": 2})
    monkeypatch.setattr(builtins, "open", real_open)
    assert str(info.value) == f"{path}: cannot write (No space left on device)"
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["plant.h5"]
    assert load_scenario(path).metadata["day"] == 1


# ------------------------------------------------------------------------------------------------- 5. lock
def _hold(path, held, release, result):
    """Child: take the plant lock, say so, hold it until told to release."""
    try:
        with plant_lock(path):
            held.set()
            release.wait(120)
        result.put("released")
    except HeliotwinError as exc:
        result.put(f"refused: {exc}")
        held.set()


def _try(path, result, timeout=None):
    """Child: try to take the plant lock once."""
    try:
        with plant_lock(path, timeout=timeout):
            result.put("acquired")
    except HeliotwinError as exc:
        result.put(f"refused: {exc}")


def test_two_processes_contend_for_one_plant(tmp_path):
    ctx = multiprocessing.get_context("fork")
    path = str(tmp_path / "plant.h5")
    held, release, result = ctx.Event(), ctx.Event(), ctx.Queue()
    holder = ctx.Process(target=_hold, args=(path, held, release, result))
    holder.start()
    try:
        assert held.wait(120)
        # This process, and a third one, are refused at once while the holder updates the plant.
        with pytest.raises(HeliotwinError) as info:
            with plant_lock(path):
                pass
        assert str(info.value).startswith(f"another heliotwin command is updating {path}")
        assert len(str(info.value).splitlines()) == 1
        other = ctx.Process(target=_try, args=(path, result))
        other.start()
        other.join(120)
        assert result.get(timeout=120).startswith("refused: another heliotwin command is updating")
        # One that waits gets the lock once the holder is done.
        release.set()
        with plant_lock(path, timeout=120) as lock:
            assert lock == lock_path(path) and os.path.exists(lock)
        holder.join(120)
        assert result.get(timeout=120) == "released"
    finally:
        release.set()
        holder.join(120)
    # The lock is free again for anyone; the plant file itself was never created or touched.
    waiter = ctx.Process(target=_try, args=(path, result, 5))
    waiter.start()
    waiter.join(120)
    assert result.get(timeout=120) == "acquired" and not os.path.exists(path)


def test_a_killed_holder_frees_the_lock(tmp_path):
    ctx = multiprocessing.get_context("fork")
    path = str(tmp_path / "plant.h5")
    held, release, result = ctx.Event(), ctx.Event(), ctx.Queue()
    holder = ctx.Process(target=_hold, args=(path, held, release, result))
    holder.start()
    assert held.wait(120)
    os.kill(holder.pid, signal.SIGKILL)
    holder.join(120)
    with plant_lock(path):  # the kernel dropped the dead process's lock; the stale .lock file is harmless
        assert os.path.exists(lock_path(path))


def test_a_lock_in_a_missing_folder_names_the_lock_file(tmp_path):
    path = tmp_path / "nowhere" / "plant.h5"
    with pytest.raises(InputFileError, match="plant.h5.lock"):
        with plant_lock(path):
            pass
    with pytest.raises(HeliotwinError, match="timeout"):
        with plant_lock(tmp_path / "plant.h5", timeout=-1):
            pass


def test_a_writer_refuses_a_plant_that_changed_since_it_was_read(tmp_path):
    path = tmp_path / "plant.h5"
    path.write_bytes(b"version 1")
    stamp = file_stamp(path)
    assert stamp.exists and stamp.size == 9
    check_unchanged(path, stamp)  # unchanged: no error
    # replaced by rename (what an atomic writer does), even with the same size and modification time
    other = tmp_path / "other.h5"
    other.write_bytes(b"version 2")
    os.utime(other, ns=(stamp.mtime_ns, stamp.mtime_ns))
    os.replace(other, path)
    with pytest.raises(InputFileError, match="was replaced") as info:
        check_unchanged(path, stamp)
    assert str(info.value).startswith(f"{path}: ") and len(str(info.value).splitlines()) == 1
    stamp = file_stamp(path)
    with open(path, "ab") as fh:  # modified in place
        fh.write(b"+")
    with pytest.raises(InputFileError, match="was modified"):
        check_unchanged(path, stamp)
    stamp = file_stamp(path)
    path.unlink()
    with pytest.raises(InputFileError, match="was removed"):
        check_unchanged(path, stamp)
    missing = file_stamp(path)
    assert missing == FileStamp(False)
    check_unchanged(path, missing)  # still absent: fine (a first write)
    path.write_bytes(b"new")
    with pytest.raises(InputFileError, match="was created"):
        check_unchanged(path, missing)
