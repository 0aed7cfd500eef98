"""``images`` method: a rotation invisible to the centroid (mirror about its own normal) learned from images."""
import torch
from helpers.calibrate import TARGET as CENTROID_TARGET
from helpers.calibrate import TRUE, jueliche_like, simulate

from heliotwin import scene
from heliotwin.calibrate.methods.images import IMAGE_PARAMETERS, fit_images_method
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.field.facets import ideal_surfaces
from heliotwin.field.plant import Facets, SunSettings
from heliotwin.field.targets import PlanarTarget
from heliotwin.raytrace.gaussian import FootprintSettings, trace_gaussian

F64 = torch.float64
TARGET = PlanarTarget.from_center_normal("synthetic_target", [0.0, -3.24, 20.0], [0.0, 1.0, 0.0], 8.0, 8.0)
SUN = SunSettings(sigma=0.002, slope_error=0.0005)
RES, SAMPLES = (32, 32), (6, 6)


def _long_heliostat():
    """Four facets in a row (6 m x 0.5 m): an elongated spot whose orientation shows the rotation."""
    n = 4
    tr = torch.tensor([[[-2.25 + 1.5 * i, 0.0, 0.0] for i in range(n)]], dtype=F64)
    ce = torch.tensor([0.75, 0.0, 0.0], dtype=F64).expand(1, n, 3).clone()
    cn = torch.tensor([0.0, 0.25, 0.0], dtype=F64).expand(1, n, 3).clone()
    kin = jueliche_like(1).replace(position=torch.tensor([[-3.0, 25.0, 1.5]], dtype=F64))
    return kin, ideal_surfaces(Facets(tr, ce, cn))


def test_images_learn_rotation_about_the_mirror_normal():
    kin, srf = _long_heliostat()
    names = tuple(IMAGE_PARAMETERS)
    assert names[-1] == "concentrator_tilt_n" and names[:8] == STONE8
    truth = torch.tensor([[*TRUE.values(), 0.03]], dtype=F64)
    kin_true = apply_deviations(kin, truth, names)
    batch = simulate(kin_true, 10, 0, target=TARGET)
    # the tilt does not move the mirror normal: centroids cannot see it
    n0 = apply_deviations(kin, truth[:, :8], STONE8)
    from heliotwin.calibrate import metrics

    assert float(metrics.pointing_error(n0, batch).max()) < 1e-9
    pw, nw, ar, _, _ = scene.world_surface(kin_true, srf, batch.heliostat_index, batch.motor_steps, samples=SAMPLES)
    flux = trace_gaussian(pw, nw, ar, batch.sun.float(), TARGET, resolution=RES, sun=SUN,
                          footprint=FootprintSettings(mode="convolve"))
    images = {int(batch.record_id[i]): flux.bitmap[i] for i in range(len(batch) - 2)}  # 2 records: centroid only
    model = fit_images_method(kin, batch, None, images=images, surfaces=srf, targets={TARGET.name: TARGET}, sun=SUN,
                              field_prior=False, iterations=8, resolution=RES, samples=SAMPLES)
    est = dict(zip(model.names, model.delta[0].tolist()))
    assert abs(est["concentrator_tilt_n"] - 0.03) < 3e-3
    s = model.extras["summary"]
    assert s["image_records_train"] == 8
    assert s["image_terms_after"]["pixel"] < 0.3 * s["image_terms_before"]["pixel"]
    assert float(model.pointing_error(batch).mean()) < 5e-4


def test_images_method_needs_surfaces_and_skips_broken_images(tmp_path):
    import pytest

    from heliotwin.errors import HeliotwinError

    kin, srf = _long_heliostat()
    batch = simulate(kin, 6, 1)
    with pytest.raises(HeliotwinError):
        fit_images_method(kin, batch, None, images={})
    bad = tmp_path / "broken-flux.png"
    bad.write_bytes(b"not a png")
    model = fit_images_method(kin, batch, None, images={int(batch.record_id[0]): str(bad)}, surfaces=srf,
                              targets={CENTROID_TARGET.name: CENTROID_TARGET}, sun=SUN, field_prior=False, iterations=2,
                              resolution=RES, samples=SAMPLES)
    assert model.extras["summary"]["image_records_train"] == 0
    assert int(batch.record_id[0]) in model.extras["summary"]["skipped_images"]
    assert torch.isfinite(model.delta).all()


