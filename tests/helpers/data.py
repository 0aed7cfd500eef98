"""The real data next to the checkout (``../shared/data``): present, or a loud failure in CI."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

#: ``../shared/data`` next to the checkout.
SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"


def require_shared(folder: Path, marker: str, what: str) -> Path:
    """``folder`` when ``folder / marker`` exists; else skip the test, or fail it when ``CI=true`` (CI must
    never pass by skipping the real-data tests)."""
    if not (Path(folder) / marker).is_file():
        message = f"{what} not found at {folder}"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)
    return Path(folder)
