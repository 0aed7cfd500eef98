"""Misuse of the PAINT reader (issue 41): odd files in the plant's folder, another plant's folder, a record index
that a restored rewrite or a damaged segment would fool, a full ``$TMPDIR`` under the read-ahead helper, the
folder listed once per heliostat, a missing metadata CSV and a record under the wrong heliostat.

Each case ends in a one-line refusal naming the file, a counted and named drop, or the same records as a
reader without the index."""
from __future__ import annotations

import csv
import errno
import json
import os
import shutil
import subprocess
import tempfile
import threading

import numpy as np
import pytest
import torch
from helpers.cli import assert_one_line_error, run_cli

from heliotwin.errors import InputFileError
from heliotwin.io import paint as P
from heliotwin.io import readahead as RA
from heliotwin.io import record_index as RI
from heliotwin.io import scenario as S
from heliotwin.simulate import SimulationSettings, simulate_plant, write_paint_folder

META = os.path.join("metadata", "calibration-metadata.csv")
OLD_NS = 1_600_000_000 * 10**9  # long before any test runs: not "racily" new for the index


@pytest.fixture(scope="module")
def sim():
    """3 heliostats, a few weeks of records (simulated, deterministic)."""
    return simulate_plant(SimulationSettings(heliostats=3, seed=41, years=0.1, records_per_month=8))


@pytest.fixture()
def folder(sim, tmp_path, monkeypatch):
    """A fresh PAINT folder of ``sim`` (its own record index) that the test may change."""
    monkeypatch.setenv("HELIOTWIN_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("HELIOTWIN_CACHE", raising=False)
    root = write_paint_folder(sim, tmp_path / "plant")
    for where, _, files in os.walk(root):  # settled files: the index takes them (not "racily" new)
        for f in files:
            os.utime(os.path.join(where, f), ns=(OLD_NS, OLD_NS))
    return root


def _records(folder, hid):
    cal = os.path.join(folder, hid, "Calibration")
    return sorted((os.path.join(cal, f) for f in os.listdir(cal) if f.endswith(P.RECORD_SUFFIX)),
                  key=P._record_number)


def _in_thread(fn, timeout=20.0):
    """``fn()`` on a daemon thread: its result or exception, or a failure when it does not end (a hang)."""
    box = {}

    def run():
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box["error"] = exc
    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout)
    assert not t.is_alive(), "the reader blocked"
    if "error" in box:
        raise box["error"]
    return box["value"]


# ------------------------------------------------------------------------------------------ item 2: odd files
@pytest.mark.parametrize("kind", ["fifo", "dev-zero", "huge", "dangling", "directory"])
def test_an_odd_record_file_is_dropped_with_its_reason_and_never_blocks(folder, kind):
    ids = P.list_heliostats(folder)
    cal = os.path.join(folder, ids[0], "Calibration")
    odd = os.path.join(cal, f"999990{P.RECORD_SUFFIX}")
    if kind == "fifo":
        os.mkfifo(odd)
    elif kind == "dev-zero":
        os.symlink("/dev/zero", odd)
    elif kind == "huge":
        with open(odd, "wb") as fh:
            fh.truncate(5 * 2**30)  # sparse: 5 GiB that no reader may pass
    elif kind == "dangling":
        os.symlink(os.path.join(cal, "gone.json"), odd)
    else:
        os.mkdir(odd)
    ds = _in_thread(lambda: P.load_paint(folder, cache=False))
    clean = P.load_paint(folder, cache=False, heliostats=ids)  # the same folder, read again: the same records
    assert len(ds.records) == len(clean.records) > 0
    dropped = [s for s in ds.skipped if s["path"] == odd]
    assert len(dropped) == 1 and dropped[0]["heliostat_id"] == ids[0] and dropped[0]["record_id"] == 999990
    want = {"fifo": "a FIFO", "dev-zero": "a character device", "huge": "too large", "dangling": "dangling",
            "directory": "a directory"}[kind]
    assert want in dropped[0]["reason"]
    assert dropped[0]["field"] == ("size" if kind == "huge" else "file")


