"""The reconstruct workflow's settings: one settings object, the learner a choice inside it."""
from __future__ import annotations

import pytest

from heliotwin.errors import HeliotwinError
from heliotwin.surfaces.generalise import GeneraliseSettings
from heliotwin.surfaces.training import TrainSettings
from heliotwin.workflows.reconstruct import ReconstructionSettings


def test_each_method_gets_its_learner_settings_from_the_one_settings_object():
    g = ReconstructionSettings().learner()
    assert isinstance(g, GeneraliseSettings) and g == GeneraliseSettings()  # the defaults are the learner's
    small = ReconstructionSettings(steps=4, control_points="4x4", degree=2, slope_error_mrad=1.5).learner()
    assert (small.steps, small.eval_every, small.control_points, small.degree) == (4, 2, (4, 4), (2, 2))
    assert small.slope_grid == (1.5e-3,)
    legacy = ReconstructionSettings(method="legacy", integrator="mc", loss="l1").learner()
    assert isinstance(legacy, TrainSettings)
    assert (legacy.steps, legacy.loss, legacy.integrator) == (200, "l1", "mc")
    assert ReconstructionSettings(method="legacy").learner().loss == "kl"


@pytest.mark.parametrize("changes, needle", [
    (dict(loss="kl"), "--loss"), (dict(integrator="mc"), "--integrator"), (dict(background=0.1), "--background"),
    (dict(deflectometry="d.h5"), "--deflectometry"), (dict(start_from_deflectometry=True), "--start-from"),
    (dict(method="legacy", surface_prior_from=("a.h5",)), "--surface-prior-from"),
    (dict(method="legacy", start_from_deflectometry=True), "needs --deflectometry"),
    (dict(method="nope"), "method must be"),
])
def test_an_option_the_chosen_learner_does_not_take_is_one_line(changes, needle):
    with pytest.raises(HeliotwinError, match=needle) as exc:
        ReconstructionSettings(**changes).check()
    assert "\n" not in str(exc.value)


def test_the_checkpoint_fingerprint_follows_every_fit_setting_but_not_the_evaluation():
    base = ReconstructionSettings(method="legacy")
    assert base.fingerprint() == ReconstructionSettings(method="legacy", evaluate_mc=False).fingerprint()
    assert base.fingerprint() != ReconstructionSettings(method="legacy", steps=13).fingerprint()
    assert ReconstructionSettings().fingerprint() != ReconstructionSettings(control_points="5x5").fingerprint()
