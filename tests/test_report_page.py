"""``heliotwin report``: the plant page's content, checked on the HTML and on the gathered state (the browser
check is benchmarks/bench_report.py). A small simulated plant carries a hand-made calibration posterior and update
history, so every number on the page is known."""
from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import torch
from helpers.cli import run_cli

from heliotwin.cli import build_parser
from heliotwin.cli.report import COLOURS
from heliotwin.field.plant import Kinematics
from heliotwin.io.scenario import next_scenario, provenance_entry, write_scenario
from heliotwin.optimise.aimstate import aimpoint_state, instant_state
from heliotwin.raytrace.field import equator_aim_points
from heliotwin.simulate import SimulationSettings
from heliotwin.simulate.plant import nominal_plant
from heliotwin.workflows.field import sun_direction_at
from heliotwin.workflows.report import (
    QUANTITIES,
    ReportSettings,
    alarm_rows,
    heliostat_detail,
    heliostat_state,
    plant_report,
    surface_deviation,
)
from heliotwin.workflows.report_page import render_page

NAMES = ("initial_angle_1", "initial_angle_2", "joint_tilt_1_n")
DAY = 86400.0
T0 = 1.7e9  # POSIX s of the first record
WHEN = "2023-03-20T11:30:00+00:00"


def _learned(plant, with_aim: bool) -> dict:
    """Calibration (posterior: variance (k+1)^2 1e-8 rad^2 on each offset of heliostat k) and two updates: every
    heliostat two records a day apart; heliostat 1 alarms in update 2 (statistic 40), heliostat 2 in update 1
    (statistic 12) and update 2 (statistic 9)."""
    ids = list(plant.field.ids)
    h = len(ids)
    cov = torch.zeros(h, 3, 3, dtype=torch.float64)
    for k in range(h):
        cov[k, 0, 0] = cov[k, 1, 1] = (k + 1) ** 2 * 1e-8
        cov[k, 2, 2] = 1e-8
    kin = plant.field.kinematics
    cal = {"method": "lm", "heliostats": ids, "parameter_names": list(NAMES),
           "deviations": torch.zeros(h, 3, dtype=torch.float64),
           "nominal": {f.name: getattr(kin, f.name) for f in dataclasses.fields(Kinematics)},
           "posterior": {"covariance": cov, "noise_rad": torch.full((h,), 2e-4, dtype=torch.float64)}}
    heliostat = torch.arange(h).repeat(2)
    t = torch.cat([torch.full((h,), T0), torch.full((h,), T0 + DAY)]) + heliostat.double() * 60.0
    t[h + 3] = T0 + 5 * DAY  # heliostat 3 has the latest record of the plant
    update = torch.cat([torch.ones(h), torch.full((h,), 2.0)]).long()
    alarm = torch.zeros(2 * h, dtype=torch.bool)
    stat = torch.ones(2 * h, dtype=torch.float64)
    for row, s in ((h + 1, 40.0), (2, 12.0), (h + 2, 9.0)):
        alarm[row], stat[row] = True, s
    mean = torch.zeros(2 * h, 3)
    mean[:, 0] = 1e-3 * torch.arange(2 * h)
    history = {"heliostat": heliostat.int(), "record_id": torch.arange(2 * h) + 1000, "time": t,
               "mean": mean, "variance": torch.full((2 * h, 3), 1e-8), "innovation": torch.full((2 * h, 2), 3e-4),
               "d2": stat.clone(), "statistic": stat, "window": torch.ones(2 * h, dtype=torch.int32),
               "alarm": alarm, "predicted_error": torch.full((2 * h,), 5e-4, dtype=torch.float64),
               "update": update.int()}
    learned = {"calibration": cal,
               "assimilation": {"heliostats": ids, "parameter_names": list(NAMES), "history": history,
                                "threshold": torch.tensor([6.0], dtype=torch.float64), "updates": torch.tensor([2]),
                                "calibrations": torch.tensor([1]), "kappa": torch.tensor([1.0], dtype=torch.float64),
                                "false_alarm_rate": torch.tensor([1e-3], dtype=torch.float64)}}
    if with_aim:
        sun = sun_direction_at(plant, time_utc=WHEN)
        aim = equator_aim_points(plant.targets["receiver"], kin.position)
        learned["aimpoints"] = aimpoint_state({"i000": instant_state(plant, WHEN, aim, sun, power_w=1.0,
                                                                     peak_flux_w_m2=1.0)}, peak_limit_w_m2=2.0e5)
    return learned


@pytest.fixture(scope="module")
def scenario():
    plant = nominal_plant(SimulationSettings(heliostats=12))  # PAINT-like: calibration targets and a receiver
    return next_scenario(None, plant, learned=_learned(plant, True), step=provenance_entry("demo", command="test"))


