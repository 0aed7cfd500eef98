"""Shared pytest fixtures (keep small; add yours below).

Shared helper *functions* live in the namespace package ``tests/helpers/`` (one module per area, no
``__init__.py``), imported as ``from helpers.<area> import ...``: pyproject's ``pythonpath = ["tests"]``
puts ``tests/`` on ``sys.path`` under every import mode.
"""
from __future__ import annotations

from pathlib import Path

import pytest
from helpers.data import SHARED_DATA, require_shared

#: The real PAINT data shipped next to the checkout (see its README.md).
PAINT_DIR = SHARED_DATA / "paint"


@pytest.fixture(scope="session")
def paint_dir() -> Path:
    """The real PAINT folder; skips the test when it is missing (fails instead when ``CI=true``)."""
    return require_shared(PAINT_DIR, "WRI1030197-tower-measurements.json", "real PAINT data")
