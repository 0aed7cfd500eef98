"""Aim points that hold the peak limit with a stated probability under the pointing posterior (issue 31, item 4):
the robust aim points exceed the limit in at most about ``1 - confidence`` of independent Monte-Carlo draws of
the plant, the deterministic ones in clearly more; the draws reproduce the exact model's aim-point displacement;
a plant without a posterior is refused in one line."""
import pandas as pd
import pytest
import torch
from helpers.cli import run_cli
from helpers.field import learned_posterior

from heliotwin.io.scenario import save_scenario
from heliotwin.optimise import robust as R
from heliotwin.optimise.aimpoints import calibrate_images, optimise_aimpoints
from heliotwin.optimise.testbed import generated_plant
from heliotwin.raytrace.field import tracking_normals
from heliotwin.sun import direction_from_time

TIME = "2024-06-21T11:00:00Z"


def _case(sd_mrad=3.0):
    plant, atm = generated_plant("radial", 40, "cylinder", tower=30.0)
    s = plant.site
    sun = direction_from_time(pd.DatetimeIndex([pd.Timestamp(TIME)]), s.latitude_deg, s.longitude_deg,
                              s.altitude_m)[0]
    return plant, atm, sun, learned_posterior(plant, sd_mrad)


@pytest.fixture(scope="module")
def case():
    plant, atm, sun, learned = _case()
    model, eq = calibrate_images(plant, sun, atm, (20, 48))
    limit = 0.8 * float(eq.flux.max())
    det = optimise_aimpoints(plant, sun, limit, atmosphere=atm, equator=eq, model=model)
    rob, rep = R.robust_aimpoints(plant, sun, limit, 0.9, learned, atmosphere=atm, equator=eq, model=model,
                                  deterministic=det, draws=200, seed=0)
    return plant, atm, sun, learned, model, limit, det, rob, rep


def test_robust_aim_points_hold_the_limit_with_the_asked_probability(case):
    plant, atm, sun, learned, model, limit, det, rob, rep = case
    assert rep["robust"]["exceedance_probability"] <= rep["decision_probability"] < 0.1
    # met only when the exact (Clopper-Pearson) bound of the draws' share is below 1 - confidence
    assert rep["met"] == (rep["exceedance_upper_95"] <= 0.1) and rep["exceedance_upper_95"] < 0.11
    assert rob.peak_flux_w_m2 <= limit and det.peak_flux_w_m2 <= limit  # both hold it undisturbed
    # independent draws (another seed, twice as many): robust near 1 - confidence, deterministic clearly above
    post = R.pointing_posterior(plant, learned, sun, det.aim)
    dn = R.draw_normal_errors(post, 400, torch.Generator().manual_seed(7))
    p_det = R.exceedance(plant, sun, det, limit, dn, atmosphere=atm, model=model)["probability"]
    p_rob = R.exceedance(plant, sun, rob, limit, dn, atmosphere=atm, model=model)["probability"]
    assert p_rob <= 0.1 + 0.05  # 0.05: ~3 binomial standard errors at 400 draws
    assert p_det >= p_rob + 0.03
    assert 0.0 <= rep["power_cost"] < 0.02  # a spread of the peak, not a field on standby


def test_draws_turn_the_normal_by_the_posterior_and_keep_the_slant_range(case):
    plant, _, sun, learned, _, _, det, _, _ = case
    post = R.pointing_posterior(plant, learned, sun, det.aim)
    assert post.calibrated == len(plant.field.ids)
    dn = R.draw_normal_errors(post, 2000, torch.Generator().manual_seed(0))
    assert float((dn * post.normal).sum(-1).abs().max()) < 1e-12  # in the mirror plane
    # per in-plane axis: the offsets' 3 mrad (two axes of the actuators' plane, ~orthogonal) and the 0.2 mrad noise
    sd = dn.pow(2).sum(-1).mean(0).div(2).sqrt()
    assert torch.allclose(sd, post.sd_mrad() * 1e-3, rtol=0.1)
    pos = plant.field.kinematics.position.double()
    moved = R.perturbed_aim(plant, sun, det.aim, dn[:3])
    n = tracking_normals(pos, moved, sun.double())
    target = torch.nn.functional.normalize(post.normal + dn[:3], dim=-1)
    assert torch.allclose(n, target, atol=1e-12)
    assert torch.allclose(torch.linalg.vector_norm(moved - pos, dim=-1),
                          torch.linalg.vector_norm(det.aim.double() - pos, dim=-1))


