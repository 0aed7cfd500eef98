"""The networks' keep rule (``calibrate/methods/keep.py``): a hybrid / MLP network only where records it was not
fitted on show a significant gain; otherwise the method is exactly ``lm``; the evidence is reported."""
import json
import math

import pytest
import torch
from helpers.calibrate import TRUE, jueliche_like, simulate, with_weekly_times
from helpers.cli import run_cli
from scipy.stats import wilcoxon

from heliotwin.calibrate.methods import keep
from heliotwin.calibrate.methods.hybrid import fit_hybrid_method
from heliotwin.calibrate.methods.lm import fit_lm_method
from heliotwin.calibrate.methods.mlp import fit_mlp_method
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.calibrate.protocol.pipeline import RunConfig, run_calibration
from heliotwin.errors import HeliotwinError
from heliotwin.io.paint import load_paint
from heliotwin.simulate import SimulationSettings, simulate_plant, write_paint_folder

F64 = torch.float64


def _true(h=1):
    kin = jueliche_like(h)
    return kin, apply_deviations(kin, torch.tensor([[TRUE[k] for k in STONE8]] * h, dtype=F64), STONE8)


def _gear_error(kin, b, amplitude):
    """A periodic error of both axes' motor steps over their range [increments]: no rigid body has it."""
    frac = (b.motor_steps - kin.min_steps[b.heliostat_index]) / (kin.max_steps - kin.min_steps)[b.heliostat_index]
    b.motor_steps = b.motor_steps + amplitude * torch.sin(2 * math.pi * frac)
    return b


def test_check_split_holds_out_each_heliostats_latest_fifth_and_keeps_untimed_records_for_fitting():
    kin, true = _true(2)
    b = simulate(true, 20, 1)
    g = torch.Generator().manual_seed(0)
    b.time = 1.6e9 + torch.randperm(40, generator=g).to(F64) * 86400.0  # shuffled: order must come from the times
    b.time[[0, 1, 25]] = float("nan")  # untimed: cannot be "latest"
    fit, check = keep.check_split(b, None)
    assert len(fit) + len(check) == 40
    for h, n_timed in ((0, 18), (1, 19)):
        t_check = check.time[check.heliostat_index == h]
        t_fit = fit.time[fit.heliostat_index == h]
        assert len(t_check) == round(0.2 * n_timed)  # 4 each
        assert torch.isfinite(t_check).all() and float(t_check.min()) > float(t_fit[torch.isfinite(t_fit)].max())
    assert int(torch.isnan(fit.time).sum()) == 3
    # A run's own validation records are the check records as they are.
    va = b.subset(torch.arange(5))
    assert keep.check_split(b, va) == (b, va)


def test_paired_gain_test_needs_records_significance_and_a_positive_mean():
    g = torch.Generator().manual_seed(1)
    rigid = 1e-3 + 1e-4 * torch.rand(6 + 5 + 15 + 6, generator=g, dtype=F64)
    gain = torch.cat([torch.full((6,), 2e-4, dtype=F64),  # 6 wins: p = 1/64
                      torch.full((5,), 2e-4, dtype=F64),  # 5 wins: too few records to test
                      torch.tensor([1e-5 * (k + 1) for k in range(14)] + [-5e-3], dtype=F64),  # 14 small wins, 1 loss
                      torch.tensor([1e-4, -1e-4, 2e-4, -2e-4, 3e-4, -3e-4], dtype=F64)])  # a coin
    hidx = torch.tensor([0] * 6 + [1] * 5 + [2] * 15 + [3] * 6)
    kept, ev = keep.paired_gain_test(rigid, rigid - gain, hidx, 4)
    assert kept.tolist() == [True, False, False, False]
    assert ev[0]["p_value"] == pytest.approx(1 / 64) and ev[0]["wins"] == 6 and ev[0]["n_check"] == 6
    assert ev[0]["mean_gain_mrad"] == pytest.approx(0.2) and ev[0]["reason"] is None and ev[0]["kept"]
    assert ev[1]["p_value"] is None and "5 validation records < 6" in ev[1]["reason"]
    # the signed-rank test alone would pass heliostat 2 (p < 0.05); its mean gain is negative
    assert ev[2]["p_value"] == pytest.approx(float(wilcoxon(gain[11:26].numpy(), alternative="greater").pvalue))
    assert ev[2]["p_value"] < 0.01 and ev[2]["mean_gain_mrad"] < 0 and "not positive" in ev[2]["reason"]
    assert ev[3]["p_value"] > 0.3 and "not significant" in ev[3]["reason"]
    # Benjamini-Hochberg over the 3 tested heliostats: heliostat 0 has the second smallest p
    assert ev[0]["tests"] == 3 and ev[0]["threshold"] == pytest.approx(0.05 * 2 / 3)


