"""Running the ``heliotwin`` command in tests (shared through the ``tests/helpers`` namespace package)."""
from __future__ import annotations

from heliotwin.cli import main


def run_cli(capsys, *argv):
    """Run ``heliotwin ARGV...`` in-process; return ``(exit status, stdout, stderr)``."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code, err, *needles):
    """A user error: non-zero exit and one stderr line ``heliotwin: error: ...`` holding every needle."""
    assert code != 0
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("heliotwin: error: "), lines[0]
    for n in needles:
        assert n in lines[0], (n, lines[0])
