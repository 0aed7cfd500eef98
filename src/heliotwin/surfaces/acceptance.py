"""Decisions about a learned surface that do not depend on how it was fitted (functional).

* :func:`wilson_interval`: 95 % Wilson score interval of a binomial proportion (how many test images improved).
* :func:`robust_outliers`: training images to drop as inconsistent -- robust z-score of each image's held-out
  L1 (under a fit to the *other* training images) against the median and MAD of all of them, two-sided: an
  image the others predict far *worse* than the rest (a halo they cannot produce) or far *better* (the
  others are fitted badly because this image pulled the shared optics, e.g. a broad halo choosing a large
  slope error) is inconsistent with them either way.
* :func:`shrink_to_accept`: the acceptance rule. A learned surface is accepted only if no training image is
  worse than under the ideal (start) surface; otherwise the deviation from the start is shrunk,
  ``d = d0 + alpha (d1 - d0)``, and the largest ``alpha`` of a decreasing grid that satisfies the rule (and,
  among those, the lowest mean training L1) is kept. ``alpha = 0`` is the start surface, so the rule always
  holds after it.

References: Wilson, E. B. (1927), J. Am. Stat. Assoc. 22, 209-212. Iglewicz & Hoaglin (1993), "How to detect
and handle outliers" (modified z-score, 0.6745 = 1 / 1.4826).
"""
from __future__ import annotations

import math
import statistics

__all__ = ["wilson_interval", "robust_outliers", "shrink_to_accept", "ALPHAS", "Z_DROP", "Z_FLOOR"]

#: Shrink factors tried by the acceptance rule, largest first.
ALPHAS = (1.0, 0.8, 0.6, 0.4, 0.2, 0.1, 0.0)
#: Robust z-score above which a training image is dropped as inconsistent.
Z_DROP = 3.0
#: Floor of the robust scale [L1]: half the L1 between two images of one heliostat taken minutes apart
#: (0.07-0.10, the metric's floor), so that with few images a tiny MAD does not flag ordinary scatter.
Z_FLOOR = 0.04


def wilson_interval(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of ``k`` successes in ``n`` trials (default 95 %); ``(0, 1)`` for ``n = 0``."""
    if n <= 0:
        return 0.0, 1.0
    p = k / n
    den = 1.0 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, mid - half), min(1.0, mid + half)


def robust_outliers(heldout_l1: list[float], z_drop: float = Z_DROP, floor: float = Z_FLOOR,
                    keep_at_least: int = 2) -> tuple[list[int], list[float]]:
    """Indices of images whose held-out L1 is an outlier, and every image's robust z-score.

    ``z = (x - median) / max(1.4826 MAD, floor)``; an image is dropped if ``|z| > z_drop``; at most
    ``len - keep_at_least`` images are dropped (the largest ``|z|`` first).
    """
    med = statistics.median(heldout_l1)
    mad = statistics.median(abs(x - med) for x in heldout_l1)
    scale = max(1.4826 * mad, floor)
    z = [(x - med) / scale for x in heldout_l1]
    worst = sorted((i for i, v in enumerate(z) if abs(v) > z_drop), key=lambda i: -abs(z[i]))
    return sorted(worst[:max(0, len(heldout_l1) - keep_at_least)]), z


def shrink_to_accept(l1_of_alpha, ideal_l1: list[float], alphas=ALPHAS, tol: float = 1e-6) -> tuple[float, list]:
    """The acceptance rule (module docstring).

    Parameters
    ----------
    l1_of_alpha : callable
        ``alpha -> list of training-image L1`` of the shrunk surface.
    ideal_l1 : list of float
        Training-image L1 of the start (ideal) surface.

    Returns
    -------
    alpha : float
    tried : list of dict
        ``{"alpha", "l1", "ok"}`` per alpha evaluated (stops at the first acceptable one).
    """
    tried = []
    for a in alphas:
        l1 = l1_of_alpha(float(a))
        ok = all(x <= y + tol for x, y in zip(l1, ideal_l1))
        tried.append({"alpha": float(a), "l1": [float(x) for x in l1], "ok": ok})
        if ok:
            return float(a), tried
    return 0.0, tried
