"""Damaged learned state in a scenario file: every dataset of ``/learned/{calibration, assimilation, surfaces}``
set to NaN, truncated, reshaped, retyped, deleted or made a scalar is refused on load with one line naming the
file and the HDF5 object (exit 2) by every command that reads it -- never an internal error (exit 1) nor a
silent NaN result. The campaign over all damages and readers is ``benchmarks/fuzz_learned.py``.
"""
from __future__ import annotations

import json
import math

import pytest
from helpers.cli import assert_one_line_error, run_cli
from helpers.learned import DAMAGES, damage, learned_datasets, learned_scenario

from heliotwin.errors import InputFileError
from heliotwin.io.scenario import load_scenario

SUN = ("--sun-azimuth", "10", "--sun-elevation", "40")

#: Damages the readers accept by design: optional entries deleted, NaN where it means "not given", a [1]
#: value stored as a scalar (read back as [1]), a shorter list of training records.
ACCEPTED = {
    ("assimilation/version", "missing"), ("calibration/drift/model", "missing"),
    ("calibration/drift/offset", "missing"), ("calibration/drift/static_deviations", "missing"),
    ("calibration/drift/time", "nan"), ("calibration/focal_spot", "missing"), ("calibration/method", "missing"),
    ("calibration/nominal/max_angle", "nan"), ("calibration/nominal/min_angle", "nan"),
    ("calibration/posterior/drift_rad", "missing"), ("calibration/posterior/walk_scale", "missing"),
    ("surfaces/S1/train_records", "truncated"), ("surfaces/S1/train_records", "scalar"),
    ("calibration/process_noise_choice/validation_error_mrad", "nan"),  # NaN: no record left to validate on
}
ONE_VALUE = ("assimilation/version", "assimilation/updates", "assimilation/calibrations", "assimilation/threshold",
             "assimilation/kappa", "assimilation/false_alarm_rate", "calibration/posterior/drift_rad",
             "calibration/posterior/walk_scale", "calibration/drift/process_noise_rad2_per_day")


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return learned_scenario(tmp_path_factory.mktemp("learned") / "base.h5")


def _accepted(name: str, how: str) -> bool:
    key = name.removeprefix("learned/")
    return (key, how) in ACCEPTED or (how == "scalar" and key in ONE_VALUE)


def test_every_damaged_learned_dataset_is_refused_on_load_naming_it(base, tmp_path):
    """Each dataset once, the damages in turn (all 6 over the datasets; the campaign tries every pair): refused
    naming the object, or one of the damages the readers accept by design."""
    names = learned_datasets(base)
    assert {n.split("/")[1] for n in names} == {"calibration", "assimilation", "surfaces"} and len(names) > 50
    tried = 0
    for i, name in enumerate(names):
        for how in (DAMAGES[i % len(DAMAGES)],):
            if not damage(base, tmp_path / "d.h5", name, how):
                continue
            tried += 1
            try:
                load_scenario(tmp_path / "d.h5")
            except InputFileError as exc:
                text = str(exc)
                assert "\n" not in text and "d.h5" in text, text
                assert f"/{name.rsplit('/', 1)[0]}" in text, (name, how, text)
            else:
                assert _accepted(name, how), f"{name} {how}: accepted"
    assert tried > 40


@pytest.mark.parametrize("name, how", [("learned/calibration/deviations", "nan"),
                                       ("learned/calibration/posterior/covariance", "truncated"),
                                       ("learned/calibration/nominal/position", "wrong_shape"),
                                       ("learned/calibration/heliostats", "wrong_dtype"),
                                       ("learned/assimilation/history/mean", "nan"),
                                       ("learned/assimilation/window/g", "missing"),
                                       ("learned/surfaces/S1/displacement", "scalar"),
                                       ("learned/surfaces/S1/optics", "wrong_dtype")])
def test_every_reader_refuses_a_damaged_learned_group_in_one_line(base, tmp_path, capsys, paint_dir, name, how):
    assert damage(base, tmp_path / "d.h5", name, how)
    sc, out = tmp_path / "d.h5", tmp_path / "o.json"
    commands = [("scenario", "show", sc, "--json", out),
                ("aim", "--scenario", sc, "--heliostat", "S1", *SUN, "--aim", "0,0,50", "--json", out),
                ("trace", "--paint", paint_dir, "--scenario", sc, "--heliostat", "S1", "--record", "1",
                 "-o", tmp_path / "t.png"),
                ("validate", "--paint", paint_dir, "--scenario", sc, "--json", out),
                ("predict", "--scenario", sc, "--quiet", "--json", out),
                ("plan", "--scenario", sc, "--heliostat", "S1", "--quiet", "--json", out),
                ("field", "--scenario", sc, "--aim", "scenario", *SUN, "--quiet", "--json", out),
                ("update", "--scenario", sc, "--paint", paint_dir, "-o", tmp_path / "u.h5"),
                ("history", "--scenario", sc, "--heliostat", "S1", "--json", out)]
    for argv in commands:
        code, _, err = run_cli(capsys, *argv)
        assert code == 2, (argv[0], code, err)
        assert_one_line_error(code, err, "d.h5", f"/{name.rsplit('/', 1)[0]}")
    assert not out.exists() and not (tmp_path / "u.h5").exists()


def test_the_undamaged_scenario_reads_without_nan(base, tmp_path, capsys):
    """The baseline of the damages: the same commands succeed on the intact file with finite reports."""
    out = tmp_path / "o.json"
    code, _, err = run_cli(capsys, "aim", "--scenario", base, "--heliostat", "S1", *SUN, "--aim", "0,0,50",
                           "--json", out)
    assert code == 0, err
    report = json.loads(out.read_text())
    assert math.isfinite(report["expected_error_mrad"]) and report["expected_error_mrad"] > 0
    code, _, err = run_cli(capsys, "history", "--scenario", base, "--heliostat", "S1", "--json", out)
    assert code == 0, err
    assert "nan" not in out.read_text().lower()
