"""The incremental PAINT record index: a folder that grows costs its new files; a changed, removed or racily
written file invalidates its own entry only; the index is never trusted over the files."""
from __future__ import annotations

import json
import multiprocessing
import os
import shutil

import numpy as np
import pytest
import torch

from heliotwin.io import paint as P
from heliotwin.io import record_index as RI
from heliotwin.simulate import SimulationSettings, simulate_plant, write_paint_folder

OLD_NS = 1_600_000_000 * 10**9  # file times far from "now": indexable at once (not racy)


def _age(folder):
    """Date every file of the folder back (a real plant's files are older than RACY_NS when read)."""
    for base, _, files in os.walk(folder):
        for f in files:
            os.utime(os.path.join(base, f), ns=(OLD_NS, OLD_NS))


@pytest.fixture()
def folder(tmp_path, monkeypatch):
    monkeypatch.setenv("HELIOTWIN_CACHE_DIR", str(tmp_path / "cache"))
    sim = simulate_plant(SimulationSettings(heliostats=3, seed=4, years=0.3, records_per_month=6))
    out = write_paint_folder(sim, tmp_path / "plant")
    _age(out)
    return out


def _record_files(folder):
    out = []
    for hid in P.list_heliostats(folder):
        cal = os.path.join(folder, hid, "Calibration")
        out += sorted((os.path.join(cal, f) for f in os.listdir(cal) if f.endswith(P.RECORD_SUFFIX)),
                      key=lambda p: P._record_number(p))
    return out


def _same(a, b):
    assert torch.equal(a.record_id, b.record_id) and torch.equal(a.motor_steps, b.motor_steps)
    # geodesy in batches of another size may round the last bit differently (a nanometre is the same spot)
    assert torch.equal(a.focal_spots.isnan(), b.focal_spots.isnan())
    assert torch.allclose(a.focal_spots.nan_to_num(), b.focal_spots.nan_to_num(), rtol=0, atol=1e-9)
    assert torch.equal(a.time.nan_to_num(), b.time.nan_to_num()) and a.path == b.path and a.target == b.target
    assert torch.equal(a.weather.nan_to_num(), b.weather.nan_to_num())


def _reference(folder):
    """The records as the one-file-at-a-time reference reader reads them."""
    ids = P.list_heliostats(folder)
    site, targets = P.read_tower(P.find_tower_file(folder))
    times, weather = P.read_metadata(folder)
    return P._read_one_by_one(P._listing(folder, ids), ids, site, targets, times, weather)


def _raw(folder, stats=None):
    ids = P.list_heliostats(folder)
    site, targets = P.read_tower(P.find_tower_file(folder))
    return P.read_records(folder, ids, site, targets, cache=True, stats=stats)


def _move_out(folder, tmp_path, n):
    """Take the last ``n`` record files (and their metadata rows) out of the folder: the folder "before"."""
    files = sorted(_record_files(folder), key=P._record_number)[-n:]
    keep = tmp_path / "later"
    keep.mkdir()
    moved = []
    for f in files:
        dest = keep / os.path.basename(f)
        shutil.move(f, dest)
        moved.append((f, str(dest)))
    meta = os.path.join(folder, "metadata", "calibration-metadata.csv")
    text = open(meta).read()
    lines = text.splitlines(keepends=True)
    later_ids = {str(P._record_number(f)) for f, _ in moved}
    head = [ln for ln in lines if ln.split(",")[0] not in later_ids]
    tail = [ln for ln in lines[1:] if ln.split(",")[0] in later_ids]
    with open(meta, "w") as fh:
        fh.write("".join(head))
    os.utime(meta, ns=(OLD_NS, OLD_NS))
    return moved, tail


def test_index_reopens_the_same_records_as_the_reference_reader(folder):
    stats = {}
    cold = _raw(folder, stats)
    assert stats["parsed"] == stats["files"] > 0
    warm_stats = {}
    warm = _raw(folder, warm_stats)
    assert warm_stats == {"files": stats["files"], "parsed": 0, "indexed": stats["files"], "skipped": 0,
                          "refused": 0}
    ref = _reference(folder)
    _same(cold, warm)
    assert torch.equal(warm.record_id, ref.record_id) and warm.path == ref.path
    assert torch.allclose(warm.focal_spots.nan_to_num(), ref.focal_spots.nan_to_num(), atol=1e-9)
    assert torch.equal(warm.time.nan_to_num(), ref.time.nan_to_num())


