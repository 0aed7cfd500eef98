"""Aim points over a day with warm starts: an instant started from the previous instant's optimised aim points
holds the limit on the exact (hard-occlusion) model, keeps the power of a cold start within 0.5 %, and takes
fewer optimiser steps; ``aimpoints --day`` reports every instant and the day's energy; a day without a daylight
instant is a one-line error."""
import dataclasses
import json

import pandas as pd
import pytest
import torch
from helpers.cli import assert_one_line_error, run_cli

from heliotwin.errors import HeliotwinError
from heliotwin.field.demo import demo_field_plant
from heliotwin.optimise.aimpoints import AimSettings, calibrate_images, evaluate, optimise_aimpoints
from heliotwin.sun import direction_from_time
from heliotwin.workflows.field import sun_instants

TIMES = ("2023-06-21T09:00:00Z", "2023-06-21T09:15:00Z")
EXCESS = 1.35  # equator aiming exceeds the limit by 35 % at the first instant
KNOBS = AimSettings()  # the command's defaults: 300 Adam steps per round cold, 100 warm


def _sun(plant, text):
    s = plant.site
    return direction_from_time(pd.DatetimeIndex([pd.Timestamp(text)]), s.latitude_deg, s.longitude_deg,
                               s.altitude_m)[0]


@pytest.fixture(scope="module")
def two_instants():
    """60 heliostats: the first instant optimised cold, the second cold and warm-started from the first."""
    plant, atm = demo_field_plant(60)
    first, second = (_sun(plant, t) for t in TIMES)
    model, eq = calibrate_images(plant, first, atm, (20, 48))
    limit = float(eq.flux.max()) / EXCESS
    prev = optimise_aimpoints(plant, first, limit, KNOBS, atmosphere=atm, equator=eq, model=model)
    model2, eq2 = calibrate_images(plant, second, atm, (20, 48))
    cold = optimise_aimpoints(plant, second, limit, KNOBS, atmosphere=atm, equator=eq2, model=model2)
    warm = optimise_aimpoints(plant, second, limit, KNOBS, atmosphere=atm, start_aim=prev.aim,
                              start_multipliers=prev.multipliers, start_margin=prev.parameter)
    return plant, atm, second, limit, eq2, prev, cold, warm


def test_predicted_warm_start_is_never_a_result_and_holds_the_limit(two_instants):
    """``start_field``: round 0 predicted from the previous instant's exact result (no exact check of the start);
    the answer is an exactly checked round that holds the limit, with the power of a cold start."""
    plant, atm, sun, limit, eq, prev, cold, _ = two_instants
    assert prev.exact is not None and torch.equal(prev.exact.flux, prev.flux)
    pred = optimise_aimpoints(plant, sun, limit, KNOBS, atmosphere=atm, start_aim=prev.aim,
                              start_multipliers=prev.multipliers, start_margin=prev.parameter,
                              start_field=prev.exact)
    first = pred.history[0]
    assert first["predicted"] and not first["feasible"]  # a prediction is never feasible, whatever its peak
    assert pred.exact_checks == len(pred.history) - 1 >= 1  # every other round an exact check
    assert pred.violation(limit) == 0.0 and evaluate(plant, sun, pred.aim, atm).peak_flux_w_m2 <= limit
    assert pred.power_w >= 0.995 * cold.power_w
    assert pred.iterations < cold.iterations


def test_warm_start_holds_the_limit_on_the_exact_check(two_instants):
    plant, atm, sun, limit, eq, prev, cold, warm = two_instants
    assert float(eq.flux.max()) > 1.2 * limit  # the limit bites at this instant too
    assert warm.peak_flux_w_m2 <= limit and warm.violation(limit) == 0.0
    again = evaluate(plant, sun, warm.aim, atm)  # an independent exact evaluation of the returned aim points
    assert again.peak_flux_w_m2 <= limit
    assert again.power_w == pytest.approx(warm.power_w, rel=1e-9)
    rec = plant.targets["receiver"]
    assert float(rec.to_local(warm.aim)[:, 1].abs().max()) <= 0.5 * rec.height + 1e-9  # on the receiver
    assert warm.standby == 0