def test_false_discovery_rate_over_the_heliostats_rejects_a_lone_marginal_gain():
    """One heliostat at p = 1/64 is a discovery alone, but not among 11 tested heliostats where 10 show nothing."""
    gain = torch.cat([torch.full((6,), 2e-4, dtype=F64),
                      torch.tensor([1e-4, -1e-4, 2e-4, -2e-4, 3e-4, -3e-4], dtype=F64).repeat(10)])
    hidx = torch.arange(11).repeat_interleave(6)
    rigid = torch.full((66,), 1e-3, dtype=F64)
    kept, ev = keep.paired_gain_test(rigid, rigid - gain, hidx, 11)
    assert not bool(kept.any()) and ev[0]["threshold"] == pytest.approx(0.05 / 11)
    kept1, _ = keep.paired_gain_test(rigid[:6], rigid[:6] - gain[:6], hidx[:6], 1)
    assert kept1.tolist() == [True]


def _rigid_heliostats(seed=4):
    """Three heliostats with a pure rigid-body error, 1 mrad noise, weekly records: 30 training, 10 later test."""
    kin, true = _true(3)
    b = simulate(true, 40, seed, noise=1e-3)
    b.time = 1.6e9 + (torch.arange(120) % 40).to(F64) * 7 * 86400.0
    first = (torch.arange(120) % 40) < 30
    return kin, b.subset(first), b.subset(~first)


def test_hybrid_rejects_its_network_on_rigid_heliostats_and_is_exactly_lm_with_the_evidence_reported():
    kin, tr, te = _rigid_heliostats()
    model = fit_hybrid_method(kin, tr, None, depth=2, hidden=2, steps=60, lr=1e-2, field_prior=False)
    lm = fit_lm_method(kin, tr, None, field_prior=False)
    assert not bool(model.extras["use_net"].any())
    for hid, info in model.extras["per_heliostat"].items():
        ev = info["keep_test"]
        # the latest 6 of 30 records and the 6 before them checked on, a test ran, the reason is in the report
        assert [f["n_check"] for f in ev["folds"]] == [6, 6] and ev["n_check"] == 12
        assert ev["p_value"] is not None and info["fallback_reason"] == ev["reason"]
        assert ev["wins"] + ev["losses"] <= 12 and ev["rigid_check_mrad"] > 0 and ev["tests"] == 3
    assert model.extras["summary"]["heliostats_using_network"] == 0
    assert model.extras["summary"]["keep_rule"]["level"] == keep.LEVEL
    assert torch.equal(model.delta, lm.delta)
    assert torch.allclose(model.pointing_error(te), lm.pointing_error(te), atol=1e-12)
    # determinism: the same seed gives the same evidence and the same model
    again = fit_hybrid_method(kin, tr, None, depth=2, hidden=2, steps=60, lr=1e-2, field_prior=False)
    assert again.extras["per_heliostat"] == model.extras["per_heliostat"]
    assert torch.equal(again.pointing_error(te), model.pointing_error(te))


def test_networks_are_never_tested_on_too_few_validation_records():
    """``--train 20`` carves 4 validation records: below the minimum, no network is even trained; exactly lm."""
    kin, tr, te = _rigid_heliostats(5)
    tr20, va = tr.subset((tr.time < 1.6e9 + 16 * 7 * 86400.0)), tr.subset((tr.time >= 1.6e9 + 16 * 7 * 86400.0)
                                                                          & (tr.time < 1.6e9 + 20 * 7 * 86400.0))
    model = fit_mlp_method(kin, tr20, va, field_prior=False, every="6h")
    lm = fit_lm_method(kin, tr20, va, field_prior=False)
    info = model.extras["per_heliostat"]["S0"]
    assert info["uses_network"] is False and info["keep_test"]["n_check"] == 8 and info["keep_test"]["p_value"] is None
    assert "validation records per block [4, 4]: fewer than 6" in info["fallback_reason"]
    assert torch.allclose(model.pointing_error(te), lm.pointing_error(te), atol=1e-12)


@pytest.mark.slow
def test_hybrid_keeps_a_network_for_a_gear_error_and_it_wins_on_later_records():
    """A periodic motor-step error (~1 mrad) no rigid body has: with 100 chronological training records the
    network passes the test on the latest 20 and the 20 before (p < 0.05, positive gains) and beats lm on the 30
    later records."""
    kin, true = _true(1)
    b = _gear_error(kin, with_weekly_times(simulate(true, 130, 7, noise=3e-4)), 150.0)
    tr, te = b.subset(torch.arange(100)), b.subset(torch.arange(100, 130))
    model = fit_hybrid_method(kin, tr, None, depth=4, hidden=4, steps=600, lr=1e-2, field_prior=False)
    ev = model.extras["per_heliostat"]["S0"]["keep_test"]
    assert ev["kept"] and ev["n_check"] == 40 and ev["p_value"] < 0.05 and ev["mean_gain_mrad"] > 0.1, ev
    lm = fit_lm_method(kin, tr, None, field_prior=False)
    e_net, e_lm = float(model.pointing_error(te).mean()), float(lm.pointing_error(te).mean())
    assert e_net < 0.8 * e_lm, (e_net, e_lm)


