"""The in-silico plant: deterministic, read unchanged by the PAINT reader, a tower's schedule, the noise and steps
it was asked for, a score that is zero for the truth, and a calibration that recovers the truth."""
from __future__ import annotations

import dataclasses
import json
import math
import tempfile

import numpy as np
import pytest
import torch
from helpers.cli import assert_one_line_error, run_cli

from heliotwin.calibrate.methods.lm import fit_lm
from heliotwin.calibrate.metrics import pointing_error
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.calibrate.priors import LOOSE_SIGMA
from heliotwin.evaluation import score
from heliotwin.io.images import read_png
from heliotwin.io.paint import HELIOSTAT_DIR, load_paint
from heliotwin.io.scenario import load_scenario, write_scenario
from heliotwin.simulate import SimulationSettings, simulate_plant, truth_scenario, write_paint_folder
from heliotwin.simulate.plant import DRIFTING, draw_steps, drift_at, nominal_plant, true_kinematics
from heliotwin.workflows.calibrate import CalibrationSettings, calibrate

#: No drift, no steps: the truth is static, so a static calibration can recover it.
STATIC = dict(drift_mrad_per_sqrt_day=0.0, step_rate_per_year=0.0)


@pytest.fixture(scope="module")
def small():
    """12 heliostats, 1.5 years, static truth (shared by the tests that only read)."""
    return simulate_plant(SimulationSettings(heliostats=12, seed=5, years=1.5, records_per_month=4, **STATIC))


@pytest.fixture(scope="module")
def small_folder(small, tmp_path_factory):
    return write_paint_folder(small, tmp_path_factory.mktemp("sim") / "plant")


def load_paint_records(sim):
    """The simulated records as the reader's table (through a written folder)."""
    with tempfile.TemporaryDirectory() as d:
        return load_paint(write_paint_folder(sim, f"{d}/plant")).records


def load_scenario_like(sim, kinematics):
    """The truth scenario of ``sim`` with other kinematics (what a calibration would write)."""
    truth = truth_scenario(sim)
    return dataclasses.replace(truth, plant=dataclasses.replace(
        truth.plant, field=dataclasses.replace(truth.plant.field, kinematics=kinematics)))


def _by_id(sim, table):
    """Rows of ``sim.records`` in the order of ``table``'s record ids."""
    at = {int(r): i for i, r in enumerate(sim.records.record_id.tolist())}
    return torch.tensor([at[int(r)] for r in table.record_id.tolist()])


def test_same_seed_same_plant_other_seed_other_plant():
    s = SimulationSettings(heliostats=6, seed=11, years=0.5)
    a, b = simulate_plant(s), simulate_plant(s)
    c = simulate_plant(dataclasses.replace(s, seed=12))
    assert torch.equal(a.static, b.static) and torch.equal(a.records.motor_steps, b.records.motor_steps)
    assert torch.equal(a.records.focal_spots.nan_to_num(), b.records.focal_spots.nan_to_num())
    assert torch.equal(a.records.time, b.records.time) and a.records.target == b.records.target
    assert not torch.equal(a.static, c.static)


def test_folder_is_read_unchanged_by_the_paint_reader(small, small_folder):
    ds = load_paint(small_folder)
    table = ds.records
    assert ds.skipped == [] and len(table) == len(small.records) > 400
    assert ds.plant.field.ids == small.plant.field.ids
    assert torch.allclose(ds.plant.field.kinematics.position, small.plant.field.kinematics.position, atol=1e-6)
    row = _by_id(small, table)
    rec = small.records
    assert torch.equal(table.motor_steps, rec.motor_steps[row])
    assert torch.allclose(table.sun_elevation, rec.sun_elevation[row], atol=1e-12)
    assert torch.allclose(table.sun_azimuth, rec.sun_azimuth[row], atol=1e-12)
    # Both centroids come back where they were put (WGS84 lat-first there and ENU back: micrometres).
    same = torch.isfinite(rec.focal_spots[row]) == torch.isfinite(table.focal_spots)
    assert bool(same.all())
    assert torch.allclose(table.focal_spots.nan_to_num(), rec.focal_spots[row].nan_to_num(), atol=1e-6)
    # Times where the metadata has a row, none where it was left out.
    has = rec.has_time[row]
    assert torch.equal(table.time[has], rec.time[row][has]) and bool(table.time[~has].isnan().all())
    assert table.target == [rec.target[i] for i in row.tolist()]
    # Weather rows where drawn (the reader's five columns), none elsewhere.
    wx = rec.weather[row][:, :5]
    assert torch.allclose(table.weather.nan_to_num(), wx.nan_to_num(), atol=1e-4)
    assert 0.2 < float(torch.isfinite(table.weather[:, 0]).float().mean()) < 0.5