def test_a_symlink_to_a_regular_record_is_read_as_the_file(folder, tmp_path):
    hid = P.list_heliostats(folder)[0]
    first = _records(folder, hid)[0]
    store = tmp_path / "store.json"
    shutil.move(first, store)
    os.symlink(store, first)
    ds = P.load_paint(folder, cache=False)
    assert not ds.skipped
    assert P._record_number(first) in ds.records.record_id.tolist()


@pytest.mark.parametrize("which", ["metadata", "tower", "properties"])
def test_a_fifo_for_a_folder_file_is_one_line_naming_it(folder, which):
    if which == "metadata":
        path = os.path.join(folder, META)
    elif which == "tower":
        path = P.find_tower_file(folder)
    else:
        hid = P.list_heliostats(folder)[1]
        path = os.path.join(folder, hid, "Properties", f"{hid}-heliostat-properties.json")
    os.remove(path)
    os.mkfifo(path)
    with pytest.raises(InputFileError) as err:
        _in_thread(lambda: P.load_paint(folder))
    assert str(err.value).startswith(path) and "a FIFO" in str(err.value)
    assert "\n" not in str(err.value)


def test_read_regular_caps_what_it_reads(tmp_path):
    p = tmp_path / "a.json"
    p.write_bytes(b"x" * 100)
    assert P.read_regular(p, 100) == b"x" * 100
    assert P.read_regular(p, 100, start=90) == b"x" * 10
    with pytest.raises(InputFileError, match="too large"):
        P.read_regular(p, 99)
    with pytest.raises(InputFileError, match="a character device"):
        P.read_regular("/dev/zero", 10**6)


# ------------------------------------------------------------------------ item 4: another plant's folder
def _shift_heliostat(folder, hid, metres_north):
    path = os.path.join(folder, hid, "Properties", f"{hid}-heliostat-properties.json")
    data = json.load(open(path))
    data["heliostat_position"][0] += metres_north / 111_195.0  # degrees of latitude
    json.dump(data, open(path, "w"))
    return path


def test_a_folder_whose_heliostat_stands_elsewhere_is_refused_naming_heliostat_and_file(folder):
    plant = P.load_paint(folder, with_records=False).plant
    P.load_paint_on_plant(folder, plant, source="plant.h5")  # its own folder: accepted
    hid = plant.field.ids[1]
    path = _shift_heliostat(folder, hid, 143.0)
    with pytest.raises(InputFileError) as err:
        P.load_paint_on_plant(folder, plant, source="plant.h5")
    msg = str(err.value)
    assert msg.startswith(path) and f"heliostat {hid} is 143." in msg and f"m from plant.h5's {hid}" in msg
    assert "another plant's folder" in msg


def test_a_surveyed_position_within_a_metre_is_the_same_heliostat(folder):
    plant = P.load_paint(folder, with_records=False).plant
    _shift_heliostat(folder, plant.field.ids[0], 0.5)
    assert len(P.load_paint_on_plant(folder, plant).records) > 0


def test_records_with_a_scenario_check_positions_too(folder, tmp_path):
    plant = P.load_paint(folder, with_records=False).plant
    S.save_scenario(plant, tmp_path / "p.h5")
    _shift_heliostat(folder, plant.field.ids[2], 30.0)
    with pytest.raises(InputFileError, match="another plant's folder"):
        S.load_records(folder, str(tmp_path / "p.h5"))


def test_a_record_seen_under_another_heliostat_is_refused(folder):
    plant = P.load_paint(folder, with_records=False).plant
    a, b = plant.field.ids[:2]
    moved = _records(folder, a)[0]
    rid = P._record_number(moved)
    owners = {rid: a}
    dest = os.path.join(folder, b, "Calibration", os.path.basename(moved))
    shutil.move(moved, dest)
    for skip in (None, np.asarray([rid])):  # also when the seen record is left out by id before reading
        with pytest.raises(InputFileError) as err:
            P.load_paint_on_plant(folder, plant, seen_owners=owners, skip_record_ids=skip)
        assert str(err.value).startswith(dest) and f"saw it under {a}" in str(err.value)


