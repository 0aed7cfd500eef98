"""Aim points under a peak-flux limit: the optimiser meets a limit that equator aiming exceeds by 40 %, keeps
almost all of the power, beats the aiming-factor heuristic, and goes through the scenario file to ``field``."""
import json
import math

import pytest
import torch
from helpers.cli import run_cli
from helpers.field import dense_field, write_layout, write_plant_toml

from heliotwin.field.layout import plant_from_layout
from heliotwin.optimise.aimpoints import aiming_factor, evaluate, optimise_aimpoints
from heliotwin.raytrace.field import equator_aim_points
from heliotwin.sun import direction_from_paint_angles

SUN_EL = 50.0


@pytest.fixture(scope="module")
def small_field(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("aim")
    layout = write_layout(tmp, dense_field(4, 6, first_row=30.0, spacing=(4.5, 4.0)))
    toml = write_plant_toml(tmp)
    plant, atm = plant_from_layout(layout, toml)
    sun = direction_from_paint_angles(torch.tensor(0.0, dtype=torch.float64),
                                      torch.tensor(math.radians(SUN_EL), dtype=torch.float64))
    eq = evaluate(plant, sun, equator_aim_points(plant.targets["receiver"], plant.field.kinematics.position), atm)
    return plant, atm, sun, eq, layout, toml


def test_optimised_aim_points_meet_the_limit_with_little_power_lost(small_field):
    plant, atm, sun, eq, _, _ = small_field
    limit = eq.peak_flux_w_m2 / 1.4  # equator aiming exceeds the limit by 40 %
    best = optimise_aimpoints(plant, sun, limit, atmosphere=atm, iterations=100)
    assert best.violation(limit) == 0.0  # exact (hard-occlusion) re-evaluation, not the training model
    assert best.power_w >= 0.98 * eq.power_w
    rec = plant.targets["receiver"]
    y = rec.to_local(best.aim)[:, 1]
    assert float(y.abs().max()) <= 0.5 * rec.height  # aim points stay on the receiver
    factor = aiming_factor(plant, sun, limit, atmosphere=atm)
    # the heuristic either cannot meet the limit at all, or meets it with less power
    assert factor.violation(limit) > 0.0 or best.power_w > factor.power_w


def test_aimpoints_command_writes_scenario_read_by_field(small_field, tmp_path, capsys):
    _, _, _, eq, layout, toml = small_field
    h5, aimed, js, fj = tmp_path / "p.h5", tmp_path / "aimed.h5", tmp_path / "a.json", tmp_path / "f.json"
    assert run_cli(capsys, "scenario", "from-layout", layout, "--config", toml, "-o", h5)[0] == 0
    limit = eq.peak_flux_w_m2 / 1.4
    code, out, err = run_cli(capsys, "aimpoints", "--scenario", h5, "--sun-azimuth", "0", "--sun-elevation", SUN_EL,
                             "--peak-limit", limit, "--iterations", 60, "-o", aimed, "--json", js)
    assert code == 0, err
    rep = json.loads(js.read_text())
    assert rep["equator"]["violation"] == pytest.approx(0.4, abs=1e-3)
    assert set(rep) >= {"equator", "aiming_factor", "optimised"}
    code, out, err = run_cli(capsys, "field", "--scenario", aimed, "--aim", "scenario", "--sun-azimuth", "0",
                             "--sun-elevation", SUN_EL, "--json", fj)
    assert code == 0, err
    field = json.loads(fj.read_text())
    # motor steps through the plant's kinematics put the reflected sun on the optimised aim points
    from heliotwin.field import kinematics as kin_ops
    from heliotwin.geometry import angle_between, reflect
    from heliotwin.io.scenario import load_scenario

    sc = load_scenario(aimed)
    ap = sc.learned["aimpoints"]
    ok = ap["reachable"]
    assert int(ok.sum()) == rep["optimised"]["motor_steps_reachable"] > 0
    R, c = kin_ops.forward(sc.plant.field.kinematics.index(torch.nonzero(ok).flatten()), ap["motor_steps"][ok])
    sun = ap["sun_direction"]
    out_dir = reflect(-sun.expand(len(c), 3), kin_ops.mirror_normal(R))
    assert float(angle_between(out_dir, ap["aim"][ok] - c).max()) < 1e-6
    assert field["receiver"]["peak_flux_w_m2"] == pytest.approx(rep["optimised"]["peak_flux_w_m2"], rel=1e-6)
    assert field["receiver"]["power_w"] == pytest.approx(rep["optimised"]["power_w"], rel=1e-6)
