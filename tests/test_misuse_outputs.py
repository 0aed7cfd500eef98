"""Misuse of the daily loop's outputs (issue 41 items 1, 3, 10): an output onto the plant or onto an input record,
a refused output that still left a lock behind, a symlinked plant replaced by a regular file, a dangling lock
symlink whose target was created, implausible ``--peak-limit`` / ``--draws``, and scenario datasets whose shapes
claim far more than the file holds.

Each case ends in a one-line refusal that changes nothing, or the plant updated through its link."""
from __future__ import annotations

import os
import shutil

import h5py
import numpy as np
import pandas as pd
import pytest
from helpers.cli import assert_one_line_error, run_cli

from heliotwin.cli import main
from heliotwin.errors import HeliotwinError, InputFileError
from heliotwin.field.update import select_heliostats
from heliotwin.io.scenario import load_scenario, save_scenario
from heliotwin.io.weather import read_dni_series, weather_for_year
from heliotwin.simulate import SimulationSettings, simulate_plant, write_paint_folder
from heliotwin.workflows.aimpoints import check_draws_memory

DAY = ("--no-aim", "--day", "2021-12-01", "--quiet")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A 3-heliostat simulated plant's folder and its calibrated plant file (a few seconds)."""
    root = tmp_path_factory.mktemp("outputs")
    sim = simulate_plant(SimulationSettings(heliostats=3, seed=41, years=0.3, records_per_month=8))
    folder = write_paint_folder(sim, root / "base")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HELIOTWIN_CACHE_DIR", str(root / "cache"))
        assert main(["calibrate", "--paint", str(folder), "--min-records", "5", "-o", str(root / "p.h5"),
                     "--quiet"]) == 0
    return root


