"""The plant's year heliostat by heliostat (workflows.year, raytrace.annual, ``heliotwin year``)."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from helpers.cli import run_cli
from helpers.field import learned_posterior

from heliotwin.calibrate.params import apply_deviations
from heliotwin.io.scenario import Scenario, load_scenario, save_scenario
from heliotwin.optimise.testbed import generated_plant
from heliotwin.raytrace import annual as A
from heliotwin.raytrace.field import FACTORS, equator_aim_points, field_optics
from heliotwin.workflows.year import YearSettings, plant_year

NAMES = ["initial_angle_1", "initial_angle_2"]


@pytest.fixture(scope="module")
def tiny():
    plant, atm = generated_plant("radial", 6, "cylinder")
    sc = Scenario(plant=plant, extras=atm.to_extras(), learned=learned_posterior(plant, sd_mrad=1.0), path="")
    res = plant_year(sc, settings=YearSettings(every="3h", draws=4, check_hours=60))
    return plant, atm, sc, res


def test_rows_and_months_sum_to_the_field(tiny):
    _, _, _, res = tiny
    y = res.scenario.learned["year"]
    e = np.asarray(y["heliostats"]["energy_mwh"])
    assert e.min() > 0
    assert e.sum() == pytest.approx(y["annual_energy_mwh"], rel=1e-12)
    assert np.sum(y["monthly_energy_mwh"]) == pytest.approx(y["annual_energy_mwh"], rel=1e-10)
    # efficiency = energy / (DNI energy on the mirrors), field and rows alike
    assert y["annual_energy_mwh"] / y["annual_dni_energy_on_mirrors_mwh"] == pytest.approx(
        res.report["field_efficiency"])
    assert 0 < res.report["field_efficiency"] < 1


def test_interpolation_against_the_direct_sum(tiny):
    check = tiny[3].report["interpolation"]
    assert check["checked_hours"] == 60
    assert check["median_error"] <= 0.01 and check["p95_error"] <= 0.03 and check["field_error"] <= 0.003


def test_factors_product_is_efficiency_at_one_node(tiny):
    plant, atm, _, _ = tiny
    z = A.DEFAULT_GRID.shape[1]
    suns = A.DEFAULT_GRID.suns(torch.tensor([10 * z + z // 2]))  # one sun: the DNI-weighted means are its values
    aim = equator_aim_points(plant.targets["receiver"], plant.field.kinematics.position.double())
    t = A.heliostat_tables(plant, suns, aim, atmosphere=atm)
    prod = torch.ones_like(t["efficiency"])
    for name in FACTORS:
        prod = prod * t[name]
    torch.testing.assert_close(prod, t["efficiency"], rtol=1e-6, atol=1e-9)


def test_tracking_loss_is_the_posteriors_and_shrinks_with_it():
    """The controller aims with the learned kinematics; the loss is the expected loss over the posterior, so a
    tighter calibration loses less, and a heliostat that moves exactly as learned loses nothing."""
    plant, atm = generated_plant("radial", 6, "cylinder")
    losses = []
    for sd in (3.0, 1.0, 0.3):
        sc = Scenario(plant=plant, extras=atm.to_extras(), learned=learned_posterior(plant, sd_mrad=sd), path="")
        y = plant_year(sc, settings=YearSettings(every="3h", draws=8)).scenario.learned["year"]["heliostats"]
        losses.append(np.asarray(y["tracking_loss_mwh"]))
    assert np.all(losses[0] > 0)
    assert losses[0].sum() > losses[1].sum() > losses[2].sum() > 0
    z = A.DEFAULT_GRID.shape[1]
    suns = A.DEFAULT_GRID.suns(torch.tensor([9 * z + z // 2, 11 * z + z // 2 - 1]))
    aim = equator_aim_points(plant.targets["receiver"], plant.field.kinematics.position.double())
    kin = plant.field.kinematics.to(dtype=torch.float64)
    rows = torch.arange(len(plant.field.ids))
    same = A.tracking_tables(plant, suns, aim.expand(2, -1, -1), rows, kin, [kin])
    torch.testing.assert_close(same, torch.ones_like(same), rtol=0, atol=1e-9)
    out = []
    for mrad in (3.0, 10.0, 30.0):  # (1 mrad can gain: the tiny receiver is smaller than the image)
        d = torch.zeros(rows.numel(), 2, dtype=torch.float64)
        d[:, 0] = mrad * 1e-3
        ratio = A.tracking_tables(plant, suns, aim.expand(2, -1, -1), rows, kin, [apply_deviations(kin, d, NAMES)])
        out.append(float((1 - ratio).mean()))
    assert 0 < out[0] < out[1] < out[2]


def test_hourly_sums_are_the_interpolated_hours():
    """hourly_sums equals an explicit loop over instants of (bilinear interpolation x exact cosine x DNI)."""
    gen = torch.Generator().manual_seed(3)
    grid = A.DEFAULT_GRID
    az = (torch.rand(40, generator=gen, dtype=torch.float64) - 0.5) * 2 * np.pi
    el = torch.rand(40, generator=gen, dtype=torch.float64) * 1.4 + 0.01
    q = torch.rand(40, generator=gen, dtype=torch.float64) * 900
    idx, w = A.bilinear_weights(grid, az, el)
    nodes = A.needed_nodes(idx, w, q)
    col = A.node_columns(nodes, idx, w)
    table = torch.rand(3, nodes.numel(), generator=gen, dtype=torch.float64)
    cos = torch.rand(3, 40, generator=gen, dtype=torch.float64)
    months = torch.randint(0, 12, (40,), generator=gen)
    want = torch.zeros(3, 12, dtype=torch.float64)
    for t in range(40):
        for k in range(4):
            if w[t, k] > 0:
                want[:, months[t]] += table[:, int((nodes == idx[t, k]).nonzero())] * w[t, k] * cos[:, t] * q[t]
    torch.testing.assert_close(A.hourly_sums(table, cos, col, w, q, months, 12), want)
    torch.testing.assert_close(A.hourly_sums(table, cos, col, w, q), want.sum(-1))


def test_hourly_cosine_is_the_field_models():
    plant, atm = generated_plant("radial", 5, "flat")
    pos = plant.field.kinematics.position.double()
    aim = equator_aim_points(plant.targets["receiver"], pos)
    suns = A.DEFAULT_GRID.suns(torch.tensor([100, 120, 150]))
    want = torch.stack([field_optics(plant, s, atmosphere=atm, aim=aim).cosine.double() for s in suns], -1)
    torch.testing.assert_close(A.hourly_cosine(pos, aim, suns), want, rtol=1e-6, atol=1e-9)


def test_intervals_ordered(tiny):
    hel = tiny[3].scenario.learned["year"]["heliostats"]
    lo, mid, hi = (np.asarray(hel[k]) for k in ("tracking_loss_low_mwh", "tracking_loss_mwh",
                                                 "tracking_loss_high_mwh"))
    assert np.all(lo <= mid) and np.all(mid <= hi) and np.any(hi > lo)


def test_uncalibrated_heliostats_have_unknown_tracking_loss():
    plant, atm = generated_plant("radial", 3, "flat")
    sc = Scenario(plant=plant, extras=atm.to_extras(), path="")
    res = plant_year(sc, settings=YearSettings(every="4h", draws=0))
    hel = res.scenario.learned["year"]["heliostats"]
    assert np.isnan(hel["tracking_loss_mwh"]).all()
    assert res.report["tracking_loss_unknown_heliostats"] == 3 and res.report["notes"]


def test_cli_outputs_stored_and_never_over_the_input(tmp_path, capsys):
    plant, atm = generated_plant("radial", 4, "tilted-flat")
    src = tmp_path / "p.h5"
    save_scenario(plant, src, extras=atm.to_extras(), learned=learned_posterior(plant, sd_mrad=1.0))
    before = src.read_bytes()
    code, _, err = run_cli(capsys, "year", "--scenario", str(src), "--every", "4h", "--draws", "2",
                           "-o", str(tmp_path / "y.h5"), "--csv", str(tmp_path / "h.csv"),
                           "--json", str(tmp_path / "y.json"), "--quiet")
    assert code == 0, err
    assert src.read_bytes() == before
    rep = json.loads((tmp_path / "y.json").read_text())
    for key in ("annual_energy_mwh", "annual_dni_energy_on_mirrors_mwh", "dni_share_below_horizon", "site",
                "time_convention", "monthly_energy_mwh"):
        assert key in rep
    rows = list(csv.DictReader(open(tmp_path / "h.csv")))
    assert list(rows[0])[:11] == ["id", "energy_mwh", "efficiency", *FACTORS, "tracking_loss_mwh",
                                  "surface_loss_mwh"]
    assert sum(float(x["energy_mwh"]) for x in rows) == pytest.approx(rep["annual_energy_mwh"], rel=1e-9)
    y = load_scenario(tmp_path / "y.h5").learned["year"]
    assert y["annual_energy_mwh"] == pytest.approx(rep["annual_energy_mwh"])
    assert y["heliostats"]["energy_mwh"].shape == (4,)
    code, _, err = run_cli(capsys, "year", "--scenario", str(src), "-o", str(src), "--json",
                           str(tmp_path / "z.json"))
    assert code == 2 and "--in-place" in err
    assert src.read_bytes() == before and not (tmp_path / "z.json").exists()


def test_tables_dealt_over_processes_are_the_one_process_tables(tiny):
    """Two worker processes (nodes dealt alternately, gathered on rank 0) give the one-process year."""
    _, _, sc, res = tiny
    two = plant_year(sc, settings=YearSettings(every="3h", draws=4, nproc=2))
    for name in ("efficiency", "cosine", "tracking_ratio", "aim"):
        torch.testing.assert_close(two.tables[name], res.tables[name], rtol=1e-12, atol=1e-12)
    one = res.scenario.learned["year"]["heliostats"]
    got = two.scenario.learned["year"]["heliostats"]
    for name in ("energy_mwh", "tracking_loss_mwh", "efficiency"):
        np.testing.assert_allclose(got[name], one[name], rtol=1e-12)
    assert two.report["tables_processes"] == 2 and res.report["tables_processes"] == 1


def test_a_far_weather_file_and_dni_below_the_horizon_are_warned(tiny):
    """pvlib's Greensboro TMY3 on a plant at Juelich: its site is ~6,900 km away and much of its DNI falls while
    the sun is down at the plant; both are one-line warnings in the report (printed by the CLI)."""
    import os

    import pvlib

    from heliotwin.io.weather import read_dni_series

    _, _, sc, _ = tiny
    tmy3 = os.path.join(os.path.dirname(pvlib.__file__), "data", "723170TYA.CSV")
    res = plant_year(sc, read_dni_series(tmy3), YearSettings(draws=0))
    warnings = res.report["warnings"]
    assert any("km from the plant" in w for w in warnings)
    assert res.report["dni_share_below_horizon"] > 0.005
    assert any("below the horizon" in w and tmy3 in w for w in warnings)
    assert tiny[3].report["warnings"] == []  # clear sky at the plant: nothing to warn


def test_api_year_is_the_workflow_and_writes_the_plant(tiny, tmp_path):
    from heliotwin import api

    _, _, sc, res = tiny
    out = tmp_path / "year.h5"
    got = api.year(sc, every="3h", draws=4, output=out)
    np.testing.assert_allclose(got.scenario.learned["year"]["heliostats"]["energy_mwh"],
                               res.scenario.learned["year"]["heliostats"]["energy_mwh"], rtol=1e-12)
    stored = load_scenario(out).learned["year"]
    assert stored["annual_energy_mwh"] == pytest.approx(got.report["annual_energy_mwh"], rel=1e-12)


def test_optimised_aiming_holds_the_limit_at_the_nodes_and_costs_energy(tiny):
    """``aim="optimised"``: aim points optimised per node (warm-started) under a binding limit; at a node the
    exact map of the field with those aim points stays under the limit, and the year earns less than with the
    equator aim points the limit cuts."""
    plant, atm, sc, res = tiny
    aim_eq = equator_aim_points(plant.targets["receiver"], plant.field.kinematics.position.double())
    k = int(res.tables["efficiency"].sum(0).argmax())  # the node where the field earns most
    sun = res.tables["suns"][k]
    peak_eq = float(field_optics(plant, sun, atmosphere=atm, aim=aim_eq).flux.max())
    limit = 0.7 * peak_eq
    opt = plant_year(sc, settings=YearSettings(every="3h", draws=0, aim="optimised", peak_limit_w_m2=limit))
    aims = opt.tables["aim"]
    assert not torch.equal(aims[0], aims[-1])  # one set per node
    peak = float(field_optics(plant, sun, atmosphere=atm, aim=aims[k].to(plant.field.kinematics.position)).flux.max())
    assert peak <= limit * 1.02
    e_opt = opt.scenario.learned["year"]["annual_energy_mwh"]
    assert 0.5 * res.report["annual_energy_mwh"] < e_opt < res.report["annual_energy_mwh"]
