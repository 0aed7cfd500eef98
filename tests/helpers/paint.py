"""Copies of the real PAINT folder that a test may corrupt (shared through the ``tests/helpers`` package)."""
from __future__ import annotations

import shutil
from pathlib import Path


def copy_paint(paint_dir: Path, dest: Path, heliostats=("AA39",), *, metadata: bool = True) -> Path:
    """A PAINT folder at ``dest / "paint"`` with the tower file and the given heliostats (copied), and the
    metadata CSVs (the records' times: a chrono split, ``validate`` and ``report --paint`` need them) unless
    ``metadata`` is False (a damaged folder)."""
    root = Path(dest) / "paint"
    root.mkdir()
    shutil.copy(Path(paint_dir) / "WRI1030197-tower-measurements.json", root)
    if metadata:
        shutil.copytree(Path(paint_dir) / "metadata", root / "metadata")
    for h in heliostats:
        shutil.copytree(Path(paint_dir) / h, root / h)
    return root
