"""One settings-selection rule for every learner (``heliotwin.calibrate.choice.lowest``)."""
from __future__ import annotations

import math

import pytest

from heliotwin.calibrate.choice import lowest
from heliotwin.calibrate.protocol import selection


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
