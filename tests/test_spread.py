"""One predicted pointing spread (issue 42 item 5): ``plan``, ``daily`` and the report print the same number for the
same heliostat and day, the plan ranks by exactly that number, and what it announces is what it plans.

The plant: four Jülich-like heliostats fitted (lm, Laplace posterior) on 8, 14, 20 and 26 records, so their spreads
differ, with a stored random walk of the axis offsets and a state time, so the day matters."""
from __future__ import annotations

import datetime as dt
import re
from html import escape as html_escape

import numpy as np
import pandas as pd
import pytest
import torch
from helpers.calibrate import TRUE, jueliche_like, scenario_round_trip, simulate, with_weekly_times

from heliotwin.calibrate.clock import grown_covariance
from heliotwin.calibrate.methods.lm import fit_lm_method
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.calibrate.protocol.plan import plant_plan
from heliotwin.calibrate.spread import DEFINITION, predicted_spread, reference_sun, stored_nominal
from heliotwin.cli.update import print_plan
from heliotwin.field import kinematics as K
from heliotwin.workflows.plan import PlanSettings, plan
from heliotwin.workflows.report import ReportSettings, plant_report

F64 = torch.float64
Q_MRAD2_PER_DAY = 0.002
COUNTS = (8, 14, 20, 26)


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    kin = jueliche_like(len(COUNTS))
    true = apply_deviations(kin, torch.tensor([[TRUE[n] for n in STONE8]] * len(COUNTS), dtype=F64), STONE8)
    recs = simulate(true, max(COUNTS), 3, noise=3e-4)
    keep = torch.cat([torch.arange(max(COUNTS)) < c for c in COUNTS])  # records are grouped by heliostat
    recs = with_weekly_times(recs.subset(keep))
    model = fit_lm_method(kin, recs, None, bags=0, field_prior=False, fit_focal_spot=None)
    sc = scenario_round_trip(tmp_path_factory.mktemp("spread"), kin, model)
    cal = sc.learned["calibration"]
    state = float(recs.time.max())
    cal["drift"] = {"time": torch.full((len(COUNTS),), state, dtype=F64)}
    cal["process_noise_choice"] = {"process_noise_mrad2_per_day": torch.tensor([Q_MRAD2_PER_DAY])}
    day = dt.datetime.fromtimestamp(state + 86400.0, dt.timezone.utc).date().isoformat()
    return sc, recs, day


def _printed(capsys, plan_dict) -> list[str]:
    print_plan(plan_dict)
    return capsys.readouterr().out.splitlines()


def test_the_spread_is_the_rms_error_of_the_normal_that_posterior_draws_give(plant):
    """What the number means: draw deviations from the posterior grown to the day, aim every drawn heliostat at the
    target for each reference sun position with the MAP model's motor steps, and the RMS angle between the drawn
    and the MAP mirror normals is the spread (to the draws' and the linearisation's accuracy)."""
    sc, _, day = plant
    sp = predicted_spread(sc, day)
    cal = sc.learned["calibration"]
    names = list(cal["parameter_names"])
    sun = reference_sun(sc.plant.site, pd.Timestamp(day, tz="UTC"))
    aim = sc.plant.targets[sp.target].center
    g = torch.Generator().manual_seed(0)
    for h in (0, 3):
        kin = stored_nominal(cal, [h]).index([0] * len(sun))
        delta = torch.as_tensor(cal["deviations"], dtype=F64)[h]
        map_kin = apply_deviations(kin, delta.expand(len(sun), -1).clone(), names)
        steps, ok = K.inverse(map_kin, aim.double().expand(len(sun), 3), sun, strict=False)
        n_map = K.mirror_normal(K.forward(map_kin, steps)[0])[ok]
        chol = torch.linalg.cholesky(sp.covariance[h])
        sq = []
        for _ in range(64):
            d = delta + chol @ torch.randn(len(delta), generator=g, dtype=F64)
            drawn = apply_deviations(kin, d.expand(len(sun), -1).clone(), names)
            n = K.mirror_normal(K.forward(drawn, steps)[0])[ok]
            sq.append(((n - n_map) ** 2).sum(-1).mean())
        rms_mrad = 1e3 * float(torch.stack(sq).mean().sqrt())
        assert rms_mrad == pytest.approx(float(sp.spread_mrad[h]), rel=0.2), (h, rms_mrad, sp.spread_mrad[h])
    # fewer records, larger spread; the walk grows it with the days since the state
    assert float(sp.spread_mrad[0]) > float(sp.spread_mrad[3])
    later = predicted_spread(sc, "2035-06-01")
    assert bool((later.spread_mrad > sp.spread_mrad).all())
    cov, days = grown_covariance(cal, names, pd.Timestamp("2035-06-01T12:00Z").timestamp())
    assert torch.allclose(later.covariance, cov) and float(days.min()) > 365


