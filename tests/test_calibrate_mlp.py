"""``mlp``: per-axis networks from (sun, aim) to motor steps, pretrained on the heliostat's rigid body."""
import math

import torch
from helpers.calibrate import TRUE, jueliche_like, scenario_round_trip, simulate

from heliotwin.calibrate import metrics
from heliotwin.calibrate.methods.lm import fit_lm_method
from heliotwin.calibrate.methods.mlp import aim_mlp, fit_mlp_method
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.calibrate.scenario import aim, network_entry
from heliotwin.field import kinematics as K

FAST = dict(pretrain_steps=300, polish_steps=100, finetune_steps=60, every="3h", field_prior=False)


def _true_kinematics():
    kin = jueliche_like(1)
    return kin, apply_deviations(kin, torch.tensor([[TRUE[k] for k in STONE8]], dtype=torch.float64), STONE8)


def test_pretrained_mlp_reproduces_its_rigid_body_and_falls_back_without_gain(tmp_path):
    kin, true = _true_kinematics()
    b = simulate(true, 40, 3, noise=5e-4)
    tr, va, te = b.subset(torch.arange(26)), b.subset(torch.arange(26, 32)), b.subset(torch.arange(32, 40))
    model = fit_mlp_method(kin, tr, va, **FAST)
    info = model.extras["per_heliostat"]["S0"]
    # Before fine-tuning the network is its rigid body (to first order in the step error of the metric).
    assert abs(info["validation_after_pretraining_mrad"] - info["rigid_validation_mrad"]) < 0.02
    assert model.extras["summary"]["pretraining_rms_increments"] < 10.0
    # A rigid truth with 0.5 mrad noise leaves nothing to learn: the rigid body is used.
    assert info["rigid_validation_mrad"] < 1.0
    assert info["uses_network"] is False and not bool(model.extras["use_net"][0])
    assert torch.equal(model.pointing_error(te), metrics.pointing_error(model.kinematics, te))
    assert float(model.pointing_error(te).mean()) < 1.0e-3
    # The stored network says so too: aiming uses the rigid body's inverse kinematics ...
    entry = model.extras["networks"]["S0"]
    steps = aim_mlp(entry, model.kinematics, te.sun[:1], te.spot[:1])
    assert torch.allclose(steps, K.inverse(model.kinematics, te.spot[:1], te.sun[:1], strict=False)[0])
    # ... and a stored network that is used reproduces the model's own step predictions.
    entry_on = {"config": dict(entry["config"], use_net=True), "state": entry["state"]}
    model.extras["use_net"][0] = True
    direct = model.predict_steps(te.subset(torch.arange(1)))
    assert torch.allclose(aim_mlp(entry_on, model.kinematics, te.sun[:1], te.spot[:1]), direct, atol=1e-6)
    model.extras["use_net"][0] = False
    # Through the scenario file: the plant holds the rigid body, the stored network says "not used".
    sc = scenario_round_trip(tmp_path, kin, model)
    assert torch.equal(sc.plant.field.kinematics.joint_tilt, model.kinematics.joint_tilt)
    assert network_entry(sc.learned, "S0")["config"]["use_net"] is False
    ans = aim(sc, "S0", float(te.sun_azimuth[0]), float(te.sun_elevation[0]), te.spot[0].tolist())
    assert ans["method"] == "mlp" and torch.allclose(torch.tensor([ans["motor_steps"]], dtype=torch.float64), steps)


def test_mlp_learns_a_non_rigid_step_error_that_lm_cannot():
    """A periodic gear error in the motor steps (~2 mrad) is outside every rigid body: the fine-tuned
    network learns it and is kept; on held-out records it beats lm on the same records."""
    kin, true = _true_kinematics()
    b = simulate(true, 150, 5, noise=2e-4)
    frac = (b.motor_steps - kin.min_steps) / (kin.max_steps - kin.min_steps)
    b.motor_steps = b.motor_steps + 120.0 * torch.sin(2 * math.pi * 1.5 * frac)
    tr, va, te = b.subset(torch.arange(90)), b.subset(torch.arange(90, 110)), b.subset(torch.arange(110, 150))
    model = fit_mlp_method(kin, tr, va, **dict(FAST, finetune_steps=300, finetune_lr=3e-3))
    info = model.extras["per_heliostat"]["S0"]
    assert info["uses_network"] is True, info
    lm = fit_lm_method(kin, tr, va, bags=0, field_prior=False)
    e_mlp, e_lm = float(model.pointing_error(te).mean()), float(lm.pointing_error(te).mean())
    assert e_mlp < 0.8 * e_lm, (e_mlp, e_lm)


def test_mlp_without_validation_records_keeps_its_rigid_body_exactly_as_lm():
    # The online split's first rounds have no validation records: nothing can show that the network helps,
    # so the rigid body (lm's fit on the same records) is used; an empty pose batch is not an error.
    kin, true = _true_kinematics()
    b = simulate(true, 30, 3, noise=5e-4)
    tr, va, te = b.subset(torch.arange(20)), b.subset(torch.arange(0)), b.subset(torch.arange(20, 30))
    assert K.inverse(kin, te.spot[:0], te.sun[:0], strict=False)[0].shape[0] == 0
    model = fit_mlp_method(kin, tr, va, **FAST)
    assert not bool(model.extras["use_net"][0])
    lm = fit_lm_method(kin, tr, va, field_prior=False)
    assert torch.allclose(model.pointing_error(te), lm.pointing_error(te), atol=1e-9)