def _gear_fleet(h=6, n=45, n_train=30, seed=7):
    """``h`` heliostats with the same gear error (150 increments over the range), weekly records: each heliostat's
    first ``n_train`` for training, the rest for test."""
    kin, true = _true(h)
    b = _gear_error(kin, simulate(true, n, seed, noise=3e-4), 150.0)
    b.time = 1.6e9 + (torch.arange(n * h) % n).to(F64) * 7 * 86400.0
    first = (torch.arange(n * h) % n) < n_train
    return kin, b.subset(first), b.subset(~first)


@pytest.mark.slow
def test_fleet_pretraining_learns_a_shared_error_no_heliostat_shows_alone():
    """Six heliostats with the same gear error and 30 training records each: alone, at most one network passes the
    keep test (18-24 fit records hardly learn it); pretrained on the fleet, most do, and the hybrid beats lm on
    later records."""
    kin, tr, te = _gear_fleet()
    opts = dict(depth=4, hidden=4, steps=600, lr=1e-2, field_prior=False)
    lm = fit_lm_method(kin, tr, None, field_prior=False)
    alone = fit_hybrid_method(kin, tr, None, **opts)
    fleet = fit_hybrid_method(kin, tr, None, pretrain="fleet", **opts)
    assert int(alone.extras["use_net"].sum()) <= 1
    assert int(fleet.extras["use_net"].sum()) >= 4 and fleet.extras["summary"]["pretrain"] == "fleet"
    e_fleet, e_lm = float(fleet.pointing_error(te).mean()), float(lm.pointing_error(te).mean())
    assert e_fleet < 0.8 * e_lm, (e_fleet, e_lm)


def test_hybrid_names_an_unknown_pretraining():
    kin, tr, _ = _gear_fleet(h=1, n=10, n_train=8)
    with pytest.raises(HeliotwinError, match="pretrain must be one of none, fleet"):
        fit_hybrid_method(kin, tr, None, pretrain="plant")


@pytest.mark.slow
def test_calibrate_reports_the_keep_test_per_heliostat_in_its_json(tmp_path, capsys):
    """A ``--split current`` run (no validation records carved): each heliostat is checked on its latest fifth,
    and the JSON report carries the evidence per heliostat and the rule in the overall method info."""
    sim = simulate_plant(SimulationSettings(heliostats=2, seed=3, years=0.6, records_per_month=6))
    folder = write_paint_folder(sim, tmp_path / "paint")
    report = tmp_path / "cal.json"
    code, _, err = run_cli(capsys, "calibrate", "--paint", folder, "--method", "hybrid", "--min-records", 20,
                           "-o", tmp_path / "cal.h5", "--json", report, "--no-plots")
    assert code == 0, err
    rep = json.loads(report.read_text())
    assert rep["overall"]["method_info"]["keep_rule"]["level"] == keep.LEVEL
    infos = [h["method_info"] for h in rep["heliostats"].values() if h.get("status") == "ok"]
    assert infos
    for info in infos:
        ev = info["keep_test"]
        assert ev["n_check"] >= keep.MIN_CHECK and ev["p_value"] is not None, ev
        assert info["uses_network"] is ev["kept"] and (ev["reason"] is None) is ev["kept"]


def test_a_study_run_reports_the_keep_test_of_its_validation_records(tmp_path):
    """``--split chrono --train 30``: the run's 6 validation records (its latest) are the check records; the report
    (what ``--json`` writes) carries each heliostat's evidence."""
    sim = simulate_plant(SimulationSettings(heliostats=2, seed=3, years=0.6, records_per_month=6))
    folder = write_paint_folder(sim, tmp_path / "paint")
    cfg = RunConfig(paint=str(folder), method="hybrid", split="chrono", train=30, test=5, min_records=35,
                    method_options={"depth": 2, "steps": 40})
    rep, model, _ = run_calibration(cfg, load_paint(folder))
    ok = [h for h in rep["heliostats"].values() if h.get("status") == "ok"]
    assert ok and rep["overall"]["method_info"]["keep_rule"]["min_check"] == keep.MIN_CHECK
    for h in ok:
        ev = h["method_info"]["keep_test"]
        assert [f["n_check"] for f in ev["folds"]] == [6, 6] and ev["p_value"] is not None, ev
        assert ev["tests"] == len(ok)
        assert h["method_info"]["uses_network"] is ev["kept"]