def test_images_alone_recover_a_kinematic_error_through_camera_effects():
    """Images only (camera centroids garbage): the pointing error at new suns falls well below nominal's.

    The images are rendered from the true kinematics and then saturated, noised and background-cut as a
    camera does (:func:`heliotwin.simulate.images.camera`); the records' camera centroids are replaced by
    spots 2 m off, so any leak of them into the fit would show.
    """
    import numpy as np

    from heliotwin.calibrate.methods.images import image_centroid_records
    from heliotwin.simulate.images import camera

    kin, srf = _long_heliostat()
    truth = torch.tensor([list(TRUE.values())], dtype=F64)
    kin_true = apply_deviations(kin, truth, STONE8)
    batch = simulate(kin_true, 12, 3, target=TARGET)
    train, test = batch.subset(list(range(8))), batch.subset(list(range(8, 12)))
    pw, nw, ar, _, _ = scene.world_surface(kin_true, srf, train.heliostat_index, train.motor_steps, samples=(10, 10))
    flux = trace_gaussian(pw, nw, ar, train.sun.float(), TARGET, resolution=(64, 64), sun=SUN,
                          footprint=FootprintSettings(mode="window"))
    shot = camera(flux.bitmap.double(), np.random.default_rng(0))
    images = {int(r): shot[i] for i, r in enumerate(train.record_id.tolist())}
    train.spot = train.spot + 2.0 * TARGET.right  # wrong camera centroids: must not be used
    seen = image_centroid_records(train, images, {TARGET.name: TARGET}, RES)
    assert seen.spot_other is None and float((seen.spot - batch.spot[:8]).norm(dim=-1).max()) < 0.3
    model = fit_images_method(kin, train, None, images=images, surfaces=srf, targets={TARGET.name: TARGET}, sun=SUN,
                              field_prior=False, centroids=False, iterations=6, resolution=RES, samples=SAMPLES)
    from heliotwin.calibrate import metrics

    nominal = float(metrics.pointing_error(kin, test).median())
    learned = float(model.pointing_error(test).median())
    assert nominal > 5e-3 and learned < 0.02 * nominal


def test_images_without_validation_keep_their_best_training_state_on_aa39(paint_dir):
    """Real AA39, its 7 earliest image records (one of them ~60 mrad off every model), no validation records:
    the fit keeps each heliostat's lowest training loss, so a step that made it worse (a bounds or validity
    restore after an L-BFGS step) is not returned. Before, that step was the result: 43 mrad on every record."""
    from heliotwin.calibrate.methods import get_method
    from heliotwin.io.paint import load_paint

    ds = load_paint(paint_dir, heliostats=["AA39"])
    t, plant = ds.records, ds.plant
    order = sorted(range(len(t)), key=lambda i: int(t.record_id[i]))  # PAINT ids ascend with time
    tr = sorted([i for i in order if t.flux_png[i]][:7])
    train, test = t.subset(tr), t.subset([i for i in order if i not in tr])
    images = {int(t.record_id[i]): t.flux_png[i] for i in tr}
    model = fit_images_method(plant.field.kinematics, train, None, images=images, surfaces=plant.field.surfaces,
                              targets=plant.targets, sun=plant.sun)
    lm = get_method("lm")(plant.field.kinematics, train, None)
    assert float(model.pointing_error(train).median()) <= float(lm.pointing_error(train).median())
    from heliotwin.calibrate import metrics

    assert float(model.pointing_error(test).median()) < float(metrics.pointing_error(plant.field.kinematics,
                                                                                        test).median())