@pytest.fixture(scope="module")
def page(scenario):
    return plant_report(scenario, None, ReportSettings(plan_heliostats=1, plan_count=2, plan_every="6h", detail=5))[1]


def test_state_reads_intervals_alarms_and_days_from_the_stored_posterior_and_history(scenario):
    s = heliostat_state(scenario)
    ids = s["ids"]
    assert s["interval_mrad"][0] == pytest.approx(1e3 * 2 * 1.96 * np.sqrt(2e-8))
    assert s["interval_mrad"][4] == pytest.approx(5 * s["interval_mrad"][0])
    assert list(s["alarms"][:4]) == [0, 1, 2, 0] and list(s["alarms_latest"][:4]) == [0, 1, 1, 0]
    assert s["reference_time"] == T0 + 5 * DAY
    assert s["days_since_record"][3] == 0.0
    assert s["days_since_record"][0] == pytest.approx(4.0)  # its latest record: T0 + 1 day
    assert np.all(s["predicted_error_mrad"] == pytest.approx(0.5)) and len(ids) == 12
    assert set(QUANTITIES) <= set(s) and set(COLOURS) == set(QUANTITIES)


def test_alarms_are_the_latest_updates_sorted_by_size_with_an_action(scenario):
    rows = alarm_rows(scenario)
    ids = scenario.plant.field.ids
    assert [(a["heliostat"], a["statistic"]) for a in rows] == [(ids[1], 40.0), (ids[2], 9.0)]
    assert rows[0]["action"].startswith("inspect the drive") and rows[1]["action"].startswith("take a calibration")
    assert len(alarm_rows(scenario, latest_only=False)) == 3
    d = heliostat_detail(scenario, ids[2])
    assert d["alarm"] == [True, True] and d["offsets_mrad"]["initial_angle_1"] == pytest.approx([2.0, 14.0])


def test_page_is_self_contained_and_shows_map_alarms_plan_receiver_and_provenance(page, scenario):
    html = page["html"]
    ids = scenario.plant.field.ids
    assert not re.search(r"<script[^>]+src=|<link[^>]+href=\"?http", html)  # nothing fetched from anywhere
    assert "Plotly" in html and len(html) > 3_000_000  # plotly.js inlined
    assert 'id="fieldmap"' in html and "plotly_click" in html
    assert f'id="h-{ids[1]}"' in html and f'href="#h-{ids[1]}"' in html
    assert html.index(f'<a href="#h-{ids[1]}">') < html.index(f'<a href="#h-{ids[2]}">')  # sorted by size
    assert "inspect the drive" in html
    # alarmed heliostats are planned first; the coverage section follows tomorrow's plan (the same ranking)
    assert page["plan"] and page["plan"][0] in (ids[1], ids[2]) and page["plan"][0] == page["tomorrow"]["heliostats"][0]
    assert "sun-position coverage" in html
    assert page["receiver"] and "peak-flux limit 200 kW/m²" in html and "0° = aperture normal" in html
    assert "2023-03-20T11:30Z" in html and 'id="receiver"' in html
    assert "command=test" in html  # provenance with its inputs


def test_detail_sections_are_capped_and_ranked(page, scenario):
    ids = scenario.plant.field.ids
    assert len(page["detail"]) == 5 and page["detail"][:2] == [ids[1], ids[2]]


def test_a_ten_thousand_heliostat_page_stays_small():
    """The page's size grows by the map's arrays only (no per-heliostat figure beyond ``detail``)."""
    n = 10_000
    rng = np.random.default_rng(0)
    state = {"ids": [f"H{i:05d}" for i in range(n)], "x_m": rng.uniform(-800, 800, n), "y_m": rng.uniform(0, 900, n),
             "reference_time": T0, "threshold": 6.0}
    state.update({k: rng.uniform(0, 3, n) for k in QUANTITIES})
    described = {"plant": {"heliostats": n}, "learned": {"kinematics": {"calibrated": False}}, "provenance": [],
                 "file": "x.h5"}
    html = render_page(described=described, state=state, quantities=QUANTITIES, colour="interval_mrad", alarms=[],
                       details=[], plans=[], receiver=None)
    assert len(html.encode()) < 8_000_000  # plotly.js is 4.8 MB of it
    body = html.split("</head>", 1)[1]  # the page after the inlined plotly.js
    assert body.count(r'"hovertemplate":"\u003cb\u003e%{text}') == 1  # every heliostat in one (WebGL) trace
    assert body.count('"method":"restyle"') == len(QUANTITIES)  # the colour menu, one button per quantity


