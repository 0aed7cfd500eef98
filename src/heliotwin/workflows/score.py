"""The ``score`` workflow: how close a learned scenario comes to a simulated plant's truth.

Kept apart from :mod:`heliotwin.workflows.simulate` (which draws plants with priors learned by calibration) so
that scoring a plant does not import the calibration methods: ``score`` is one of the commands an engineer runs
on a plant every day, and its start-up is part of its time.
"""
from __future__ import annotations

from ..evaluation import score as score_plant
from ..io.scenario import Scenario

__all__ = ["score"]


def score(truth: Scenario, scenario: Scenario, *, suns: int = 16, seed: int = 0, flux: bool = True
          ) -> tuple[Scenario, dict]:
    """Score ``scenario`` against ``truth`` (unchanged scenario back; the report is the answer).

    ``suns`` sun positions drawn by ``seed`` give the pointing error [mrad]; ``flux`` (a flag) also compares the
    receiver flux maps at the first sun (relative L1 [1], power ratio [1]). The report is
    :func:`heliotwin.evaluation.score`'s plus the two scenarios' paths.
    """
    report = score_plant(truth, scenario, suns=suns, seed=seed, flux=flux)
    report.update(truth=truth.path or None, scenario=scenario.path or None)
    return scenario, report
