"""The record table: every check in one place, one reason per skipped record, selection and sources."""
from __future__ import annotations

import json
import shutil

import pytest
import torch
from helpers.paint import copy_paint

from heliotwin.errors import InputFileError
from heliotwin.io.paint import load_paint


@pytest.fixture()
def aa39_copy(tmp_path, paint_dir):
    """A PAINT folder with only AA39 (copied), free to corrupt."""
    return copy_paint(paint_dir, tmp_path)


def _records(root):
    return sorted((root / "AA39" / "Calibration").glob("*-calibration-properties.json"))


def _edit(path, fn):
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def test_unusable_records_are_skipped_with_one_reason_each(aa39_copy):
    recs = _records(aa39_copy)
    _edit(recs[0], lambda d: d["motor_position"].__setitem__("axis_2_motor_position", 1e7))
    _edit(recs[1], lambda d: d.__setitem__("target_name", "receiver"))
    ds = load_paint(aa39_copy)
    assert len(ds.records) == 16 and len(ds.skipped) == 2
    by_id = {s["record_id"]: s for s in ds.skipped}
    first, second = (int(p.name.split("-")[0]) for p in recs[:2])
    assert "axis 2" in by_id[first]["reason"] and by_id[first]["field"] == "motor_position.axis_2_motor_position"
    assert "not planar" in by_id[second]["reason"] and by_id[second]["path"] == str(recs[1])
    # Asking for a skipped record names its file, field and reason.
    with pytest.raises(InputFileError, match=r"axis_2_motor_position\].*outside actuator range"):
        ds.record(first)


def test_a_centroid_off_its_plane_falls_back_to_the_other_source(aa39_copy, paint_dir):
    good = load_paint(paint_dir, ["AA39"]).records
    both = torch.isfinite(good.focal_spots).all(-1).all(-1)
    i = int(both.nonzero()[0])
    rid = int(good.record_id[i])
    path = aa39_copy / "AA39" / "Calibration" / f"{rid}-calibration-properties.json"
    # Move the HeliOS centroid 1 m off the target plane (north, towards the field): beyond the 0.1 m tolerance.
    _edit(path, lambda d: d["focal_spot"].__setitem__("HeliOS", [d["focal_spot"]["HeliOS"][0] + 1e-5,
                                                               *d["focal_spot"]["HeliOS"][1:]]))
    t = load_paint(aa39_copy).records
    j = t.index_of(rid)
    assert not bool(torch.isfinite(t.focal_spots[j, 0]).all())  # HeliOS dropped
    assert t.source[j] == "UTIS" and torch.equal(t.spot[j], good.focal_spots[i, 1])


def test_duplicate_record_ids_are_an_error_naming_both_files(aa39_copy):
    src = _records(aa39_copy)[0]
    other = aa39_copy / "AB38" / "Calibration"
    shutil.copytree(aa39_copy / "AA39" / "Properties", aa39_copy / "AB38" / "Properties")
    (aa39_copy / "AB38" / "Properties" / "AA39-heliostat-properties.json").rename(
        aa39_copy / "AB38" / "Properties" / "AB38-heliostat-properties.json")
    other.mkdir(parents=True)
    shutil.copy(src, other / src.name)
    with pytest.raises(InputFileError, match="duplicate record id") as exc:
        load_paint(aa39_copy)
    assert src.name in str(exc.value) and "AB38" in str(exc.value)


def test_select_for_heliostats_and_sources(paint_dir):
    ds = load_paint(paint_dir, ["AA39", "BG62", "AK32"])
    t = ds.records
    sub = t.for_heliostats(["AK32", "AA39"])
    assert sub.heliostat_ids == ["AK32", "AA39"]
    assert len(sub) == len(t.select(heliostat="AK32")) + len(t.select(heliostat="AA39"))
    names = [sub.heliostat_ids[h] for h in sub.heliostat_index.tolist()]
    assert set(names) == {"AK32", "AA39"}
    assert len(t.select(heliostat="AA39", with_centered_image=True)) == 10
    rows = t.select(record_ids=t.record_id[:3].tolist())
    assert rows.record_id.tolist() == t.record_id[:3].tolist()


def test_records_on_a_scenario_of_another_plant_are_a_one_line_error(paint_dir, tmp_path):
    from dataclasses import replace

    from heliotwin.field.demo import demo_plant
    from heliotwin.io.scenario import load_records, save_scenario
    from heliotwin.site import Site

    demo = demo_plant(num_heliostats=3)
    path = save_scenario(demo, tmp_path / "demo.h5")
    with pytest.raises(InputFileError, match=r"\[/field/ids\]: heliostat\(s\) .* not in the PAINT folder"):
        load_records(paint_dir, path)
    moved = replace(demo, site=Site(48.0, 11.0, 500.0, "elsewhere"))
    aa39 = load_paint(paint_dir, ["AA39"]).plant
    with pytest.raises(InputFileError, match=r"\[/site\]"):
        load_records(paint_dir, save_scenario(replace(aa39, site=moved.site), tmp_path / "moved.h5"))
    ds, sc = load_records(paint_dir, save_scenario(aa39, tmp_path / "aa39.h5"))
    assert sc.plant.field.ids == ["AA39"] and len(ds.records) == 18