def _renamed_copy(src, dst, new_ids):
    """``src`` copied to ``dst`` with its heliostats renamed to ``new_ids`` (another plant whose ids match)."""
    shutil.copytree(src, dst)
    old = P.list_heliostats(dst)
    names = dict(zip(old, new_ids))
    for o, n in names.items():
        os.rename(os.path.join(dst, o), os.path.join(dst, f"tmp-{n}"))
    for o, n in names.items():
        os.rename(os.path.join(dst, f"tmp-{n}"), os.path.join(dst, n))
        os.rename(os.path.join(dst, n, "Properties", f"{o}-heliostat-properties.json"),
                  os.path.join(dst, n, "Properties", f"{n}-heliostat-properties.json"))
    for name in ("calibration-metadata.csv", "calibration-weather.csv"):
        path = os.path.join(dst, "metadata", name)
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


def test_update_refuses_another_plants_folder_by_command_line(folder, tmp_path, capsys):
    """Calibrated on its own folder, a plant refuses a different simulated plant whose heliostat ids match."""
    old = 1_600_000_000
    for root, _, files in os.walk(folder):
        for f in files:
            os.utime(os.path.join(root, f), (old, old))
    cal = tmp_path / "cal.h5"
    code, _, err = run_cli(capsys, "calibrate", "--paint", folder, "--min-records", 5, "--train", 1000000, "-o", cal,
                           "--quiet")
    assert code == 0, err
    other_sim = simulate_plant(SimulationSettings(heliostats=3, seed=42, years=0.1, records_per_month=8))
    other = _renamed_copy(write_paint_folder(other_sim, tmp_path / "other-src"), tmp_path / "other",
                          P.list_heliostats(folder))
    code, _, err = run_cli(capsys, "update", "--scenario", cal, "--paint", other, "-o", tmp_path / "x.h5")
    assert_one_line_error(code, err, "another plant's folder", "-heliostat-properties.json", str(cal))
    assert not (tmp_path / "x.h5").exists()
    code, out, err = run_cli(capsys, "update", "--scenario", cal, "--paint", folder, "-o", tmp_path / "y.h5")
    assert code == 0, err  # its own folder is still accepted


# ---------------------------------------------------------------------------------------- item 6: the index
def _same_size_edit(path) -> tuple[str, float]:
    """The text of ``path`` with its first motor step changed by one, the same length; and the old step."""
    text = open(path).read()
    steps = json.loads(text)["motor_position"]["axis_1_motor_position"]
    other = steps + 1 if len(str(steps + 1)) == len(str(steps)) else steps - 1
    new = text.replace(f": {steps},", f": {other},", 1)
    assert len(new) == len(text) and new != text
    return new, float(steps)


@pytest.mark.parametrize("how", ["rewritten", "replaced"])
def test_a_rewrite_with_restored_size_and_mtime_is_read_again(folder, how):
    """``cp -p`` / ``rsync -a`` / ``touch -d``: new bytes, the same size and mtime (rewritten in place or replaced
    by a new file): the indexed read agrees with the read without the index."""
    P.load_paint(folder, cache=True)  # indexed
    assert RI.read_entries(folder)[1]
    path = _records(folder, P.list_heliostats(folder)[0])[2]
    st = os.stat(path)
    new, steps = _same_size_edit(path)
    target = path if how == "rewritten" else path + ".new"
    with open(target, "w") as fh:
        fh.write(new)
    os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns))
    if how == "replaced":
        os.replace(target, path)
    assert os.stat(path).st_size == st.st_size and os.stat(path).st_mtime_ns == st.st_mtime_ns
    indexed = P.load_paint(folder, cache=True)
    plain = P.load_paint(folder, cache=False)
    rid = P._record_number(path)
    i, j = indexed.records.index_of(rid), plain.records.index_of(rid)
    assert float(plain.records.motor_steps[j, 0]) != steps
    assert torch.equal(indexed.records.motor_steps[i], plain.records.motor_steps[j])
    assert indexed.reading["parsed"] == 1 and indexed.reading["indexed"] == indexed.reading["files"] - 1


