"""The real data next to the checkout (``../shared/data``): present, or a loud failure in CI."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

#: ``../shared/data`` next to the checkout.
SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
#: The real PAINT folder: ``$HELIOTWIN_PAINT`` when set (another copy of the data), else ``../shared/data/paint``.
PAINT_DIR = Path(os.environ["HELIOTWIN_PAINT"]) if os.environ.get("HELIOTWIN_PAINT") else SHARED_DATA / "paint"
#: Why real-data tests were skipped in this run (the conftest's terminal summary says it loudly).
SKIPPED: list = []


def require_shared(folder: Path, marker: str, what: str) -> Path:
    """``folder`` when ``folder / marker`` exists; else skip the test, or fail it when ``CI=true`` (CI must
    never pass by skipping the real-data tests). Each skip is recorded in :data:`SKIPPED` for the run's summary."""
    if not (Path(folder) / marker).is_file():
        message = f"{what} not found at {folder}"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        SKIPPED.append(message)
        pytest.skip(message)
    return Path(folder)
