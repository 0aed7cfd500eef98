"""Ctrl-C (SIGINT) and SIGTERM in the middle of a command or of its writes: exit 130 / 143, one line, and
nothing left behind -- no output, no staging folder, no temporary file, existing outputs untouched."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import heliotwin

SRC = Path(heliotwin.__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(os.name != "posix", reason="POSIX signals")


def _env():
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")]),
                OMP_NUM_THREADS="1", HELIOTWIN_DEBUG="0")


def _default_sigint():
    # A child inherits an ignored SIGINT from a shell that started the test run in the background (`cmd &`
    # without job control), and Python then installs no KeyboardInterrupt handler: Ctrl-C would not reach it.
    # The commands are tested as a terminal starts them.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _wait_for(predicate, proc, timeout=120.0):
    t0 = time.monotonic()
    while not predicate():
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"process ended before the signal: {proc.returncode}\n{out}\n{err}")
        if time.monotonic() - t0 > timeout:
            proc.kill()
            pytest.fail("timed out waiting for the command to start its work")
        time.sleep(0.02)


#: A command that stages its output and then writes it slowly, chunk by chunk, through the CLI's safety net.
_SLOW_WRITER = """
import sys, time
from argparse import Namespace
from heliotwin.cli.common import run_command
from heliotwin.io.report import output_set

def func(args):
    with output_set() as out:
        path = out.file(args.path, "--json")
        with open(path, "w") as fh:
            fh.write("x" * 100)
            fh.flush()
            for _ in range(600):
                fh.write("y")
                time.sleep(0.05)
    return 0

sys.exit(run_command(Namespace(func=func, path=sys.argv[1])))
"""


@pytest.mark.parametrize("sig, code, word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")])
def test_signal_during_a_write_leaves_the_old_output_and_nothing_else(tmp_path, sig, code, word):
    out = tmp_path / "report.json"
    out.write_text("old")
    proc = subprocess.Popen([sys.executable, "-c", _SLOW_WRITER, str(out)], env=_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint)

    def writing():
        staged = [p for d in tmp_path.glob(".heliotwin-*") for p in d.iterdir()]
        return bool(staged) and staged[0].stat().st_size >= 100

    _wait_for(writing, proc)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err
    assert err.strip() == f"heliotwin: {word}; nothing was written"
    assert out.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["report.json"]


# Slow and timing-dependent (the signal is sent 0.3 s "into the tracing"): in two of three full-suite runs on
# the busy 2-core machine the demo ran to the end with exit 0 instead of stopping, which was not reproduced
# alone or under synthetic load. Out of the default run until it waits for a deterministic event; the
# mechanism itself is covered deterministically by the slow-writer test above. (2026-11-28: the slow-writer's
# SIGINT case failed the same way, exit 0, in a CI run started with `&` from a script: SIGINT was ignored from
# the start, inherited. Both tests now reset it in the child, _default_sigint; that was likely the cause here.)
@pytest.mark.slow
@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_during_demo_leaves_no_output_folder(tmp_path, sig, code):
    """``heliotwin demo`` killed while tracing: neither its folder nor its --json report appears."""
    folder, report = tmp_path / "demo", tmp_path / "demo.json"
    proc = subprocess.Popen([sys.executable, "-m", "heliotwin", "demo", "--out", str(folder), "--json", str(report),
                             "--heliostats", "2000", "--quiet"], env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint)
    _wait_for(lambda: any(tmp_path.glob(".heliotwin-*")), proc)
    time.sleep(0.3)  # into the tracing
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    assert len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def _children(pid: int) -> list[int]:
    """Live (non-zombie) processes whose parent is ``pid``, from /proc."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            out.append(int(entry.name))
    return out


def _alive(pid: int) -> bool:
    try:
        return (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


# Slow (a scenario of 4800 heliostats, then a command that spawns two torch processes: about a minute on the
# busy 2-core machine). The signal waits for deterministic events: the workers' process-group store exists and
# both workers run. The commands must outlast that: the field's ranks work ~2 s after the store appears (1,200
# heliostats took ~1.2 s, and a 1 s wait then let the command finish first on an idle machine), and the aim
# points run without end (a limit of 200 W/m2 that full power cannot hold keeps Adam at its 10^6 steps).
@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads the process tree from /proc")
@pytest.mark.parametrize("command", ["field", "aimpoints"])
def test_sigterm_with_nproc_ends_the_workers_with_the_command(tmp_path, command):
    """SIGTERM while two ranks work: exit 143 with one line, the workers gone within 5 s of the command's end,
    their folder removed, no output."""
    from helpers.field import dense_field, write_layout, write_plant_toml

    temp = tmp_path / "tmp"
    temp.mkdir()
    write_layout(tmp_path, dense_field(60, 80) if command == "field" else dense_field(2, 3))
    write_plant_toml(tmp_path)
    env = dict(_env(), TMPDIR=str(temp))
    subprocess.run([sys.executable, "-m", "heliotwin", "scenario", "from-layout", str(tmp_path / "layout.csv"),
                    "--config", str(tmp_path / "plant.toml"), "-o", str(tmp_path / "p.h5"), "--quiet"], env=env,
                   check=True)
    sun = ["--sun-azimuth", "10", "--sun-elevation", "40", "--nproc", "2", "--resolution", "8x4", "--quiet"]
    argv = (["field", "--integrator", "mc", "--json", "f.json"] if command == "field" else
            ["aimpoints", "--peak-limit", "1000", "--iterations", "1000000", "--no-baselines", "-o", "o.h5",
             "--json", "o.json"])
    before = sorted(p.name for p in tmp_path.iterdir())
    proc = subprocess.Popen([sys.executable, "-m", "heliotwin", *argv, "--scenario", "p.h5", *sun], cwd=tmp_path,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    def descendants():
        return [w for c in _children(proc.pid) for w in [c, *_children(c)]]

    _wait_for(lambda: any(temp.glob("heliotwin-ranks-*/store")) and len(descendants()) >= 2, proc, timeout=300)
    workers = descendants()
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert err.strip() == "heliotwin: terminated; nothing was written"
    deadline = time.monotonic() + 5.0
    while any(_alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [w for w in workers if _alive(w)]
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert not list(temp.glob("heliotwin-ranks-*")) and not list(temp.glob("pytorch-errorfile-*"))
