"""Hybrid features extrapolate sanely; the fallback needs a significant validation gain; fit-spot choice."""
import math

import torch
from helpers.calibrate import TRUE, jueliche_like, scenario_round_trip, simulate, with_weekly_times

from heliotwin.calibrate.inputs import MIN_SOURCE_PAIRS, fit_spots, source_offsets
from heliotwin.calibrate.methods.hybrid import SECONDS_PER_YEAR, aim_hybrid, features, fit_hybrid_method
from heliotwin.calibrate.methods.lm import fit_lm_method
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.calibrate.scenario import aim, network_entry
from heliotwin.field import kinematics as K


def _batch_with_times(n=24, seed=3):
    kin = jueliche_like(1)
    return kin, with_weekly_times(simulate(kin, n, seed, noise=1e-3))


def test_age_feature_is_clamped_to_the_training_range():
    kin, b = _batch_with_times()
    t0 = torch.tensor([float(b.time[0])], dtype=torch.float64)
    span = torch.tensor([float(b.time[9] - b.time[0])], dtype=torch.float64)
    x = features(b, kin, t0, span)
    age = x[:, 4]
    assert float(age[0]) == 0.0 and abs(float(age[9]) - 1.0) < 1e-12
    assert float(age.max()) == 1.0 and float(age.min()) == 0.0  # years later: still the last training state
    assert torch.isfinite(x).all() and float(x.abs().max()) <= 1.0 + 1e-12


def test_hybrid_falls_back_without_a_significant_gain():
    kin, b = _batch_with_times()
    tr, va = b.subset(torch.arange(20)), b.subset(torch.arange(20, 23))  # 3 validation records < MIN_VALIDATION
    model = fit_hybrid_method(kin, tr, va, steps=20, depth=2, field_prior=False)
    info = model.extras["per_heliostat"]["S0"]
    assert info["uses_network"] is False and "validation records" in info["fallback_reason"]
    assert float(model.pointing_error(b).mean()) < 5e-3


def test_fit_spots_prefers_utis_average_and_metric_source():
    kin, b = _batch_with_times(6)
    b.source = ["HeliOS"] * 6
    other = b.spot + torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64)
    other[0] = float("nan")
    b.spot_other = other
    u = fit_spots(b, "utis")
    assert torch.equal(u.spot[0], b.spot[0]) and torch.allclose(u.spot[1:], other[1:])
    a = fit_spots(b, "average")
    assert torch.allclose(a.spot[1:], b.spot[1:] + torch.tensor([0.0, 0.0, 0.05], dtype=torch.float64))
    assert fit_spots(b, "HeliOS").spot.equal(b.spot) and fit_spots(b, None) is b
    assert not math.isnan(float(u.spot.sum()))
    assert SECONDS_PER_YEAR > 0


def test_harmonised_moves_utis_into_the_metric_frame_per_target():
    """UTIS = HeliOS - a per-target offset + noise: ``harmonised`` recovers the HeliOS frame from the batch's
    own pairs, keeps HeliOS where a record has no UTIS or its target too few pairs, and lowers the scatter."""
    kin, b = _batch_with_times(24)
    g = torch.Generator().manual_seed(5)
    truth = b.spot.clone()
    offsets = {"lower": torch.tensor([0.0, 0.0, 0.08], dtype=torch.float64),
               "upper": torch.tensor([0.03, 0.0, -0.02], dtype=torch.float64),
               "rare": torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)}
    b.target = ["lower"] * 12 + ["upper"] * 10 + ["rare"] * 2  # "rare": fewer pairs than MIN_SOURCE_PAIRS
    assert 2 < MIN_SOURCE_PAIRS
    b.source = ["HeliOS"] * 24
    b.spot = truth + 0.02 * torch.randn(24, 3, generator=g, dtype=torch.float64)  # HeliOS: noisier
    shift = torch.stack([offsets[t] for t in b.target])
    b.spot_other = truth - shift + 0.002 * torch.randn(24, 3, generator=g, dtype=torch.float64)
    b.spot_other[0] = float("nan")  # a record without UTIS keeps its HeliOS centroid
    b.focal_spots = torch.stack([b.spot, b.spot_other], 1)  # (HeliOS, UTIS), as the PAINT reader stores them
    est, known = source_offsets(b)
    assert known.tolist() == [False] + [True] * 21 + [False, False]
    assert torch.allclose(est[known], shift[known], atol=0.015)  # the median of 11/10 noisy pairs
    h = fit_spots(b, "harmonised")
    assert torch.equal(h.spot[0], b.spot[0]) and torch.equal(h.spot[22:], b.spot[22:])
    err_h = (h.spot[1:22] - truth[1:22]).norm(dim=-1).mean()
    err_raw = (b.spot[1:22] - truth[1:22]).norm(dim=-1).mean()
    err_utis = (fit_spots(b, "UTIS").spot[1:22] - truth[1:22]).norm(dim=-1).mean()
    assert err_h < 0.5 * err_raw and err_h < 0.5 * err_utis  # less scatter than HeliOS, no offset unlike UTIS


