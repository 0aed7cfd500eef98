"""The reconstruct workflow's settings: one settings object, one learner."""
from __future__ import annotations

import dataclasses

import pytest

from heliotwin.errors import HeliotwinError
from heliotwin.surfaces.fit import SurfaceSettings
from heliotwin.surfaces.generalise import CV_BATCH_IMAGES, CV_FOLDS, CV_OPTICS_IMAGES
from heliotwin.workflows.reconstruct import ReconstructionSettings


def test_the_learner_settings_come_from_the_one_settings_object():
    g = ReconstructionSettings().learner()
    # the defaults are the learner's; every image trains: K-fold cross-validation over mini-batches
    assert isinstance(g, SurfaceSettings) and g == SurfaceSettings(folds=CV_FOLDS, batch_images=CV_BATCH_IMAGES,
                                                                   optics_images=CV_OPTICS_IMAGES)
    assert ReconstructionSettings(train_latest=3).learner() == SurfaceSettings()  # a study: leave-one-out, full batch
    assert ReconstructionSettings(train_first=3).learner() == SurfaceSettings()
    small = ReconstructionSettings(steps=4, control_points="4x4", degree=2, slope_error_mrad=1.5).learner()
    assert (small.steps, small.eval_every, small.control_points, small.degree) == (4, 2, (4, 4), (2, 2))
    assert small.slope_grid == (1.5e-3,)
    assert not {"method", "loss", "integrator", "background"} & {f.name for f in dataclasses.fields(
        ReconstructionSettings)}


def test_inconsistent_options_and_unknown_learner_settings_are_one_line():
    with pytest.raises(HeliotwinError, match="not --train-records and --train-first") as exc:
        ReconstructionSettings(train_records=(1, 2), train_first=3).check()
    assert "\n" not in str(exc.value)
    with pytest.raises(HeliotwinError, match="not --train-first and --train-latest"):
        ReconstructionSettings(train_first=3, train_latest=3).check()
    with pytest.raises(HeliotwinError, match="unknown optimizer 'sgd'"):
        SurfaceSettings(optimizer="sgd")
    with pytest.raises(HeliotwinError, match="unknown image loss 'l3'"):
        SurfaceSettings(loss="l3")


def test_the_checkpoint_fingerprint_follows_every_fit_setting_but_not_the_device():
    base = ReconstructionSettings()
    assert base.fingerprint() == ReconstructionSettings(device="cpu").fingerprint()
    assert base.fingerprint() != ReconstructionSettings(steps=13).fingerprint()
    assert base.fingerprint() != ReconstructionSettings(control_points="5x5").fingerprint()
