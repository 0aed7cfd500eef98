"""The embedded whole-field demo: the generated field, and the demo's outputs and figures."""
import json
import math

import pytest
import torch

from heliotwin.field.demo import demo_field_plant, demo_field_positions, run_field_demo


def test_demo_field_is_a_northern_radial_staggered_field():
    pos = demo_field_positions(2000)
    assert pos.shape == (2000, 3)
    r = torch.linalg.vector_norm(pos[:, :2], dim=-1)
    assert float(r.min()) == pytest.approx(27.5, abs=1e-9)
    az = torch.rad2deg(torch.atan2(pos[:, 0], pos[:, 1]))
    assert float(az.abs().max()) < 60.0
    d = torch.cdist(pos[:, :2], pos[:, :2]) + 1e9 * torch.eye(2000, dtype=torch.float64)
    assert float(d.min(1).values.min()) > math.hypot(3.22, 2.56) / 2 * 1.5  # no two mirrors collide


def test_demo_field_plant_has_canted_facets_and_a_cylinder_receiver():
    plant, atm = demo_field_plant(30)
    assert plant.field.facets.translation.shape == (30, 4, 3)
    assert plant.targets["receiver"].kind == "cylinder" and plant.sun.sunshape == "limb-darkened"
    assert atm.coefficients[0] == pytest.approx(0.006789)


def test_run_field_demo_writes_figures_and_a_consistent_summary(tmp_path):
    rep = run_field_demo(tmp_path, num_heliostats=40, iterations=15)
    for name in ("field_efficiency.png", "losses.png", "flux_equator.png", "flux_optimised.png", "summary.json"):
        assert (tmp_path / name).stat().st_size > 0
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["heliostats"] == 40
    a = saved["aim_points"]
    assert a["peak_limit_w_m2"] == pytest.approx(0.75 * a["equator_peak_w_m2"])
    assert a["optimised_peak_w_m2"] < 0.9 * a["equator_peak_w_m2"]  # the optimiser really spreads the flux
    assert a["power_vs_equator"] > 0.95
    assert rep["field"]["efficiency"]["total"] == pytest.approx(saved["field"]["efficiency"]["total"])
