"""Allowable-flux maps: the receiver's limit per map cell, from a HALOS-style CSV or per-panel limits in a TOML.

CSV (``--flux-limit FILE.csv``)
-------------------------------
NREL HALOS' ``allowable_flux.csv`` layout: a headerless numeric table, one line per row of measurement points from the
**top** of the receiver to the bottom, one column per point **around** a cylinder (from where the model's unrolled
map starts, the left edge of ``heliotwin field``'s map) or **across** a flat receiver (left to right seen from the
field). Any number of rows and columns; the file's cells tile the receiver's whole height and width evenly. Lines
starting with ``#`` are comments; one of them may state the unit: ``# unit: W/m2`` (the default), ``kW/m2`` (HALOS'
own unit) or ``MW/m2``, and the values are converted to W/m^2. A file with no unit line whose largest value is below
1,000 (no receiver's limit is below the sun's own 1 kW/m^2: such a file is in kW/m^2 or MW/m^2) is refused, with the
line to add.

Resampling onto the model's grid is **conservative**: a model cell takes the lowest limit of the file cells it
overlaps (by a positive length along both axes), so no model cell allows more than any part of the receiver under
it. A file on the model's own grid is taken as it is.

TOML (``--flux-limit plant.toml``: its ``[receiver.flux_limit]`` table)
--------------------------------------------------------------------
::

    [receiver.flux_limit]
    panels_w_m2 = [1.0e6, 1.0e6, ...]   # one limit per panel [W/m2], panels of equal width left to right (around a
                                        # cylinder from where the unrolled map starts)
    flow_path = [3, 2, 1, 0, 4, 5, 6, 7]  # optional: the panels in the order the heat-transfer fluid passes them
                                        # (0-based, each panel once; default 0, 1, ..., N-1)
    derating = [1.0, 0.95, ..., 0.33]   # optional: factor in (0, 1] on the limit at each step of the flow path
                                        # (as many as panels; default 1): the hot outlet's limit is lowest
    top_bottom_w_m2 = 3.0e5             # optional: the limit on the top and bottom rows of the model's map [W/m2]
                                        # (a header's and a footer's, where tubes bend), if lower

The panel ``p``'s limit is ``panels_w_m2[p] * derating[k]`` where ``flow_path[k] = p``; resampled onto the model's
columns conservatively (a column over two panels takes the lower limit).

Shapes: maps [rows, cols] (row 0 = top) [W/m^2], float64.
"""
from __future__ import annotations

import math
import os
import sys

import numpy as np
import torch

from ..errors import InputFileError
from ..field.flux_limit import RANGE_W_M2, parse_flux_limit_table
from .problem import FluxLimit

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["UNITS", "read_flux_limit_csv", "panel_limit_grid", "parse_flux_limit_table", "resample_min",
           "load_flux_limit", "combine"]

#: Units a flux-limit CSV may state (``# unit: ...``), with their factor to W/m^2.
UNITS = {"w/m2": 1.0, "kw/m2": 1e3, "mw/m2": 1e6}


def _unit_line(line: str):
    """The unit factor a comment line states (``# unit: kW/m2``), None if it states none; raises on an unknown
    unit."""
    body = line.lstrip("#").strip().lower().replace(" ", "").replace("²", "2").replace("^", "")
    if not body.startswith("unit"):
        return None
    name = body[4:].lstrip(":=")
    if name not in UNITS:
        raise ValueError(f"unknown unit {name!r} (expected W/m2, kW/m2 or MW/m2)")
    return UNITS[name]


