"""Outputs an engineer can read and reuse: receiver flux figures on one scale with the limit contour, the
numeric map as CSV and in the JSON (the same numbers), the shipped examples, the demo's scenario, and
``scenario show``/``export`` on it."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from helpers.cli import run_cli

from heliotwin.examples import EXAMPLES, example_path
from heliotwin.field.demo import demo_field_plant
from heliotwin.field.layout import plant_from_layout
from heliotwin.io.export import read_flux_map_csv
from heliotwin.io.scenario import load_scenario
from heliotwin.plots import plot_receiver_flux, receiver_extent
from heliotwin.workflows.demo import run_field_demo


@pytest.fixture(scope="module")
def layout_scenario(tmp_path_factory):
    """The shipped example layout + plant description, as a user builds it (``scenario from-layout``)."""
    folder = tmp_path_factory.mktemp("examples")
    code = __import__("heliotwin.cli", fromlist=["main"]).main(
        ["scenario", "from-layout", str(example_path("layout.csv")), "--config", str(example_path("plant.toml")),
         "-o", str(folder / "plant.h5")])
    assert code == 0
    return folder / "plant.h5"


def test_shipped_examples_build_the_plant_they_describe():
    plant, atm = plant_from_layout(example_path("layout.csv"), example_path("plant.toml"))
    assert set(EXAMPLES) == {"layout.csv", "plant.toml"}
    assert len(plant.field.ids) == 300
    rec = plant.targets["receiver"]
    assert rec.kind == "cylinder" and float(rec.radius) == 4.1 and float(rec.height) == 5.0
    # the shipped layout is the demo field's first 300 heliostats (to the 1 mm it is written with)
    demo, _ = demo_field_plant(300)
    torch.testing.assert_close(plant.field.kinematics.position, demo.field.kinematics.position, atol=6e-4, rtol=0)


def test_examples_copy_refuses_to_overwrite(tmp_path, capsys):
    code, out, _ = run_cli(capsys, "examples", "--copy", tmp_path)
    assert code == 0 and sorted(p.name for p in tmp_path.iterdir()) == ["layout.csv", "plant.toml"]
    code, _, err = run_cli(capsys, "examples", "--copy", tmp_path)
    assert code == 2 and "exists" in err


def test_field_flux_figure_csv_and_json_hold_the_same_map(layout_scenario, tmp_path, capsys):
    code, _, err = run_cli(capsys, "field", "--scenario", layout_scenario, "--sun-azimuth", 0, "--sun-elevation", 50,
                           "--json", tmp_path / "f.json", "--flux", tmp_path / "f.png", "--flux-csv",
                           tmp_path / "f.csv")
    assert code == 0, err
    rep = json.loads((tmp_path / "f.json").read_text())
    flux, xs, ys = read_flux_map_csv(tmp_path / "f.csv")
    np.testing.assert_allclose(flux, np.array(rep["receiver"]["flux_map_w_m2"]), rtol=1e-5)
    ext = rep["receiver"]["flux_map_extent_m"]
    assert flux.shape == (20, 48) and ext == pytest.approx([-12.88, 12.88, -2.5, 2.5], abs=0.01)  # 2 pi r x height
    cell = (ext[1] - ext[0]) * (ext[3] - ext[2]) / flux.size
    assert flux.sum() * cell == pytest.approx(rep["receiver"]["map_power_w"], rel=1e-5)  # the map is in W/m^2
    assert flux.max() == pytest.approx(rep["receiver"]["peak_flux_w_m2"], rel=1e-5)
    assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_receiver_figure_shares_one_scale_and_draws_the_limit():
    plant, _ = demo_field_plant(4)
    rec = plant.targets["receiver"]
    low, high = torch.zeros(20, 48), torch.zeros(20, 48)
    low[8:12, 20:28], high[9:11, 22:26] = 300e3, 900e3
    fig = plot_receiver_flux({"before": high, "after": low}, rec, limit_w_m2=600e3)
    panels = [ax for ax in fig.axes if ax.images]
    assert len(panels) == 2
    assert {im.get_clim() for ax in panels for im in ax.images} == {(0.0, 900.0)}  # kW/m^2, one scale
    assert panels[0].get_xlabel() == "arc along the unrolled receiver [m]"
    assert panels[0].images[0].get_extent() == pytest.approx(receiver_extent(rec))
    assert len(panels[0].collections) == 1 and not panels[1].collections  # the limit contour where it is crossed
    assert "peak 900 kW/m²" in panels[0].get_title() and "peak 300 kW/m²" in panels[1].get_title()


def test_aimpoints_flux_folder_has_before_after_and_numeric_maps(layout_scenario, tmp_path, capsys):
    (tmp_path / "maps").mkdir()
    code, _, err = run_cli(capsys, "aimpoints", "--scenario", layout_scenario, "--sun-azimuth", 0, "--sun-elevation",
                           50, "--peak-limit", 100000, "--iterations", 40, "--no-baselines", "--resolution", "24x10",
                           "-o", tmp_path / "aimed.h5", "--json", tmp_path / "a.json", "--flux", tmp_path / "maps",
                           "--quiet")
    assert code == 0, err
    names = sorted(p.name for p in (tmp_path / "maps").iterdir())
    assert names == ["i000_before_after.png", "i000_equator.csv", "i000_equator.png", "i000_optimised.csv",
                     "i000_optimised.png", "i000_utilisation.png"]
    rep = json.loads((tmp_path / "a.json").read_text())
    eq, _, _ = read_flux_map_csv(tmp_path / "maps" / "i000_equator.csv")
    opt, _, _ = read_flux_map_csv(tmp_path / "maps" / "i000_optimised.csv")
    assert eq.shape == (10, 24)
    assert eq.max() == pytest.approx(rep["equator"]["peak_flux_w_m2"], rel=1e-5)
    assert opt.max() == pytest.approx(rep["optimised"]["peak_flux_w_m2"], rel=1e-5)


def test_demo_writes_a_scenario_to_go_on_from(tmp_path, capsys):
    rep = run_field_demo(tmp_path / "demo", num_heliostats=40, iterations=40)
    assert "plant.h5" in rep["files"] and (tmp_path / "demo" / "flux_before_after.png").exists()
    sc = load_scenario(tmp_path / "demo" / "plant.h5")
    assert len(sc.plant.field.ids) == 40 and "atmosphere" in sc.extras
    assert [p["step"] for p in sc.provenance] == ["demo"]
    # scenario show: what it holds, in text and JSON
    code, out, _ = run_cli(capsys, "scenario", "show", tmp_path / "demo" / "plant.h5", "--json", tmp_path / "s.json")
    assert code == 0 and "40 heliostats" in out and "nominal (not calibrated)" in out and "heliotwin demo" in out
    shown = json.loads((tmp_path / "s.json").read_text())
    assert shown["plant"]["heliostats"] == 40 and shown["learned"]["aimpoints"]["instants"] == 1
    assert "/learned/aimpoints" in shown["learned_groups"]
    assert shown["provenance"][0]["step"] == "demo" and shown["provenance"][0]["utc"]
    # go on from it: field with the stored aim points meets the demo's limit
    code, _, err = run_cli(capsys, "field", "--scenario", tmp_path / "demo" / "plant.h5", "--aim", "scenario",
                           "--time", rep["time_utc"], "--json", tmp_path / "f.json")
    assert code == 0, err
    field = json.loads((tmp_path / "f.json").read_text())
    assert field["receiver"]["peak_flux_w_m2"] <= rep["aim_points"]["peak_limit_w_m2"] * 1.001
    # and export it for SolarPILOT / SolTrace
    code, _, err = run_cli(capsys, "scenario", "export", tmp_path / "demo" / "plant.h5", "--solarpilot",
                           tmp_path / "sp.csv", "--soltrace", tmp_path / "st.stinput", "--time", rep["time_utc"])
    assert code == 0, err
    again, _ = plant_from_layout(tmp_path / "sp.csv", tmp_path / "sp.toml")
    torch.testing.assert_close(again.field.kinematics.position, sc.plant.field.kinematics.position, atol=1e-5,
                               rtol=0)


def test_validate_keeps_calibrated_and_nominal_heliostats_apart():
    """A partly learned plant: the calibrated heliostats' medians are not mixed with the nominal ones', and
    the report says what each metric computes (its centred L1 is not reconstruct's)."""
    from types import SimpleNamespace

    from heliotwin.workflows.validate import METRICS, split_by_state

    def h(err, l1):
        return {"median_pointing_error_mrad": err, "median_distance_m": err / 10, "median_centered_l1": l1,
                "median_centered_cross_correlation": None}

    report = {"heliostats": {"AK32": h(0.6, None), "BH60": h(0.8, None), "AA39": h(3.0, 0.205), "BF41": h(5.0, None)}}
    scenario = SimpleNamespace(learned={"calibration": {"method": "lm", "heliostats": ["AK32", "BH60"]},
                                        "surfaces": {"AA39": {}}})
    split_by_state(report, scenario)
    assert report["by_state"]["calibrated"]["heliostats"] == ["AK32", "BH60"]
    assert report["by_state"]["calibrated"]["median_pointing_error_mrad"] == pytest.approx(0.7)
    assert report["by_state"]["nominal"]["median_pointing_error_mrad"] == pytest.approx(4.0)
    assert report["by_state"]["nominal"]["median_centered_l1"] == pytest.approx(0.205)
    assert report["heliostats"]["AA39"] | {} == {**h(3.0, 0.205), "kinematics": "nominal", "surface": "learned"}
    assert "camera model" in METRICS["median_centered_l1"] and "l1_learned" in METRICS["median_centered_l1"]


def test_prediction_figure_draws_the_year_with_units():
    from heliotwin.plots import plot_prediction

    rep = {"heliostat": "AA39", "target": "t", "year": 2023, "every": "1h", "instants": 2,
           "series": {"time": ["2023-06-21T10:00:00+00:00", "2023-06-21T11:00:00+00:00"], "power_w": [3e3, 4e3],
                      "peak_learned_w_m2": [5e4, 6e4], "peak_ideal_w_m2": [7e4, 8e4],
                      "l1_ideal_vs_learned": [0.1, 0.2]}}
    fig = plot_prediction(rep)
    ax = fig.axes
    assert [a.get_ylabel() for a in ax] == ["power on the target [kW]", "peak flux [kW/m²]",
                                           "L1 of the unit-sum images [-]"]
    assert list(ax[0].lines[0].get_ydata()) == [3.0, 4.0] and len(ax[1].lines) == 2


def test_api_field_and_aimpoints_call_the_workflows(layout_scenario, tmp_path, capsys):
    from heliotwin import api

    rep, result = api.field_efficiency(layout_scenario, sun_azimuth_deg=0, sun_elevation_deg=50)
    code, _, _ = run_cli(capsys, "field", "--scenario", layout_scenario, "--sun-azimuth", 0, "--sun-elevation", 50,
                         "--json", tmp_path / "f.json")
    cli = json.loads((tmp_path / "f.json").read_text())
    assert rep["receiver"]["power_w"] == pytest.approx(cli["receiver"]["power_w"], rel=1e-9)
    sc = load_scenario(layout_scenario)
    limit = 0.8 * rep["receiver"]["peak_flux_w_m2"]
    aimed, arep, maps = api.optimise_aimpoints(sc, limit, sun_azimuth_deg=0, sun_elevation_deg=50,
                                               settings=api.AimpointSettings(limit, iterations=40, baselines=False),
                                               output=tmp_path / "aimed.h5")
    assert arep["optimised"]["peak_flux_w_m2"] <= limit * 1.001 and len(maps) == 1
    # the aim points' exact check sums its map in float64, `field` in float32: the same map to ~1e-5 of the peak
    assert float(maps[0]["equator aiming"].max()) == pytest.approx(rep["receiver"]["peak_flux_w_m2"], rel=2e-5)
    fig = api.plot_receiver_flux(maps[0], sc.plant.targets["receiver"], limit_w_m2=limit)
    assert len([a for a in fig.axes if a.images]) == 2
    written = api.export_plant(tmp_path / "aimed.h5", solarpilot=tmp_path / "sp.csv")
    assert written["solarpilot_config"].endswith("sp.toml") and (tmp_path / "sp.toml").exists()
    # what was learned goes out: the stored optimised aim points, not equator aiming (issue 42 item 5)
    assert written["aim_points"] == "optimised"
    stored = load_scenario(tmp_path / "aimed.h5").learned["aimpoints"]["aim"]
    with open(tmp_path / "sp.csv", newline="") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    table = torch.tensor([[float(r[k]) for k in ("x_aimpoint", "y_aimpoint", "z_aimpoint")] for r in rows])
    assert torch.allclose(table, torch.as_tensor(stored, dtype=table.dtype), atol=1e-4)
    eq = api.export_plant(tmp_path / "aimed.h5", solarpilot=tmp_path / "eq.csv", aim="equator")
    with open(tmp_path / "eq.csv", newline="") as fh:
        zs = {round(float(r["z_aimpoint"]), 6) for r in csv.DictReader(ln for ln in fh if not ln.startswith("#"))}
    assert eq["aim_points"] == "equator" and len(zs) == 1  # the receiver centre without a sun
    assert float(table[:, 2].std()) > 0.01  # the optimised ones spread over the receiver


def test_progress_is_a_line_per_stage_in_a_log_and_silent_when_quiet():
    import io

    from heliotwin.progress import Stages

    log, err = io.StringIO(), io.StringIO()
    with Stages(2, "heliotwin demo", stream=err, lines=log) as bar:
        bar.start("field model")
        bar.step("field model")
        bar.start("aim points")
        bar.step("aim points")
    lines = log.getvalue().splitlines()
    assert lines[0] == "heliotwin demo: 1/2 field model ..."
    assert lines[3].startswith("heliotwin demo: 2/2 aim points done")
    assert err.getvalue() == ""  # no bar's carriage returns in a log, nothing on stderr
    quiet = io.StringIO()
    with Stages(2, "x", enabled=False, stream=io.StringIO(), lines=quiet) as bar:
        bar.start("a")
        bar.step("a")
    assert quiet.getvalue() == ""


def test_a_step_on_an_uncalibrated_heliostat_says_it_runs_on_nominal_kinematics():
    from types import SimpleNamespace

    from heliotwin.workflows.show import kinematics_note

    sc = SimpleNamespace(path="a.h5", learned={"calibration": {"method": "lm", "heliostats": ["AK32", "BH60"]}})
    note = kinematics_note(sc, "AA39")
    assert note.startswith("AA39: no calibration in a.h5 (calibrated: AK32, BH60)") and "nominal kinematics" in note
    assert "\n" not in note
    assert kinematics_note(sc, "AK32") == "AK32: calibrated kinematics (lm) from a.h5"
    assert "no calibration (no scenario)" in kinematics_note(None, "AA39")