def test_a_grown_folder_parses_only_its_new_files_and_metadata_rows(folder, tmp_path):
    moved, tail = _move_out(folder, tmp_path, 4)
    first = {}
    _raw(folder, first)
    for f, dest in moved:  # a new day arrives: record files and appended metadata rows
        shutil.move(dest, f)
        os.utime(f, ns=(OLD_NS, OLD_NS))
    meta = os.path.join(folder, "metadata", "calibration-metadata.csv")
    with open(meta, "a") as fh:
        fh.write("".join(tail))
    os.utime(meta, ns=(OLD_NS + 10**9, OLD_NS + 10**9))
    stats = {}
    grown = _raw(folder, stats)
    assert stats == {"files": first["files"] + 4, "parsed": 4, "indexed": first["files"], "skipped": 0,
                     "refused": 0}
    ref = _reference(folder)
    assert torch.equal(grown.record_id, ref.record_id)
    assert torch.equal(grown.time.nan_to_num(), ref.time.nan_to_num())  # the appended rows' times arrived
    assert bool(torch.isfinite(grown.time[-4:]).all())


def test_a_changed_record_invalidates_its_own_entry_only(folder):
    _raw(folder)
    path = _record_files(folder)[0]
    data = json.loads(open(path).read())
    data["motor_position"]["axis_1_motor_position"] += 1
    with open(path, "w") as fh:
        json.dump(data, fh)
    os.utime(path, ns=(OLD_NS + 10**9, OLD_NS + 10**9))
    stats = {}
    again = _raw(folder, stats)
    assert stats["parsed"] == 1
    rid = P._record_number(path)
    row = int((again.record_id == rid).nonzero()[0])
    assert again.motor_steps[row, 0] == data["motor_position"]["axis_1_motor_position"]


def test_added_removed_and_racy_files(folder):
    n = len(_raw(folder))
    path = _record_files(folder)[0]
    copy = os.path.join(os.path.dirname(path), "999999-calibration-properties.json")
    shutil.copy(path, copy)  # written just now: racy, parsed but not indexed
    stats = {}
    assert len(_raw(folder, stats)) == n + 1 and stats["parsed"] == 1
    stats = {}
    _raw(folder, stats)
    assert stats["parsed"] == 1  # still racy: a same-size rewrite within the same mtime tick would go unseen
    os.utime(copy, ns=(OLD_NS, OLD_NS))
    _raw(folder)
    stats = {}
    _raw(folder, stats)
    assert stats["parsed"] == 0
    os.remove(copy)
    os.remove(path)
    assert len(_raw(folder)) == n - 1


def test_rewritten_metadata_or_a_new_image(folder):
    raw = _raw(folder)
    rid = int(raw.record_id[0])
    meta = os.path.join(folder, "metadata", "calibration-metadata.csv")
    lines = open(meta).read().splitlines()
    with open(meta, "w") as fh:  # not an append: the stored bytes changed, parsed whole
        fh.write("\n".join(ln for ln in lines if not ln.startswith(f"{rid},")) + "\n")
    png = os.path.join(os.path.dirname(raw.path[0]), f"{rid}-flux.png")
    open(png, "wb").close()
    again = _raw(folder)
    row = int((again.record_id == rid).nonzero()[0])
    assert torch.isnan(again.time[row]) and again.flux_png[row] == png


def test_a_damaged_or_foreign_index_is_never_trusted(folder):
    first = _raw(folder)
    (seg,) = [os.path.join(RI.index_dir(folder), f) for f in os.listdir(RI.index_dir(folder)) if f.startswith("seg-")]
    with open(seg, "wb") as fh:
        fh.write(b"not an index")
    for f in os.listdir(RI.index_dir(folder)):
        if f.startswith("csv-"):
            with open(os.path.join(RI.index_dir(folder), f), "wb") as fh:
                fh.write(b"garbage")
    stats = {}
    _same(first, _raw(folder, stats))
    assert stats["parsed"] == stats["files"]
    # An entry whose key does not match the file (forged motor steps under another size) is ignored.
    entries, _ = RI.read_entries(folder)
    entries["motor_steps"] = entries["motor_steps"] + 7.0
    entries["size"] = entries["size"] + 1
    RI.append_entries(folder, entries)
    _same(first, _raw(folder))


def test_many_segments_are_compacted_and_stale_entries_dropped(folder, monkeypatch):
    monkeypatch.setattr(RI, "MAX_SEGMENTS", 2)
    files = _record_files(folder)
    _raw(folder)
    for k in range(3):  # three rewrites of one file: three segments, two stale entries
        with open(files[k], "a") as fh:
            fh.write(" ")
        os.utime(files[k], ns=(OLD_NS + (k + 1) * 10**9,) * 2)
        _raw(folder)
    segments = [f for f in os.listdir(RI.index_dir(folder)) if f.startswith("seg-")]
    entries, _ = RI.read_entries(folder)
    assert len(segments) <= 2
    assert len(entries["record_id"]) <= len(files) + 1
    _same(_raw(folder), _reference(folder))


