"""Shared pytest fixtures (keep small; add yours below).

Shared helper *functions* live in the namespace package ``tests/helpers/`` (one module per area, no
``__init__.py``), imported as ``from helpers.<area> import ...``: pyproject's ``pythonpath = ["tests"]``
puts ``tests/`` on ``sys.path`` under every import mode.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest
from helpers.data import SHARED_DATA, require_shared

# Commands run as subprocesses (``python -m heliotwin``) import the same checkout as the tests themselves
# (pyproject's ``pythonpath`` covers this process only), whichever checkout the package was installed from.
_SRC = str(Path(__file__).resolve().parents[1] / "src")
_PATHS = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
os.environ["PYTHONPATH"] = os.pathsep.join([_SRC] + _PATHS)

#: The real PAINT data shipped next to the checkout (see its README.md).
PAINT_DIR = SHARED_DATA / "paint"


@pytest.fixture(scope="session")
def paint_dir() -> Path:
    """The real PAINT folder; skips the test when it is missing (fails instead when ``CI=true``)."""
    return require_shared(PAINT_DIR, "WRI1030197-tower-measurements.json", "real PAINT data")
