"""``heliotwin calibrate`` progress: one line per step of the run when stderr is not a terminal (a log file, a
pipe), nothing with ``--quiet``."""
import io
from argparse import Namespace

from heliotwin.calibrate.protocol.pipeline import STEPS
from heliotwin.cli.calibrate import _progress


def test_a_run_logs_one_line_per_step_when_not_on_a_terminal():
    log = io.StringIO()
    line = _progress(Namespace(quiet=False), stream=log)
    assert callable(line)  # pytest's captured stderr is not a terminal
    for index, (name, _) in enumerate(STEPS[:3]):
        line(name, index, len(STEPS))
    lines = log.getvalue().splitlines()
    assert lines == [f"heliotwin calibrate: step {i + 1}/{len(STEPS)} {name}" for i, (name, _) in enumerate(STEPS[:3])]


def test_quiet_silences_progress():
    assert _progress(Namespace(quiet=True), stream=io.StringIO()) is False
