"""``reconstruct --nproc 2`` ended by SIGTERM (issue 41): exit 143 with one line and no warning after it (the
workers' progress bars once held multiprocessing semaphores that a terminated worker never unlinked, and the
resource tracker printed "There appear to be N leaked semaphore objects" as the command exited), nothing
half-written: no plant, no report, only whole heliostat checkpoints that a ``--resume`` reads."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

import heliotwin
from heliotwin import api
from heliotwin.workflows.reconstruct_plant import HeliostatResults

SRC = Path(heliotwin.__file__).resolve().parents[1]
# A heliostat's learner takes a few seconds at 30 steps: the worker with two heliostats still works on its
# second one when the first heliostat's checkpoint appears (the signal's deterministic moment).
FLAGS = ("--steps", "30", "--control-points", "4x4", "--degree", "2", "--slope-error", "1.5", "--device", "cpu",
         "--quiet")


def _env(temp: Path) -> dict:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")]),
                OMP_NUM_THREADS="1", HELIOTWIN_DEBUG="0", TMPDIR=str(temp))


# Slow: a simulated folder with images (~5 s) and two spawned torch workers learning surfaces (~10-20 s).
@pytest.mark.slow
@pytest.mark.skipif(os.name != "posix", reason="POSIX signals")
@pytest.mark.parametrize("whole_group", [False, True], ids=["parent", "process-group"])
def test_sigterm_during_nproc_reconstruct_warns_of_nothing_and_writes_nothing_half(tmp_path, whole_group):
    folder, temp = tmp_path / "paint", tmp_path / "tmp"
    temp.mkdir()
    api.simulate(folder, heliostats=6, images=3, years=1, seed=0)  # 3 heliostats with images: shards of 2 and 1
    out, rep, ckpt = tmp_path / "plant.h5", tmp_path / "plant.json", tmp_path / "plant.h5.ckpt"
    proc = subprocess.Popen([sys.executable, "-m", "heliotwin", "reconstruct", "--paint", str(folder), "--heliostats",
                             "all", "--nproc", "2", *FLAGS, "-o", str(out), "--json", str(rep)], cwd=tmp_path,
                            env=_env(temp), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # its own process group: a scheduler's kill of the job's group
    try:
        t0 = time.monotonic()
        while not list(ckpt.glob("*.ckpt")):  # a worker finished a heliostat: both have made their progress bars
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() - t0 < 600, "no heliostat finished"
            time.sleep(0.02)
        if whole_group:
            os.killpg(proc.pid, signal.SIGTERM)
        else:
            proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 143, err
    assert "leaked" not in err and "resource_tracker" not in err and "Warning" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("heliotwin: "), err
    assert not out.exists() and not rep.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["paint", "plant.h5.ckpt", "tmp"]
    assert not list(temp.glob("heliotwin-*")) and not list(temp.glob("pytorch-errorfile-*"))  # workers' folders
    # what the killed run kept is whole heliostats only, each one readable as a resume would read it
    names = sorted(p.name for p in ckpt.iterdir())
    assert names and all(n.endswith(".ckpt") for n in names), names
    tags = {str(d["tag"]) for d in (torch.load(p, weights_only=True) for p in ckpt.iterdir())}
    got = HeliostatResults.at(ckpt, tags.pop()).read()
    assert sorted(got) == [n[: -len(".ckpt")] for n in names] and not tags
    assert all(r["row"]["status"] == "learned" for r in got.values())
