"""One plant, one loop: PAINT -> calibrate -> reconstruct -> validate / aim / predict through scenario files."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from helpers.cli import run_cli

from heliotwin.field import kinematics as K
from heliotwin.geometry import angle_between, reflect
from heliotwin.io.scenario import load_scenario
from heliotwin.sun import direction_from_paint_angles

CALIBRATED = "BH60,BG62,AK32,BH35"


@pytest.fixture(scope="module")
def calibrated(paint_dir, tmp_path_factory):
    """``calibrate -o`` on four heliostats (lm, chrono, 30/30): the scenario and the report."""
    out = tmp_path_factory.mktemp("chain")
    code = _main("calibrate", "--paint", paint_dir, "--heliostats", CALIBRATED, "--method", "lm", "--train", "30",
                 "--test", "30", "--no-plots", "--no-curve", "--json", out / "cal.json", "-o", out / "a.h5")
    assert code == 0
    return out, json.loads((out / "cal.json").read_text())


def _main(*argv) -> int:
    from heliotwin.cli import main

    return main([str(a) for a in argv])


def test_validate_on_the_calibrated_plant_reproduces_calibrates_test_errors(calibrated, paint_dir, capsys):
    out, report = calibrated
    code, _, _ = run_cli(capsys, "validate", "--paint", str(paint_dir), "--scenario", str(out / "a.h5"),
                         "--heliostats", CALIBRATED, "--no-images", "--quiet", "--json", str(out / "v.json"))
    assert code == 0
    rows = {r["record"]: r for r in json.loads((out / "v.json").read_text())["records"]}
    tested = report["test_records"]
    assert len(tested) == 4 * 30
    worst = max(abs(rows[t["record"]]["pointing_error_mrad"] - t["pointing_error_mrad"]) for t in tested)
    assert worst < 1e-6  # one metric, one plant: the same number record by record
    import statistics

    assert statistics.median(t["pointing_error_mrad"] for t in tested) < 3
    assert statistics.median(t["nominal_pointing_error_mrad"] for t in tested) > 10
    # ... and the nominal plant gives calibrate's nominal errors.
    code, _, _ = run_cli(capsys, "validate", "--paint", str(paint_dir), "--heliostats", CALIBRATED, "--no-images",
                         "--quiet", "--json", str(out / "v0.json"))
    rows0 = {r["record"]: r for r in json.loads((out / "v0.json").read_text())["records"]}
    assert max(abs(rows0[t["record"]]["pointing_error_mrad"] - t["nominal_pointing_error_mrad"]) for t in tested) < 1e-6


def test_the_scenario_carries_the_calibration_and_its_provenance(calibrated, paint_dir):
    out, report = calibrated
    sc = load_scenario(out / "a.h5")
    cal = sc.learned["calibration"]
    assert cal["method"] == "lm" and cal["heliostats"] == CALIBRATED.split(",")
    assert cal["deviations"].shape == (4, len(cal["parameter_names"]))
    assert "prior" in cal and cal["prior"]["sigma"].shape == (len(cal["parameter_names"]),)
    step = sc.provenance[-1]
    assert step["step"] == "calibrate" and step["method"] == "lm"
    assert Path(step["source"]).resolve() == paint_dir.resolve()  # a symlinked ../shared resolves the same
    assert sorted(step["records"]) == sorted(CALIBRATED.split(","))
    assert all(len(ids) == 30 for ids in step["records"].values())  # training + validation ids
    # Heliostats that were not calibrated keep their nominal kinematics.
    from heliotwin.io.scenario import scenario_from_paint

    nominal = scenario_from_paint(paint_dir)
    other = [i for i, h in enumerate(nominal.field.ids) if h not in CALIBRATED.split(",")]
    assert torch.equal(sc.plant.field.kinematics.joint_tilt[other], nominal.field.kinematics.joint_tilt[other])
    mine = [nominal.field.ids.index(h) for h in CALIBRATED.split(",")]
    assert not torch.equal(sc.plant.field.kinematics.joint_tilt[mine], nominal.field.kinematics.joint_tilt[mine])


def test_aim_with_the_calibrated_plant_reflects_the_sun_onto_the_aim_point(calibrated, capsys):
    out, _ = calibrated
    code, text, _ = run_cli(capsys, "aim", "--scenario", str(out / "a.h5"), "--heliostat", "BH60",
                            "--sun-azimuth", "-20", "--sun-elevation", "35", "--aim=0,-3.24,36",
                            "--json", str(out / "aim.json"))
    assert code == 0 and "[lm]" in text
    ans = json.loads((out / "aim.json").read_text())
    plant = load_scenario(out / "a.h5").plant
    kin = plant.field.kinematics.index([plant.field.index_of("BH60")])
    R, c = K.forward(kin, torch.tensor([[ans["motor_steps"]]], dtype=torch.float64))
    sun = direction_from_paint_angles(torch.tensor([-20.0]).deg2rad(), torch.tensor([35.0]).deg2rad())
    ray = reflect(-sun.reshape(3), K.mirror_normal(R).reshape(3))
    to_aim = torch.tensor([0.0, -3.24, 36.0], dtype=torch.float64) - c.reshape(3)
    assert float(angle_between(ray, to_aim)) < 1e-6


def test_reconstruct_on_the_calibrated_plant_then_trace_and_predict(calibrated, paint_dir, capsys):
    out, _ = calibrated
    code, _, _ = run_cli(capsys, "reconstruct", "--paint", str(paint_dir), "--scenario", str(out / "a.h5"),
                         "--heliostat", "AA39", "--train-first", "3", "--steps", "15", "--slope-error", "2",
                         "--no-mc", "--quiet", "--control-points", "5x5", "--degree", "2",
                         "--json", str(out / "r.json"), "-o", str(out / "b.h5"))
    assert code == 0
    sc = load_scenario(out / "b.h5")
    assert [p["step"] for p in sc.provenance] == ["calibrate", "reconstruct"]
    assert set(sc.learned) == {"calibration", "surfaces"} and list(sc.learned["surfaces"]) == ["AA39"]
    a = load_scenario(out / "a.h5")
    assert torch.equal(sc.plant.field.kinematics.joint_tilt, a.plant.field.kinematics.joint_tilt)
    h = sc.plant.field.index_of("AA39")
    cp = sc.plant.field.surfaces.control_points
    assert cp.shape[2:4] == (5, 5) and float((cp[h, ..., 2] - cp[h, ..., 2].mean()).abs().max()) > 0
    # trace and predict read the learned plant
    code, _, _ = run_cli(capsys, "trace", "--paint", str(paint_dir), "--scenario", str(out / "b.h5"),
                         "--heliostat", "AA39", "--record", "151375", "--integrator", "gaussian", "--samples", "16",
                         "--out", str(out / "t.png"), "--json", str(out / "t.json"))
    assert code == 0
    t = json.loads((out / "t.json").read_text())
    assert t["surface"] == "learned for AA39" and t["kinematics"].startswith("calibrated (lm)")
    code, _, err = run_cli(capsys, "predict", "--scenario", str(out / "b.h5"), "--year", "2023", "--every", "61h",
                           "--quiet", "--json", str(out / "p.json"))
    assert code == 0, err
    p = json.loads((out / "p.json").read_text())
    assert p["heliostat"] == "AA39" and p["instants"] > 0


def test_a_scenario_of_another_kind_or_a_newer_version_is_one_line(tmp_path, paint_dir, capsys):
    import h5py

    bad = tmp_path / "other.h5"
    with h5py.File(bad, "w") as h5:
        h5.attrs["format"] = "heliotwin-calibration"
    code, _, err = run_cli(capsys, "validate", "--paint", str(paint_dir), "--scenario", str(bad), "--json",
                           str(tmp_path / "v.json"))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "/@format" in err and str(bad) in err
    assert not (tmp_path / "v.json").exists()
