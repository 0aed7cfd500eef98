"""The embedded whole-field demo: the generated field (Jülich extent, no collisions, blocking a few per cent),
and the demo's outputs and figures, from the library and from ``heliotwin demo``."""
import csv
import json
import math

import pytest
import torch
from helpers.cli import assert_one_line_error, run_cli

from heliotwin.field.demo import (
    HELIOSTAT_HEIGHT,
    HELIOSTAT_WIDTH,
    demo_field_plant,
    demo_field_positions,
)
from heliotwin.plots import loss_waterfall
from heliotwin.raytrace.field import FACTORS, field_optics, summary
from heliotwin.sun import direction_from_paint_angles
from heliotwin.workflows.demo import CHAIN, run_field_demo


def test_demo_field_is_a_northern_radial_staggered_field_of_julich_extent():
    pos = demo_field_positions(2000, max_east=135.0)  # as demo_field_plant(2000)
    assert pos.shape == (2000, 3)
    r = torch.linalg.vector_norm(pos[:, :2], dim=-1)
    assert float(r.min()) == pytest.approx(27.5, abs=1e-9)
    az = torch.rad2deg(torch.atan2(pos[:, 0], pos[:, 1]))
    assert float(az.abs().max()) < 60.0
    # PAINT's Jülich field: rows from ~25 m to ~300 m north, within about +/-130 m east-west
    assert 200.0 < float(pos[:, 1].max()) < 310.0 and float(pos[:, 0].abs().max()) <= 135.0
    d = torch.cdist(pos[:, :2], pos[:, :2]) + 1e9 * torch.eye(2000, dtype=torch.float64)
    assert float(d.min(1).values.min()) >= math.hypot(HELIOSTAT_WIDTH, HELIOSTAT_HEIGHT) - 1e-9  # no collisions


@pytest.mark.parametrize("az,el", [(0.0, 39.0), (70.0, 25.0)])
def test_demo_field_loses_a_few_percent_to_blocking(az, el):
    """Spaced from the no-blocking distance: exact blocking costs a few per cent at a noon and a morning sun,
    not the ~20 % of a uniformly dense field (1000 heliostats: out to ~200 m)."""
    plant, atm = demo_field_plant(1000)
    sun = direction_from_paint_angles(torch.tensor(math.radians(az), dtype=torch.float64),
                                      torch.tensor(math.radians(el), dtype=torch.float64))
    with torch.no_grad():
        rep = summary(field_optics(plant, sun, atmosphere=atm), plant)
    e = rep["field"]["efficiency_power_weighted"]
    assert 0.95 < e["blocking"] < 1.0 and e["shading"] > 0.85


def test_demo_field_plant_has_canted_facets_and_a_cylinder_receiver():
    plant, atm = demo_field_plant(30)
    assert plant.field.facets.translation.shape == (30, 4, 3)
    assert plant.targets["receiver"].kind == "cylinder" and plant.sun.sunshape == "limb-darkened"
    assert atm.coefficients[0] == pytest.approx(0.006789)


def test_run_field_demo_writes_figures_and_a_consistent_summary(tmp_path):
    rep = run_field_demo(tmp_path, num_heliostats=40)
    for name in ("field_efficiency.png", "losses.png", "flux_equator.png", "flux_optimised.png", "heliostats.csv",
                 "summary.json"):
        assert (tmp_path / name).stat().st_size > 0
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["heliostats"] == 40
    a = saved["aim_points"]
    assert a["peak_limit_w_m2"] == pytest.approx(0.75 * a["equator_peak_w_m2"])
    assert a["optimised_peak_w_m2"] < 0.9 * a["equator_peak_w_m2"]  # the optimiser really spreads the flux
    assert a["violation"] == 0.0 and a["optimised_peak_w_m2"] <= a["peak_limit_w_m2"]  # met on the exact map
    assert a["power_vs_equator"] > 0.98
    assert rep["field"]["efficiency"]["total"] == pytest.approx(saved["field"]["efficiency"]["total"])
    # the demo's loss chain holds the tower's shadow (after the heliostats' own shading) and adds up: DNI x mirror
    # area = the chain's power on the receiver + every stage's loss
    chain = saved["chain"]
    assert list(saved["losses"]) == list(CHAIN) == ["cosine", "shading", "tower_shading", *FACTORS[2:]]
    lost = sum(saved["losses"][k]["power_w"] for k in CHAIN)
    assert saved["dni_w_m2"] * saved["mirror_area_m2"] == pytest.approx(chain["power_w"] + lost, rel=1e-9)
    # the 40 heliostats nearest the tower, north of it, with a noon sun in the south: its shadow takes a real share,
    # and the chain's MW is the field model's (which leaves the shadow out, per heliostat in the CSV) times it
    assert 0.02 < saved["losses"]["tower_shading"]["fraction"] < 0.5
    rows = list(csv.DictReader(open(tmp_path / "heliostats.csv")))
    assert len(rows) == 40 and sum(float(r["power_w"]) for r in rows) == pytest.approx(saved["receiver"]["power_w"])
    assert chain["power_w"] == pytest.approx(chain["tower_shading_power_weighted"] * saved["receiver"]["power_w"])
    assert chain["power_w"] < 0.98 * saved["receiver"]["power_w"]
    assert chain["efficiency"] == pytest.approx(chain["power_w"] / (saved["dni_w_m2"] * saved["mirror_area_m2"]))
    # the waterfall draws the shadow as its own falling bar, and what reaches the receiver is the chain's share
    steps = loss_waterfall(saved["losses"], saved["dni_w_m2"] * saved["mirror_area_m2"])
    assert [st["name"] for st in steps] == list(CHAIN)
    assert 100.0 - sum(st["lost_pct"] for st in steps) == pytest.approx(100.0 * chain["efficiency"], rel=1e-9)


def test_demo_command_runs_the_field_and_stages_its_outputs(tmp_path, capsys):
    out, js = tmp_path / "demo", tmp_path / "demo.json"
    code, stdout, _ = run_cli(capsys, "demo", "-o", out, "--heliostats", "30", "--iterations", "3", "--json", js)
    assert code == 0 and "field efficiency" in stdout
    chain = json.loads(js.read_text())["chain"]
    assert f"{chain['power_w'] / 1e6:.2f} MW on the receiver (the tower's shadow included" in stdout
    saved = json.loads((out / "summary.json").read_text())
    assert json.loads(js.read_text())["receiver"] == saved["receiver"] and saved["heliostats"] == 30
    assert 0.5 < saved["field"]["efficiency_power_weighted"]["total"] < 0.95
    assert sorted(p.name for p in out.iterdir()) == sorted(saved["files"])


def test_demo_command_refuses_classic_options_without_classic(tmp_path, capsys):
    code, _, err = run_cli(capsys, "demo", "-o", tmp_path / "demo", "--integrator", "mc")
    assert_one_line_error(code, err, "--integrator", "--classic")
    assert list(tmp_path.iterdir()) == []
