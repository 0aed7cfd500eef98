"""The `heliotwin` command line: outputs that make physical sense, and one-line errors for bad input."""
import json

import pytest
from helpers.cli import assert_one_line_error as _assert_one_line_error
from helpers.cli import run_cli as _run
from helpers.paint import copy_paint


def test_demo_writes_images_and_consistent_summary(tmp_path, capsys):
    out = tmp_path / "demo"
    code, stdout, _ = _run(capsys, "demo", "--classic", "--out", str(out), "--heliostats", "6",
                           "--rays-per-point", "16", "--resolution", "64")
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    for name in ("receiver-flux.png", "calibration-spot.png", "field.png"):
        assert (out / name).stat().st_size > 0
    rec = summary["receiver"]
    # energy: the receiver cannot intercept more than was reflected; an aimed field hits it mostly
    assert 0.5 * summary["total_power_w"] < rec["intercepted_power_w"] <= summary["total_power_w"] * (1 + 1e-6)
    # reflected power = DNI * sum(A cos) * rho: check against the per-heliostat cosines
    area = 4 * 1.605 * 1.275
    expected = sum(summary["dni_w_m2"] * area * h["cosine_efficiency"] * summary["reflectivity"]
                   for h in summary["per_heliostat"])
    assert summary["total_power_w"] == pytest.approx(expected, rel=1e-3)
    # the calibration spot lands on its aim point (nominal kinematics, inverse then forward)
    spot = summary["calibration_spot"]
    assert sum((a - b) ** 2 for a, b in zip(spot["centroid_enu_m"], spot["aim_point_enu_m"])) ** 0.5 < 0.15
    assert "receiver intercepts" in stdout


@pytest.fixture()
def small_paint(tmp_path, paint_dir):
    """A PAINT folder with only AA39 (copied) that tests may corrupt."""
    return copy_paint(paint_dir, tmp_path)


def _first_record(root):
    return sorted((root / "AA39" / "Calibration").glob("*-calibration-properties.json"))[0]


def test_trace_real_record_report(small_paint, tmp_path, capsys):
    rec = _first_record(small_paint)
    rid = rec.name.split("-")[0]
    png, js = tmp_path / "f.png", tmp_path / "f.json"
    code, _, err = _run(capsys, "trace", "--paint", str(small_paint), "--heliostat", "AA39", "--record", rid,
                        "--integrator", "mc", "--rays-per-point", "8", "--samples", "20", "--resolution", "64",
                        "--out", str(png), "--json", str(js))
    assert code == 0, err
    r = json.loads(js.read_text())
    assert png.stat().st_size > 0
    assert r["mirror_area_m2"] == pytest.approx(4 * 2 * 0.80248 * 2 * 0.63749, rel=1e-3)
    assert 0 < r["mean_incidence_cosine"] <= 1
    assert r["total_power_w"] == pytest.approx(r["dni_w_m2"] * r["mirror_area_m2"] * r["mean_incidence_cosine"]
                                               * r["reflectivity"], rel=1e-4)
    assert r["intercepted_power_w"] <= r["total_power_w"] * (1 + 1e-6)
    # nominal kinematics miss the measured spot by decimetres to a metre or two, not by tens of metres
    meas = r["measured_spot_enu_m"]["HeliOS"]
    miss = sum((a - b) ** 2 for a, b in zip(r["centroid_enu_m"], meas)) ** 0.5
    assert miss < 3.0
    assert abs(r["centroid_wgs84"]["latitude_deg"] - 50.9134) < 1e-3


def test_malformed_json_names_file(small_paint, tmp_path, capsys):
    rec = _first_record(small_paint)
    rec.write_text("{ not json")
    out = tmp_path / "x.png"
    code, _, err = _run(capsys, "trace", "--paint", str(small_paint), "--heliostat", "AA39", "--record",
                        rec.name.split("-")[0], "--out", str(out))
    _assert_one_line_error(code, err, rec.name, "malformed JSON")
    assert not out.exists()


def test_missing_key_and_unknown_target(small_paint, tmp_path, capsys):
    rec = _first_record(small_paint)
    data = json.loads(rec.read_text())
    data["target_name"] = "no_such_target"
    rec.write_text(json.dumps(data))
    code, _, err = _run(capsys, "validate", "--paint", str(small_paint), "--json", str(tmp_path / "v.json"), "--quiet")
    _assert_one_line_error(code, err, rec.name, "target_name", "no_such_target")
    assert not (tmp_path / "v.json").exists()
    del data["motor_position"]
    data["target_name"] = "solar_tower_juelich_lower"
    rec.write_text(json.dumps(data))
    code, _, err = _run(capsys, "validate", "--paint", str(small_paint), "--json", str(tmp_path / "v.json"), "--quiet")
    _assert_one_line_error(code, err, rec.name, "motor_position")


def test_motor_steps_outside_range_and_sun_below_horizon(small_paint, tmp_path, capsys):
    rec = _first_record(small_paint)
    rid = rec.name.split("-")[0]
    data = json.loads(rec.read_text())
    data["motor_position"]["axis_1_motor_position"] = 10_000_000
    rec.write_text(json.dumps(data))
    out = tmp_path / "x.png"
    code, _, err = _run(capsys, "trace", "--paint", small_paint, "--heliostat", "AA39", "--record", rid, "--out", out)
    _assert_one_line_error(code, err, rec.name, "motor_position", "outside")
    assert not out.exists()
    data = json.loads(_first_record(small_paint).read_text())
    data["motor_position"]["axis_1_motor_position"] = 30000
    data["sun_elevation"] = -5.0
    rec.write_text(json.dumps(data))
    code, _, err = _run(capsys, "trace", "--paint", small_paint, "--heliostat", "AA39", "--record", rid, "--out", out)
    _assert_one_line_error(code, err, rec.name, "sun_elevation", "horizon")
    assert not out.exists()


def test_unknown_heliostat_and_unreadable_png(small_paint, tmp_path, capsys):
    code, _, err = _run(capsys, "trace", "--paint", str(small_paint), "--heliostat", "ZZ99", "--record", "1",
                        "--out", str(tmp_path / "x.png"))
    _assert_one_line_error(code, err, "ZZ99")
    png = next((small_paint / "AA39" / "Calibration").glob("*-flux-centered.png"))
    png.write_bytes(b"not a png")
    code, _, err = _run(capsys, "validate", "--paint", str(small_paint), "--json", str(tmp_path / "v.json"), "--quiet")
    _assert_one_line_error(code, err, png.name)
    assert not (tmp_path / "v.json").exists()


def test_scenario_from_paint_and_bad_hdf5(small_paint, tmp_path, capsys):
    out = tmp_path / "plant.h5"
    code, _, err = _run(capsys, "scenario", "from-paint", str(small_paint), "-o", str(out))
    assert code == 0, err
    from heliotwin.io.scenario import load_scenario
    sc = load_scenario(out)
    plant = sc.plant if hasattr(sc, "plant") else sc[0]
    assert plant.field.ids == ["AA39"]
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"garbage")
    with pytest.raises(Exception) as exc:
        load_scenario(bad)
    assert "bad.h5" in str(exc.value)