@pytest.fixture()
def work(built, tmp_path, monkeypatch):
    """A fresh copy of the folder (``base``) and the plant (``p.h5``) in the test's own folder, its cwd."""
    shutil.copytree(built / "base", tmp_path / "base")
    shutil.copy(built / "p.h5", tmp_path / "p.h5")
    monkeypatch.setenv("HELIOTWIN_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _cli(capsys, *argv):
    """:func:`run_cli`, with argparse's refusals (``SystemExit``) as an exit status too."""
    try:
        return run_cli(capsys, *argv)
    except SystemExit as exc:
        out, err = capsys.readouterr()
        return exc.code, out, err


def _steps(path) -> int:
    return len(load_scenario(path).provenance)


# ------------------------------------------------------------------------------------- outputs vs inputs
def test_daily_json_onto_the_plant_is_refused_and_the_plant_kept(work, capsys):
    before = (work / "p.h5").read_bytes()
    code, _, err = run_cli(capsys, "daily", "--plant", "p.h5", "--paint", "base", *DAY, "--json", "p.h5")
    assert_one_line_error(code, err, "p.h5", "--json")
    assert code == 2
    assert (work / "p.h5").read_bytes() == before  # still the plant, not a JSON report
    assert not (work / "p.h5.lock").exists()


def test_daily_output_onto_an_input_record_is_refused_and_the_record_kept(work, capsys):
    record = sorted((work / "base").glob("*/Calibration/*-calibration-properties.json"))[0]
    text = record.read_text()
    code, _, err = run_cli(capsys, "daily", "--plant", "p.h5", "--paint", "base", *DAY, "-o", record)
    assert_one_line_error(code, err, record.name, "-o", "--paint")
    assert record.read_text() == text
    assert not os.path.exists(f"{record}.lock")


def test_a_refused_output_folder_leaves_no_lock_beside_it(work, capsys):
    code, _, err = run_cli(capsys, "daily", "--plant", "p.h5", "--paint", "base", *DAY, "-o", "base")
    assert_one_line_error(code, err, "base", "-o")
    assert sorted(p.name for p in work.iterdir()) == ["base", "p.h5"]  # no base.lock, no p.h5.lock


# ------------------------------------------------------------------------------------------ symlinks
def test_daily_on_a_symlinked_plant_updates_its_target_and_keeps_the_link(work, capsys):
    (work / "link.h5").symlink_to("p.h5")
    steps = _steps(work / "p.h5")
    code, _, err = run_cli(capsys, "daily", "--plant", "link.h5", "--paint", "base", *DAY)
    assert code == 0, err
    assert (work / "link.h5").is_symlink() and os.readlink(work / "link.h5") == "p.h5"
    assert _steps(work / "p.h5") == steps + 1 and load_scenario(work / "p.h5").provenance[-1]["step"] == "daily"
    # one plant, one lock: the target's
    assert (work / "p.h5.lock").exists() and not (work / "link.h5.lock").exists()


def test_update_in_place_on_a_symlinked_plant_updates_its_target(work, capsys):
    (work / "plants").mkdir()
    shutil.move(work / "p.h5", work / "plants" / "p.h5")
    (work / "link.h5").symlink_to(work / "plants" / "p.h5")
    steps = _steps(work / "plants" / "p.h5")
    code, _, err = run_cli(capsys, "update", "--scenario", "link.h5", "--paint", "base", "-o", "link.h5",
                           "--in-place", "--quiet")
    assert code == 0, err
    assert (work / "link.h5").is_symlink()
    assert _steps(work / "plants" / "p.h5") == steps + 1
    assert not (work / "link.h5.lock").exists()


def test_a_dangling_lock_symlink_is_refused_without_creating_its_target(work, capsys):
    (work / "p.h5.lock").symlink_to(work / "elsewhere")
    before = (work / "p.h5").read_bytes()
    code, _, err = run_cli(capsys, "daily", "--plant", "p.h5", "--paint", "base", *DAY)
    assert_one_line_error(code, err, "p.h5.lock", "symbolic link")
    assert not (work / "elsewhere").exists()
    assert (work / "p.h5").read_bytes() == before


# -------------------------------------------------------------------------------------- argument bounds
@pytest.mark.parametrize("value", ["1e-300", "999", "1e9", "nan"])
def test_daily_peak_limit_outside_1kw_100mw_is_refused(work, capsys, value):
    before = (work / "p.h5").read_bytes()
    code, _, err = _cli(capsys, "daily", "--plant", "p.h5", "--paint", "base", "--day", "2021-12-01",
                           "--peak-limit", value, "--quiet")
    assert_one_line_error(code, err, "--peak-limit", "1 kW/m2 .. 100 MW/m2")
    assert (work / "p.h5").read_bytes() == before


def test_aimpoints_peak_limit_and_draws_are_bounded(work, capsys):
    sun = ("--sun-azimuth", "10", "--sun-elevation", "40")
    code, _, err = _cli(capsys, "aimpoints", "--scenario", "p.h5", *sun, "--peak-limit", "1e-300", "-o", "o.h5")
    assert_one_line_error(code, err, "--peak-limit")
    code, _, err = _cli(capsys, "aimpoints", "--scenario", "p.h5", *sun, "--peak-limit", "3e5", "--confidence",
                           "0.9", "--draws", "100000000", "-o", "o.h5")
    assert_one_line_error(code, err, "--draws", "100000")
    assert not (work / "o.h5").exists()


def test_draws_beyond_half_the_memory_are_refused_with_the_estimate():
    check_draws_memory(1000, 300, memory_bytes=8 << 30)  # 115 MB of 8 GiB: fine
    with pytest.raises(HeliotwinError, match=r"--draws 100000: .* 10000 heliostats need about 357.6 GiB.* at most "):
        check_draws_memory(100_000, 10_000, memory_bytes=8 << 30)


# -------------------------------------------------------------------------------------- dataset shapes
def _replace(path, name, **kw):
    with h5py.File(path, "r+") as h5:
        del h5[name]
        h5.create_dataset(name, **kw)


def test_a_dataset_claiming_a_terabyte_is_refused_before_it_is_read(work):
    """An unwritten chunked dataset costs the file nothing but claims 1 TiB: refused naming file and dataset
    (it was allocated before any check: MemoryError, or worse, a machine swapping)."""
    path = work / "p.h5"
    _replace(path, "field/width", shape=(3, 2**38), dtype="float32", chunks=(1, 2**20))
    assert path.stat().st_size < 200_000
    with pytest.raises(InputFileError) as err:
        load_scenario(path)
    assert "/field/width" in str(err.value) and "p.h5" in str(err.value) and "GiB" in str(err.value)


def test_a_dataset_claiming_more_than_its_file_stores_is_refused(work):
    """2 GiB claimed (under the absolute cap) over a file of some kB: more than any compression packs."""
    path = work / "p.h5"
    _replace(path, "field/height", shape=(3, 2**27), dtype="float32", chunks=(1, 2**20), compression="gzip")
    with pytest.raises(InputFileError) as err:
        load_scenario(path)
    assert "/field/height" in str(err.value) and "stores" in str(err.value)


def test_a_per_heliostat_dataset_with_the_wrong_row_count_is_refused(work):
    path = work / "p.h5"
    _replace(path, "field/width", data=np.ones(4, dtype="float32"))
    with pytest.raises(InputFileError) as err:
        load_scenario(path)
    assert "/field/width" in str(err.value) and "3 rows" in str(err.value)


def test_the_cli_names_the_dataset_in_one_line(work, capsys):
    _replace(work / "p.h5", "field/width", shape=(3, 2**38), dtype="float32", chunks=(1, 2**20))
    code, _, err = run_cli(capsys, "daily", "--plant", "p.h5", "--paint", "base", *DAY)
    assert_one_line_error(code, err, "p.h5", "/field/width")


# ------------------------------------------------------------------------------- item 10: site and positions
@pytest.mark.parametrize("attr, value, needle", [("latitude_deg", 200.0, "latitude in [-90, 90]"),
                                                 ("longitude_deg", -181.0, "longitude in [-180, 180]"),
                                                 ("altitude_m", 1e5, "altitude in")])
def test_an_impossible_site_is_refused_naming_the_attribute(work, attr, value, needle):
    with h5py.File("p.h5", "a") as h5:
        h5["site"].attrs[attr] = value
    with pytest.raises(InputFileError) as e:
        load_scenario("p.h5")
    assert e.value.field == f"/site@{attr}" and needle in str(e.value)


def test_a_heliostat_far_off_the_tower_is_refused_naming_it(work, capsys):
    with h5py.File("p.h5", "a") as h5:
        pos = h5["field/kinematics/position"][()]
        pos[1, 0] = 1e300
        h5["field/kinematics/position"][...] = pos
        hid = h5["field/ids"].asstr()[1]
    code, _, err = run_cli(capsys, "field", "--scenario", "p.h5", "--sun-azimuth", "10", "--sun-elevation", "40",
                           "--json", "f.json", "--quiet")
    assert_one_line_error(code, err, "p.h5", "/field/kinematics/position", hid, "20000 m")
    assert not (work / "f.json").exists()


# ----------------------------------------------------------------------------------------------- item 12
@pytest.mark.parametrize("flag, value, needle", [("--every", "0min", "between 1min and 31d"),
                                                 ("--every", "5parsecs", "a time step like"),
                                                 ("--day", "1850-06-21", "out of range"),
                                                 ("--day", "2021-13-45", "a UTC date like")])
def test_daily_times_are_checked_in_one_line(work, capsys, flag, value, needle):
    before = (work / "p.h5").read_bytes()
    code, _, err = _cli(capsys, "daily", "--plant", "p.h5", "--paint", "base", "--no-aim", "--quiet",
                        *(() if flag == "--day" else ("--day", "2021-12-01")), f"{flag}={value}")
    assert_one_line_error(code, err, flag, needle)
    assert code == 2 and (work / "p.h5").read_bytes() == before


def test_a_valid_time_out_of_range_is_said_to_be_out_of_range(work, capsys):
    code, _, err = run_cli(capsys, "field", "--scenario", "p.h5", "--time", "1850-06-21T12:00:00Z", "--json",
                           "f.json", "--quiet")
    assert_one_line_error(code, err, "--time", "out of range")
    assert "cannot be parsed" not in err and "cannot parse" not in err


# ----------------------------------------------------------------------------------- item 12: field
def test_field_on_a_plant_without_heliostats_is_a_one_line_error(work, capsys):
    save_scenario(select_heliostats(load_scenario(work / "p.h5").plant, []), work / "zero.h5")
    code, _, err = _cli(capsys, "field", "--scenario", "zero.h5", "--sun-azimuth", "10", "--sun-elevation", "40",
                        "--json", "f.json", "--resolution", "8x4", "--quiet")
    assert_one_line_error(code, err, "zero.h5", "no heliostats")


# ---------------------------------------------------------------------------------------- item 11: weather gaps
def test_a_year_with_every_second_dni_missing_is_not_annual(tmp_path):
    t = pd.date_range("2023-01-01", "2024-01-01", freq="1h", tz="UTC", inclusive="left")
    with open(tmp_path / "w.csv", "w") as fh:
        fh.write("time,dni\n")
        for i, ti in enumerate(t):
            fh.write(f"{ti.isoformat()},{'nan' if i % 2 else 700.0}\n")
    wy = weather_for_year(read_dni_series(tmp_path / "w.csv"), 2023)
    assert wy.annual is False and wy.coverage["annual"] is False  # was: annual, at a 2 h step read off the rows left
    assert any("50.0 % of the rows" in a and "too many for an annual" in a for a in wy.assumptions)
