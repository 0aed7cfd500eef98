"""Train/validation/test splits of one heliostat's records and sun-position coverage (Leibauer MSc, PAINT).

A sun position is the point ``(azimuth, elevation)`` [rad] (PAINT convention); distances between records
are Euclidean in that plane. Every function here works on ONE heliostat's records (numpy arrays of length
n) and returns index arrays into them; :func:`split_records` applies a split to every heliostat of a
:class:`~heliotwin.io.records.RecordTable`.

Sizes
-----
``n_train`` (``--train N``) counts every record a method may see; the validation set (``n_val``) is carved
out of those N, never out of the test set. For each split type the test set and the N-record pool are
chosen by the type's rule, and the validation set is carved from the pool *by the same rule applied to the
pool* (e.g. chronological: the latest V of the pool; azimuth: the pool's largest azimuths), so that
validation imitates the train -> test shift a little.

Split types
-----------
chrono
    Records without a time are dropped (counted). Test = the latest T, pool = the earliest N.
isolation
    Rank records by their mean distance to their 3 nearest neighbours: most isolated T -> test, next V ->
    validation, the rest -> train (a seeded random subset when more than N - V remain).
random
    Seeded random T records -> test, a seeded random N of the rest -> pool (the MLP paper's protocol:
    interpolation between sun positions the training records already cover).
region
    Region sampler: circles of radius 0.25 rad around seeded random records; whole circles go to the test
    set until it has T records (the last circle is cut by distance to its centre), then likewise for
    validation; the rest -> train.
azimuth, solstice, balanced, high_variance
    PAINT's benchmark splits, re-implemented from their published description (PAINT documentation,
    "DatasetSplitter"): PAINT's *validation* set (the set its rule makes most different from training) is
    our test set; PAINT's *training* set is our pool; PAINT's remaining *test* records are unused.

    * azimuth: pool = the N smallest sun azimuths, test = the T largest.
    * solstice: pool = the N records closest (day of year) to the winter solstice, test = the T closest
      to the summer solstice (records without a time are dropped).
    * balanced: k-means (T clusters) on (azimuth, elevation); one record per cluster -> test, a second
      one per cluster -> PAINT's test (unused), filled from the pool when clusters are singletons; the
      rest -> pool (a seeded random subset of N).
    * high_variance: mean distance to the k nearest neighbours, descending: the top T -> test, the next
      T -> unused, the bottom N -> pool.
"""
from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
import torch

from ...errors import HeliotwinError

SPLIT_TYPES = ("chrono", "isolation", "region", "random", "azimuth", "solstice", "balanced", "high_variance")


# ------------------------------------------------------------------------------------------ distances
def sun_points(azimuth, elevation) -> np.ndarray:
    """Stack sun angles [rad] into points (n, 2)."""
    return np.stack([np.asarray(azimuth, dtype=float), np.asarray(elevation, dtype=float)], -1).reshape(-1, 2)


def distance_matrix(a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
    """Euclidean distances between sun points, (n, m) [rad]."""
    b = a if b is None else b
    return np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1))


