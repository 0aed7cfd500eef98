"""The networks' keep rule (``hybrid``, ``mlp``): a network only where held-out records show a gain beyond noise.

Per heliostat, on the records a method may see (``--train``: training + validation):

1. *check records* ``V``: the validation records the run carved out of ``--train`` (the split's own rule:
   the latest records in a chronological run); where the run carved none (``--split current``, the online
   split's rounds), the latest :data:`CHECK_FRACTION` of each heliostat's timed training records (the share the
   run's default validation takes, :meth:`~heliotwin.calibrate.protocol.config.RunConfig.n_validation`). The
   other records are the *fit records* ``A``.
2. Both candidates are fitted on ``A`` only: the rigid body (exactly ``lm``) and the rigid body plus its network,
   trained a fixed number of steps. Nothing about the network is chosen on ``V`` (no early stopping there): the
   earlier rule stopped each network at its best validation step and then tested it on the same records, which
   let noise through (on real heliostats: kept on 3 of 8, worse on test than ``lm``).
3. *test*: the paired per-record gain ``g = e_rigid - e_network`` on ``V``, one-sided Wilcoxon signed-rank test
   (exact below 50 records, :func:`scipy.stats.wilcoxon`) on at least :data:`MIN_CHECK` records, its p-values
   held to a false-discovery rate of :data:`LEVEL` over the heliostats tested in the run (Benjamini-Hochberg:
   with one heliostat, plain ``p <= LEVEL``), and a positive mean gain (the signed-rank test alone would admit a
   network that wins most records by a little and loses one by a lot). Otherwise the heliostat uses the rigid
   body alone. Why the false-discovery rate: each heliostat at 5 % would keep about one network in twenty where
   none helps, and a run calibrates tens of heliostats; held to 5 % of the kept ones, the kept networks are the
   ones that win (the uncorrected 5 % kept 3 of 22 networks on the 11 shared PAINT heliostats at chrono 30/30,
   p = 0.016-0.047, one of them 0.08 mrad worse on test).
4. A kept network is refitted on every record the method may see (``A`` + ``V``), on top of ``lm`` fitted on the
   same records: the deployed model never knows less than ``lm`` does.

Settings, stated a priori (none tuned on any test record): :data:`LEVEL` = 0.05, the usual level (here a
false-discovery rate);
:data:`MIN_CHECK` = 6, the fewest records at which an exact one-sided signed-rank test at 0.05 still tolerates one
lost record (with 5 every record must win: p = 1/32); :data:`CHECK_FRACTION` = 0.2, the run's default validation
share. With ``--train 30`` a chronological run checks on 6 records; with ``--train 20`` or fewer (4 or fewer) no
network can be kept, and the method is exactly ``lm``.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy.stats import wilcoxon

from ...io.records import RecordTable

#: One-sided significance level of the paired gain.
LEVEL = 0.05
#: Fewest check records per heliostat for a network to be kept at all.
MIN_CHECK = 6
#: Share of a heliostat's timed training records checked on when the run carved no validation.
CHECK_FRACTION = 0.2
#: Gains below this [rad] count as ties (left out of the signed-rank test): float noise, not a difference.
TIE = 1e-9


def check_split(train: RecordTable, validation: RecordTable | None,
                fraction: float = CHECK_FRACTION) -> tuple[RecordTable, RecordTable]:
    """Fit records ``A`` and check records ``V`` (see module docstring, step 1), over the heliostat axis of ``train``.

    ``validation`` given and non-empty: ``(train, validation)``. Otherwise each heliostat's latest
    ``round(fraction * n_timed)`` timed records of ``train`` are checked on (records without a time stay fit records:
    they cannot be ordered).
    """
    if validation is not None and len(validation):
        return train, validation
    t = train.time
    if t is None or not len(train):
        return train, train.subset([])
    timed = torch.isfinite(t)
    key = torch.where(timed, t, torch.full_like(t, -math.inf))
    # Rank of each record in its heliostat's time order: sort by time, then stably by heliostat.
    order = torch.argsort(key, stable=True)
    order = order[torch.argsort(train.heliostat_index[order], stable=True)]
    hidx = train.heliostat_index[order]
    counts = torch.bincount(hidx, minlength=train.num_heliostats)
    start = torch.cumsum(counts, 0) - counts
    rank = torch.arange(len(order), device=order.device) - start[hidx]
    n_timed = torch.bincount(train.heliostat_index[timed], minlength=train.num_heliostats)
    n_check = torch.round(fraction * n_timed.to(torch.float64)).long()
    is_check = torch.zeros(len(train), dtype=torch.bool, device=order.device)
    is_check[order] = rank >= (counts - n_check)[hidx]
    is_check &= timed
    return train.subset(~is_check), train.subset(is_check)


def paired_gain_test(err_rigid: torch.Tensor, err_net: torch.Tensor, heliostat_index: torch.Tensor, h: int, *,
                     testable: torch.Tensor | None = None, level: float = LEVEL,
                     min_check: int = MIN_CHECK) -> tuple[torch.Tensor, dict]:
    """Which heliostats keep their network, with the evidence.

    Parameters
    ----------
    err_rigid, err_net : torch.Tensor, [R]
        Pointing error [rad] of each check record under the rigid body and under the rigid body + network (both
        fitted without the check records).
    heliostat_index : torch.Tensor, [R], long
    h : int
        Heliostats H.
    testable : torch.Tensor, [H], bool, optional
        Heliostats whose network was trained at all (the others are reported, never kept).
    level, min_check : float, int
        See :data:`LEVEL`, :data:`MIN_CHECK`.

    Returns
    -------
    keep : torch.Tensor, [H], bool
    evidence : dict
        Heliostat index -> ``{"kept", "reason", "n_check", "mean_gain_mrad", "median_gain_mrad", "wins", "losses",
        "p_value", "threshold", "tests", "rigid_check_mrad", "network_check_mrad", "level", "min_check"}`` (gains:
        rigid minus network, positive = the network helps; ``p_value`` None where no test ran; ``threshold``: the
        Benjamini-Hochberg bound its p-value had to meet among the ``tests`` heliostats tested; ``reason`` None
        where kept).
    """
    keep = torch.zeros(h, dtype=torch.bool)
    gain_all = (err_rigid - err_net).detach().cpu().double().numpy()
    hidx = heliostat_index.detach().cpu().numpy()
    er, en = err_rigid.detach().cpu().double().numpy(), err_net.detach().cpu().double().numpy()
    evidence = {}
    tested = []
    for i in range(h):  # heliostats (tens), once per fit
        m = hidx == i
        g = gain_all[m]
        n = int(len(g))
        ev = {"kept": False, "reason": None, "n_check": n, "level": level, "min_check": min_check,
              "mean_gain_mrad": float(g.mean()) * 1e3 if n else None,
              "median_gain_mrad": float(np.median(g)) * 1e3 if n else None,
              "wins": int((g > TIE).sum()), "losses": int((g < -TIE).sum()), "p_value": None,
              "rigid_check_mrad": float(er[m].mean()) * 1e3 if n else None,
              "network_check_mrad": float(en[m].mean()) * 1e3 if n else None}
        evidence[i] = ev
        if n < min_check:
            ev["reason"] = f"{n} validation records < {min_check}"
            continue
        if testable is not None and not bool(testable[i]):
            ev["reason"] = "no network trained (too few fit records)"
            continue
        nz = g[np.abs(g) > TIE]
        ev["p_value"] = 1.0 if len(nz) == 0 else float(wilcoxon(nz, alternative="greater", zero_method="wilcox").pvalue)
        tested.append(i)
    passed = benjamini_hochberg([evidence[i]["p_value"] for i in tested], level)
    for i, (ok, threshold) in zip(tested, passed):
        ev = evidence[i]
        ev["threshold"], ev["tests"] = threshold, len(tested)
        if not ok:
            ev["reason"] = (f"gain {ev['mean_gain_mrad']:.3f} mrad on {ev['n_check']} validation records not "
                            f"significant (one-sided Wilcoxon p = {ev['p_value']:.3f}, needs <= {threshold:.4f}: "
                            f"{level} false-discovery rate over {len(tested)} heliostats)")
        elif not ev["mean_gain_mrad"] > 0.0:
            ev["reason"] = f"mean gain {ev['mean_gain_mrad']:.3f} mrad not positive"
        else:
            keep[i] = True
            ev["kept"] = True
    return keep.to(err_rigid.device), evidence


def benjamini_hochberg(p_values: list, level: float = LEVEL) -> list[tuple[bool, float]]:
    """Benjamini-Hochberg at false-discovery rate ``level`` over m p-values: per p-value, (rejected, its threshold
    ``k / m * level`` at its rank k, ascending). With m = 1 it is the plain test ``p <= level``.

    >>> [(ok, round(t, 4)) for ok, t in benjamini_hochberg([0.01, 0.04, 0.03], 0.05)]
    [(True, 0.0167), (True, 0.05), (True, 0.0333)]
    >>> [(ok, round(t, 4)) for ok, t in benjamini_hochberg([0.016, 0.047] + [0.5] * 9, 0.05)[:2]]
    [(False, 0.0045), (False, 0.0091)]
    """
    m = len(p_values)
    order = sorted(range(m), key=lambda j: p_values[j])
    thresholds = [0.0] * m
    largest = 0
    for k, j in enumerate(order, start=1):
        thresholds[j] = k / m * level
        if p_values[j] <= thresholds[j]:
            largest = k
    rejected = set(order[:largest])
    return [(j in rejected, thresholds[j]) for j in range(m)]