def test_an_index_segment_with_record_ids_as_text_is_ignored(folder):
    P.load_paint(folder, cache=True)
    entries, segments = RI.read_entries(folder)
    assert len(segments) == 1 and len(entries["record_id"]) > 0
    forged = dict(entries)
    forged["record_id"] = entries["record_id"].astype("U")  # what trusted would make every record "without a time"
    for path in segments:
        os.remove(path)
    np.savez(os.path.join(RI.index_dir(folder), "seg-00000000000000000001-1-forged.npz"),
             version=np.array(RI.INDEX_VERSION), **forged)
    assert RI.read_entries(folder)[1] == []  # the old reader took it (and every record was "without a time")
    ds = P.load_paint(folder, cache=True)
    plain = P.load_paint(folder, cache=False)
    assert torch.equal(ds.records.record_id, plain.records.record_id)
    assert torch.equal(ds.records.time.nan_to_num(), plain.records.time.nan_to_num())
    assert ds.reading["parsed"] == ds.reading["files"]  # nothing taken from the forged segment
    assert not RI.valid_segment(forged)


@pytest.mark.parametrize("column,value", [("motor_steps", np.nan), ("sun_elevation", np.inf), ("size", -5)])
def test_an_index_segment_with_non_finite_or_negative_values_is_ignored(folder, column, value):
    P.load_paint(folder, cache=True)
    entries, _ = RI.read_entries(folder)
    bad = {k: v.copy() for k, v in entries.items()}
    bad[column][0] = value
    assert RI.valid_segment(entries) and not RI.valid_segment(bad)


# ------------------------------------------------------------------------------- item 7: read-ahead helper
def _paths(tmp_path, n=20):
    out = []
    for i in range(n):
        p = tmp_path / f"{i}.json"
        p.write_text("{}")
        out.append(str(p))
    return out


@pytest.mark.skipif(not hasattr(os, "posix_fadvise"), reason="posix_fadvise is Linux's")
def test_a_full_tmpdir_does_not_touch_the_read_ahead(tmp_path, monkeypatch):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.delenv("HELIOTWIN_READ_AHEAD", raising=False)
    for name in ("mkstemp", "mkdtemp", "NamedTemporaryFile", "TemporaryFile"):
        monkeypatch.setattr(tempfile, name, full)
    with RA.read_ahead(_paths(tmp_path), min_files=1) as running:
        assert running  # no list file: the paths go on the helper's stdin


def test_a_helper_that_cannot_start_is_no_error(tmp_path, monkeypatch):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.delenv("HELIOTWIN_READ_AHEAD", raising=False)
    monkeypatch.setattr(subprocess, "Popen", full)
    monkeypatch.setattr(RA.os, "posix_fadvise", lambda *a: None, raising=False)
    with RA.read_ahead(_paths(tmp_path), min_files=1) as running:
        assert not running
    with pytest.raises(KeyError), RA.read_ahead(_paths(tmp_path), min_files=1):
        raise KeyError("the block's own error still propagates")


@pytest.mark.skipif(not hasattr(os, "posix_fadvise"), reason="posix_fadvise is Linux's")
def test_the_helper_passes_a_fifo_in_the_list(tmp_path, monkeypatch):
    monkeypatch.delenv("HELIOTWIN_READ_AHEAD", raising=False)
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    paths = [str(fifo)] + _paths(tmp_path)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))  # where a list file would go
    os.mkdir(tmp_path / "tmp")
    with RA.read_ahead(paths, min_files=1) as running:
        assert running
        assert [open(p).read() for p in paths[1:]] == ["{}"] * (len(paths) - 1)  # read as without the helper
    assert os.listdir(tmp_path / "tmp") == []  # no list file, nothing left behind


