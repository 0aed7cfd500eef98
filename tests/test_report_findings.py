"""The findings of issue 32 that a plant page reads from, each pinned: ``scenario show`` counts from the full
lists, ``scenario export`` round-trips a simulated plant (PAINT-like facets, tilted cylinder receiver), ``score``
refuses a truth that ``simulate`` did not write, a closed pipe ends quietly, the demo's loss chart is a
waterfall that adds up, and receiver maps name their instant, their limit and the angle axis's origin."""
from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import pytest
import torch

import heliotwin
from heliotwin.errors import HeliotwinError
from heliotwin.evaluation import score, truth_missing
from heliotwin.field.demo import demo_field_plant
from heliotwin.field.layout import plant_from_layout
from heliotwin.io.export import export_solarpilot
from heliotwin.io.scenario import next_scenario, provenance_entry, write_scenario
from heliotwin.plots import angle_origin, loss_waterfall, plot_loss_waterfall, plot_receiver_flux
from heliotwin.raytrace.field import FACTORS, field_optics
from heliotwin.simulate import SimulationSettings, simulate_plant, truth_scenario
from heliotwin.simulate.plant import nominal_plant
from heliotwin.sun import direction_from_paint_angles
from heliotwin.workflows.demo import _loss_breakdown
from heliotwin.workflows.show import LISTED_IDS, describe_scenario, format_description

SUN = direction_from_paint_angles(torch.tensor(0.35, dtype=torch.float64), torch.tensor(0.7, dtype=torch.float64))


@pytest.fixture(scope="module")
def demo():
    """The demo plant (60 heliostats), its atmosphere and its field result at :data:`SUN`."""
    plant, atm = demo_field_plant(60)
    with torch.no_grad():
        return plant, atm, field_optics(plant, SUN, atmosphere=atm)


@pytest.fixture(scope="module")
def small_sim():
    """A simulated plant of 8 heliostats with a month of records (its truth is a ``simulate`` truth)."""
    return simulate_plant(SimulationSettings(heliostats=8, years=0.08, seed=5))


def _scenario(plant, learned=None, step="from-layout"):
    return next_scenario(None, plant, learned=learned or {}, step=provenance_entry(step))


# ------------------------------------------------------------------------------------------ scenario show
def test_show_counts_calibrated_heliostats_from_the_full_list_and_caps_only_the_listed_ids(demo):
    many = [f"H{i:04d}" for i in range(LISTED_IDS + 145)]
    sc = _scenario(demo[0], {"calibration": {"method": "lm", "heliostats": many}})
    d = describe_scenario(sc)
    k = d["learned"]["kinematics"]
    assert k["count"] == 1145 and len(k["heliostats"]) == LISTED_IDS
    assert "calibrated (lm) for 1145 heliostats" in format_description(d)


# ---------------------------------------------------------------------------------------- scenario export
def test_export_round_trips_a_simulated_plant_with_its_tilted_receiver_and_paint_like_facets(tmp_path):
    plant = nominal_plant(SimulationSettings(heliostats=12))
    rec = plant.targets["receiver"]
    assert abs(float(rec.normal[2])) > 0.1  # PAINT's receiver: tilted, not vertical
    export_solarpilot(plant, tmp_path / "layout.csv", tmp_path / "plant.toml")
    again, atm = plant_from_layout(tmp_path / "layout.csv", tmp_path / "plant.toml")
    back = again.targets["receiver"]
    for name in ("center", "normal", "up", "right"):
        torch.testing.assert_close(getattr(back, name), getattr(rec, name), atol=1e-9, rtol=0, msg=name)
    with torch.no_grad():
        want, got = field_optics(plant, SUN, atmosphere=atm), field_optics(again, SUN, atmosphere=atm)
    for name in FACTORS + ("efficiency",):
        torch.testing.assert_close(getattr(got, name), getattr(want, name), atol=1e-6, rtol=0, msg=name)
    assert float(got.power_w.sum()) == pytest.approx(float(want.power_w.sum()), rel=1e-6)
    torch.testing.assert_close(got.flux, want.flux, atol=1e-4 * float(want.flux.max()), rtol=0)


def test_export_refuses_facets_it_cannot_describe(demo, tmp_path):
    plant = demo[0]
    f = plant.field.facets
    skewed = dataclasses.replace(f, canting_e=f.canting_e + torch.tensor([0.0, 0.01, 0.0], dtype=f.canting_e.dtype))
    odd = dataclasses.replace(plant, field=dataclasses.replace(plant.field, facets=skewed))
    with pytest.raises(HeliotwinError, match="canted otherwise than on-axis"):
        export_solarpilot(odd, tmp_path / "layout.csv", tmp_path / "plant.toml")


