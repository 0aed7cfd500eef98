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


def test_interval_rule_at_least_takes_the_narrowest_interval_reaching_the_target():
    """Records whose errors an interval must cover: the ``at_least`` rule never picks a drift whose coverage
    falls short of 0.9 when one reaches it, and no larger drift than needed."""
    import torch

    g = torch.Generator().manual_seed(1)
    r = 400
    normal = torch.nn.functional.normalize(torch.randn(r, 3, generator=g, dtype=torch.float64), dim=-1)
    inputs = [{"jacobian": torch.zeros(r, 3, 8, dtype=torch.float64), "normal": normal,
               "covariance": torch.eye(8, dtype=torch.float64).expand(r, 8, 8) * 1e-12,
               "walk": None, "noise": torch.full((r,), 2e-4, dtype=torch.float64),
               # errors of a 1 mrad offset the training records could not show
               "error": 1e-3 * torch.randn(r, generator=g, dtype=torch.float64).abs() * 1.5}]
    drift, _, cov = selection.choose_interval(inputs, samples=1000, rule="at_least")
    assert cov[(drift, 1.0)] >= 0.9
    smaller = [d for d in selection.DRIFT_GRID if d < drift]
    assert all(cov[(d, 1.0)] < 0.9 for d in smaller)
    closest, _, _ = selection.choose_interval(inputs, samples=1000)
    assert closest <= drift
    with pytest.raises(ValueError):
        selection.choose_interval(inputs, rule="widest")
