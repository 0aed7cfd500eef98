"""What was learned goes out (issue 42 item 5): ``aimpoints --in-place`` replaces the plant under its lock as
``update --in-place`` does, refuses -o == --scenario without the flag, and updates a symlinked plant through its
target; ``scenario export`` writes the stored optimised aim points (``tests/test_outputs.py`` checks the table)."""
from __future__ import annotations

import os

import torch
from helpers.cli import assert_one_line_error, run_cli

from heliotwin.io.lock import lock_path
from heliotwin.io.scenario import load_scenario, save_scenario
from heliotwin.optimise.testbed import generated_plant

TIME = "2024-06-21T11:00:00Z"


def _plant(tmp_path):
    plant, atm = generated_plant("radial", 30, "cylinder", tower=30.0)
    return save_scenario(plant, tmp_path / "p.h5", extras=atm.to_extras())


def _aim(capsys, sc, out, *extra):
    return run_cli(capsys, "aimpoints", "--scenario", sc, "--time", TIME, "--peak-limit", 200000, "--iterations", 40,
                   "--no-baselines", "-o", out, "--json", os.path.join(os.path.dirname(out), "a.json"), *extra)


def test_aimpoints_in_place_needs_the_flag_and_then_replaces_the_plant(tmp_path, capsys):
    sc = _plant(tmp_path)
    before = open(sc, "rb").read()
    code, _, err = _aim(capsys, sc, sc)
    assert_one_line_error(code, err, "--in-place")
    assert open(sc, "rb").read() == before and not os.path.exists(lock_path(sc))  # nothing touched
    code, _, err = _aim(capsys, sc, sc, "--in-place")
    assert code == 0, err
    after = load_scenario(sc)
    assert after.learned["aimpoints"]["aim"].shape == (30, 3) and after.provenance[-1]["step"] == "aimpoints"
    assert not any(n.startswith((".tmp-", ".heliotwin-")) for n in os.listdir(tmp_path))


def test_aimpoints_in_place_on_a_symlinked_plant_updates_its_target(tmp_path, capsys):
    sc = _plant(tmp_path)
    link = tmp_path / "current.h5"
    os.symlink(sc.name, link)
    code, _, err = _aim(capsys, link, link, "--in-place")
    assert code == 0, err
    assert os.path.islink(link) and "aimpoints" in load_scenario(sc).learned  # the target holds the new plant
    stored = torch.as_tensor(load_scenario(link).learned["aimpoints"]["aim"])
    assert torch.equal(stored, torch.as_tensor(load_scenario(sc).learned["aimpoints"]["aim"]))
