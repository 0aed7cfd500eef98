"""Shared pytest fixtures (keep small; add yours below).

Shared helper *functions* live in the namespace package ``tests/helpers/`` (one module per area, no
``__init__.py``), imported as ``from helpers.<area> import ...``: pyproject's ``pythonpath = ["tests"]``
puts ``tests/`` on ``sys.path`` under every import mode.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest
from helpers.data import PAINT_DIR, SKIPPED, require_shared

# Commands run as subprocesses (``python -m heliotwin``) import the same checkout as the tests themselves
# (pyproject's ``pythonpath`` covers this process only), whichever checkout the package was installed from.
_SRC = str(Path(__file__).resolve().parents[1] / "src")
_PATHS = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
os.environ["PYTHONPATH"] = os.pathsep.join([_SRC] + _PATHS)



@pytest.fixture(scope="session")
def paint_dir() -> Path:
    """The real PAINT folder; skips the test when it is missing (fails instead when ``CI=true``)."""
    return require_shared(PAINT_DIR, "WRI1030197-tower-measurements.json", "real PAINT data")


def pytest_terminal_summary(terminalreporter):
    """Say loudly when real-data tests were skipped (outside CI, where they fail instead)."""
    if not SKIPPED:
        return
    where = sorted(set(SKIPPED))
    terminalreporter.write_sep("!", f"{len(SKIPPED)} REAL-DATA TESTS SKIPPED", yellow=True, bold=True)
    for line in where:
        terminalreporter.write_line(f"  {line}", yellow=True)
    terminalreporter.write_line("  put the data at ../shared/data next to the checkout, or point HELIOTWIN_PAINT at a "
                                "PAINT folder; with CI=true these tests fail instead of skipping", yellow=True)