def _drifting(n, seed, drift):
    """One heliostat whose axis-1 encoder offset drifts by ``drift`` [rad] over its ``n`` weekly records."""
    kin = jueliche_like(1)
    d = torch.tensor([TRUE[k] for k in STONE8], dtype=torch.float64).expand(n, 8).clone()
    d[:, 0] += drift * torch.linspace(0, 1, n, dtype=torch.float64)
    b = simulate(apply_deviations(kin.index(torch.zeros(n, dtype=torch.long)), d, STONE8), 1, seed)
    b.heliostat_index = torch.zeros(n, dtype=torch.long)
    b.heliostat_ids = ["S0"]
    return kin, with_weekly_times(b)


def test_hybrid_network_follows_a_drift_the_rigid_body_cannot(tmp_path):
    kin, b = _drifting(40, 1, 6e-3)
    tr, va, te = b.subset(torch.arange(30)), b.subset(torch.arange(30, 36)), b.subset(torch.arange(36, 40))
    model = fit_hybrid_method(kin, tr, va, field_prior=False)
    info = model.extras["per_heliostat"]["S0"]
    assert info["uses_network"] is True and info["fallback_reason"] is None
    assert info["hybrid_validation_mrad"] < 0.5 * info["rigid_validation_mrad"]
    # later records (age clamped to the last training state): still better than the static rigid body
    rigid = fit_lm_method(kin, tr, va, field_prior=False, bags=0)
    assert float(model.pointing_error(te).mean()) < 0.6 * float(rigid.pointing_error(te).mean())
    # Through the scenario file: the network is stored bit for bit and aiming uses it.
    sc = scenario_round_trip(tmp_path, kin, model)
    entry = network_entry(sc.learned, "S0")
    stored = model.extras["networks"]["S0"]
    assert entry["config"]["kind"] == "hybrid" and entry["config"]["use_net"] is True
    assert all(torch.equal(entry["state"][k], v) for k, v in stored["state"].items())
    az, el = float(te.sun_azimuth[0]), float(te.sun_elevation[0])
    ans = aim(sc, "S0", az, el, te.spot[0].tolist())
    assert ans["method"] == "hybrid"
    expected = aim_hybrid(stored, model.kinematics, te.sun[:1], te.spot[:1]).reshape(2)
    assert torch.allclose(torch.tensor(ans["motor_steps"], dtype=torch.float64), expected, atol=1e-6)
    rigid_steps = K.inverse(model.kinematics, te.spot[:1], te.sun[:1], strict=False)[0].reshape(2)
    assert float((expected - rigid_steps).abs().max()) > 1.0  # the network moves the motors


def test_hybrid_learns_a_drift_that_lm_cannot():
    """A motor offset that drifts by ~150 increments (~3 mrad) over the training span is outside every static
    rigid body; the hybrid's age input lets its network follow it: kept on validation, better than lm on
    held-out records of the same span."""
    kin = jueliche_like(1)
    true = apply_deviations(kin, torch.tensor([[TRUE[k] for k in STONE8]], dtype=torch.float64), STONE8)
    b = with_weekly_times(simulate(true, 90, 11, noise=2e-4))
    age = torch.arange(90, dtype=torch.float64) / 89
    b.motor_steps = b.motor_steps + torch.stack([150.0 * age, -100.0 * age], -1)
    perm = torch.randperm(90, generator=torch.Generator().manual_seed(0))
    tr, va, te = (b.subset(perm[a:z].sort().values) for a, z in ((0, 50), (50, 65), (65, 90)))
    model = fit_hybrid_method(kin, tr, va, depth=4, hidden=4, steps=600, lr=1e-2, field_prior=False)
    assert model.extras["per_heliostat"]["S0"]["uses_network"] is True, model.extras["per_heliostat"]
    lm = fit_lm_method(kin, tr, va, bags=0, field_prior=False)
    e_h, e_lm = float(model.pointing_error(te).mean()), float(lm.pointing_error(te).mean())
    assert e_h < 0.8 * e_lm, (e_h, e_lm)
