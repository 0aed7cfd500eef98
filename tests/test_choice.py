"""One settings-selection rule for every learner (``heliotwin.calibrate.choice.lowest``)."""
from __future__ import annotations

import math

import pytest
from scipy.stats import binomtest

from heliotwin.calibrate.choice import lowest, sign_test, worth_its_cost
from heliotwin.calibrate.protocol import selection
from heliotwin.calibrate.protocol.config import RunConfig


def test_lowest_finite_score_wins_ties_go_to_the_earlier_candidate():
    assert lowest({"a": 3.0, "b": 1.0, "c": 1.0}) == "b"
    assert lowest({(0.0, 10): 0.2, (0.1, 10): 0.2}) == (0.0, 10)  # the plainer setting is listed first
    assert lowest({"failed": math.nan, "ok": 5.0, "inf": math.inf}) == "ok"
    assert lowest({"x": math.nan, "y": math.inf}) == "x"  # nothing finite: the first
    with pytest.raises(ValueError):
        lowest({})


def test_calibration_selection_uses_the_rule_on_median_errors():
    """Leave-heliostats-out CV: the candidate with the lowest median over held-out heliostats, ties to the
    earlier; a candidate whose every fit failed (no finite error) loses to any that ran."""
    cands = [{"prior": "run"}, {"prior": "plant"}, {"prior": "run", "bags": 10}]
    scores = {selection.label(cands[0]): {"h1": 1.0, "h2": 3.0, "h3": 2.0},   # median 2.0
              selection.label(cands[1]): {"h1": 1.5, "h2": 1.5, "h3": 9.0},   # median 1.5
              selection.label(cands[2]): {"h1": None, "h2": None, "h3": None}}  # failed: inf
    assert selection.select(scores, cands) is cands[1]
    scores[selection.label(cands[0])] = {"h1": 1.5, "h2": 1.5, "h3": 1.0}    # median 1.5: tie, earlier wins
    assert selection.select(scores, cands) is cands[0]


def test_sign_test_is_scipys_exact_binomial_tail():
    for better, worse in [(0, 0), (5, 0), (8, 2), (60, 40), (3, 17), (120, 80)]:
        expected = binomtest(better, better + worse, 0.5, alternative="greater").pvalue if better + worse else 1.0
        assert sign_test(better, worse) == pytest.approx(expected, rel=1e-9)


def test_costlier_setting_only_when_it_wins_beyond_chance():
    """A costlier candidate (bags) that is better on 150 of 200 held-out heliostats is taken; one whose
    differences are noise (a lower median by a hair, as often as not better) is not; ties are left out."""
    cheap = {f"h{i}": 1.0 + 0.01 * i for i in range(200)}
    clearly = {k: v - (0.05 if i < 150 else -0.05) for i, (k, v) in enumerate(cheap.items())}
    take, info = worth_its_cost(cheap, clearly)
    assert take and info["better"] == 150 and info["worse"] == 50 and info["p"] < 1e-10
    noise = {k: v + (-0.001 if i % 2 else 0.0012) for i, (k, v) in enumerate(cheap.items())}
    take, info = worth_its_cost(cheap, noise)
    assert not take and info["better"] == 100 and info["median_costly"] < info["median_cheap"] + 0.01
    take, info = worth_its_cost({"a": 1.0, "b": math.nan, "c": 2.0}, {"a": 1.0, "b": 0.5, "d": 0.1})
    assert not take and (info["better"], info["worse"], info["ties"]) == (0, 0, 1)


def test_current_settings_take_a_costlier_candidate_only_when_it_wins():
    """Each candidate of a current plant is run on the validation protocol once; bagging and the random walk
    are taken only when they predict more heliostats' held-out records better than chance (here: the walk wins
    on all 12, bagging on none), and the walk's process noise is the one its validation run chose."""
    def runner_with(gain_bags, gain_walk):
        calls = []

        def runner(cfg, dataset):
            b, walk = cfg.method_options["bags"], cfg.drift_model == "kalman"
            calls.append((b, cfg.drift_model, cfg.process_noise))
            gain = gain_walk if walk else (gain_bags if b else 0.0)
            rep = {"heliostats": {f"h{i}": {"status": "ok", "mean_test_mrad": 1.0 + 0.1 * i - gain}
                                  for i in range(12)},
                   "overall": {"seconds": 1.0 + b, "method_info": {"process_noise_mrad2_per_day": 0.003}}}
            return rep, None, {"bags": b, "walk": walk}
        return runner, calls

    cfg = RunConfig(paint="x", method_options={"half_life_days": 30.0})
    runner, calls = runner_with(0.0, 0.05)
    chosen, run, info = selection.choose_current(cfg, None, runner=runner)
    assert calls == [(0, "none", "auto"), (10, "none", "auto"), (0, "kalman", "auto")]
    assert info["chosen"] == "random-walk offset" and run[2] == {"bags": 0, "walk": True}
    assert chosen.drift_model == "kalman" and chosen.process_noise == 0.003 and chosen.method_options["bags"] == 0
    assert [t["taken"] for t in info["tests"]] == [False, True] and info["tests"][1]["better"] == 12
    runner, calls = runner_with(0.05, 0.0)  # bagging wins; the walk is then judged against the bagged fits
    chosen, run, info = selection.choose_current(cfg, None, runner=runner)
    assert info["chosen"] == "static, 10 bags" and chosen.drift_model == "none" and chosen.method_options["bags"] == 10
    assert info["tests"][1]["against"] == "static, 10 bags" and info["tests"][1]["worse"] == 12
    runner, calls = runner_with(0.0, 0.0)
    chosen, run, info = selection.choose_current(cfg, None, runner=runner, drift=False)
    assert len(calls) == 2 and info["chosen"] == "static" and info["tests"][0]["ties"] == 12
