"""The plant's own clock and honest claims of the day (issue 42 item 3, issue 41 items 5 and 8).

* a plant whose records ended years ago plans the day after its latest record, not the wall clock's tomorrow,
  and says so; a current plant plans tomorrow;
* the pointing posterior at an instant grows by the stored random walk over the days since the state's time;
* ``--confidence`` claims a probability only when the draws can show it (exact Clopper-Pearson bound);
* aim points that hold the limit by sending heliostats to standby make the day need a person (exit 3).
"""
from __future__ import annotations

import copy
import datetime as dt

import pandas as pd
import pytest
import torch
from helpers.calibrate import TRUE, jueliche_like, scenario_round_trip, simulate
from helpers.field import learned_posterior

from heliotwin.calibrate.clock import BEHIND_DAYS, grown_covariance, latest_record_time, planned_day
from heliotwin.calibrate.methods.lm import fit_lm_method
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.io.scenario import Scenario
from heliotwin.optimise import robust as R
from heliotwin.optimise.aimpoints import calibrate_images, optimise_aimpoints
from heliotwin.optimise.testbed import generated_plant
from heliotwin.raytrace.field import equator_aim_points
from heliotwin.sun import direction_from_time
from heliotwin.workflows.aimpoints import AimpointSettings, aimpoints
from heliotwin.workflows.daily import day_attention
from heliotwin.workflows.field import sun_instants
from heliotwin.workflows.plan import PlanSettings
from heliotwin.workflows.plan import plan as plan_workflow

TIME = "2024-06-21T11:00:00Z"
DAY_S = 86400.0


def _utc(text: str) -> float:
    return pd.Timestamp(text).timestamp()


def _learned_with_walk(n=3, state="2021-12-30T12:00Z", q_mrad2=0.05, names=("initial_angle_1", "initial_angle_2",
                                                                          "tilt")):
    p = len(names)
    cov = (1e-3) ** 2 * torch.eye(p, dtype=torch.float64).expand(n, p, p).clone()
    return {"calibration": {"heliostats": [f"H{i}" for i in range(n)], "parameter_names": list(names),
                            "posterior": {"covariance": cov, "noise_rad": torch.full((n,), 2e-4)},
                            "process_noise_choice": {"process_noise_mrad2_per_day": torch.tensor([q_mrad2])},
                            "drift": {"time": torch.tensor([_utc(state), _utc(state) - 10 * DAY_S, float("nan")],
                                                           dtype=torch.float64)[:n]}}}


def test_a_plant_years_behind_plans_the_day_after_its_latest_record_and_says_so():
    learned = _learned_with_walk()
    now = dt.datetime(2026, 12, 7, 9, 0, tzinfo=dt.timezone.utc)
    day, why = planned_day(learned, None, now)
    assert day == "2021-12-31"  # the day after the latest state time (H0's 2021-12-30), not 2026-12-08
    assert "2021-12-30" in why and "2026-12-07" in why and "--day" in why
    assert latest_record_time(learned) == pytest.approx(_utc("2021-12-30T12:00Z"))


def test_a_current_plant_plans_tomorrow_and_a_given_day_is_kept():
    learned = _learned_with_walk()
    soon = dt.datetime(2021, 12, 30, 12, tzinfo=dt.timezone.utc) + dt.timedelta(days=BEHIND_DAYS - 0.5)
    assert planned_day(learned, None, soon) == ((soon.date() + dt.timedelta(days=1)).isoformat(),
                                                 "tomorrow by the wall clock (UTC)")
    assert planned_day(learned, "2024-06-21", soon) == ("2024-06-21", "given (--day)")
    assert planned_day({}, None, soon)[0] == (soon.date() + dt.timedelta(days=1)).isoformat()  # no record time


def test_the_covariance_grows_by_the_walk_over_the_days_since_the_state():
    learned = _learned_with_walk()
    cal = learned["calibration"]
    when = _utc("2022-01-09T12:00Z")
    cov, days = grown_covariance(cal, cal["parameter_names"], when)
    assert days.tolist() == pytest.approx([10.0, 20.0, 0.0])  # the third has no state time: not grown
    base = cal["posterior"]["covariance"]
    grown = 0.05e-6 * days
    for c in (0, 1):  # the two axis offsets walk
        assert torch.allclose(cov[:, c, c], base[:, c, c] + grown)
    assert torch.equal(cov[:, 2, 2], base[:, 2, 2])  # the tilt does not
    before, days0 = grown_covariance(cal, cal["parameter_names"], _utc("2021-01-01"))
    assert torch.equal(before, base) and not days0.any()  # never shrunk before the state time


def _plant_case():
    plant, atm = generated_plant("radial", 40, "cylinder", tower=30.0)
    s = plant.site
    sun = direction_from_time(pd.DatetimeIndex([pd.Timestamp(TIME)]), s.latitude_deg, s.longitude_deg,
                              s.altitude_m)[0]
    return plant, atm, sun


def test_the_pointing_spread_decades_later_grows_as_the_stored_walk_says():
    plant, _, sun = _plant_case()
    learned = learned_posterior(plant, 1.0)
    cal = learned["calibration"]
    h = len(cal["heliostats"])
    state = _utc(TIME)
    cal["drift"] = {"time": torch.full((h,), state, dtype=torch.float64)}
    cal["process_noise_choice"] = {"process_noise_mrad2_per_day": torch.tensor([0.01])}
    aim = equator_aim_points(plant.targets["receiver"], plant.field.kinematics.position)
    later = _utc("2100-12-01T11:00Z")
    now = R.pointing_posterior(plant, learned, sun, aim).sd_mrad()
    same = R.pointing_posterior(plant, learned, sun, aim, when_s=state).sd_mrad()
    far = R.pointing_posterior(plant, learned, sun, aim, when_s=later)
    assert torch.allclose(now, same)
    assert float(far.sd_mrad().median()) > 10 * float(now.median())  # 0.01 mrad^2/day over 76 years: ~17 mrad
    # exactly the posterior whose offsets' variances were grown by hand
    by_hand = copy.deepcopy(learned)
    days = (later - state) / DAY_S
    by_hand["calibration"]["posterior"]["covariance"] = cal["posterior"]["covariance"] + 0.01e-6 * days * torch.eye(2)
    del by_hand["calibration"]["drift"], by_hand["calibration"]["process_noise_choice"]
    assert torch.allclose(far.sd_mrad(), R.pointing_posterior(plant, by_hand, sun, aim).sd_mrad())
    assert float(far.walk_days.min()) == pytest.approx(days)


