"""The receiver's allowable flux per panel as plant data: the checked ``[receiver.flux_limit]`` table of a plant TOML.

The plant file reader (:mod:`heliotwin.field.layout`) checks the table when it reads the plant, and
``aimpoints``/``daily --flux-limit plant.toml`` (:mod:`heliotwin.optimise.fluxmap`) turns it into a map on the
model's grid; both read it through :func:`parse_flux_limit_table`, which lives on the plant's floor so that the
plant reader does not stand on the optimiser. The table's keys are documented in :mod:`heliotwin.optimise.fluxmap`.
"""
from __future__ import annotations

from ..errors import InputFileError

__all__ = ["RANGE_W_M2", "TOML_KEYS", "parse_flux_limit_table"]

#: Plausible limits on one cell [W/m^2], and on ``--peak-limit`` (``heliotwin.optimise.aimstate.PEAK_LIMIT_RANGE_W_M2``
#: explains the bounds).
RANGE_W_M2 = (1e3, 1e8)
#: Keys of the TOML's ``[receiver.flux_limit]`` table.
TOML_KEYS = ("panels_w_m2", "flow_path", "derating", "top_bottom_w_m2")


def parse_flux_limit_table(table, path, where: str = "receiver.flux_limit") -> dict:
    """The checked ``[receiver.flux_limit]`` table: ``{"panels": [N] W/m^2 (derated along the flow path),
    "top_bottom": W/m^2 or None}``; one-line :class:`InputFileError` naming the file and key otherwise."""
    if not isinstance(table, dict):
        raise InputFileError(path, "expected a table", field=where)
    unknown = sorted(set(table) - set(TOML_KEYS))
    if unknown:
        raise InputFileError(path, f"unknown key (expected {', '.join(TOML_KEYS)})", field=f"{where}.{unknown[0]}")

    def numbers(key, n=None):
        v = table.get(key)
        if not isinstance(v, list) or not v or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                       for x in v):
            raise InputFileError(path, "expected a non-empty list of numbers", field=f"{where}.{key}")
        if n is not None and len(v) != n:
            raise InputFileError(path, f"expected {n} entries (one per panel), got {len(v)}", field=f"{where}.{key}")
        return [float(x) for x in v]

    if "panels_w_m2" not in table:
        raise InputFileError(path, "missing key (one limit per panel [W/m2])", field=f"{where}.panels_w_m2")
    panels = numbers("panels_w_m2")
    n = len(panels)
    lo, hi = RANGE_W_M2
    for i, v in enumerate(panels):
        if not lo <= v <= hi:
            raise InputFileError(path, f"limit {v:g} W/m2 out of 1 kW/m2 .. 100 MW/m2 (W/m2, not kW/m2?)",
                                 field=f"{where}.panels_w_m2[{i}]")
    flow = list(range(n))
    if "flow_path" in table:
        v = table["flow_path"]
        if not isinstance(v, list) or sorted(x if isinstance(x, int) and not isinstance(x, bool) else -1
                                             for x in v) != list(range(n)):
            raise InputFileError(path, f"expected each panel index 0..{n - 1} once", field=f"{where}.flow_path")
        flow = list(v)
    derating = numbers("derating", n) if "derating" in table else [1.0] * n
    for i, d in enumerate(derating):
        if not 0.0 < d <= 1.0:
            raise InputFileError(path, f"expected a factor in (0, 1], got {d:g}", field=f"{where}.derating[{i}]")
    derated = [0.0] * n
    for step, panel in enumerate(flow):
        derated[panel] = panels[panel] * derating[step]
    if min(derated) < lo:
        raise InputFileError(path, f"a derated limit {min(derated):g} W/m2 is below 1 kW/m2", field=f"{where}.derating")
    top = table.get("top_bottom_w_m2")
    if top is not None and (isinstance(top, bool) or not isinstance(top, (int, float)) or not lo <= top <= hi):
        raise InputFileError(path, "expected a limit [W/m2] in 1 kW/m2 .. 100 MW/m2", field=f"{where}.top_bottom_w_m2")
    return {"panels": derated, "top_bottom": None if top is None else float(top)}
