"""A simulated folder that grows a day at a time (issue 42 item 6): ``simulate --until`` then ``--extend`` gives the
one-shot history's records and metadata rows, appends only, and refuses a folder it did not grow."""
from __future__ import annotations

import csv
import json
import os

import pytest
from helpers.cli import assert_one_line_error, run_cli

ARGS = ("--heliostats", 5, "--years", 0.2, "--seed", 4, "--quiet")


def _records(folder) -> dict:
    out = {}
    for hid in sorted(os.listdir(folder)):
        cal = os.path.join(folder, hid, "Calibration")
        if os.path.isdir(cal):
            for name in sorted(os.listdir(cal)):
                with open(os.path.join(cal, name)) as fh:
                    out[(hid, name)] = json.load(fh)
    return out


def _rows(folder) -> list:
    with open(os.path.join(folder, "metadata", "calibration-metadata.csv"), newline="") as fh:
        return list(csv.reader(fh))


def _close(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))
    if isinstance(a, float):
        return a == pytest.approx(b, rel=1e-13, abs=1e-12)  # batched geodesy: the last bit may differ
    return a == b


def test_until_then_extend_is_the_one_shot_history_appended(tmp_path, capsys):
    code, _, err = run_cli(capsys, "simulate", *ARGS, "--out", tmp_path / "full")
    assert code == 0, err
    grown = tmp_path / "grown"
    code, _, err = run_cli(capsys, "simulate", *ARGS, "--out", grown, "--until", "2021-02-01")
    assert code == 0, err
    first = _records(grown)
    assert 0 < len(first) < len(_records(tmp_path / "full"))
    stamps = {k: os.stat(os.path.join(grown, k[0], "Calibration", k[1])).st_mtime_ns for k in first}
    rows_first = _rows(grown)
    for days in (10, 60, 30):
        code, _, err = run_cli(capsys, "simulate", "--extend", grown, "--days", days, "--quiet")
        assert code == 0, err
    full, done = _records(tmp_path / "full"), _records(grown)
    assert full.keys() == done.keys() and all(_close(full[k], done[k]) for k in full)
    assert _rows(grown) == _rows(tmp_path / "full")  # the same rows, in order
    assert _rows(grown)[:len(rows_first)] == rows_first  # appended only
    assert all(os.stat(os.path.join(grown, k[0], "Calibration", k[1])).st_mtime_ns == t for k, t in stamps.items())
    assert json.loads((grown / "simulation.json").read_text())["until"] == "2021-05-12"  # 2021-02-01 + 100 days


def test_extend_refuses_a_folder_it_did_not_grow(tmp_path, capsys):
    run_cli(capsys, "simulate", *ARGS, "--out", tmp_path / "full")
    code, _, err = run_cli(capsys, "simulate", "--extend", tmp_path / "full", "--days", 1)
    assert_one_line_error(code, err, "simulation.json", "--until")


def test_simulate_does_not_overwrite_an_existing_truth_file(tmp_path, capsys):
    truth = tmp_path / "truth.h5"
    truth.write_bytes(b"keep me")
    code, _, err = run_cli(capsys, "simulate", *ARGS, "--out", tmp_path / "p", "--truth", truth)
    assert_one_line_error(code, err, "truth.h5", "exists")
    assert truth.read_bytes() == b"keep me" and not (tmp_path / "p").exists()


def test_simulate_limits_are_said_in_the_users_terms(tmp_path, capsys):
    from heliotwin.field.demo import demo_field_positions
    from heliotwin.simulate.plant import DEMO_FIELD_MAX, check_size

    assert len(demo_field_positions(DEMO_FIELD_MAX)) == DEMO_FIELD_MAX  # the demo field's real capacity
    code, _, err = run_cli(capsys, "simulate", "--heliostats", 67600, "--out", tmp_path / "big")
    assert_one_line_error(code, err, "demo field holds at most", "--layout")
    assert "max_east" not in err and not (tmp_path / "big").exists()
    from heliotwin.errors import HeliotwinError
    from heliotwin.simulate import SimulationSettings

    huge = SimulationSettings(heliostats=20000, years=40, records_per_month=500)
    with pytest.raises(HeliotwinError, match="GiB of (memory|disk)"):
        check_size(huge, 20000, 4, tmp_path / "p")
    assert not any(tmp_path.iterdir())  # refused before anything was staged
