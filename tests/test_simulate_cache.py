"""The PAINT record cache: re-opened only while the folder's files are unchanged, never trusted otherwise."""
from __future__ import annotations

import json
import os
import shutil

import pytest
import torch

from heliotwin.io import paint as P
from heliotwin.simulate import SimulationSettings, simulate_plant, write_paint_folder


@pytest.fixture()
def folder(tmp_path, monkeypatch):
    monkeypatch.setenv("HELIOTWIN_CACHE_DIR", str(tmp_path / "cache"))
    sim = simulate_plant(SimulationSettings(heliostats=3, seed=4, years=0.3, records_per_month=6))
    return write_paint_folder(sim, tmp_path / "plant")


def _no_parsing(monkeypatch):
    """Make reading the files fail: a load that succeeds came from the cache."""
    def boom(*args, **kwargs):
        raise AssertionError("the files were parsed")
    monkeypatch.setattr(P, "_parse_all", boom)


def _first_record(folder):
    hid = P.list_heliostats(folder)[0]
    cal = os.path.join(folder, hid, "Calibration")
    name = sorted(f for f in os.listdir(cal) if f.endswith("-calibration-properties.json"))[0]
    return os.path.join(cal, name)


def _same(a, b):
    assert torch.equal(a.record_id, b.record_id) and torch.equal(a.motor_steps, b.motor_steps)
    assert torch.equal(a.focal_spots.nan_to_num(), b.focal_spots.nan_to_num())
    assert torch.equal(a.time.nan_to_num(), b.time.nan_to_num()) and a.path == b.path and a.target == b.target


def test_cache_reopens_the_same_table(folder, monkeypatch):
    cold = P.load_paint(folder, cache=True)
    assert os.path.exists(P.record_cache_path(folder, P.list_heliostats(folder)))
    _no_parsing(monkeypatch)
    _same(cold.records, P.load_paint(folder, cache=True).records)


def test_cache_is_what_the_one_file_reader_reads(folder):
    fast = P.load_paint(folder, cache=False).records
    site, targets = P.read_tower(P.find_tower_file(folder))
    ids = P.list_heliostats(folder)
    listing = P._listing(folder, ids)
    times, weather = P.read_metadata(folder)
    slow = P._read_one_by_one(listing, ids, site, targets, times, weather)
    assert torch.equal(fast.record_id, slow.record_id[:len(fast)]) and len(fast) == len(slow)
    assert torch.allclose(fast.focal_spots.nan_to_num(), slow.focal_spots.nan_to_num(), atol=1e-9)


def test_a_changed_record_invalidates_the_cache(folder, monkeypatch):
    P.load_paint(folder, cache=True)
    path = _first_record(folder)
    data = json.loads(open(path).read())
    data["motor_position"]["axis_1_motor_position"] += 1
    with open(path, "w") as fh:
        json.dump(data, fh)
    os.utime(path, ns=(os.stat(path).st_atime_ns, os.stat(path).st_mtime_ns + 1_000_000))
    rid = int(os.path.basename(path).split("-")[0])
    again = P.load_paint(folder, cache=True).records
    row = again.index_of(rid)
    assert again.motor_steps[row, 0] == data["motor_position"]["axis_1_motor_position"]


def test_an_added_or_removed_record_invalidates_the_cache(folder):
    n = len(P.load_paint(folder, cache=True).records)
    path = _first_record(folder)
    copy = os.path.join(os.path.dirname(path), "999999-calibration-properties.json")
    shutil.copy(path, copy)
    assert len(P.load_paint(folder, cache=True).records) == n + 1
    os.remove(copy)
    os.remove(path)
    assert len(P.load_paint(folder, cache=True).records) == n - 1


def test_changed_metadata_or_a_new_image_invalidates_the_cache(folder):
    table = P.load_paint(folder, cache=True).records
    rid = int(table.record_id[0])
    meta = os.path.join(folder, "metadata", "calibration-metadata.csv")
    lines = open(meta).read().splitlines()
    with open(meta, "w") as fh:
        fh.write("\n".join(ln for ln in lines if not ln.startswith(f"{rid},")) + "\n")
    png = os.path.join(os.path.dirname(table.path[0]), f"{rid}-flux.png")
    open(png, "wb").close()
    again = P.load_paint(folder, cache=True).records
    row = again.index_of(rid)
    assert torch.isnan(again.time[row]) and again.flux_png[row] == png


def test_a_damaged_or_foreign_cache_is_never_trusted(folder):
    first = P.load_paint(folder, cache=True).records
    path = P.record_cache_path(folder, P.list_heliostats(folder))
    with open(path, "wb") as fh:
        fh.write(b"not a cache")
    _same(first, P.load_paint(folder, cache=True).records)
    # A cache of another key (written for other files) is ignored even when it reads cleanly.
    ids = P.list_heliostats(folder)
    site, targets = P.read_tower(P.find_tower_file(folder))
    forged = P._parse_all(P._listing(folder, ids), ids, site, targets, {}, {})
    forged.motor_steps += 7.0
    P._save_cache(path, "another key", forged)
    _same(first, P.load_paint(folder, cache=True).records)


def test_large_folders_cache_by_default_unless_switched_off(folder, monkeypatch):
    path = P.record_cache_path(folder, P.list_heliostats(folder))
    monkeypatch.setenv("HELIOTWIN_CACHE", "0")
    monkeypatch.setattr(P, "CACHE_MIN_RECORDS", 1)
    P.load_paint(folder)
    assert not os.path.exists(path)
    monkeypatch.delenv("HELIOTWIN_CACHE")
    P.load_paint(folder)
    assert os.path.exists(path)
    monkeypatch.setattr(P, "CACHE_MIN_RECORDS", 10**9)
    os.remove(path)
    P.load_paint(folder)
    assert not os.path.exists(path)
