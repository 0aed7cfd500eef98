"""Choosing a setting by validation: the one rule of every learner that picks among candidates.

Calibration's leave-heliostats-out cross-validation (:func:`heliotwin.calibrate.protocol.selection.select`:
the median error over held-out heliostats), the surface learner's leave-one-image-out choice of penalty weight
and step count (:func:`heliotwin.surfaces.generalise.loo_select`: the mean held-out L1) and the in-silico
study's Laplacian weight score their candidates differently, but choose the same way: the lowest score wins,
a tie goes to the candidate listed first (grids list the plainer setting first, so a setting that does not
help on held-out data is not taken), and a candidate whose score is not finite (a failed fit) never wins over
one whose score is.

A costlier setting (more bootstrap bags, say) is held to more than a lower median: :func:`worth_its_cost` takes
it only when it is better on more held-out units than chance explains (a one-sided sign test), so the cheaper
setting wins where the two do equally well.
"""
from __future__ import annotations

import math
from collections.abc import Mapping

__all__ = ["lowest", "worth_its_cost", "sign_test"]


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


def sign_test(better: int, worse: int) -> float:
    """One-sided sign test: the probability of ``better`` or more wins in ``better + worse`` fair coin tosses
    (ties left out before counting). The exact binomial tail (``scipy.stats.binomtest(..., alternative="greater")``
    gives the same; ``tests/test_choice.py``).

    >>> round(sign_test(8, 2), 4)
    0.0547
    """
    n = better + worse
    if n == 0:
        return 1.0
    return sum(math.comb(n, k) for k in range(better, n + 1)) / 2.0 ** n


def worth_its_cost(cheap: Mapping, costly: Mapping, level: float = 0.05) -> tuple[bool, dict]:
    """Whether a costlier candidate beats a cheaper one on held-out units by more than chance.

    Parameters
    ----------
    cheap, costly : mapping of unit (e.g. heliostat id) -> score
        Validation scores of the two candidates (lower is better), paired by unit; units missing from either or
        not finite in either are left out.
    level : float
        Significance of the one-sided sign test on the paired differences.

    Returns
    -------
    (take_costly, info) : (bool, dict)
        ``info``: ``better`` / ``worse`` / ``ties`` (units where the costly one scored lower / higher / equal),
        ``p`` (:func:`sign_test`), ``median_cheap`` / ``median_costly`` over the paired units.

    >>> worth_its_cost({"a": 1.0, "b": 1.0}, {"a": 0.9, "b": 0.9})[0]  # two wins are no evidence
    False
    """
    units = [u for u in cheap if u in costly and math.isfinite(float(cheap[u])) and math.isfinite(float(costly[u]))]
    diff = [float(costly[u]) - float(cheap[u]) for u in units]
    better, worse = sum(d < 0 for d in diff), sum(d > 0 for d in diff)
    p = sign_test(better, worse)

    def med(values):
        v = sorted(values)
        return float("nan") if not v else (v[(len(v) - 1) // 2] + v[len(v) // 2]) / 2.0

    info = {"better": better, "worse": worse, "ties": len(diff) - better - worse, "p": p,
            "median_cheap": med(float(cheap[u]) for u in units), "median_costly": med(float(costly[u]) for u in units)}
    return p < level, info