# ------------------------------------------------------------------------------------------------- score
def test_score_refuses_a_truth_that_simulate_did_not_write_and_names_what_is_missing(small_sim):
    truth = truth_scenario(small_sim)
    assert truth_missing(truth) == []
    plain = _scenario(small_sim.plant)
    with pytest.raises(HeliotwinError) as err:
        score(plain, truth, suns=2, flux=False)
    text = str(err.value)
    assert "not a 'heliotwin simulate' truth" in text and "/learned/simulation" in text
    assert "method 'truth'" in text and "'simulate' provenance step" in text
    calibrated = dataclasses.replace(truth, learned={**truth.learned, "calibration": {
        **truth.learned["calibration"], "method": "lm"}})
    assert truth_missing(calibrated) == ["/learned/calibration of method 'truth' (the true kinematics; found "
                                         "method 'lm')"]


# ------------------------------------------------------------------------------------------- closed pipe
def test_a_closed_pipe_ends_the_command_quietly_with_its_usual_exit_status(demo, tmp_path):
    path = write_scenario(_scenario(demo[0]), tmp_path / "plant.h5")
    src = os.path.dirname(os.path.dirname(heliotwin.__file__))  # the checkout under test, not an installed copy
    env = dict(os.environ, HELIOTWIN_DEBUG="0", PYTHONPATH=os.pathsep.join([src, os.environ.get("PYTHONPATH", "")]))
    p = subprocess.Popen([sys.executable, "-m", "heliotwin", "scenario", "show", str(path)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, env=env)
    p.stdout.close()  # the reader is gone before the command writes (``| head -0``)
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 0 and err == ""


# ---------------------------------------------------------------------------------------- loss waterfall
def test_loss_fractions_of_the_demo_add_up_to_the_plant_loss(demo):
    plant, _, result = demo
    losses = _loss_breakdown(result)
    total = result.dni * float(result.mirror_area.double().sum())
    # the demo's chain: the field model's product times the tower's shadow (which the product leaves out)
    delivered = float((result.dni * result.mirror_area.double() * result.efficiency.double()
                       * result.tower_shading.double()).sum())
    assert list(losses) == ["cosine", "shading", "tower_shading", *FACTORS[2:]]
    assert sum(v["fraction"] for v in losses.values()) == pytest.approx(1.0 - delivered / total, rel=1e-9)
    # the reflectance stage: its loss of DNI x area is smaller than its own loss (1 - reflectivity)
    assert losses["reflectance"]["fraction"] < losses["reflectance"]["own_fraction"]
    assert losses["reflectance"]["own_fraction"] == pytest.approx(1.0 - plant.sun.reflectivity, rel=1e-6)


def test_the_loss_waterfall_bars_add_up_to_the_plant_loss():
    losses = {k: {"power_w": w} for k, w in zip(FACTORS, (1.0e6, 0.2e6, 0.3e6, 0.1e6, 0.5e6, 0.9e6))}
    steps = loss_waterfall(losses, 10e6)
    assert [s["name"] for s in steps] == list(FACTORS)
    assert steps[0]["top_pct"] == 100.0 and steps[1]["top_pct"] == pytest.approx(90.0)
    assert steps[-1]["own_loss_pct"] == pytest.approx(100.0 * 0.9 / 7.9)  # 1 - factor of what reaches it
    fig = plot_loss_waterfall(losses, 10e6)
    ax = fig.axes[0]
    falling = [p for p in ax.patches if p.get_gid() == "loss"]
    assert len(falling) == len(FACTORS)
    assert sum(p.get_height() for p in falling) == pytest.approx(30.0)  # 3 MW of 10 MW
    tops = [p.get_y() + p.get_height() for p in falling]
    assert tops == pytest.approx([100.0, 90.0, 88.0, 85.0, 84.0, 79.0])  # each falls from where the last ended
    assert "add up to 30.0 %" in ax.get_title()


# ------------------------------------------------------------------------------------------ receiver maps
def test_receiver_maps_name_time_sun_limit_and_where_the_angle_axis_starts(demo):
    plant, _, result = demo
    receiver = plant.targets["receiver"]
    limit = 0.5 * float(result.flux.max())
    fig = plot_receiver_flux({"equator aiming": result.flux}, receiver, limit_w_m2=limit,
                             instant={"time_utc": "2023-03-20T11:30:00+00:00", "sun_enu": SUN})
    title = fig._suptitle.get_text()
    assert "2023-03-20T11:30Z" in title and "sun azimuth" in title and "elevation 40.1°" in title
    ax = fig.axes[0]
    assert any(type(c).__name__ in ("QuadContourSet", "ContourSet") for c in ax.collections + ax.get_children())
    assert any(f"limit {limit / 1e3:.0f} kW/m²" in t.get_text() for t in ax.get_legend().get_texts())
    n = receiver.normal.tolist()
    facing = "N" if n[1] > 0.7 else "S" if n[1] < -0.7 else "E" if n[0] > 0 else "W"
    assert angle_origin(receiver).startswith(f"0° = aperture normal, facing {facing} ")
    labels = [a.get_xlabel() for a in fig.axes[0].child_axes]
    assert any("0° = aperture normal" in t for t in labels)
