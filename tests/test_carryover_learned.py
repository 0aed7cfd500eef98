"""Settings learned once per plant (``--learn-settings``) and reused by routine runs without recomputation."""
import pytest

from heliotwin.calibrate.protocol import selection
from heliotwin.calibrate.protocol.config import RunConfig, validate_config
from heliotwin.calibrate.protocol.pipeline import run_calibration

LEARN_ON = ["AK32", "BE36", "BF55", "BH60"]
NEW = ["BH58", "BF41"]  # never seen by the choice, its prior or its interval calibration
TWO = ({"prior": "run", "bags": 0}, {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 1.0, "bags": 0})


@pytest.mark.slow  # two CV candidates on the real folder (~1 min on 2 busy cores)
def test_settings_learned_once_are_reused_without_choosing_again(paint_dir, tmp_path, monkeypatch):
    from heliotwin.calibrate.scenario import KEY, save_calibration
    from heliotwin.io.paint import load_paint
    from heliotwin.io.scenario import load_scenario

    monkeypatch.setattr(selection, "CANDIDATES", TWO)
    ds = load_paint(paint_dir)
    learn = RunConfig(paint=str(paint_dir), heliostats=LEARN_ON, train=10, test=30, learn_settings=True,
                      prior_exclude=NEW)
    validate_config(learn)
    before = selection.CALLS["choose_for_run"]
    rep, model, _ = run_calibration(learn, ds)
    assert selection.CALLS["choose_for_run"] == before + 1
    choice = rep["settings_choice"]
    assert choice["learned_for_plant"] and not set(NEW) & set(choice["heliostats"])
    assert set(LEARN_ON) <= set(choice["heliostats"])  # learned on the plant's own heliostats, not excluded
    sc = tmp_path / "plant.h5"
    save_calibration(sc, ds.plant, model, focal_spot="HeliOS", settings_choice=choice)
    stored = load_scenario(sc).learned[KEY]
    assert "settings_choice" in stored and "prior" in stored

    routine = RunConfig(paint=str(paint_dir), heliostats=NEW, train=10, test=30, prior_from=str(sc),
                        settings="stored")
    rep2, _, _ = run_calibration(routine, ds)
    assert selection.CALLS["choose_for_run"] == before + 1  # reused: nothing chosen again
    used = rep2["settings_choice"]
    assert used["used"] and used["chosen"] == choice["chosen"]
    assert rep2["config"]["method_options"]["drift"] == pytest.approx(1e-3 * choice["drift_mrad"])
    # the interval calibration carried to heliostats it never saw: coverage measured on their test records
    assert all(rep2["heliostats"][h]["status"] == "ok" for h in NEW)
    cov = rep2["overall"]["interval_90_coverage"]
    assert cov is not None and 0.0 <= cov <= 1.0