def test_the_exact_bound_of_zero_exceedances_in_50_draws():
    assert R.exceedance_upper_bound(0, 50) == pytest.approx(1 - 0.05 ** (1 / 50), rel=1e-9)  # 0.058
    assert R.exceedance_upper_bound(50, 50) == 1.0
    assert R.draws_needed(1e-7) == pytest.approx(3.0e7, rel=0.01) and R.draws_needed(0.1) == 29
    share = R.decision_share(0.1, 200)
    k = round(share * 200)
    assert R.exceedance_upper_bound(k, 200) <= 0.1 < R.exceedance_upper_bound(k + 1, 200)
    assert R.decision_share(1e-7, 50) == 0.0


def test_fifty_draws_do_not_claim_a_one_in_ten_million_exceedance():
    plant, atm, sun = _plant_case()
    learned = learned_posterior(plant, 0.5)
    model, eq = calibrate_images(plant, sun, atm, (20, 48))
    limit = 1.2 * float(eq.flux.max())  # held by equator aiming with room: no draw of 50 goes over it
    det = optimise_aimpoints(plant, sun, limit, atmosphere=atm, equator=eq, model=model)
    _, rep = R.robust_aimpoints(plant, sun, limit, 0.9999999, learned, atmosphere=atm, equator=eq, model=model,
                                deterministic=det, draws=50, seed=0)
    assert rep["robust"]["exceedance_probability"] == 0.0  # none of the draws is over the limit ...
    assert not rep["met"]  # ... which shows only p < 5.8 %, not p < 1e-7
    assert rep["robust"]["exceedance_upper_95"] == pytest.approx(0.0582, abs=1e-3)
    assert rep["draws_needed"] > 10 ** 7 and "--draws" in rep["why_not_met"] and not rep["tightenings"]


def test_standby_heliostats_make_the_day_need_a_person():
    aim = {"limit_met": True, "standby_heliostats": 7, "instants": [
        {"instant": TIME, "standby_heliostats": 7, "power_w": 2500.0, "power_lost_w": 75500.0,
         "equator_power_w": 78000.0}]}
    why = day_attention([], aim)
    assert len(why) == 1 and "7 heliostat(s) on standby" in why[0] and "2.5 kW" in why[0] and "78 kW" in why[0]
    full = {"limit_met": True, "standby_heliostats": 0, "instants": [
        {"instant": TIME, "standby_heliostats": 0, "power_w": 77000.0, "equator_power_w": 78000.0}]}
    assert day_attention([], full) == []
    spilled = {"limit_met": True, "standby_heliostats": 0, "instants": [
        {"instant": TIME, "standby_heliostats": 0, "power_w": 3000.0, "equator_power_w": 78000.0}]}
    assert "off the receiver" in day_attention([], spilled)[0]  # no standby, but the light is spilled


def test_aimpoints_at_a_time_far_from_the_records_grow_the_posterior_by_the_walk():
    plant, atm, _ = _plant_case()
    learned = learned_posterior(plant, 0.5)
    h = len(plant.field.ids)
    learned["calibration"]["drift"] = {"time": torch.full((h,), _utc(TIME), dtype=torch.float64)}
    learned["calibration"]["process_noise_choice"] = {"process_noise_mrad2_per_day": torch.tensor([0.01])}
    scenario = Scenario(plant, extras=atm.to_extras(), learned=learned)
    settings = AimpointSettings(peak_limit_w_m2=1e6, confidence=0.9, draws=40, baselines=False, iterations=50)
    _, rep = aimpoints(scenario, sun_instants(plant, times="2025-06-21T11:00Z"), settings)
    robust = rep["instants"][0]["robust"]
    assert robust["walk_days"]["median"] == pytest.approx(365.0, abs=0.01)
    assert 0 < robust["robust"]["exceedance_upper_95"] <= 1


def test_plan_proposes_only_instants_after_the_plants_latest_record(tmp_path):
    kin = jueliche_like(1)
    true = apply_deviations(kin, torch.tensor([[TRUE[n] for n in STONE8]], dtype=torch.float64), STONE8)
    model = fit_lm_method(kin, simulate(true, 40, 1, noise=3e-4), None, bags=0, field_prior=False,
                          fit_focal_spot=None)
    sc = scenario_round_trip(tmp_path, kin, model)
    sc.learned["calibration"]["drift"] = {"time": torch.tensor([_utc("2021-07-15T12:00Z")], dtype=torch.float64)}
    now = dt.datetime(2026, 12, 7, tzinfo=dt.timezone.utc)
    _, rep = plan_workflow(sc, "S0", PlanSettings(every="2h", count=3), now=now)
    times = [pd.Timestamp(p["time"]) for p in rep["proposals"]]
    assert rep["candidates_from"]["day"] == "2021-07-16" and len(times) == 3
    assert all(pd.Timestamp("2021-07-16", tz="UTC") <= t < pd.Timestamp("2022-07-16", tz="UTC") for t in times)