def read_flux_limit_csv(path) -> np.ndarray:
    """The allowable flux [W/m^2] of a HALOS-layout CSV (module docstring), [rows, cols] as in the file.

    Raises
    ------
    InputFileError
        One line naming the file and the row/column: unreadable, empty, ragged rows, a value that is not a finite
        number, a limit out of 1 kW/m^2 .. 100 MW/m^2 (after the unit), no unit line on a file in kW/m^2 or MW/m^2.
    """
    text = os.fspath(path)
    try:
        with open(text, encoding="utf-8-sig") as fh:
            lines = fh.read().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(text, f"cannot read the flux-limit map ({exc.__class__.__name__}: {exc})") from None
    factor, rows = None, []
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            try:
                f = _unit_line(stripped)
            except ValueError as exc:
                raise InputFileError(text, str(exc), field=f"line {number}") from None
            factor = factor if f is None else f
            continue
        cells = [c.strip() for c in stripped.rstrip(",").split(",")]
        values = []
        for col, cell in enumerate(cells, start=1):
            try:
                v = float(cell)
            except ValueError:
                v = float("nan")
            if not math.isfinite(v):
                raise InputFileError(text, f"expected a finite number, got {cell!r}",
                                     field=f"row {len(rows) + 1} (line {number}), column {col}")
            values.append(v)
        if rows and len(values) != len(rows[0]):
            raise InputFileError(text, f"{len(values)} columns, the first row has {len(rows[0])}",
                                 field=f"row {len(rows) + 1} (line {number})")
        rows.append(values)
    if not rows:
        raise InputFileError(text, "no rows (expected a table of allowable flux, rows top to bottom)")
    grid = np.asarray(rows, dtype=np.float64)
    if factor is None:
        if grid.max() < RANGE_W_M2[0]:
            raise InputFileError(text, f"the largest limit is {grid.max():g}, below 1 kW/m2 if in W/m2: the file is in "
                                 "kW/m2 (HALOS' unit) or MW/m2; add a first line '# unit: kW/m2' (or MW/m2)")
        factor = 1.0
    grid = grid * factor
    lo, hi = RANGE_W_M2
    bad = np.argwhere((grid < lo) | (grid > hi))
    if bad.size:
        r, c = (int(v) for v in bad[0])
        raise InputFileError(text, f"limit {grid[r, c]:g} W/m2 out of 1 kW/m2 .. 100 MW/m2",
                             field=f"row {r + 1}, column {c + 1}")
    return grid


def _spans(n_from: int, n_to: int):
    """For each of ``n_to`` even cells over [0, 1], the range ``(lo, hi)`` (hi exclusive) of the ``n_from`` even
    cells it overlaps by a positive length (integer arithmetic: exact)."""
    return [((i * n_from) // n_to, -(-((i + 1) * n_from) // n_to)) for i in range(n_to)]


def resample_min(grid: np.ndarray, resolution) -> np.ndarray:
    """``grid`` [R, C] (even cells over the receiver) onto ``resolution = (rows, cols)``: each model cell the minimum
    of the grid cells it overlaps (conservative), [rows, cols]."""
    rows, cols = (int(r) for r in resolution)
    g = np.asarray(grid, dtype=np.float64)
    by_row = np.stack([g[a:b].min(0) for a, b in _spans(g.shape[0], rows)])  # [rows, C]
    return np.stack([by_row[:, a:b].min(1) for a, b in _spans(g.shape[1], cols)], axis=1)


def panel_limit_grid(parsed: dict, resolution) -> np.ndarray:
    """The model-grid map [rows, cols] [W/m^2] of a parsed ``[receiver.flux_limit]`` table
    (:func:`parse_flux_limit_table`)."""
    rows, cols = (int(r) for r in resolution)
    out = resample_min(np.asarray([parsed["panels"]], dtype=np.float64), (rows, cols))
    if parsed["top_bottom"] is not None:
        out[[0, -1]] = np.minimum(out[[0, -1]], parsed["top_bottom"])
    return out


def load_flux_limit(path, resolution) -> FluxLimit:
    """The allowable-flux map of a ``.csv`` (HALOS layout) or ``.toml`` (``[receiver.flux_limit]``) file on the model's
    ``(rows, cols)`` grid (module docstring)."""
    text = os.fspath(path)
    if text.lower().endswith(".toml"):
        try:
            with open(text, "rb") as fh:
                doc = tomllib.load(fh)
        except OSError as exc:
            raise InputFileError(text, f"cannot read ({exc.__class__.__name__}: {exc})") from None
        except tomllib.TOMLDecodeError as exc:
            raise InputFileError(text, f"malformed TOML ({exc})") from None
        table = (doc.get("receiver") or {}).get("flux_limit") if isinstance(doc.get("receiver"), dict) else None
        if table is None:
            raise InputFileError(text, "no [receiver.flux_limit] table", field="receiver.flux_limit")
        grid = panel_limit_grid(parse_flux_limit_table(table, text), resolution)
    else:
        grid = resample_min(read_flux_limit_csv(text), resolution)
    return FluxLimit(torch.as_tensor(grid), os.path.basename(text))


def combine(peak_limit: float | None, limit: FluxLimit | None, resolution) -> FluxLimit:
    """The limit per cell of a peak limit and a map together: the lower of the two in every cell (either may be
    None, not both)."""
    if limit is None:
        return FluxLimit.uniform(float(peak_limit), resolution)
    limit = FluxLimit.of(limit, resolution)
    if peak_limit is None:
        return limit
    return FluxLimit(torch.clamp(limit.cells, max=float(peak_limit)), limit.source)