def test_true_kinematics_explain_every_record_up_to_the_noise(tmp_path):
    sim = simulate_plant(SimulationSettings(heliostats=5, seed=2, years=1.0, centroid_noise_mrad=0.0,
                                            camera_offset_m=0.0))
    table = load_paint(write_paint_folder(sim, tmp_path / "p")).records
    row = _by_id(sim, table)
    kin = true_kinematics(sim.plant.field.kinematics.index(table.heliostat_index), sim.static[table.heliostat_index],
                          sim.names, sim.records.drift[row])
    err = pointing_error(kin, table, per_record=True)
    assert float(err.max()) < 1e-9  # rad: the records are exactly what the true heliostats did
    assert float(pointing_error(sim.plant.field.kinematics, table).median()) > 1e-3  # nominal is mrad off


def test_schedule_is_daytime_and_one_heliostat_per_target_at_a_time(small):
    rec, s = small.records, small.settings
    assert float(rec.sun_elevation.min()) > math.radians(s.min_elevation_deg)
    for name in set(rec.target):
        t = np.sort(rec.time.numpy()[[x == name for x in rec.target]])
        assert np.diff(t).min() >= s.slot_seconds / 2  # a calibration occupies its target for a slot
    months = len(small.records) / (12 * 18.0)
    assert 3.0 < months < 4.5  # about records_per_month = 4 (some miss the target or fall below the horizon)


def test_centroid_noise_and_camera_offsets_are_recovered(small):
    rec, s = small.records, small.settings
    pos = small.plant.field.kinematics.position[rec.heliostat_index]
    slant = torch.linalg.vector_norm(rec.true_spot - pos, dim=-1)
    targets = small.plant.targets
    right = torch.stack([targets[t].right for t in rec.target])
    up = torch.stack([targets[t].up for t in rec.target])
    err = rec.focal_spots[:, 0] - rec.true_spot
    angles = torch.cat([(err * right).sum(-1) / slant, (err * up).sum(-1) / slant])
    assert float(angles.std()) == pytest.approx(s.centroid_noise_mrad * 1e-3, rel=0.08)
    assert abs(float(angles.mean())) < 3 * s.centroid_noise_mrad * 1e-3 / math.sqrt(len(angles))
    # UTIS: missing at the requested rate; where present, off by its target's camera offset.
    utis = torch.isfinite(rec.focal_spots[:, 1]).all(-1)
    assert 1 - float(utis.float().mean()) == pytest.approx(s.utis_missing, abs=0.05)
    for name, offset in small.camera_offsets.items():
        on = utis & torch.tensor([t == name for t in rec.target])
        diff = (rec.focal_spots[on, 1] - rec.focal_spots[on, 0]).median(0).values
        assert torch.allclose(diff, offset, atol=0.01)
    assert 1 - float(rec.has_time.float().mean()) == pytest.approx(s.time_missing, abs=0.02)


