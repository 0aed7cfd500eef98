"""``mlp``: per-heliostat networks from (sun, aim) to motor steps, with the rigid body as fallback."""
import torch
from helpers.calibrate import TRUE, jueliche_like, scenario_round_trip, simulate

from heliotwin.calibrate import metrics
from heliotwin.calibrate.methods.mlp import aim_mlp, fit_mlp_method
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.calibrate.scenario import aim, network_entry
from heliotwin.field import kinematics as K


def test_mlp_finetunes_and_falls_back_to_a_better_rigid_body(tmp_path):
    kin = jueliche_like(1)
    true = apply_deviations(kin, torch.tensor([[TRUE[k] for k in STONE8]], dtype=torch.float64), STONE8)
    b = simulate(true, 40, 3, noise=5e-4)
    tr, va, te = b.subset(torch.arange(26)), b.subset(torch.arange(26, 32)), b.subset(torch.arange(32, 40))
    model = fit_mlp_method(kin, tr, va, pretrain_steps=200, finetune_steps=50, every="12h",
                           rigid_options={"iterations": 5})
    info = model.extras["per_heliostat"]["S0"]
    # fine-tuning on the real records improves the pretrained network on validation ...
    assert info["validation_after_finetuning_mrad"] < info["validation_after_pretraining_mrad"]
    # ... but 26 records of an exact rigid body (0.5 mrad noise) are not beaten: the rigid body is used
    assert info["rigid_validation_mrad"] < 1.0 < info["validation_after_finetuning_mrad"]
    assert info["uses_network"] is False and not bool(model.extras["use_net"][0])
    assert torch.equal(model.pointing_error(te), metrics.pointing_error(model.kinematics, te))  # the rigid body
    assert float(model.pointing_error(te).mean()) < 1.5e-3
    # the stored network says so too: aiming uses the rigid body's inverse kinematics
    entry = model.extras["networks"]["S0"]
    steps = aim_mlp(entry, model.kinematics, te.sun[:1], te.spot[:1])
    assert torch.allclose(steps, K.inverse(model.kinematics, te.spot[:1], te.sun[:1], strict=False)[0])
    # Through the scenario file: the plant holds the rigid body, the stored network says "not used".
    sc = scenario_round_trip(tmp_path, kin, model)
    assert torch.equal(sc.plant.field.kinematics.joint_tilt, model.kinematics.joint_tilt)
    assert network_entry(sc.learned, "S0")["config"]["use_net"] is False
    ans = aim(sc, "S0", float(te.sun_azimuth[0]), float(te.sun_elevation[0]), te.spot[0].tolist())
    assert ans["method"] == "mlp" and torch.allclose(torch.tensor([ans["motor_steps"]], dtype=torch.float64), steps)
