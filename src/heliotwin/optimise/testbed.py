"""Generated plants for testing aim points on fields nobody tuned the optimiser to.

:func:`generated_plant` builds a plant from a few words: a layout (radial-staggered north field, surround
field, Jülich-style grid), a receiver (vertical full cylinder, vertical flat panel, tilted flat panel, or the
Jülich-like tilted 60-degree cylinder segment), a tower height and a receiver size. Every heliostat is a
Jülich-size 2 x 2 facet heliostat canted on-axis at its slant range; the sun is the limb-darkened one at DNI
900 W/m^2 with 1.53 mrad slope error. The plant is a pure function of the arguments (no random draws).

Used by ``benchmarks/bench_aimpoints.py`` (the test bed's table) and the aim-point tests. :func:`flux_limit_map`
gives the test bed's allowable-flux maps (a HALOS-like map and a flow-path derating), shaped on the model's grid
and scaled per case so that they bind (``--testbed --flux-maps``).

>>> plant, atmosphere = generated_plant("radial", 40, "tilted-cylinder", tower=55.0)
>>> len(plant.field.ids), plant.targets["receiver"].kind
(40, 'cylinder')
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..atmosphere import Atmosphere
from ..errors import HeliotwinError
from ..field.demo import HELIOSTAT_HEIGHT, HELIOSTAT_WIDTH, demo_field_positions
from ..field.layout import Layout, PlantConfig, build_plant
from ..field.plant import Plant, SunSettings
from ..site import Site
from .fluxmap import panel_limit_grid, resample_min
from .problem import FluxLimit

__all__ = ["LAYOUTS", "RECEIVERS", "FLUX_MAPS", "generated_plant", "field_positions", "flux_limit_map",
           "scaled_to_bind"]

LAYOUTS = ("radial", "surround", "grid")
RECEIVERS = ("cylinder", "flat", "tilted-flat", "tilted-cylinder")
TILT_DEG = 25.0  #: downward tilt of the tilted receivers' normals [deg] (Jülich's receiver: ~25 deg)
#: The test bed's allowable-flux map shapes (:func:`flux_limit_map`).
FLUX_MAPS = ("halos", "flow-path")
#: HALOS' middle band [W/m^2]: blocks of columns across (around) the receiver, and its top and bottom rows.
HALOS_BAND_W_M2 = (0.6e6, 0.8e6, 1.0e6, 1.2e6, 1.0e6, 0.8e6, 0.6e6)
HALOS_EDGE_W_M2 = 0.3e6
#: The flow-path map: 8 panels at 1 MW/m^2, the fluid passing them left to right, derated linearly to 0.33 of the
#: limit at the hot outlet.
FLOW_PANELS, FLOW_OUTLET = 8, 0.33


def field_positions(layout: str, heliostats: int, tower: float) -> torch.Tensor:
    """Pivot positions [H, 3] ENU [m] about the tower base (z = 0).

    ``radial``: radial-staggered rings within +/-60 deg of north from half the tower height out
    (:func:`heliotwin.field.demo.demo_field_positions`, DELSOL-style slip planes); ``surround``: the same all
    around the tower; ``grid``: east-west rows north of the tower, staggered by half a column, 2 mirror widths
    apart, rows 2 mirror heights apart plus 4 % of their distance, within +/-0.9 tower heights east-west
    (widening as the rows move out).
    """
    if layout == "radial":
        return demo_field_positions(heliostats, first_ring=0.5 * tower, tower_height=tower)
    if layout == "surround":
        return demo_field_positions(heliostats, first_ring=0.5 * tower, tower_height=tower, half_span_deg=180.0)
    if layout == "grid":
        out, y, row = [], 0.4 * tower, 0
        pitch = 2.0 * HELIOSTAT_WIDTH
        while len(out) < heliostats:
            half = 0.9 * tower + 0.6 * (y - 0.4 * tower)
            xs = np.arange(-half + 0.5 * pitch * (row % 2), half + 1e-9, pitch)
            out.extend((float(x), y, 0.0) for x in xs)
            y += 2.0 * HELIOSTAT_HEIGHT + 0.04 * y
            row += 1
        return torch.tensor(np.asarray(out[:heliostats], dtype=np.float64))
    raise HeliotwinError(f"unknown layout {layout!r}; expected one of {', '.join(LAYOUTS)}")


def generated_plant(layout: str = "radial", heliostats: int = 300, receiver: str = "cylinder", *,
                    tower: float = 55.0, size: float = 1.0) -> tuple[Plant, Atmosphere]:
    """A plant of ``heliostats`` Jülich-size heliostats in ``layout`` around a ``receiver`` on a tower.

    Parameters
    ----------
    layout : {"radial", "surround", "grid"}
        See :func:`field_positions`.
    heliostats : int
        H >= 1.
    receiver : {"cylinder", "flat", "tilted-flat", "tilted-cylinder"}
        ``cylinder``: a vertical 360-degree cylinder; ``flat``: a vertical panel facing the field;
        ``tilted-flat``: that panel tilted :data:`TILT_DEG` down towards the field; ``tilted-cylinder``: a
        60-degree cylinder segment whose axis leans :data:`TILT_DEG` towards the field (Jülich's receiver).
    tower : float
        Height of the receiver's centre above the pivots [m].
    size : float
        Receiver scale [1]: height ``5 m x size x (H / 2000)^(1/4)``; cylinder radius 0.82 x the height,
        panel width 1.2 x the height, the segment's radius 0.83 x the height.

    Returns
    -------
    plant : Plant
    atmosphere : Atmosphere
        SolarPILOT's default.
    """
    if receiver not in RECEIVERS:
        raise HeliotwinError(f"unknown receiver {receiver!r}; expected one of {', '.join(RECEIVERS)}")
    pos = field_positions(layout, int(heliostats), float(tower))
    height = 5.0 * float(size) * (int(heliostats) / 2000.0) ** 0.25
    towards = pos[:, :2].mean(0)
    if layout == "surround":  # a surround field: the receiver's reference side faces north
        towards = torch.tensor([0.0, 1.0], dtype=torch.float64)
    towards = towards / torch.linalg.vector_norm(towards)
    t = math.radians(TILT_DEG)
    horizontal = [float(towards[0]), float(towards[1]), 0.0]
    tilted = [math.cos(t) * horizontal[0], math.cos(t) * horizontal[1], -math.sin(t)]
    centre = [0.0, 0.0, float(tower)]
    if receiver == "cylinder":
        spec = {"type": "cylinder", "center": centre, "height": height, "normal": None, "radius": 0.82 * height,
                "opening_angle": 2 * math.pi}
    elif receiver == "tilted-cylinder":
        axis = [math.sin(t) * horizontal[0], math.sin(t) * horizontal[1], math.cos(t)]
        spec = {"type": "cylinder", "center": centre, "height": height, "normal": tilted, "axis": axis,
                "radius": 0.83 * height, "opening_angle": math.radians(60.0)}
    else:
        spec = {"type": "planar", "center": centre, "height": height, "width": 1.2 * height,
                "normal": horizontal if receiver == "flat" else tilted}
    sun = SunSettings(sunshape="limb-darkened", slope_error=1.53e-3, dni=900.0, reflectivity=0.9)
    config = PlantConfig(Site(), HELIOSTAT_WIDTH, HELIOSTAT_HEIGHT, (2, 2), "on-axis", None, spec, sun,
                         Atmosphere())
    ids = [f"G{i:05d}" for i in range(pos.shape[0])]
    return build_plant(Layout(ids, pos, list(range(len(ids))), f"generated-{layout}"), config), config.atmosphere


def flux_limit_map(kind: str, resolution) -> np.ndarray:
    """An allowable-flux map shape [rows, cols] [W/m^2] on the model's grid (row 0 = top).

    ``halos``: HALOS' ``allowable_flux.csv`` shape, :data:`HALOS_EDGE_W_M2` on the top and bottom rows, the middle
    band :data:`HALOS_BAND_W_M2` in seven equal blocks of columns (resampled conservatively: a column over two
    blocks takes the lower). ``flow-path``: :data:`FLOW_PANELS` panels at 1 MW/m^2 derated linearly along the flow
    (left to right) to :data:`FLOW_OUTLET` at the outlet (:func:`heliotwin.optimise.fluxmap.panel_limit_grid`).
    """
    rows, cols = (int(r) for r in resolution)
    if kind == "halos":
        out = resample_min(np.asarray([HALOS_BAND_W_M2]), (rows, cols))
        out[[0, -1]] = HALOS_EDGE_W_M2
        return out
    if kind == "flow-path":
        derating = np.linspace(1.0, FLOW_OUTLET, FLOW_PANELS)
        return panel_limit_grid({"panels": list(1e6 * derating), "top_bottom": None}, (rows, cols))
    raise HeliotwinError(f"unknown flux map {kind!r}; expected one of {', '.join(FLUX_MAPS)}")


def scaled_to_bind(shape: np.ndarray, equator_flux, fraction: float, source: str = "map") -> FluxLimit:
    """``shape`` [rows, cols] scaled so that equator aiming's map ``equator_flux`` [rows, cols] [W/m^2] exceeds it by
    ``1 / fraction``: its largest ``flux / limit`` is ``1 / fraction`` (``fraction`` [-] < 1: the limit binds), as
    the test bed's flat limits are ``fraction`` x the equator peak. The limit's cells are in [W/m^2]."""
    cells = torch.as_tensor(np.asarray(shape, dtype=np.float64))
    scale = float((equator_flux.detach().cpu().to(torch.float64) / cells).max()) * float(fraction)
    return FluxLimit(cells * scale, source)
