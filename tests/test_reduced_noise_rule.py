"""The reduced models' interval and rule (issue 42 item 1): a few bad centroids do not set a reduced heliostat's
expected error (on ``../shared/data/paint`` they put its p95 at 16 mrad for heliostats that fit their other records
to 1 mrad), and the rule is what its validation evidence says, not a fixed choice.
"""
from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from heliotwin.calibrate.protocol import reduced
from heliotwin.io.paint import load_paint
from heliotwin.simulate import SimulationSettings, simulate_plant, write_paint_folder
from heliotwin.simulate.writer import truth_scenario


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    sim = simulate_plant(SimulationSettings(heliostats=2, seed=5, years=0.3, records_per_month=30))
    ds = load_paint(write_paint_folder(sim, tmp_path_factory.mktemp("noise") / "paint"))
    return ds.plant.field.kinematics, ds.records


def _noise(kin, recs, monkeypatch=None, sigmas=None):
    """Per heliostat [H]: the record noise [mrad] of the reduced fit's posterior (all 8 under the nominal prior)."""
    if monkeypatch is not None:
        monkeypatch.setattr(reduced, "OUTLIER_SIGMAS", sigmas)
    model, _ = reduced.fit_reduced(kin, recs, reduced.Rule(((1, "all 8"),), True), None, 0.3e-3)
    return 1e3 * model.extras["posterior"]["noise_rad"]


def _corrupt(recs, heliostat: int, k: int, metres: float):
    """``recs`` with the centroids of ``heliostat``'s first ``k`` records moved by ``metres`` upward on the target
    (both camera systems): bad centroids, tens of mrad off at a heliostat's distance."""
    rows = (recs.heliostat_index == heliostat).nonzero().flatten()[:k]
    shift = torch.zeros_like(recs.spot)
    shift[rows, 2] = metres
    other = None if recs.spot_other is None else recs.spot_other + shift
    return replace(recs, spot=recs.spot + shift, spot_other=other)


def test_a_few_bad_centroids_do_not_set_a_reduced_heliostats_noise(records, monkeypatch):
    kin, recs = records
    n = int((recs.heliostat_index == 0).sum())
    assert n >= 15
    clean = _noise(kin, recs)
    bad = _corrupt(recs, 0, 3, 5.0)
    capped = _noise(kin, bad)
    # the other heliostat is untouched; the corrupted one's noise stays near its clean value
    assert abs(float(capped[1] - clean[1])) < 1e-6
    assert float(capped[0]) < 2.0 * float(clean[0]), (capped, clean)
    # what the uncapped sum of squares gave (the old estimate): several times the clean noise
    uncapped = _noise(kin, bad, monkeypatch, float("inf"))
    assert float(uncapped[0]) > 4.0 * float(clean[0]), (uncapped, clean)


def test_a_heliostat_whose_records_are_all_off_keeps_its_large_noise(records):
    """The cap bounds single records, scaled by the heliostat's own median residual: a heliostat that fits none of
    its records (here every centroid scattered by metres) is not made to look precise."""
    kin, recs = records
    rows = (recs.heliostat_index == 0).nonzero().flatten()
    g = torch.Generator().manual_seed(0)
    shift = torch.zeros_like(recs.spot)
    shift[rows, 2] = 3.0 * torch.randn(len(rows), generator=g, dtype=recs.spot.dtype)
    other = None if recs.spot_other is None else recs.spot_other + shift
    noisy = _noise(kin, replace(recs, spot=recs.spot + shift, spot_other=other))
    assert float(noisy[0]) > 5.0 * float(_noise(kin, recs)[0])


def test_the_rule_is_what_its_evidence_says(five):
    """Each validated record count's choice is the candidate its held-out errors rank first (fewest free
    parameters first, a richer one only when strictly lower, nominal when lower still), and the steps are those
    choices; with nominal kinematics that already are the truth, no reduced model beats them."""
    rule = reduced.choose_rule(five["nominal"], five["records"], five["deviations"], 30, seed=0)
    assert rule.validated
    _check_evidence(rule)
    assert rule.fewest is not None and rule.choice(3) != "nominal"
    exact = reduced.choose_rule(five["truth"], five["records"], torch.zeros_like(five["deviations"]), 30, seed=0)
    _check_evidence(exact)
    counts = [k for k in exact.evidence if k.isdigit()]
    assert counts and all(exact.evidence[k]["nominal"] < 1.0 for k in counts)  # nominal = truth: noise only
    assert exact.fewest is None and exact.steps != rule.steps, (exact.steps, rule.steps)


def _check_evidence(rule):
    choices = []
    for key in sorted((k for k in rule.evidence if k.isdigit()), key=int):
        row = rule.evidence[key]
        best = "nominal"
        for name in reduced.PARAMETER_SETS:
            if row[name] < row["nominal"] and (best == "nominal" or row[name] < row[best]):
                best = name
        assert row["chosen"] == best, (key, row)
        choices.append((int(key), best))
    steps = [c for i, c in enumerate(choices) if i == 0 or choices[i - 1][1] != c[1]]
    assert list(rule.steps) == steps


@pytest.fixture(scope="module")
def five(tmp_path_factory):
    """Five simulated heliostats with static true kinematics (no drift, no steps) and 60+ records each: their
    nominal and true kinematics, records, and each one's loose fit (what a run's fold priors are learned from)."""
    sim = simulate_plant(SimulationSettings(heliostats=5, seed=9, years=0.5, records_per_month=14,
                                            drift_mrad_per_sqrt_day=0.0, step_rate_per_year=0.0))
    ds = load_paint(write_paint_folder(sim, tmp_path_factory.mktemp("five") / "paint"))
    nominal = ds.plant.field.kinematics
    model, _ = reduced.fit_reduced(nominal, ds.records, reduced.Rule(((1, "all 8"),), True), None, 0.3e-3)
    truth = truth_scenario(sim).plant.field.kinematics
    return {"nominal": nominal, "records": ds.records, "deviations": model.delta.detach().double().cpu(),
            "truth": truth.to(dtype=nominal.position.dtype)}