def test_plan_daily_and_the_report_print_the_same_spread_for_the_same_heliostat_and_day(plant, capsys):
    sc, recs, day = plant
    sp = predicted_spread(sc, day)
    ours = {h: float(v) for h, v in zip(sp.ids, sp.spread_mrad)}
    # daily's plan (plant_plan is what daily runs; print_plan is what it prints)
    daily = plant_plan(sc, day=day, slots=4, every="1h")
    assert daily["spread_mrad"] == pytest.approx(ours, rel=1e-12)
    assert daily["spread_definition"] == DEFINITION
    lines = _printed(capsys, daily)
    assert any(DEFINITION in ln for ln in lines)
    for p in daily["proposals"]:
        assert p["spread_now_mrad"] == pytest.approx(ours[p["heliostat"]], rel=1e-12)
        row = next(ln for ln in lines if f" {p['heliostat']} " in ln)
        assert f"predicted pointing spread {ours[p['heliostat']]:.3f} -> " in row
    # plan for one heliostat on that day
    for hid in ("S0", "S2"):
        _, ans = plan(sc, hid, PlanSettings(day=day, every="6h", count=2))
        assert ans["spread_day"] == day and ans["spread_now_mrad"] == pytest.approx(ours[hid], rel=1e-12)
        # the records it proposes lower that same number
        after = [p["spread_after_mrad"] for p in ans["proposals"]]
        assert ours[hid] > after[0] > after[1]
    # the report: tomorrow's table and the sun-position coverage section, the same day and number
    _, rep = plant_report(sc, recs, ReportSettings(flux=False, plan_heliostats=2, plan_count=1, plan_every="12h",
                                                   plan_slots=4, detail=0))
    html = rep["html"]
    assert rep["tomorrow"]["day"] == day
    tomorrow = html[html.index("<table id='tomorrow'>"):]
    tomorrow = tomorrow[:tomorrow.index("</table>")]
    coverage = html[html.index("<table id='plan'>"):]
    coverage = coverage[:coverage.index("</table>")]
    assert rep["plan"] == rep["tomorrow"]["heliostats"][:2]  # the coverage section follows tomorrow's ranking
    for hid in rep["plan"]:
        assert f"{ours[hid]:.3f} -> " in tomorrow and f"{ours[hid]:.3f} on {day}" in coverage
    assert html_escape(DEFINITION) in html


def test_the_plan_ranks_by_the_printed_spread_and_plans_what_it_announces(plant, capsys):
    sc, _, day = plant
    p = plant_plan(sc, day=day, slots=3, every="1h")
    spread = p["spread_mrad"]
    got = [q["heliostat"] for q in p["proposals"]]
    assert got == sorted(spread, key=lambda h: -spread[h])[:3]  # the three largest, largest first
    lines = _printed(capsys, p)
    printed = [float(m.group(1)) for ln in lines if (m := re.search(r"pointing spread (\d+\.\d+) -> ", ln))]
    assert len(printed) == 3 and printed == sorted(printed, reverse=True)
    assert "3 of 3 slot(s) planned" in lines[0] and "ranked by" in lines[0]
    # an alarmed heliostat comes first whatever its spread; the rest stay in spread order
    smallest = min(spread, key=spread.get)
    u = plant_plan(sc, day=day, slots=3, every="1h", urgent=[smallest])
    assert [q["heliostat"] for q in u["proposals"]] == [smallest] + got[:2]
    assert u["proposals"][0]["reason"] == "step alarm"
    # more slots than heliostats: the count says how many and why fewer, and every planned record is printed
    many = plant_plan(sc, day=day, slots=10, every="1h")
    lines = _printed(capsys, many)
    assert "4 of 10 slot(s) planned (the plant has 4 calibrated heliostat(s), one record each)" in lines[0]
    assert sum(1 for ln in lines if re.match(r"\s+\d+\. \d{4}-\d{2}-\d{2}T\d{2}:\d{2}Z ", ln)) == 4
    assert np.isfinite(many["median_spread_mrad"]) and many["p95_spread_mrad"] >= many["median_spread_mrad"]