def knn_mean_distance(points: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean distance of each point to its ``k`` nearest other points, (n,) [rad] (inf when n == 1)."""
    n = len(points)
    if n <= 1:
        return np.full(n, np.inf)
    d = distance_matrix(points)
    np.fill_diagonal(d, np.inf)
    k = min(k, n - 1)
    return np.sort(d, axis=1)[:, :k].mean(1)


def coverage(azimuth, elevation) -> dict:
    """Coverage of the sky by a record set: mean and variance of nearest-neighbour distances [rad].

    A small mean means densely sampled sun positions; a large variance means clustered ones with gaps.
    Also reports the number of 0.25 rad circles needed to cover the points (:func:`region_cover`).
    """
    p = sun_points(azimuth, elevation)
    if len(p) < 2:
        return {"n": int(len(p)), "nn_mean_rad": None, "nn_var_rad2": None, "regions_0p25": int(len(p))}
    nn = knn_mean_distance(p, 1)
    return {"n": int(len(p)), "nn_mean_rad": float(nn.mean()), "nn_var_rad2": float(nn.var()),
            "regions_0p25": int(len(region_cover(p, 0.25)))}


def mean_train_test_distance(train_points: np.ndarray, test_points: np.ndarray) -> float | None:
    """Mean over test records of the distance [rad] to the nearest training record (None if either empty)."""
    if len(train_points) == 0 or len(test_points) == 0:
        return None
    return float(distance_matrix(test_points, train_points).min(1).mean())


def region_cover(points: np.ndarray, radius: float = 0.25) -> list[int]:
    """Greedy cover of the points by circles of ``radius`` [rad]; returns the indices of the centres."""
    uncovered = np.ones(len(points), dtype=bool)
    centres = []
    d = distance_matrix(points)
    while uncovered.any():
        # The uncovered point with the most uncovered neighbours becomes a centre (greedy set cover).
        gain = ((d <= radius) & uncovered[None, :]).sum(1) * uncovered
        c = int(np.argmax(gain))
        centres.append(c)
        uncovered &= d[c] > radius
    return centres


# ------------------------------------------------------------------------------------------- helpers
def _rng(seed) -> np.random.Generator:
    return np.random.default_rng(seed)


def _take_random(idx: np.ndarray, n: int, seed) -> np.ndarray:
    """``n`` of ``idx`` chosen at random (all when fewer), order preserved."""
    if len(idx) <= n:
        return idx
    keep = np.sort(_rng(seed).choice(len(idx), size=n, replace=False))
    return idx[keep]


def day_of_year(times: np.ndarray) -> np.ndarray:
    """Fractional day of year [days] (0 = Jan 1) of ``times`` (n,) in POSIX seconds [s] (NaN stays NaN); (n,)."""
    out = np.full(len(times), np.nan)
    for i, t in enumerate(times):
        if np.isfinite(t):
            d = datetime.fromtimestamp(float(t), tz=timezone.utc)
            start = datetime(d.year, 1, 1, tzinfo=timezone.utc)
            out[i] = (d - start).total_seconds() / 86400.0
    return out


def _circular_day_distance(doy: np.ndarray, target: float) -> np.ndarray:
    d = np.abs(doy - target) % 365.25
    return np.minimum(d, 365.25 - d)


def kmeans(points: np.ndarray, k: int, seed=0, iterations: int = 100) -> np.ndarray:
    """Plain k-means (k-means++ initialisation, seeded) of ``points`` (n, d) (unit sun vectors [1] here);
    returns the cluster label of each point (n,)."""
    n = len(points)
    k = max(1, min(k, n))
    rng = _rng(seed)
    centres = [points[rng.integers(n)]]
    for _ in range(1, k):
        d2 = distance_matrix(points, np.array(centres)).min(1) ** 2
        p = d2 / d2.sum() if d2.sum() > 0 else np.full(n, 1.0 / n)
        centres.append(points[rng.choice(n, p=p)])
    c = np.array(centres)
    labels = np.zeros(n, dtype=int)
    for _ in range(iterations):
        labels = distance_matrix(points, c).argmin(1)
        new = np.array([points[labels == j].mean(0) if (labels == j).any() else c[j] for j in range(k)])
        if np.allclose(new, c):
            break
        c = new
    return labels


# -------------------------------------------------------------------------------------- split rules
def _rule(kind: str, points: np.ndarray, times: np.ndarray, n_keep: int, n_out: int, seed, k: int,
          second_set: bool = True):
    """Apply a split rule to candidates: returns (kept pool, held-out 'far' set, unused) index arrays.

    ``n_out`` records go to the held-out set chosen by the rule (for the main split: the test set; for the
    carving of validation: the validation set), up to ``n_keep`` to the pool. ``second_set``: balanced and
    high_variance also set aside PAINT's second held-out set (not when carving validation from a pool).
    """
    n = len(points)
    all_idx = np.arange(n)
    if kind == "chrono":
        order = np.argsort(times, kind="stable")
        out = order[n - n_out:] if n_out else order[:0]
        rest = order[:n - n_out]
        return rest[:n_keep], out, rest[n_keep:]
    if kind == "isolation":
        order = np.argsort(-knn_mean_distance(points, 3), kind="stable")
        out, rest = order[:n_out], order[n_out:]
        pool = _take_random(np.sort(rest), n_keep, seed)
        return pool, out, np.setdiff1d(rest, pool)
    if kind == "random":
        out = _rng(seed).permutation(n)[:n_out]
        rest = np.setdiff1d(all_idx, out)
        pool = _take_random(rest, n_keep, seed)
        return pool, np.sort(out), np.setdiff1d(rest, pool)
    if kind == "region":
        out = _region_take(points, all_idx, n_out, seed)
        rest = np.setdiff1d(all_idx, out)
        pool = _take_random(rest, n_keep, seed)
        return pool, out, np.setdiff1d(rest, pool)
    if kind == "azimuth":
        order = np.argsort(points[:, 0], kind="stable")
        pool = order[:min(n_keep, max(0, n - n_out))]
        out = order[::-1][:n_out]
        return pool, out, np.setdiff1d(all_idx, np.concatenate([pool, out]))
    if kind == "solstice":
        doy = day_of_year(times)
        winter = np.argsort(_circular_day_distance(doy, 354.5), kind="stable")  # ~Dec 21
        summer = np.argsort(_circular_day_distance(doy, 171.5), kind="stable")  # ~Jun 21
        out = summer[:n_out]
        pool = np.array([i for i in winter if i not in set(out.tolist())][:n_keep], dtype=int)
        return pool, out, np.setdiff1d(all_idx, np.concatenate([pool, out]))
    if kind == "balanced":
        labels = kmeans(points, n_out, seed)
        rng = _rng(seed)
        out, second = [], []
        for j in np.unique(labels):
            members = rng.permutation(np.nonzero(labels == j)[0])
            out.append(members[0])
            if len(members) > 1:
                second.append(members[1])
        out = np.array(out[:n_out], dtype=int)
        rest = np.setdiff1d(all_idx, out)
        if not second_set:
            second = []
        missing = n_out - len(second) if second_set else 0
        spare = np.setdiff1d(rest, second)
        if missing > 0:  # fill PAINT's second held-out set from the remaining records
            second += list(rng.permutation(spare)[:missing])
        second = np.array(second[:n_out], dtype=int)
        rest = np.setdiff1d(rest, second)
        pool = _take_random(rest, n_keep, seed)
        return pool, out, np.setdiff1d(all_idx, np.concatenate([pool, out]))
    if kind == "high_variance":
        order = np.argsort(-knn_mean_distance(points, k), kind="stable")
        out = order[:n_out]
        rest = order[n_out:]
        if second_set:
            rest = rest[n_out:]  # PAINT's second held-out set (unused here)
        pool = rest[::-1][:n_keep]  # the most typical records
        return np.sort(pool), out, np.setdiff1d(all_idx, np.concatenate([pool, out]))
    raise HeliotwinError(f"unknown split type {kind!r}; known: {', '.join(SPLIT_TYPES)}")


def _region_take(points: np.ndarray, candidates: np.ndarray, n_out: int, seed, radius: float = 0.25) -> np.ndarray:
    """Region sampler: whole circles of ``radius`` around random records until ``n_out`` are taken."""
    rng = _rng(seed)
    free = list(candidates)
    taken: list[int] = []
    while len(taken) < n_out and free:
        c = free[int(rng.integers(len(free)))]
        d = np.sqrt(((points[free] - points[c]) ** 2).sum(-1))
        inside = [free[i] for i in np.argsort(d, kind="stable") if d[i] <= radius]
        inside = inside[: n_out - len(taken)]  # cut the last circle by distance to its centre
        taken += inside
        free = [i for i in free if i not in set(inside)]
    return np.array(sorted(taken), dtype=int)


def split_indices(kind: str, azimuth, elevation, times, n_train: int, n_val: int, n_test: int | None,
                  seed: int = 0, k: int = 3) -> dict:
    """Split one heliostat's records.

    Parameters
    ----------
    kind : str
        One of :data:`SPLIT_TYPES`.
    azimuth, elevation : array (n,)
        Sun angles [rad].
    times : array (n,)
        POSIX seconds [s], NaN when unknown (dropped by the time-based types).
    n_train : int
        Records a method may see (training + validation).
    n_val : int
        Validation records carved out of ``n_train``.
    n_test : int or None
        Test records; None = every record not in the pool.
    seed : int
        Seeds every random choice (isolation/region/balanced subsets).

    Returns
    -------
    dict
        ``train``, ``validation``, ``test``, ``unused`` index arrays; ``dropped_no_time`` count.
    """
    if kind not in SPLIT_TYPES:
        raise HeliotwinError(f"unknown split type {kind!r}; known: {', '.join(SPLIT_TYPES)}")
    if n_train < 1 or n_val < 0 or n_val >= n_train or (n_test is not None and n_test < 1):
        raise HeliotwinError(f"split sizes need train >= 1, 0 <= validation < train, test >= 1 "
                             f"(got train {n_train}, validation {n_val}, test {n_test})")
    pts = sun_points(azimuth, elevation)
    times = np.asarray(times, dtype=float).reshape(-1)
    idx = np.arange(len(pts))
    dropped = 0
    if kind in ("chrono", "solstice"):
        ok = np.isfinite(times)
        dropped = int((~ok).sum())
        idx = idx[ok]
    p, t = pts[idx], times[idx]
    n = len(idx)
    n_out = n_test if n_test is not None else max(0, n - n_train)
    n_out = min(n_out, n)
    pool, out, unused = _rule(kind, p, t, n_train, n_out, seed, k)
    # Carve validation out of the pool by the same rule (seed offset so random choices differ).
    if n_val and len(pool) > 1:
        v = min(n_val, len(pool) - 1)
        sub_train, sub_val, sub_unused = _rule(kind, p[pool], t[pool], len(pool) - v, v, seed + 1, k,
                                               second_set=False)
        train, val = pool[np.sort(sub_train)], pool[np.sort(sub_val)]
        unused = np.concatenate([unused, pool[sub_unused]])
    else:
        train, val = np.sort(pool), pool[:0]
    return {"train": idx[np.sort(train)], "validation": idx[np.sort(val)], "test": idx[np.sort(out)],
            "unused": np.sort(np.concatenate([idx[np.asarray(unused, dtype=int)],
                                              np.setdiff1d(np.arange(len(pts)), idx)])).astype(int),
            "dropped_no_time": dropped}


def split_records(batch, kind: str, n_train: int, n_val: int, n_test: int | None, seed: int = 0):
    """Split every heliostat of a :class:`RecordTable`.

    Returns
    -------
    train, validation, test : torch.Tensor, (n_train,), (n_validation,), (n_test,), long
        Indices into ``batch`` (all heliostats together).
    info : dict of heliostat id -> dict
        Sizes, ``dropped_no_time``, coverage of train/test and the mean train-to-test distance [rad].
    """
    out = {"train": [], "validation": [], "test": []}
    info = {}
    # the split is bookkeeping on the host: a table on the GPU is read once (its indices work there too)
    az_all, el_all, t_all = (x.detach().cpu().numpy() for x in (batch.sun_azimuth, batch.sun_elevation, batch.time))
    by_heliostat = batch.rows_by_heliostat()
    for h, hid in enumerate(batch.heliostat_ids):
        rows = by_heliostat[h].cpu().numpy()
        if len(rows) == 0:
            info[hid] = {"n_records": 0, "train": 0, "validation": 0, "test": 0, "dropped_no_time": 0}
            continue
        az, el, tt = az_all[rows], el_all[rows], t_all[rows]
        s = split_indices(kind, az, el, tt, n_train, n_val, n_test, seed=seed + h)
        for key in out:
            out[key].append(torch.as_tensor(rows[s[key]], dtype=torch.long))
        pts = sun_points(az, el)
        seen = np.concatenate([s["train"], s["validation"]])
        info[hid] = {"n_records": int(len(rows)), "train": int(len(s["train"])),
                     "validation": int(len(s["validation"])),
                     "test": int(len(s["test"])), "dropped_no_time": int(s["dropped_no_time"]),
                     "mean_train_test_distance_rad": mean_train_test_distance(pts[seen], pts[s["test"]]),
                     "coverage_train": coverage(az[seen], el[seen]),
                     "coverage_test": coverage(az[s["test"]], el[s["test"]])}
    cat = {k: (torch.cat(v) if v else torch.zeros(0, dtype=torch.long)) for k, v in out.items()}
    return cat["train"], cat["validation"], cat["test"], info