def test_steps_come_at_the_requested_rate_and_add_up():
    s = SimulationSettings(heliostats=40, seed=3, years=3.0, step_rate_per_year=2.0, step_size_mrad=1.0)
    rng = np.random.default_rng(0)
    steps = draw_steps(rng, 40, 0.0, 3 * 365.25 * 86400, s)
    expected = 2.0 * 3.0 * 40
    assert abs(len(steps["time"]) - expected) < 4 * math.sqrt(expected)
    assert float(steps["size"].std()) == pytest.approx(1e-3, rel=0.15)
    # Without the random walk the drift at a time is the sum of the heliostat's earlier steps.
    hq = rng.integers(0, 40, 200)
    tq = rng.uniform(0, 3 * 365.25 * 86400, 200)
    got = drift_at(rng, hq, tq, 40, 0.0, steps, 0.0)
    sh, st, ss = (steps[k].numpy() for k in ("heliostat", "time", "size"))
    want = np.stack([ss[(sh == h) & (st < t)].sum(0) for h, t in zip(hq, tq)])
    assert np.allclose(got, want, atol=1e-15)


def test_score_is_zero_for_the_truth_and_the_offset_for_a_known_error(small):
    truth = truth_scenario(small)
    zero = score(truth, truth, suns=8, flux=False)
    assert zero["heliostats"] == 12 and zero["pointing_mrad"]["max"] < 1e-9
    assert zero["surface_mrad"]["max"] < 1e-9
    kin = apply_deviations(truth.plant.field.kinematics, torch.full((12, 1), 1e-3, dtype=torch.float64),
                           ("initial_angle_2",))
    off = dataclasses.replace(truth, plant=dataclasses.replace(
        truth.plant, field=dataclasses.replace(truth.plant.field, kinematics=kin)))
    got = score(truth, off, suns=8, flux=False)["pointing_mrad"]
    # An encoder offset of axis 2 turns the normal about an axis perpendicular to it: 1 mrad, whatever the sun.
    assert got["median"] == pytest.approx(1.0, rel=0.02) and got["max"] == pytest.approx(1.0, rel=0.02)


def test_truth_scenario_round_trips_and_holds_the_deviations(small, tmp_path):
    path = write_scenario(truth_scenario(small), tmp_path / "truth.h5")
    sc = load_scenario(path)
    cal = sc.learned["calibration"]
    assert cal["method"] == "truth" and list(cal["heliostats"]) == small.plant.field.ids
    dev = torch.as_tensor(cal["deviations"])
    names = list(cal["parameter_names"])
    assert torch.allclose(dev[:, names.index("joint_tilt_1_n")], small.static[:, list(small.names).index(
        "joint_tilt_1_n")])
    for k, n in enumerate(DRIFTING):  # the drifting offsets at the end of the history
        assert torch.allclose(dev[:, names.index(n)], small.static[:, list(small.names).index(n)]
                              + small.end_drift[:, k])
    assert score(sc, sc, suns=4, flux=False)["pointing_mrad"]["max"] < 1e-9


def test_lm_fit_recovers_the_truth(small):
    """The lm engine alone (one batched fit of every heliostat on its records): the truth within the noise."""
    table = load_paint_records(small)
    nominal = small.plant.field.kinematics
    delta, _ = fit_lm(nominal, table, names=STONE8, prior_sigma=LOOSE_SIGMA)
    fitted = load_scenario_like(small, apply_deviations(nominal, delta, STONE8))
    truth = truth_scenario(small)
    got = score(truth, fitted, suns=16, flux=False)
    noise = small.settings.centroid_noise_mrad
    assert got["pointing_per_heliostat_mrad"]["median"] < 1.5 * noise and got["pointing_mrad"]["p95"] < 4 * noise
    assert score(truth, load_scenario_like(small, nominal), suns=16, flux=False)["pointing_mrad"]["median"] > 3.0


@pytest.mark.slow
def test_lm_calibration_recovers_the_truth(tmp_path):
    """The calibrate workflow with its defaults (bagging, field prior, chronological split)."""
    sim = simulate_plant(SimulationSettings(heliostats=4, seed=6, years=0.8, records_per_month=5, **STATIC))
    folder = write_paint_folder(sim, tmp_path / "plant")
    scenario, report = calibrate(None, folder, CalibrationSettings(method="lm", min_records=20, train=30))
    assert report["overall"]["n_heliostats"] == 4
    truth = truth_scenario(sim)
    got = score(truth, scenario, suns=16, flux=False)
    noise = sim.settings.centroid_noise_mrad
    assert got["pointing_per_heliostat_mrad"]["median"] < 2 * noise
    assert got["pointing_mrad"]["p95"] < 5 * noise
    nominal = score(truth, dataclasses.replace(scenario, plant=sim.plant), suns=16, flux=False)
    assert nominal["pointing_mrad"]["median"] > 10 * got["pointing_mrad"]["median"]


