"""The ``score`` workflow: how close a learned scenario comes to a simulated plant's truth.

Kept apart from :mod:`heliotwin.workflows.simulate` (which draws plants with priors learned by calibration) so
that scoring a plant does not import the calibration methods: ``score`` is one of the commands an engineer runs
on a plant every day, and its start-up is part of its time.
"""
from __future__ import annotations

from ..evaluation import score as score_plant
from ..io.scenario import Scenario
from .show import nominal_heliostats, nominal_summary

__all__ = ["score", "summary_lines"]


def score(truth: Scenario, scenario: Scenario, *, suns: int = 16, seed: int = 0, flux: bool = True
          ) -> tuple[Scenario, dict]:
    """Score ``scenario`` against ``truth`` (unchanged scenario back; the report is the answer).

    ``suns`` sun positions drawn by ``seed`` give the pointing error [mrad]; ``flux`` (a flag) also compares the
    receiver flux maps at the first sun (relative L1 [1], power ratio [1]). The report is
    :func:`heliotwin.evaluation.score`'s plus the two scenarios' paths and ``nominal_heliostats`` (id -> why
    the calibration left it nominal; its ``worst_heliostats`` say which kinematics each had).
    """
    report = score_plant(truth, scenario, suns=suns, seed=seed, flux=flux)
    report.update(truth=truth.path or None, scenario=scenario.path or None)
    nominal = nominal_heliostats(scenario)
    report["nominal_heliostats"] = nominal
    for w in report.get("worst_heliostats", []):
        w["kinematics"] = "nominal" if w["heliostat"] in nominal else "calibrated"
    return scenario, report


def summary_lines(report: dict) -> list:
    """The lines ``heliotwin score`` prints after its figures: the worst heliostats with their error, and the
    heliostats the scenario's calibration left nominal (named, with why)."""
    lines = []
    worst = report.get("worst_heliostats") or []
    if worst:
        lines.append("worst heliostats (median pointing error over the suns): " + ", ".join(
            f"{w['heliostat']} {w['median_mrad']:.2f} mrad" + (" (nominal)" if w.get("kinematics") == "nominal" else "")
            for w in worst))
    line = nominal_summary(report.get("nominal_heliostats") or {})
    if line:
        lines.append(line)
    return lines
