"""Splits and sun-position coverage: sizes, disjointness, ordering, isolation, hand-computed coverage."""
import numpy as np
import pytest

from heliotwin.calibrate.protocol.splits import (
    SPLIT_TYPES,
    coverage,
    knn_mean_distance,
    mean_train_test_distance,
    region_cover,
    split_indices,
)
from heliotwin.errors import HeliotwinError


def sky(n=60, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.5, 1.5, n), rng.uniform(0.1, 1.1, n), 1.6e9 + np.sort(rng.uniform(0, 3e7, n))


def test_coverage_hand_example():
    az, el = np.array([0.0, 0.1, 0.3]), np.zeros(3)
    c = coverage(az, el)
    nn = np.array([0.1, 0.1, 0.2])
    assert c["nn_mean_rad"] == pytest.approx(nn.mean())
    assert c["nn_var_rad2"] == pytest.approx(nn.var())
    assert mean_train_test_distance(np.array([[0.0, 0.0]]), np.array([[0.3, 0.4], [0.0, 0.1]])) == pytest.approx(0.3)
    assert len(region_cover(np.array([[0.0, 0.0], [0.2, 0.0], [1.0, 0.0]]), 0.25)) == 2


@pytest.mark.parametrize("kind", SPLIT_TYPES)
def test_sizes_and_disjointness(kind):
    az, el, t = sky()
    s = split_indices(kind, az, el, t, 20, 4, 15, seed=1)
    tr, va, te = map(set, (s["train"], s["validation"], s["test"]))
    assert len(te) == 15 and len(va) == 4 and len(tr) == 16
    assert not (tr & va or tr & te or va & te)
    assert len(tr | va | te | set(s["unused"])) == 60


def test_chrono_orders_and_drops_missing_times():
    az, el, t = sky()
    t = t.copy()
    t[[3, 7]] = np.nan
    s = split_indices("chrono", az, el, t, 10, 2, 30)
    assert s["dropped_no_time"] == 2
    assert 3 not in s["train"] and 7 not in s["test"]
    seen = np.concatenate([s["train"], s["validation"]])
    assert t[seen].max() < t[s["test"]].min()
    # train = the earliest N: nothing unused lies before the last seen record
    assert t[s["validation"]].min() > t[s["train"]].max()  # validation = latest of the pool
    assert len(s["train"]) + len(s["validation"]) == 10
    assert set(np.argsort(np.where(np.isnan(t), np.inf, t))[:10]) == set(seen)


def test_isolation_picks_isolated_points():
    rng = np.random.default_rng(3)
    az = np.concatenate([rng.normal(0, 0.05, 40), [1.4, -1.4, 1.3]])
    el = np.concatenate([rng.normal(0.5, 0.05, 40), [1.0, 0.2, 0.15]])
    s = split_indices("isolation", az, el, np.zeros(43), 30, 0, 3)
    assert set(s["test"]) == {40, 41, 42}
    k = knn_mean_distance(np.stack([az, el], -1), 3)
    assert k[40:].min() > k[:40].max()


def test_azimuth_and_high_variance_follow_paint_description():
    az, el, t = sky()
    s = split_indices("azimuth", az, el, t, 20, 0, 10)
    assert az[s["train"]].max() < az[s["test"]].min()
    s = split_indices("high_variance", az, el, t, 20, 0, 10)
    k = knn_mean_distance(np.stack([az, el], -1), 3)
    assert k[s["test"]].min() >= k[s["train"]].max()


def test_bad_sizes_raise_one_line_error():
    az, el, t = sky(10)
    with pytest.raises(HeliotwinError):
        split_indices("chrono", az, el, t, 5, 5, 3)
    with pytest.raises(HeliotwinError):
        split_indices("nonsense", az, el, t, 5, 1, 3)


def test_random_split_is_seeded_and_spreads_the_test_set_over_the_sky():
    az, el, t = sky(80)
    a = split_indices("random", az, el, t, 30, 6, 20, seed=3)
    assert np.array_equal(a["test"], split_indices("random", az, el, t, 30, 6, 20, seed=3)["test"])
    assert not np.array_equal(a["test"], split_indices("random", az, el, t, 30, 6, 20, seed=4)["test"])
    # unlike isolation, the test records are no more isolated than the rest (interpolation protocol)
    iso = split_indices("isolation", az, el, t, 30, 6, 20, seed=3)
    d = knn_mean_distance(np.stack([az, el], -1), 3)
    assert d[a["test"]].mean() < d[iso["test"]].mean()
    # and not the latest ones either (chrono)
    assert np.median(a["test"]) < np.median(split_indices("chrono", az, el, t, 30, 6, 20)["test"])