def test_cli_simulate_then_score(tmp_path, capsys):
    out = tmp_path / "plant"
    code, text, err = run_cli(capsys, "simulate", "--heliostats", 4, "--seed", 1, "--years", 0.3, "--out", out,
                              "--json", tmp_path / "sim.json")
    assert code == 0, err
    report = json.loads((tmp_path / "sim.json").read_text())
    assert report["heliostats"] == 4 and report["records"] > 0 and (out / "truth.h5").exists()
    assert len(load_paint(out).records) == report["records"]
    code, text, err = run_cli(capsys, "score", "--truth", out / "truth.h5", "--scenario", out / "truth.h5",
                              "--no-flux", "--json", tmp_path / "score.json")
    assert code == 0, err
    assert json.loads((tmp_path / "score.json").read_text())["pointing_mrad"]["max"] < 1e-9
    # A folder that holds something is never written over.
    code, _, err = run_cli(capsys, "simulate", "--heliostats", 2, "--years", 0.1, "--out", out)
    assert_one_line_error(code, err, str(out), "--out")


def test_images_of_a_few_heliostats_from_their_true_surfaces(tmp_path):
    sim = simulate_plant(SimulationSettings(heliostats=4, seed=8, years=0.5, images=1, images_per_heliostat=3,
                                            **STATIC))
    assert len(sim.images) == 3 and len(sim.report["image_heliostats"]) == 1
    table = load_paint(write_paint_folder(sim, tmp_path / "p")).records
    paths = [p for p in table.flux_centered_png if p]
    assert len(paths) == 3 and all(f"{int(r)}-flux-centered.png" in p for r, p in
                                   zip(table.record_id, table.flux_centered_png) if p)
    image = read_png(paths[0])
    assert image.shape == (64, 64) and float(image.max()) == 1.0
    assert float((image == 1.0).float().mean()) > 0.002  # a saturated plateau
    assert float((image == 0.0).float().mean()) > 0.3  # the background is cut to zero
    # Only the imaged heliostat's surface is defective: its normals are mrad off the ideal ones.
    got = score(truth_scenario(sim), dataclasses.replace(truth_scenario(sim), plant=sim.plant), suns=2, flux=False)
    assert got["surface_mrad"]["max"] > 0.5 and got["surface_mrad"]["median"] < 1e-6


def test_large_plants_stand_on_the_radial_field_and_layouts_are_honoured(tmp_path):
    plant = nominal_plant(SimulationSettings(heliostats=450, seed=1))
    ids, pos = plant.field.ids, plant.field.kinematics.position
    assert len(set(ids)) == 450 and all(HELIOSTAT_DIR.match(h) for h in ids)
    assert float(pos[:, 1].min()) > 10.0 and 25.0 < float(pos[:, :2].norm(dim=-1).min())
    assert float(pos[:, :2].norm(dim=-1).max()) < 400.0
    assert float(torch.cdist(pos[:, :2], pos[:, :2]).add(torch.eye(450) * 1e9).min()) > 3.0  # no two collide
    csv = tmp_path / "layout.csv"
    csv.write_text("id,x,y,z\nA,-10,40,1.6\nB,0,50,1.6\nC,12,60,1.7\nD,5,80,1.5\n")
    sim = simulate_plant(SimulationSettings(seed=2, years=0.3, layout=str(csv)))
    ds = load_paint(write_paint_folder(sim, tmp_path / "p"))
    assert ds.plant.field.ids == ["AA00", "AA01", "AA02", "AA03"] and len(ds.records) > 0
    assert torch.allclose(ds.plant.field.kinematics.position,
                          torch.tensor([[-10.0, 40, 1.6], [0, 50, 1.6], [12, 60, 1.7], [5, 80, 1.5]],
                                       dtype=torch.float64), atol=1e-6)