def test_spot_jacobian_matches_the_displaced_ray_on_the_receiver(case):
    """The linear map of a normal error onto the receiver map against the exact hit of the turned ray."""
    plant, _, sun, _, _, _, det, _, _ = case
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.double()
    aim = det.aim.double()
    normal = tracking_normals(pos, aim, sun.double())
    e = torch.nn.functional.normalize(torch.linalg.cross(normal, torch.tensor([0.0, 0.0, 1.0]).double()
                                                         .expand_as(normal)), dim=-1)
    dn = 1e-4 * e
    moved = R.perturbed_aim(plant, sun, aim, dn)
    # walk along the new ray onto the cylinder's surface: solve |p + t r - axis|_horizontal = radius
    r = torch.nn.functional.normalize(moved - pos, dim=-1)
    c = rec.axis_point.double()
    d0 = pos - c
    a_ = (r[:, :2] ** 2).sum(-1)
    b_ = 2 * (d0[:, :2] * r[:, :2]).sum(-1)
    c_ = (d0[:, :2] ** 2).sum(-1) - float(rec.radius) ** 2
    t = (-b_ - (b_ ** 2 - 4 * a_ * c_).sqrt()) / (2 * a_)
    hit = pos + t[:, None] * r
    got = rec.to_local(hit) - rec.to_local(aim)
    want = torch.einsum("hkc,hc->hk", R.spot_jacobian(plant, sun, aim), dn)
    assert torch.allclose(got, want, atol=2e-2 * float(want.abs().max()))  # second order: the curved surface


def test_confidence_without_a_posterior_is_one_line(tmp_path, capsys):
    plant, atm, _, _ = _case()
    path = tmp_path / "plant.h5"
    save_scenario(plant, path)
    code, _, err = run_cli(capsys, "aimpoints", "--scenario", path, "--time", TIME, "--peak-limit", 30000,
                           "--confidence", 0.95, "-o", tmp_path / "a.h5", "--json", tmp_path / "a.json")
    err = err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "posterior" in err[0] and "--confidence" in err[0]
    assert not (tmp_path / "a.h5").exists()


def test_a_confidence_the_draws_cannot_show_is_not_met(case):
    """0 of 50 draws over the limit bounds the probability only below 5.8 % (exact, 95 %): a confidence of
    0.9999999 is not shown, whatever the draws' share (issue 41 item 8)."""
    assert R.exceedance_bound(0, 50) == pytest.approx(1 - 0.05 ** (1 / 50), rel=1e-9)
    assert R.exceedance_bound(13, 200) == pytest.approx(0.1014, abs=2e-4)
    plant, atm, sun, learned, model, limit, det, _, _ = case
    _, rep = R.robust_aimpoints(plant, sun, limit, 0.9999999, learned, atmosphere=atm, model=model,
                                deterministic=det, draws=50, seed=0, tries=1)
    assert not rep["met"] and rep["exceedance_upper_95"] > 0.05 and rep["draws_needed"] > 10 ** 7
    assert "draws are needed" in rep["met_reason"]


def test_the_pointing_spread_grows_by_the_stored_walk_to_the_aim_time(case):
    """--time 79 years after the records: the offsets' variance grows by q x days (issue 41 item 8)."""

    names = ["initial_angle_1", "initial_angle_2", "x"]
    cal = {"drift": {"names": names[:2], "time": torch.tensor([1.6e9, 1.7e9], dtype=torch.float64),
                     "process_noise_rad2_per_day": torch.tensor([1e-9], dtype=torch.float64)}}
    cov = torch.eye(3, dtype=torch.float64).expand(2, 3, 3) * 1e-8
    later = 1.6e9 + 79 * 365.25 * 86400
    grown = R.walked_covariance(cal, cov, names, later)
    days = (later - torch.tensor([1.6e9, 1.7e9], dtype=torch.float64)) / 86400
    torch.testing.assert_close(grown[:, 0, 0] - cov[:, 0, 0], 1e-9 * days)
    torch.testing.assert_close(grown[:, 2, 2], cov[:, 2, 2])  # only the walking offsets
    torch.testing.assert_close(R.walked_covariance(cal, cov, names, 1.0e9), cov)  # never shrinks before
    torch.testing.assert_close(R.walked_covariance(cal, cov, names, None), cov)
    plant, atm, sun, learned, model, limit, det, _, _ = case
    cal_l = learned["calibration"]
    if (cal_l.get("drift") or {}).get("time") is not None:
        now = R.pointing_posterior(plant, learned, sun, det.aim).sd_mrad()
        far = R.pointing_posterior(plant, learned, sun, det.aim, time_s=later).sd_mrad()
        assert float(far.median()) > float(now.median())
