"""``validate --paint`` on a folder without ``metadata/calibration-metadata.csv`` (issue 41 item 11): one line
naming the missing file, exit 2, no output; the same folder with it validates (exit 0)."""
from __future__ import annotations

import json
import shutil

import pytest
from helpers.cli import assert_one_line_error, run_cli

from heliotwin.simulate import SimulationSettings, simulate_plant, write_paint_folder


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    sim = simulate_plant(SimulationSettings(heliostats=3, seed=41, years=0.1, records_per_month=8))
    return write_paint_folder(sim, tmp_path_factory.mktemp("validate") / "base")


def test_validate_without_the_metadata_csv_is_one_line_naming_it_and_writes_nothing(folder, tmp_path, capsys):
    argv = ["validate", "--paint", folder, "--no-images", "--samples", "4", "--resolution", "32", "--quiet"]
    code, _, err = run_cli(capsys, *argv, "--json", tmp_path / "with.json")
    assert code == 0, err
    assert json.loads((tmp_path / "with.json").read_text())["overall"]["records"] > 0
    csv, kept = f"{folder}/metadata/calibration-metadata.csv", tmp_path / "kept.csv"
    shutil.move(csv, kept)
    try:
        code, _, err = run_cli(capsys, *argv, "--json", tmp_path / "without.json", "--plot", tmp_path / "v.png")
    finally:
        shutil.move(kept, csv)
    assert code == 2
    assert_one_line_error(code, err, "metadata/calibration-metadata.csv", "missing")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["with.json"]