def test_cli_writes_the_page_and_refuses_an_unknown_colour(scenario, tmp_path, capsys):
    path = write_scenario(scenario, tmp_path / "plant.h5")
    code, out, err = run_cli(capsys, "report", "--scenario", path, "-o", tmp_path / "plant.html", "--plan", "0",
                             "--no-flux")
    assert code == 0, err
    assert "12 heliostats, 2 alarm(s)" in out and (tmp_path / "plant.html").stat().st_size > 3_000_000
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["report", "--scenario", str(path), "-o", "x.html", "--colour", "nope"])
    assert exc.value.code == 2


def test_the_map_opens_on_a_quantity_the_plant_has_values_of(scenario):
    """A plant with calibrated kinematics but no posterior or history: the default colour (predicted error) has
    no value anywhere, so the map opens on "calibrated"."""
    ids = scenario.plant.field.ids
    bare = next_scenario(None, scenario.plant, learned={"calibration": {"method": "truth", "heliostats": ids}},
                         step=provenance_entry("simulate"))
    html = plant_report(bare, None, ReportSettings(plan_heliostats=0, flux=False))[1]["html"]
    assert f'"active":{list(QUANTITIES).index("calibrated")}' in html


def test_a_learned_surface_shows_its_tilt_from_the_ideal_facets(scenario):
    """Control points of heliostat 0 lifted along z in proportion to x: every normal tilts by atan(slope)."""
    ids = scenario.plant.field.ids
    f = scenario.plant.field
    cp = f.surfaces.control_points.clone()
    cp[0, ..., 2] += 1e-3 * (cp[0, ..., 0] - cp[0, ..., 0].mean(dim=(-1, -2), keepdim=True))  # slope 1 mrad
    plant = dataclasses.replace(scenario.plant, field=dataclasses.replace(
        f, surfaces=dataclasses.replace(f.surfaces, control_points=cp)))
    learned = dict(scenario.learned, surfaces={ids[0]: {}})
    sc = next_scenario(None, plant, learned=learned, step=provenance_entry("reconstruct"))
    surf = surface_deviation(sc, ids[0])
    assert surf["rms_mrad"] == pytest.approx(1.0, rel=0.05)
    assert surface_deviation(sc, ids[1])["rms_mrad"] < 1e-6
    html = plant_report(sc, None, ReportSettings(plan_heliostats=0, flux=False, detail=40))[1]["html"]
    assert f"{ids[0]}: learned surface, RMS 1.0" in html.replace("\\u003c", "<")


def test_the_alarm_table_lists_the_largest_hundred_and_counts_the_rest():
    alarms = [{"heliostat": f"H{i:04d}", "record_id": i, "time": "2021-11-24T09:11:00+00:00", "update": 1,
               "statistic": 500.0 - i, "threshold": 20.0, "innovation_mrad": 1.0, "action": "x"} for i in range(150)]
    state = {"ids": ["H0000"], "x_m": np.zeros(1), "y_m": np.zeros(1), "reference_time": T0, "threshold": 20.0}
    state.update({k: np.zeros(1) for k in QUANTITIES})
    described = {"plant": {"heliostats": 1}, "learned": {"kinematics": {"calibrated": False}}, "provenance": []}
    html = render_page(described=described, state=state, quantities=QUANTITIES, colour="alarms", alarms=alarms,
                       details=[], plans=[], receiver=None)
    table = html[html.index("<table id='alarms'>"):]
    table = table[:table.index("</table>")]
    assert table.count("<tr>") == 1 + 100 and "H0099" in table and "H0100" not in table
    assert "2021-11-24T09:11Z" in table and "... and 50 smaller alarm(s)" in html


class _Records:
    """The three fields of a RecordTable that the page reads (heliostat ids, index [R], time [R] POSIX s)."""

    def __init__(self, ids, index, time):
        self.heliostat_ids, self.heliostat_index, self.time = ids, torch.tensor(index), torch.tensor(time)

    def __len__(self):
        return len(self.time)


def test_a_paint_folders_newer_records_count_for_days_since_the_last_record(scenario):
    ids = scenario.plant.field.ids
    records = _Records([ids[5], "ZZ99"], [0, 1, 1], [T0 + 10 * DAY, T0 + 20 * DAY, float("nan")])
    s = heliostat_state(scenario, records)
    assert s["reference_time"] == T0 + 10 * DAY  # the unknown heliostat's record is not the plant's
    assert s["days_since_record"][5] == 0.0 and s["days_since_record"][3] == pytest.approx(5.0)


def test_tomorrows_plan_puts_the_alarmed_heliostats_first_on_the_day_after_the_latest_record(page, scenario):
    ids = scenario.plant.field.ids
    t = page["tomorrow"]
    assert t["day"] == "2023-11-20"  # the latest record: T0 + 5 days = 2023-11-19 22:13 UTC
    assert set(t["heliostats"][:2]) == {ids[1], ids[2]} and len(t["heliostats"]) == 12
    html = page["html"]
    assert "<table id='tomorrow'>" in html and html.count("step alarm</td>") == 2