def test_records_left_out_by_id_keep_their_index_entries(folder, monkeypatch):
    """An update's read leaves its seen records out by id before they are even stat'ed; a compaction during it
    must not drop their entries (the next whole read would parse the folder again)."""
    monkeypatch.setattr(RI, "MAX_SEGMENTS", 1)
    files = _record_files(folder)
    whole = _raw(folder)
    seen = whole.record_id[:-2].numpy()
    for k in range(2):  # two more segments: the next read compacts
        with open(files[k], "a") as fh:
            fh.write(" ")
        os.utime(files[k], ns=(OLD_NS + (k + 1) * 10**9,) * 2)
        _raw(folder)
    ids = P.list_heliostats(folder)
    site, targets = P.read_tower(P.find_tower_file(folder))
    stats: dict = {}
    some = P.read_records(folder, ids, site, targets, cache=True, stats=stats, skip_record_ids=seen)
    assert some.record_id.tolist() == whole.record_id[-2:].tolist()
    assert stats["skipped"] == len(seen) and stats["parsed"] + stats["indexed"] == 2 and stats["files"] == len(files)
    stats = {}
    again = P.read_records(folder, ids, site, targets, cache=True, stats=stats)
    assert stats["parsed"] == 0 and stats["indexed"] == len(files)
    _same(again, _reference(folder))


def _read_in_process(args):
    folder, cache = args
    os.environ["HELIOTWIN_CACHE_DIR"] = cache
    raw = _raw(folder)
    return raw.record_id.tolist(), raw.motor_steps.tolist()


def test_concurrent_readers_agree_and_leave_a_readable_index(folder, tmp_path):
    cache = os.environ["HELIOTWIN_CACHE_DIR"]
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(2) as pool:
        results = pool.map(_read_in_process, [(folder, cache)] * 4)
    assert all(r == results[0] for r in results)
    entries, segments = RI.read_entries(folder)
    assert segments and len(np.unique(entries["record_id"])) == len(results[0][0])
    assert not [f for f in os.listdir(RI.index_dir(folder)) if f.startswith(".tmp-")]


def test_a_killed_writer_leaves_only_an_ignored_temporary(folder):
    first = _raw(folder)
    junk = os.path.join(RI.index_dir(folder), ".tmp-killed.npz")
    with open(junk, "wb") as fh:
        fh.write(b"half a segm")
    stats = {}
    _same(first, _raw(folder, stats))
    assert stats["parsed"] == 0


def test_large_folders_index_by_default_unless_switched_off(folder, monkeypatch):
    where = RI.index_dir(folder)
    monkeypatch.setenv("HELIOTWIN_CACHE", "0")
    monkeypatch.setattr(P, "CACHE_MIN_RECORDS", 1)
    P.load_paint(folder)
    assert not os.path.exists(where)
    monkeypatch.delenv("HELIOTWIN_CACHE")
    ds = P.load_paint(folder)
    assert os.path.exists(where) and ds.reading["parsed"] == ds.reading["files"]
    shutil.rmtree(where)
    monkeypatch.setattr(P, "CACHE_MIN_RECORDS", 10**9)
    P.load_paint(folder)
    assert not os.path.exists(where)
    monkeypatch.setenv("HELIOTWIN_CACHE", "1")
    P.load_paint(folder)
    assert os.path.exists(where)


def test_one_heliostat_of_a_large_folder_reads_the_metadata_through_the_index(folder, monkeypatch):
    """The metadata CSV holds every record of the folder: reading one heliostat of a large folder parses it once,
    then takes it from the index (few record files would not switch the index on by themselves)."""
    meta = os.path.join(folder, "metadata", "calibration-metadata.csv")
    one = P.list_heliostats(folder)[:1]
    monkeypatch.setattr(P, "CACHE_MIN_RECORDS", 10**9)
    monkeypatch.setattr(P, "CACHE_MIN_METADATA_BYTES", 10**9)
    P.load_paint(folder, heliostats=one)
    assert RI.csv_cached(folder, meta) == (None, 0)  # a small folder: no index
    monkeypatch.setattr(P, "CACHE_MIN_METADATA_BYTES", 1)
    first = P.load_paint(folder, heliostats=one)
    stored, covered = RI.csv_cached(folder, meta)
    assert stored is not None and covered == os.path.getsize(meta)
    again = P.load_paint(folder, heliostats=one)
    _same(first.records, again.records)
    assert torch.equal(first.records.time.nan_to_num(), P.load_paint(folder, cache=False).records_of(one[0])
                       .time.nan_to_num())
    monkeypatch.setenv("HELIOTWIN_CACHE", "0")
    shutil.rmtree(RI.index_dir(folder))
    P.load_paint(folder, heliostats=one)
    assert RI.csv_cached(folder, meta) == (None, 0)