def test_warm_start_keeps_the_power_of_a_cold_start_with_fewer_steps(two_instants):
    plant, atm, sun, limit, eq, prev, cold, warm = two_instants
    assert cold.violation(limit) == 0.0
    assert warm.power_w >= 0.995 * cold.power_w
    assert warm.iterations < cold.iterations  # Adam steps on the image model, from the optimiser's own count
    assert warm.exact_checks <= len(cold.history)  # exact evaluations (cold: + the equator calibration)
    # the warm start's reference power (no equator check) is the corrected image model's estimate of equator's
    assert warm.reference_power_w == pytest.approx(float(eq.power_w.sum()), rel=0.02)
    assert warm.history[0]["power_w"] == pytest.approx(evaluate(plant, sun, prev.aim, atm).power_w, rel=1e-9)


def test_start_aim_points_of_the_wrong_shape_are_refused(two_instants):
    plant, atm, sun, limit, *_ = two_instants
    with pytest.raises(HeliotwinError, match="start aim points"):
        optimise_aimpoints(plant, sun, limit, KNOBS, atmosphere=atm, start_aim=torch.zeros(3, 3))


def test_aimpoints_day_reports_every_instant_and_the_energy(tmp_path, capsys):
    from heliotwin.io.scenario import save_scenario

    plant, atm = demo_field_plant(20)
    h5 = tmp_path / "p.h5"
    save_scenario(plant, h5, extras=atm.to_extras())
    instants = sun_instants(plant, day="2023-06-21", every="4h")
    assert len(instants) >= 3 and all(float(s[2]) > 0.17 for _, s in instants)  # above 10 deg
    limit = 0.8 * float(calibrate_images(plant, instants[1][1], atm, (20, 48))[1].flux.max())
    js = tmp_path / "day.json"
    code, out, err = run_cli(capsys, "aimpoints", "--scenario", h5, "--day", "2023-06-21", "--every", "4h",
                             "--peak-limit", limit, "--no-baselines", "--iterations", 100, "-o", tmp_path / "a.h5",
                             "--json", js)
    rep = json.loads(js.read_text())
    n = len(instants)
    assert code == (0 if rep["summary"]["limit_met_at_all"] else 3), err
    assert [i["instant"] for i in rep["instants"]] == [lbl for lbl, _ in instants]
    for k, inst in enumerate(rep["instants"]):
        o = inst["optimised"]
        assert o["warm_start"] == (k > 0) and o["peak_vs_limit"] == pytest.approx(o["peak_flux_w_m2"] / limit)
        assert inst["equator"].get("estimated", False) == (k > 0)  # warm instants: no equator check
        assert o["power_vs_equator"] == pytest.approx(o["power_w"] / inst["equator"]["power_w"])
        assert -90 <= inst["sun_azimuth_deg"] <= 180 and inst["sun_elevation_deg"] > 10
    d = rep["summary"]
    assert d["instants"] == n and d["warm_starts"] == n - 1 and d["step_s"] == 4 * 3600
    assert d["energy_kwh"] == pytest.approx(sum(i["optimised"]["power_w"] for i in rep["instants"]) * 4 / 1e3)
    assert d["worst_peak_vs_limit"] == pytest.approx(max(i["optimised"]["peak_vs_limit"] for i in rep["instants"]))
    assert d["adam_steps"] == sum(i["optimised"]["iterations"] for i in rep["instants"])
    lines = [ln for ln in out.splitlines() if ln.startswith("aimpoints ")]
    assert [ln.split()[1] for ln in lines] == [f"{k + 1}/{n}" for k in range(n)]


def test_a_day_without_daylight_is_one_line(tmp_path, capsys):
    from heliotwin.io.scenario import save_scenario

    plant, atm = demo_field_plant(10)
    polar = dataclasses.replace(plant, site=dataclasses.replace(plant.site, latitude_deg=80.0))
    with pytest.raises(HeliotwinError, match="below 10 deg"):
        sun_instants(polar, day="2023-12-21", every="15min")
    h5 = tmp_path / "p.h5"
    save_scenario(polar, h5, extras=atm.to_extras())
    js, out = tmp_path / "a.json", tmp_path / "a.h5"
    code, _, err = run_cli(capsys, "aimpoints", "--scenario", h5, "--day", "2023-12-21", "--every", "15min",
                           "--peak-limit", 1e5, "-o", out, "--json", js)
    assert_one_line_error(code, err, "--day")
    assert not js.exists() and not out.exists()


def test_day_steps_in_days_parse_without_pandas_deprecation_warning():
    """``--every 1d`` (pandas deprecates the lower-case day unit): the same step as ``1D``, no FutureWarning."""
    import warnings

    from heliotwin.workflows.field import _step

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _step("1d") == _step("1D") == pd.Timedelta(days=1)
        assert _step("1d12h") == pd.Timedelta(hours=36)
        assert _step("2 days") == pd.Timedelta(days=2)
