"""Shared pytest fixtures (keep small; add yours below).

Shared helper *functions* live in the namespace package ``tests/helpers/`` (one module per area, no
``__init__.py``), imported as ``from helpers.<area> import ...``: pyproject's ``pythonpath = ["tests"]``
puts ``tests/`` on ``sys.path`` under every import mode.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

#: The real PAINT data shipped next to the checkout (see its README.md).
PAINT_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "paint"


@pytest.fixture(scope="session")
def paint_dir() -> Path:
    """The real PAINT folder; skips the test when it is missing (fails instead when ``CI=true``)."""
    if not (PAINT_DIR / "WRI1030197-tower-measurements.json").is_file():
        message = f"real PAINT data not found at {PAINT_DIR}"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)
    return PAINT_DIR