# ----------------------------------------------------------------------------- item 9: one listing per read
def test_records_on_a_scenario_list_the_folder_once(folder, tmp_path, monkeypatch):
    plant = P.load_paint(folder, with_records=False).plant
    S.save_scenario(plant, tmp_path / "p.h5")
    calls = {"list": 0, "listdir": 0}
    real_list, real_listdir = P.list_heliostats, os.listdir

    def counting_list(root):
        calls["list"] += 1
        return real_list(root)

    def counting_listdir(path="."):
        if os.path.abspath(path) == os.path.abspath(folder):
            calls["listdir"] += 1
        return real_listdir(path)
    monkeypatch.setattr(S, "list_heliostats", counting_list)
    monkeypatch.setattr(P, "list_heliostats", counting_list)
    monkeypatch.setattr(os, "listdir", counting_listdir)
    ds, _ = S.load_records(folder, str(tmp_path / "p.h5"))
    assert len(ds.records) > 0 and len(plant.field.ids) == 3
    # once by load_records (which ids are there), once by load_paint (what it reads): not once per heliostat
    assert calls["list"] == 2 and calls["listdir"] == 2


# ----------------------------------------------------------------- item 11: missing metadata, wrong heliostat
def test_a_folder_without_its_metadata_csv_is_refused_for_an_update(folder):
    plant = P.load_paint(folder, with_records=False).plant
    os.remove(os.path.join(folder, META))
    with pytest.raises(InputFileError) as err:
        P.load_paint_on_plant(folder, plant)
    assert str(err.value).startswith(os.path.join(folder, META)) and "missing" in str(err.value)
    assert len(P.load_paint(folder).records) > 0  # a reader that needs no times still reads it (from-paint)


def _set_meta_heliostat(folder, record_id, hid):
    path = os.path.join(folder, META)
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        fields, rows = reader.fieldnames, list(reader)
    for row in rows:
        if int(row["Id"]) == record_id:
            row["HeliostatId"] = hid
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fields)
        writer.writeheader()
        writer.writerows(rows)


@pytest.mark.parametrize("cache", [False, True])
def test_a_record_whose_heliostat_contradicts_its_folder_is_dropped_with_a_reason(folder, cache):
    ids = P.list_heliostats(folder)
    by_row = _records(folder, ids[0])[1]
    _set_meta_heliostat(folder, P._record_number(by_row), ids[1])
    by_file = _records(folder, ids[2])[0]
    data = json.load(open(by_file))
    data["HeliostatId"] = "ZZ99"
    json.dump(data, open(by_file, "w"))
    before = P.load_paint(folder, cache=False, heliostats=[ids[1]])
    for _ in range(2 if cache else 1):  # indexed: the second read takes the entries from the index
        ds = P.load_paint(folder, cache=cache)
    dropped = {s["path"]: s for s in ds.skipped}
    assert set(dropped) == {by_row, by_file}
    assert dropped[by_row]["field"] == dropped[by_file]["field"] == "HeliostatId"
    assert f"names {ids[1]} for record" in dropped[by_row]["reason"] and ids[0] in dropped[by_row]["reason"]
    assert "ZZ99" in dropped[by_file]["reason"]
    rids = ds.records.record_id.tolist()
    assert P._record_number(by_row) not in rids and P._record_number(by_file) not in rids
    assert len(ds.records_of(ids[1])) == len(before.records)  # not moved to the heliostat the row names


def test_report_with_a_folder_without_its_metadata_csv_is_one_line(folder, tmp_path, capsys):
    """``report --paint`` is for the records' times (days since the last record, tomorrow's plan): without the
    metadata CSV it refused nothing and planned nothing (exit 0); now one line naming the CSV, no page written."""
    plant = P.load_paint(folder, with_records=False).plant
    S.save_scenario(plant, tmp_path / "p.h5")
    out = tmp_path / "r.html"
    code, _, err = run_cli(capsys, "report", "--scenario", tmp_path / "p.h5", "--paint", folder, "-o", out,
                           "--no-flux", "--quiet")
    assert code == 0 and out.exists(), err
    out.unlink()
    os.remove(os.path.join(folder, META))
    code, _, err = run_cli(capsys, "report", "--scenario", tmp_path / "p.h5", "--paint", folder, "-o", out,
                           "--no-flux", "--quiet")
    assert_one_line_error(code, err, os.path.join(folder, META), "missing")
    assert not out.exists()
    ds, _ = S.load_records(folder, str(tmp_path / "p.h5"))  # a reader that needs no times still reads the records
    assert len(ds.records) > 0 and bool(ds.records.time.isnan().all())
