"""One labelled sun azimuth convention and one time format on every figure (issue 42 item 7): the flux maps' titles
gave the sun azimuth clockwise from north (SolarPILOT's) unlabelled while the flags and the JSON use PAINT's, and
figures, the report and the command line wrote times three ways."""
from __future__ import annotations

import math
import re

import numpy as np
import pandas as pd
import pytest
import torch
from matplotlib.text import Text

import heliotwin.calibrate.report as R
from heliotwin.calibrate.report import plot_plan
from heliotwin.field.demo import demo_field_plant
from heliotwin.plots import instant_line, plot_receiver_flux
from heliotwin.sun import direction_from_paint_angles
from heliotwin.sunangles import paint_angles_from_direction
from heliotwin.timefmt import AZIMUTH_CONVENTION, UTC_PATTERN, utc_text
from heliotwin.workflows.report_page import _alarm_table, _tomorrow_table

ONE = re.compile(UTC_PATTERN)
#: Any other way of writing a time of day: "2023-03-20 11:30", "...+00:00", "11:30 UTC", "11:30:00".
OTHER = re.compile(r"\d{4}-\d{2}-\d{2} \d{2}:\d{2}|\+00:00|\d{2}:\d{2} UTC|\d{2}:\d{2}:\d{2}")


def _sun(az_deg: float, el_deg: float) -> torch.Tensor:
    return direction_from_paint_angles(torch.tensor(math.radians(az_deg), dtype=torch.float64),
                                       torch.tensor(math.radians(el_deg), dtype=torch.float64))


def test_one_time_format_from_every_kind_of_input():
    t = 1679311800.0  # 2023-03-20 11:30 UTC
    texts = [utc_text(t), utc_text("2023-03-20T11:30:00Z"), utc_text("2023-03-20 12:30:00+01:00"),
             utc_text("2023-03-20T11:30:59"), utc_text(pd.Timestamp("2023-03-20T11:30Z"))]
    assert texts == ["2023-03-20T11:30Z"] * 5 and all(ONE.fullmatch(x) for x in texts)
    assert utc_text(float("nan")) is None and utc_text(None) is None and utc_text("") is None
    with pytest.raises(ValueError):
        utc_text("yesterday")


def test_flux_map_titles_give_paints_azimuth_labelled_not_solarpilots():
    """A sun 30 deg east of south: PAINT's azimuth +30, SolarPILOT's (from north, clockwise) 150."""
    sun = _sun(30.0, 40.0)
    assert [float(torch.rad2deg(a)) for a in paint_angles_from_direction(sun)] == pytest.approx([30.0, 40.0])
    line = instant_line({"time_utc": "2023-03-20T11:30:00+00:00", "sun_enu": sun})
    assert line == f"2023-03-20T11:30Z, sun azimuth 30.0° ({AZIMUTH_CONVENTION}), elevation 40.0°"
    west = instant_line({"sun_enu": _sun(-75.0, 20.0)})
    assert "sun azimuth -75.0° (PAINT: 0 = south, +90 = east)" in west
    plant, _ = demo_field_plant(4)
    fig = plot_receiver_flux({"equator aiming": torch.rand(8, 16, generator=torch.Generator().manual_seed(0))},
                             plant.targets["receiver"], instant={"time_utc": "2023-03-20T11:30:00+00:00",
                                                                 "sun_enu": sun})
    title = fig._suptitle.get_text()
    assert "sun azimuth 30.0° (PAINT: 0 = south, +90 = east)" in title and "150.0" not in title
    assert ONE.search(title) and not OTHER.search(title)
    # the receiver's angle axis names a compass bearing (a direction on the ground), never a "sun azimuth"
    texts = [t.get_text() for t in fig.findobj(Text)]
    top = [t for t in texts if t.startswith("angle around")]
    assert top and "compass bearing" in top[0] and "sun azimuth" not in top[0]
    assert sum("sun azimuth" in t for t in texts) == 1  # the title's, labelled


def test_the_plan_sky_map_labels_its_azimuth_axis_and_the_spread_day(tmp_path, monkeypatch):
    ans = {"heliostat": "AA01", "target": "t", "year": 2023, "spread_day": "2023-06-21", "spread_now_mrad": 0.5,
           "sky": {"sun_azimuth_deg": np.array([-40.0, 10.0, 60.0]), "sun_elevation_deg": np.array([30.0, 50.0, 20.0]),
                   "std_now_mrad": np.array([0.6, 0.4, 0.5])},
           "proposals": [{"time": "2023-06-21T15:00:00+00:00", "sun_azimuth_deg": -40.0, "sun_elevation_deg": 30.0,
                          "spread_after_mrad": 0.3}]}
    made = []
    monkeypatch.setattr(R, "save_figure", lambda fig, path: made.append(fig))  # the figure, to read back
    plot_plan(tmp_path / "p.png", ans)
    ax = made[0].axes[0]
    assert ax.get_xlabel() == f"sun azimuth [deg] ({AZIMUTH_CONVENTION})"
    assert "predicted pointing spread on 2023-06-21 0.500 -> 0.300 mrad" in ax.get_title()


def test_report_tables_write_times_one_way_and_name_the_convention():
    plan = {"day": "2023-06-21", "target": "t", "candidates": 20, "slots": 2, "ranked_by": "spread",
            "spread_definition": "def", "median_spread_mrad": 0.4, "p95_spread_mrad": 0.6,
            "proposals": [{"heliostat": "AA01", "time": "2023-06-21T09:30:00+00:00", "sun_azimuth_deg": 60.0,
                           "sun_elevation_deg": 30.0, "reason": "step alarm", "spread_now_mrad": 0.6,
                           "spread_after_mrad": 0.3}]}
    table = _tomorrow_table(plan, set())
    assert "2023-06-21T09:30Z" in table and AZIMUTH_CONVENTION in table and not OTHER.search(table)
    assert "1 of 2 slot(s) planned" in table
    alarms = [{"heliostat": "AA01", "record_id": 1, "time": "2021-11-24T09:11:00+00:00", "statistic": 9.0,
               "threshold": 6.0, "innovation_mrad": 1.0, "action": "x"}]
    table = _alarm_table(alarms, set())
    assert "2021-11-24T09:11Z" in table and not OTHER.search(table)
