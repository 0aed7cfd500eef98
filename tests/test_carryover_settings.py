"""``--settings cv``: a run's lm settings chosen by leave-heliostats-out CV on its ``--prior-from`` archive."""
import json

import pytest
from helpers.cli import assert_one_line_error, run_cli

from heliotwin.calibrate.protocol import selection
from heliotwin.calibrate.protocol.config import RunConfig, settings_mode, validate_config
from heliotwin.calibrate.protocol.pipeline import run_calibration
from heliotwin.errors import HeliotwinError

#: Two cheap candidates (no bagging) that differ in what matters: the run's own field prior or a plant prior.
RUN = "AK32,BE36,BF55,BH60"  # >= 4: the run's own field prior is a candidate too (priors.MIN_HELIOSTATS)
TWO = ({"prior": "run", "bags": 0}, {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 1.0, "bags": 0})


def test_cv_settings_choose_on_other_heliostats_and_the_run_uses_the_choice(paint_dir, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(selection, "CANDIDATES", TWO)
    js = tmp_path / "r.json"
    code, out, err = run_cli(capsys, "calibrate", "--paint", paint_dir, "--heliostats", RUN, "--train", "10",
                             "--test", "30", "--prior-from", paint_dir, "--json", js, "--no-plots")
    assert code == 0, err
    rep = json.loads(js.read_text())
    ch = rep["settings_choice"]
    # no record of a calibrated heliostat decided anything: neither scored nor in a prior
    assert not set(RUN.split(",")) & set(ch["heliostats"]) and len(ch["heliostats"]) >= 4
    assert ch["excluded"] == RUN.split(",")
    assert set(ch["table"]) == {selection.label(c) for c in TWO}
    assert ch["chosen"] == min(ch["table"], key=ch["table"].get)  # the lowest CV median wins
    # the run ran with the chosen candidate and the interval drift chosen by CV coverage
    cfg = rep["config"]
    assert cfg["method_options"]["drift"] == pytest.approx(1e-3 * ch["drift_mrad"])
    assert cfg["prior"] == ch["candidate"]["prior"]
    coverages = list(ch["coverage"].values())
    assert min(abs(c - 0.9) for c in coverages) == pytest.approx(
        abs(ch["coverage"][f"{ch['drift_mrad']:g} mrad, walk x{ch['walk_scale']:g}"] - 0.9))
    if ch["candidate"]["prior"] == "plant":
        used = rep["overall"]["method_info"]["prior_heliostats"]
        assert not set(RUN.split(",")) & set(used)
    for hid in RUN.split(","):
        r = rep["heliostats"][hid]
        assert r["mean_test_mrad"] < 3.0 and r["mean_test_mrad"] < r["nominal_mean_test_mrad"] / 5, r
    assert 0.5 <= rep["overall"]["interval_90_coverage"] <= 1.0


def test_a_small_run_is_never_given_a_field_prior_it_cannot_have(paint_dir):
    """Fewer than 4 calibrated heliostats: the run's own field prior would fall back to the nominal prior, which
    CV never scored, so only plant-prior candidates are tried."""
    cfg = RunConfig(paint=str(paint_dir), prior_from=str(paint_dir), settings="cv", train=10, test=30)
    with pytest.raises(HeliotwinError, match="need 4 and none uses a plant prior"):
        selection.choose_for_run(cfg, ["AK32", "BE36"], runner=run_calibration, candidates=TWO[:1])


def test_settings_flag_resolution_and_errors(paint_dir, tmp_path, capsys):
    from heliotwin.cli import build_parser
    from heliotwin.cli.calibrate import _settings_mode

    parse = build_parser().parse_args
    base = ["calibrate", "--paint", str(paint_dir)]
    assert _settings_mode(parse(base + ["--prior-from", str(paint_dir)]), "lm") == "cv"
    assert _settings_mode(parse(base), "lm") == "given"  # no archive to choose on
    assert _settings_mode(parse(base + ["--prior-from", str(paint_dir), "--drift", "kalman"]), "lm") == "given"
    assert _settings_mode(parse(base + ["--prior-from", str(paint_dir), "--half-life-days", "20"]), "lm") == "given"
    assert _settings_mode(parse(base + ["--prior-from", str(tmp_path / "x.h5")]), "lm") == "given"  # no such file
    (tmp_path / "s.h5").write_bytes(b"")
    assert _settings_mode(parse(base + ["--prior-from", str(tmp_path / "s.h5")]), "lm") == "stored"  # a scenario
    with pytest.raises(HeliotwinError, match="--settings stored needs --prior-from a scenario"):
        validate_config(RunConfig(paint=str(paint_dir), settings="stored", prior_from=str(paint_dir)))
    with pytest.raises(HeliotwinError, match="applies lm settings"):
        validate_config(RunConfig(paint=str(paint_dir), settings="stored", method="gradient",
                                  prior_from=str(tmp_path / "s.h5")))
    assert _settings_mode(parse(base + ["--prior-from", str(paint_dir), "--settings", "given"]), "lm") == "given"
    assert settings_mode("auto", method="gradient", prior_from=str(paint_dir)) == "given"  # cv chooses lm settings
    assert settings_mode("cv", method="lm") == "cv"  # explicit: validate_config judges it
    with pytest.raises(HeliotwinError, match="needs --prior-from a PAINT folder"):
        validate_config(RunConfig(paint=str(paint_dir), settings="cv"))
    with pytest.raises(HeliotwinError, match="chooses lm settings"):
        validate_config(RunConfig(paint=str(paint_dir), settings="cv", method="gradient", prior_from=str(paint_dir)))
    code, out, err = run_cli(capsys, "calibrate", "--paint", paint_dir, "--settings", "cv", "--json",
                             tmp_path / "r.json")
    assert_one_line_error(code, err, "--settings cv", "PAINT folder")
    # an archive with too few heliostats outside the calibrated ones: one line, nothing written
    code, out, err = run_cli(capsys, "calibrate", "--paint", paint_dir, "--prior-from", paint_dir, "--min-records",
                             "300", "--json", tmp_path / "r.json")
    assert_one_line_error(code, err, "--settings cv needs 4 heliostats")
    assert not (tmp_path / "r.json").exists()


def test_centroid_source_and_loss_are_candidates_that_reach_the_fit(paint_dir):
    """The fit's centroid source and loss are chosen by CV like every other setting: each candidate has its own
    label (scores are keyed by it) and its settings reach the lm fit, which then lands elsewhere."""
    labels = [selection.label(c) for c in selection.CANDIDATES]
    assert len(set(labels)) == len(labels)
    tried = {(c.get("fit_focal_spot"), c.get("loss")) for c in selection.CANDIDATES}
    assert {("HeliOS", None), ("harmonised", None), (None, "linear"), (None, None)} <= tried
    base = RunConfig(paint=str(paint_dir), heliostats=["AK32", "BE36", "BF55", "BH60"], train=10, test=30)
    params = {}
    for cand in ({"prior": "run", "bags": 0}, {"prior": "run", "bags": 0, "fit_focal_spot": "HeliOS"},
                 {"prior": "run", "bags": 0, "fit_focal_spot": "harmonised"},
                 {"prior": "run", "bags": 0, "loss": "linear"}):
        cfg = selection.config_of(base, cand)
        assert all(cfg.method_options.get(k) == cand.get(k) for k in ("fit_focal_spot", "loss") if k in cand)
        rep, _, _ = run_calibration(cfg, None)
        params[selection.label(cand)] = rep["heliostats"]["BE36"]["parameters"]  # BE36 has UTIS and HeliOS
    ref = params["run/b0"]
    for lab in ("run/b0/fitHeliOS", "run/b0/fitharmonised", "run/b0/linear"):  # another fit (> 1 µrad)
        assert max(abs(params[lab][k] - ref[k]) for k in ref) > 1e-6, lab


def test_a_stored_choice_is_reused_only_where_it_is_honest(paint_dir, tmp_path, monkeypatch):
    """A ``--settings cv`` run stores its choice in the scenario; a later run with ``--prior-from`` that scenario
    uses it for heliostats the choice never saw, with the same protocol, and says why not otherwise."""
    from dataclasses import replace

    from heliotwin.calibrate.scenario import KEY, save_calibration
    from heliotwin.io.paint import load_paint
    from heliotwin.io.scenario import load_scenario

    plant_two = ({"prior": "plant", "covariance": "diag", "bags": 0},
                 {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 1.0, "bags": 0})
    monkeypatch.setattr(selection, "CANDIDATES", plant_two)
    ds = load_paint(paint_dir)
    new = ["BG62", "BH58"]  # held out of the first run's prior *and* of its choice
    first = RunConfig(paint=str(paint_dir), heliostats=RUN.split(","), train=10, test=30, prior_from=str(paint_dir),
                      settings="cv", prior_exclude=new)
    rep, model, _ = run_calibration(first, ds)
    choice = rep["settings_choice"]
    assert not set(new) & set(choice["heliostats"]) and choice["split"] == "chrono" and choice["train"] == 10
    sc = tmp_path / "a.h5"
    save_calibration(sc, ds.plant, model, focal_spot="HeliOS", settings_choice=choice)
    assert "settings_choice" in load_scenario(sc).learned[KEY]

    later = RunConfig(paint=str(paint_dir), heliostats=new, train=10, test=30, prior_from=str(sc), settings="stored")
    validate_config(later)
    rep2, _, _ = run_calibration(later, ds)
    used = rep2["settings_choice"]
    assert used["used"] and used["chosen"] == choice["chosen"]
    assert rep2["config"]["method_options"]["drift"] == pytest.approx(1e-3 * choice["drift_mrad"])
    assert rep2["config"]["prior"] == "plant" and rep2["config"]["prior_options"].get("covariance") == \
        choice["candidate"].get("covariance")
    assert all(rep2["heliostats"][h]["status"] == "ok" for h in new)

    # another protocol, a heliostat the choice scored, a choice of the run's own prior: the flags, with a reason
    cfg, rec = selection.stored_choice(replace(later, train=30), new)
    assert not rec["used"] and "train 10" in rec["reason"] and cfg.settings == "given" and not cfg.method_options
    scored = choice["heliostats"][0]
    _, rec = selection.stored_choice(later, [scored])
    assert not rec["used"] and scored in rec["reason"]
    choice_run = dict(choice, candidate={"prior": "run", "bags": 0})
    sc_run = tmp_path / "b.h5"
    save_calibration(sc_run, ds.plant, model, focal_spot="HeliOS", settings_choice=choice_run)
    _, rec = selection.stored_choice(replace(later, prior_from=str(sc_run)), new)
    assert not rec["used"] and "own field prior" in rec["reason"]
    # a scenario without a choice: the flags
    sc_none = tmp_path / "c.h5"
    save_calibration(sc_none, ds.plant, model, focal_spot="HeliOS")
    _, rec = selection.stored_choice(replace(later, prior_from=str(sc_none)), new)
    assert not rec["used"] and "no settings choice" in rec["reason"]
