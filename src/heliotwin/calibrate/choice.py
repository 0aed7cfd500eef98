"""Choosing a setting by validation: the one rule of every learner that picks among candidates.

Calibration's leave-heliostats-out cross-validation (:func:`heliotwin.calibrate.protocol.selection.select`:
the median error over held-out heliostats), the surface learner's leave-one-image-out choice of penalty weight
and step count (:func:`heliotwin.surfaces.generalise.loo_select`: the mean held-out L1) and the in-silico
study's Laplacian weight score their candidates differently, but choose the same way: the lowest score wins,
a tie goes to the candidate listed first (grids list the plainer setting first, so a setting that does not
help on held-out data is not taken), and a candidate whose score is not finite (a failed fit) never wins over
one whose score is.
"""
from __future__ import annotations

import math
from collections.abc import Mapping

__all__ = ["lowest"]


def lowest(scores: Mapping):
    """The key of ``scores`` with the lowest score.

    Parameters
    ----------
    scores : mapping of candidate -> float
        Validation score of each candidate (lower is better; e.g. an error [mrad] or an L1 [1]), in the order
        the candidates were listed.

    Returns
    -------
    The winning key: the lowest finite score, ties to the earlier key; when no score is finite, the first key.

    Raises
    ------
    ValueError
        ``scores`` is empty.

    Examples
    --------
    >>> lowest({"none": 0.5, "ridge": 0.4, "lasso": 0.4})
    'ridge'
    >>> lowest({0.0: float("nan"), 1.0: 2.0})
    1.0
    """
    keys = list(scores)
    if not keys:
        raise ValueError("no candidates to choose from")

    def rank(i: int):
        v = float(scores[keys[i]])
        return (0, v, i) if math.isfinite(v) else (1, 0.0, i)

    return keys[min(range(len(keys)), key=rank)]
