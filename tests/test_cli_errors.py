"""The issue's hostile inputs, each reproduced: one line naming file and field, exit 2 (bad input), nothing
written; and the silent wrong results it found, now errors or honest ``null``s."""
from __future__ import annotations

import json
import struct
import zlib

import pytest
from helpers.cli import assert_one_line_error, run_cli
from helpers.paint import copy_paint

from heliotwin.cli import main


@pytest.fixture()
def small_paint(tmp_path, paint_dir):
    return copy_paint(paint_dir, tmp_path)


def _records(root):
    return sorted((root / "AA39" / "Calibration").glob("*-calibration-properties.json"))


def _usage_error(capsys, *argv):
    """argparse's exit: status 2 and one line ``heliotwin: error: <command>: argument ...``."""
    with pytest.raises(SystemExit) as exc:
        main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert_one_line_error(2, err)
    return err


@pytest.mark.parametrize("argv, needle", [
    (["reconstruct", "--paint", "P", "--heliostat", "AA39", "--json", "r.json", "--steps", "0"], "--steps"),
    (["bench", "--rays-per-point", "abc"], "--rays-per-point"),
    (["demo", "--time", "not a time"], "--time"),
    (["demo", "--time", "2023-02-30T12:00:00Z"], "--time"),
    (["predict", "--scenario", "s.h5", "--json", "o.json", "--every", "0min"], "--every"),
    (["predict", "--scenario", "s.h5", "--json", "o.json", "--every", "xyz"], "--every"),
    (["trace", "--paint", "P", "--heliostat", "AA39", "--record", "1", "--out", "f.png", "--seed", str(2**64)],
     "--seed"),
    (["demo", "--seed", "-1"], "--seed"),
    (["calibrate", "--paint", "P", "--plane-tolerance", "nan"], "--plane-tolerance"),
    (["calibrate", "--paint", "P", "--plane-tolerance", "inf"], "--plane-tolerance"),
    (["calibrate", "--paint", "P", "--train", "0"], "--train"),
    (["validate", "--paint", "P", "--json", "v.json", "--resolution", "100000"], "--resolution"),
    (["reconstruct", "--paint", "P", "--heliostat", "AA39", "--json", "r.json", "--steps", "-5"],
     "--steps"),  # (--background, once checked here, is retired: refused at run time with what replaces it)
    (["reconstruct", "--paint", "P", "--heliostat", "AA39", "--json", "r.json", "--slope-error", "nan"],
     "--slope-error"),
    (["predict", "--scenario", "s.h5", "--json", "o.json", "--year", "99999"], "--year"),
    (["aim", "--scenario", "s.h5", "--heliostat", "AA39", "--sun-azimuth", "nan", "--sun-elevation", "30",
      "--aim", "0,0,30"], "--sun-azimuth"),
])
def test_every_numeric_argument_has_a_range(argv, needle, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    err = _usage_error(capsys, *argv)
    assert needle in err
    assert list(tmp_path.iterdir()) == []  # e.g. demo --time "not a time" used to leave an empty folder


def test_argument_types_normalise_what_they_accept():
    from heliotwin.cli.common import frequency, seed_int, utc_time

    assert frequency("1h") == "60min" and frequency("30min") == "30min" and frequency("1d") == "1440min"
    assert utc_time("2023-03-20T11:30:00Z") == utc_time("2023-03-20T12:30:00+01:00") == "2023-03-20T11:30:00+00:00"
    assert seed_int(str(2**63 - 1)) == 2**63 - 1


def test_negative_aim_point_is_a_value_not_an_option(tmp_path, capsys):
    """``--aim -1,-3.24,36`` used to be read as an option; now it reaches the scenario reader."""
    code, _, err = run_cli(capsys, "aim", "--scenario", tmp_path / "none.h5", "--heliostat", "AA39",
                           "--sun-azimuth", "-20", "--sun-elevation", "30", "--aim", "-1,-3.24,36")
    assert_one_line_error(code, err, "none.h5")
    assert code == 2


def test_non_utf8_metadata_csv(small_paint, tmp_path, capsys, paint_dir):
    meta = small_paint / "metadata"
    meta.mkdir(exist_ok=True)  # the copy has the real one: replaced
    (meta / "calibration-metadata.csv").write_bytes(b"Id,DateTime\n1,2023-01-01\xff\xfe\n")
    out = tmp_path / "v.json"
    code, _, err = run_cli(capsys, "validate", "--paint", small_paint, "--json", out, "--quiet", "--no-images")
    assert_one_line_error(code, err, "calibration-metadata.csv", "UTF-8")
    assert code == 2 and not out.exists()


def test_duplicate_metadata_id(small_paint, tmp_path, capsys):
    meta = small_paint / "metadata"
    meta.mkdir(exist_ok=True)  # the copy has the real one: replaced
    (meta / "calibration-metadata.csv").write_text("Id,DateTime\n1,2023-01-01\n1,2023-01-02\n")
    code, _, err = run_cli(capsys, "validate", "--paint", small_paint, "--json", tmp_path / "v.json", "--quiet")
    assert_one_line_error(code, err, "calibration-metadata.csv", "duplicate Id 1")


def test_deeply_nested_and_huge_json(small_paint, tmp_path, capsys, monkeypatch):
    rec = _records(small_paint)[0]
    rec.write_text("[" * 100_000 + "]" * 100_000)
    out = tmp_path / "v.json"
    code, _, err = run_cli(capsys, "validate", "--paint", small_paint, "--json", out, "--quiet", "--no-images")
    assert_one_line_error(code, err, rec.name)
    assert code == 2 and not out.exists()
    rec.write_text(json.dumps({"a": [[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[1]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]}))
    code, _, err = run_cli(capsys, "validate", "--paint", small_paint, "--json", out, "--quiet", "--no-images")
    assert_one_line_error(code, err, rec.name, "nested deeper")
    import heliotwin.io.paint as paint

    monkeypatch.setattr(paint, "MAX_JSON_BYTES", 100)
    code, _, err = run_cli(capsys, "validate", "--paint", small_paint, "--json", out, "--quiet", "--no-images")
    assert_one_line_error(code, err, "bytes")


def _edit_json(path, edit):
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("edit, where", [
    # a tower corner 5 700 km away (51 deg N -> 0 deg N)
    (lambda d: d["solar_tower_juelich_upper"]["coordinates"]["upper_left"].__setitem__(0, 0.0),
     "solar_tower_juelich_upper.coordinates.upper_left"),
    (lambda d: d["power_plant_properties"]["coordinates"].__setitem__(2, 1e308), None),
])
def test_implausible_tower_geometry(small_paint, tmp_path, capsys, edit, where):
    tower = small_paint / "WRI1030197-tower-measurements.json"
    _edit_json(tower, edit)
    code, _, err = run_cli(capsys, "scenario", "from-paint", small_paint, "-o", tmp_path / "p.h5")
    assert_one_line_error(code, err, tower.name, *([where] if where else []))
    assert code == 2 and not (tmp_path / "p.h5").exists()


@pytest.mark.parametrize("key, value", [
    ("kinematic_properties.actuators.0.initial_stroke_length", -0.07),
    ("kinematic_properties.concentrator_translation_n", 1e308),
    ("kinematic_properties.joint_translation_e_1", 1e6),
    ("facet_properties.facets.0.translation_vector", [1e308, 0.0, 0.0]),
    ("heliostat_position", [0.0, 6.38, 88.0]),
])
def test_implausible_heliostat_geometry(small_paint, tmp_path, capsys, key, value):
    props = small_paint / "AA39" / "Properties" / "AA39-heliostat-properties.json"

    def edit(d):
        *head, last = key.split(".")
        for k in head:
            d = d[int(k)] if k.isdigit() else d[k]
        d[last] = value

    _edit_json(props, edit)
    code, _, err = run_cli(capsys, "scenario", "from-paint", small_paint, "-o", tmp_path / "p.h5")
    assert_one_line_error(code, err, props.name, key.split(".")[-1], "implausible")
    assert code == 2 and not (tmp_path / "p.h5").exists()


def _png_header(path, width, height):
    """A PNG whose header claims ``width x height`` (8-bit grey) with a tiny body: a decompression bomb's head."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    body = zlib.compress(b"\0" * 64)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", body) + chunk(b"IEND", b""))


def _save_png(path, array):
    from PIL import Image

    Image.fromarray(array).save(path)


@pytest.mark.parametrize("kind", ["bomb", "1x1", "black", "uniform"])
def test_degenerate_or_huge_measured_images(small_paint, tmp_path, capsys, kind):
    import numpy as np

    png = sorted((small_paint / "AA39" / "Calibration").glob("*-flux-centered.png"))[0]
    if kind == "bomb":
        _png_header(png, 14000, 14000)
        needle = "larger than"
    elif kind == "1x1":
        _save_png(png, np.full((1, 1), 200, np.uint8))
        needle = "too small"
    elif kind == "black":
        _save_png(png, np.zeros((64, 64), np.uint8))
        needle = "empty"
    else:
        _save_png(png, np.full((64, 64), 255, np.uint8))
        needle = "uniform"
    out = tmp_path / "v.json"
    code, _, err = run_cli(capsys, "validate", "--paint", small_paint, "--json", out, "--quiet", "--samples", "4")
    assert_one_line_error(code, err, png.name, needle)
    assert code == 2 and not out.exists()


def test_validate_without_usable_records_is_an_error_not_a_crash(small_paint, tmp_path, capsys):
    for rec in _records(small_paint):
        _edit_json(rec, lambda d: d.__setitem__("target_name", "receiver"))  # not planar: every record skipped
    out = tmp_path / "v.json"
    code, _, err = run_cli(capsys, "validate", "--paint", small_paint, "--json", out, "--quiet")
    assert_one_line_error(code, err, "no usable record", "not planar")
    assert code == 2 and not out.exists()


def test_trace_without_light_reports_no_centroid(small_paint, tmp_path, capsys):
    """Motor steps at the end stops point the mirror away: no light arrives, so there is no centroid (the
    target centre a zero image's centroid would give is not a result)."""
    rec = _records(small_paint)[0]
    _edit_json(rec, lambda d: d.__setitem__("motor_position", {"axis_1_motor_position": 0,
                                                               "axis_2_motor_position": 0}))
    js = tmp_path / "t.json"
    code, out, err = run_cli(capsys, "trace", "--paint", small_paint, "--heliostat", "AA39", "--record",
                             rec.name.split("-")[0], "--out", tmp_path / "t.png", "--json", js,
                             "--rays-per-point", "4", "--samples", "10", "--resolution", "32")
    assert code == 0, err
    r = json.loads(js.read_text())
    assert r["intercepted_power_w"] == 0 and r["total_power_w"] > 0
    assert r["centroid_enu_m"] is None and r["centroid_wgs84"] is None and r["centroid_local_m"] is None
    assert "no centroid" in out


def test_outputs_may_not_replace_inputs_or_each_other(small_paint, tmp_path, capsys):
    rec = _records(small_paint)[0]
    before = rec.read_bytes()
    rid = rec.name.split("-")[0]
    common = ["trace", "--paint", small_paint, "--heliostat", "AA39", "--record", rid, "--samples", "4"]
    code, _, err = run_cli(capsys, *common, "--out", tmp_path / "t.png", "--json", rec)
    assert_one_line_error(code, err, rec.name, "--json", "input folder --paint")
    assert rec.read_bytes() == before
    code, _, err = run_cli(capsys, *common, "--out", tmp_path / "same", "--json", tmp_path / "same")
    assert_one_line_error(code, err, "--json", "also the output of --out")
    code, _, err = run_cli(capsys, *common, "--out", tmp_path / "no" / "t.png")
    assert_one_line_error(code, err, "--out", "does not exist")
    code, _, err = run_cli(capsys, *common, "--out", tmp_path)
    assert_one_line_error(code, err, "--out", "is a folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["paint"]


def test_failing_run_keeps_existing_outputs_and_leaves_nothing(small_paint, tmp_path, capsys):
    """A run that fails after its first output could be written replaces nothing and leaves no temp files."""
    png, js = tmp_path / "t.png", tmp_path / "t.json"
    png.write_bytes(b"old png")
    js.write_text("old json")
    code, _, err = run_cli(capsys, "trace", "--paint", small_paint, "--heliostat", "AA39", "--record", "999",
                           "--out", png, "--json", js, "--samples", "4")
    assert_one_line_error(code, err, "999")
    assert png.read_bytes() == b"old png" and js.read_text() == "old json"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["paint", "t.json", "t.png"]


def test_validate_plot_is_labelled_with_counts(small_paint, tmp_path, capsys):
    js, png = tmp_path / "v.json", tmp_path / "v.png"
    code, _, err = run_cli(capsys, "validate", "--paint", small_paint, "--json", js, "--plot", png, "--quiet",
                           "--samples", "4", "--no-images")
    assert code == 0, err
    assert png.read_bytes()[:4] == b"\x89PNG"
    report = json.loads(js.read_text())
    assert report["heliostats"]["AA39"]["records"] == report["overall"]["records"] > 0
    code, out, err = run_cli(capsys, "validate", "--paint", small_paint, "--json", js, "--samples", "4", "--no-images")
    assert code == 0, err
    cams = json.loads(js.read_text())["camera_agreement"]  # AA39's records with both centroids, per target
    assert cams and all(c["heliostats"] == 1 and c["pairs"] >= 1 for c in cams.values())
    line = next(ln for ln in out.splitlines() if ln.startswith("cameras"))
    assert all(f"{name} ({100 * c['right_m']:+.1f}, {100 * c['up_m']:+.1f})" in line for name, c in cams.items())


def test_calibrate_checks_its_outputs_before_reading_anything(tmp_path, capsys):
    """Two outputs on one path: refused before the (missing) PAINT folder is even opened."""
    code, _, err = run_cli(capsys, "calibrate", "--paint", tmp_path / "nope", "-o", tmp_path / "x",
                           "--json", tmp_path / "x")
    assert_one_line_error(code, err, "--json", "also the output of -o")
    assert list(tmp_path.iterdir()) == []
