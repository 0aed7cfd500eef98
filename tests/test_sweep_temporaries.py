"""Temporaries of killed runs (issue 41 item 12): a SIGKILL leaves a ``.tmp-*`` file of ``atomic_path`` or a
``.heliotwin-*`` staging folder behind; the next run writing to that folder removes them when their owner (the pid
in the name) is gone, or, named without a pid, when older than an hour, and touches nothing else."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from heliotwin.io.report import STALE_AGE_S, output_set, sweep_stale, write_json


@pytest.fixture(scope="module")
def dead_pid():
    """The pid of a process that has ended (and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


@pytest.fixture()
def live_pid():
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    yield proc.pid
    proc.kill()
    proc.wait()


def _leftovers(folder, pid):
    """What a run ``pid`` killed mid-write leaves: a complete temporary plant and a staging folder holding a report."""
    tmp = folder / f".tmp-{pid}-k3x9_q2a.h5"
    tmp.write_bytes(b"\x89HDF" + b"0" * 1000)
    staging = folder / f".heliotwin-{pid}-ab12cd34"
    staging.mkdir()
    (staging / "d.json").write_text("{}")
    return tmp, staging


def test_the_next_write_sweeps_a_killed_runs_temporaries(tmp_path, dead_pid):
    tmp, staging = _leftovers(tmp_path, dead_pid)
    write_json(tmp_path / "r.json", {"a": 1})
    assert not tmp.exists() and not staging.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]


def test_an_output_set_sweeps_its_folder_before_staging(tmp_path, dead_pid):
    tmp, staging = _leftovers(tmp_path, dead_pid)
    with output_set() as out:
        path = out.file(tmp_path / "d.json", "--json")
        with open(path, "w") as fh:
            fh.write("{}")
    assert not tmp.exists() and not staging.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.json"]


def test_a_live_runs_temporaries_are_kept(tmp_path, live_pid):
    tmp, staging = _leftovers(tmp_path, live_pid)
    write_json(tmp_path / "r.json", {"a": 1})
    assert tmp.exists() and (staging / "d.json").exists()


def test_pid_less_temporaries_are_swept_only_after_an_hour(tmp_path):
    old, young = tmp_path / ".tmp-abcdefgh.json", tmp_path / ".heliotwin-0123abcd"
    old.write_text("x")
    young.mkdir()
    t = 1_700_000_000.0
    os.utime(old, (t - STALE_AGE_S - 1, t - STALE_AGE_S - 1))
    os.utime(young, (t - STALE_AGE_S + 60, t - STALE_AGE_S + 60))
    assert sweep_stale(tmp_path, now=t) == [old.name]
    assert young.exists()
    assert sweep_stale(tmp_path, now=t + 120) == [young.name]


def test_a_sweep_removes_links_never_their_targets_and_nothing_else(tmp_path, dead_pid):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep.h5").write_text("plant")
    work = tmp_path / "work"
    work.mkdir()
    (work / f".tmp-{dead_pid}-abcdefgh.h5").symlink_to(outside / "keep.h5")
    (work / f".heliotwin-{dead_pid}-abcdefgh").symlink_to(outside)
    others = [".tmp-killed.npz", ".heliotwin-simulate-abcdefgh", "p.h5", ".tmp-x", f".tmp-{dead_pid}"]
    for name in others:
        (work / name).write_text("x")
    removed = sweep_stale(work, now=1e12)
    assert sorted(removed) == sorted([f".tmp-{dead_pid}-abcdefgh.h5", f".heliotwin-{dead_pid}-abcdefgh"])
    assert (outside / "keep.h5").read_text() == "plant"
    assert sorted(p.name for p in work.iterdir()) == sorted(others)


def test_temporaries_carry_their_owners_pid(tmp_path, monkeypatch):
    seen = []
    real = os.replace

    def spy(src, dst):
        seen.append(os.path.basename(src))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", spy)
    write_json(tmp_path / "r.json", {})
    assert seen and seen[0].startswith(f".tmp-{os.getpid()}-") and seen[0].endswith(".json")
