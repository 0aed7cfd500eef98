"""An embedded demo plant: a Jülich-like solar tower and a generated heliostat field, no files needed.

The tower is PAINT's Jülich tower (plant WRI1030197): the four targets are built from the surveyed corner
points of PAINT's ``WRI1030197-tower-measurements.json``, converted to ENU about the plant reference and
rounded to the millimetre, with the same constructors the PAINT reader uses
(:meth:`PlanarTarget.from_corners`, :meth:`CylinderTarget.from_outer_corners`). A demo plant and a plant
read from a PAINT download therefore share their targets to about a millimetre.

The field is generated: Jülich-style east-west rows north of the tower, staggered by half a column,
heliostats 4.4 m apart within a row, rows from 22 m to about 150 m north with the row spacing growing
from 4.6 m, within +/-60 m east-west. ``num_heliostats`` of these slots are drawn at random (a seeded
generator, so the plant is a pure function of its arguments), and each heliostat gets small Jülich-like
manufacturing/survey variations (height, actuator zero points, motor ranges). Heliostat ids follow
PAINT's ``<row letters><column>`` pattern (``AA36`` is the first row's slot on the tower's meridian).

Every heliostat is a PAINT/Jülich heliostat: 4 facets of 1.605 m x 1.275 m at
``(+/-0.8075, +/-0.6425, 0.0402)`` m, receiver-canted (each facet tilted like a paraboloid focusing at
the heliostat's slant range to the receiver), two linear actuators with PAINT's values, the concentrator
0.175 m north of joint 2, and ideal (flat, canted) NURBS surfaces.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..atmosphere import Atmosphere
from ..errors import HeliotwinError
from ..site import Site
from .actuators import ACTUATOR_NOMINAL, steps_to_angle
from .facets import ideal_surfaces, receiver_canting
from .layout import Layout, PlantConfig, build_plant
from .plant import Facets, Field, Kinematics, Plant, SunSettings
from .targets import CylinderTarget, PlanarTarget

# ---------------------------------------------------------------------------------------------- tower
#: PAINT tower corners, ENU [m] about the Jülich reference (rounded to mm).
_PLANAR_TARGETS = {
    "solar_tower_juelich_upper": dict(
        center=(-0.0135, -3.2358, 43.0977),
        corners=dict(upper_left=(4.306, -3.244, 46.684), upper_right=(-4.323, -3.227, 46.719),
                     lower_left=(4.311, -3.255, 39.476), lower_right=(-4.310, -3.222, 39.506))),
    "solar_tower_juelich_lower": dict(
        center=(-0.0135, -3.2358, 35.8815),
        corners=dict(upper_left=(4.311, -3.255, 39.476), upper_right=(-4.310, -3.222, 39.506),
                     lower_left=(4.310, -3.258, 32.268), lower_right=(-4.328, -3.202, 32.279))),
    "multi_focus_tower": dict(
        center=(-17.6049, -2.7447, 51.9797),
        corners=dict(upper_left=(-14.894, -2.763, 55.175), upper_right=(-20.306, -2.726, 55.172),
                     lower_left=(-14.904, -2.757, 48.789), lower_right=(-20.316, -2.733, 48.783))),
}
_RECEIVER = dict(
    corners=dict(upper_left=(2.258, 0.684, 57.805), upper_right=(-2.295, 0.736, 57.820),
                 lower_left=(2.218, -1.741, 52.596), lower_right=(-2.286, -1.715, 52.592)),
    normal=(0.0, 0.90630779, -0.42261826), radius=4.14, opening_angle_deg=60.0)


def demo_targets() -> dict:
    """The Jülich tower's targets (PAINT geometry), float64.

    Returns
    -------
    dict of str -> PlanarTarget | CylinderTarget
        ``solar_tower_juelich_upper`` (centre ~(0, -3.24, 43.1) m, 8.6 m x 7.2 m),
        ``solar_tower_juelich_lower`` (~(0, -3.24, 35.9) m), ``multi_focus_tower`` (~(-17.6, -2.75, 52.0) m,
        5.4 m x 6.4 m), all facing north (normal (0, 1, 0)); and the cylindrical ``receiver`` (radius
        4.14 m, 60 deg opening, aperture normal (0, 0.906, -0.423), apex ~(0, 0, 55.0) m).
    """
    out = {}
    for name, spec in _PLANAR_TARGETS.items():
        out[name] = PlanarTarget.from_corners(name, spec["corners"], (0.0, 1.0, 0.0), spec["center"])
    r = _RECEIVER
    out["receiver"] = CylinderTarget.from_outer_corners("receiver", r["corners"], r["normal"], r["radius"],
                                                        math.radians(r["opening_angle_deg"]))
    return out


# ------------------------------------------------------------------------------------------ heliostat
#: PAINT / Jülich facet layout (heliostat frame [m]); PAINT order (-e,+n), (+e,+n), (-e,-n), (+e,-n).
FACET_TRANSLATIONS = ((-0.8075, 0.6425, 0.0402), (0.8075, 0.6425, 0.0402),
                      (-0.8075, -0.6425, 0.0402), (0.8075, -0.6425, 0.0402))
FACET_HALF_WIDTH = 0.8025  #: [m] half-span along east (PAINT ``|canting_e|``)
FACET_HALF_HEIGHT = 0.6375  #: [m] half-span along north (PAINT ``|canting_n|``)
HELIOSTAT_WIDTH, HELIOSTAT_HEIGHT = 3.22, 2.56  #: [m] PAINT ``width`` / ``height``

CONCENTRATOR_TRANSLATION = (0.0, 0.175, 0.0)  #: [m] joint 2 -> concentrator, heliostat frame

# Field layout
_ROW0_NORTH, _ROW_SPACING0, _ROW_SPACING_GROWTH = 22.0, 4.6, 0.04  # [m], [m], [m/m]
_COLUMN_SPACING, _HALF_WIDTH, _FIELD_DEPTH = 4.4, 60.0, 150.0  # [m]
_CENTRE_COLUMN = 36  # PAINT-like column number of the slot on the tower meridian


def _row_letters(k: int) -> str:
    return chr(ord("A") + k // 26) + chr(ord("A") + k % 26)


def _slots(num_heliostats: int) -> list[tuple[int, int, float, float]]:
    """Candidate slots ``(row, column, east, north)``: all rows up to ~150 m north, more if needed."""
    slots, row, north = [], 0, _ROW0_NORTH
    while north <= _FIELD_DEPTH or len(slots) < num_heliostats:
        if row >= 26 * 26:
            raise HeliotwinError(f"demo_plant: num_heliostats={num_heliostats} does not fit the demo field layout")
        shift = 0.5 * _COLUMN_SPACING if row % 2 else 0.0
        cmax = int(math.floor((_HALF_WIDTH - shift) / _COLUMN_SPACING))
        cmin = -int(math.floor((_HALF_WIDTH + shift) / _COLUMN_SPACING))
        for c in range(cmin, cmax + 1):
            slots.append((row, c + _CENTRE_COLUMN, c * _COLUMN_SPACING + shift, north))
        north += _ROW_SPACING0 + _ROW_SPACING_GROWTH * (north - _ROW0_NORTH)
        row += 1
    return slots


def demo_plant(num_heliostats: int = 32, seed: int = 0, *, num_control_points: tuple[int, int] = (4, 4),
               degree: tuple[int, int] = (2, 2)) -> Plant:
    """A Jülich-like plant generated in code (deterministic in ``seed``; no global RNG is touched).

    Parameters
    ----------
    num_heliostats : int
        H >= 1. Slots are drawn from the ~500 of the 22-150 m x +/-60 m field (rows beyond 150 m are
        added when H is larger).
    seed : int
        Seed of the private ``numpy.random.Generator`` that picks slots and per-heliostat variations.
    num_control_points, degree : (int, int)
        NURBS resolution of the ideal facet surfaces.

    Returns
    -------
    Plant
        Site = Jülich reference; targets from :func:`demo_targets`; field of H heliostats sorted by id
        with float64 kinematics/facets ([H, 2], [H, 4, 3]) and ideal surfaces [H, 4, nu, nv, 3];
        default :class:`SunSettings`.

    Notes
    -----
    Per-heliostat variations (uniform): pivot height 1.45-1.80 m above the reference, 3 cm (std) survey
    jitter in east/north, initial joint angles +/-10 mrad and initial strokes +/-2 mm about PAINT's
    values, motor ranges 0 to 68400-69600 (axis 1) and 74400-76100 (axis 2) steps. ``min_angle`` /
    ``max_angle`` are the joint angles at the ends of the motor range. Facets are canted to the slant
    range from the pivot to the receiver apex.
    """
    if isinstance(num_heliostats, bool) or not isinstance(num_heliostats, (int, np.integer)) or num_heliostats < 1:
        raise HeliotwinError(f"demo_plant: num_heliostats must be a positive int, got {num_heliostats!r}")
    h = int(num_heliostats)
    rng = np.random.default_rng(seed)
    slots = _slots(h)
    pick = np.sort(rng.choice(len(slots), size=h, replace=False))
    chosen = [slots[i] for i in pick]
    ids = [f"{_row_letters(r)}{c:02d}" for r, c, _, _ in chosen]

    f64 = dict(dtype=torch.float64)
    east = np.array([s[2] for s in chosen]) + rng.normal(0.0, 0.03, h)
    north = np.array([s[3] for s in chosen]) + rng.normal(0.0, 0.03, h)
    up = rng.uniform(1.45, 1.80, h)
    position = torch.tensor(np.stack((east, north, up), axis=-1), **f64)

    def per_axis(nominal, spread):
        return torch.tensor(np.asarray(nominal)[None, :] + rng.uniform(-spread, spread, (h, 2)), **f64)

    def constant(nominal):
        return torch.tensor(nominal, **f64).expand(h, len(nominal)).clone()

    initial_angle = per_axis(ACTUATOR_NOMINAL["initial_angle"], 0.010)
    initial_stroke = per_axis(ACTUATOR_NOMINAL["initial_stroke_length"], 0.002)
    max_steps = torch.tensor(np.stack((rng.integers(68400, 69601, h), rng.integers(74400, 76101, h)), axis=-1), **f64)
    min_steps = torch.zeros(h, 2, **f64)
    clockwise = torch.tensor([[False, True]]).expand(h, 2).clone()
    linear = torch.ones(h, 2, dtype=torch.bool)
    act = dict(increment=constant(ACTUATOR_NOMINAL["increment"]), offset=constant(ACTUATOR_NOMINAL["offset"]),
               pivot_radius=constant(ACTUATOR_NOMINAL["pivot_radius"]), initial_angle=initial_angle,
               initial_stroke_length=initial_stroke)
    ends = torch.stack([steps_to_angle(s, clockwise=clockwise, linear=linear, **act) for s in (min_steps, max_steps)])
    kinematics = Kinematics(
        position=position,
        joint_translation=torch.zeros(h, 2, 3, **f64),
        concentrator_translation=constant(CONCENTRATOR_TRANSLATION),
        joint_tilt=torch.zeros(h, 2, 3, **f64),
        concentrator_tilt=torch.zeros(h, 3, **f64),
        clockwise=clockwise, linear=linear, min_steps=min_steps, max_steps=max_steps,
        min_angle=ends.amin(0), max_angle=ends.amax(0), **act)

    targets = demo_targets()
    slant = torch.linalg.vector_norm(targets["receiver"].center - position, dim=-1)
    translation = torch.tensor(FACET_TRANSLATIONS, **f64).expand(h, -1, -1).clone()
    canting_e, canting_n = receiver_canting(translation, FACET_HALF_WIDTH, FACET_HALF_HEIGHT, slant)
    facets = Facets(translation, canting_e, canting_n)
    surfaces = ideal_surfaces(facets, num_control_points=num_control_points, degree=degree)
    field = Field(ids, kinematics, facets, surfaces, torch.full((h,), HELIOSTAT_WIDTH, **f64),
                  torch.full((h,), HELIOSTAT_HEIGHT, **f64), [""] * h)
    return Plant(Site(), targets, field, SunSettings())


# ------------------------------------------------------------------------------------------ whole field
def demo_field_positions(num_heliostats: int = 2000, *, first_ring: float = 27.5, tower_height: float = 55.0,
                         width: float = HELIOSTAT_WIDTH, height: float = HELIOSTAT_HEIGHT,
                         design_sun_elevation_deg: float = 40.0, azimuth_pitch: float = 2.0, zone_reset: float = 1.4,
                         half_span_deg: float = 60.0, max_east: float | None = None) -> torch.Tensor:
    """A radial-staggered field north of the tower, spaced so that blocking costs a few per cent.

    Rings from ``first_ring`` within +/-``half_span_deg`` of north (and ``|east| <= max_east`` when given),
    as many as the count needs. :func:`demo_field_plant` keeps Jülich's extent (PAINT: rows from ~25 m to
    ~300 m north within about +/-130 m east-west, ``max_east=135``) for up to 2200 heliostats: 2000 reach
    ~285 m.

    * **Along a ring** the heliostats are ``azimuth_pitch`` mirror widths apart when a zone starts (a gap of
      one mirror width lets the reflected beam pass between the two staggered heliostats of the ring ahead);
      the angular pitch is kept through the zone, so the arc spacing grows with the radius, and a new zone
      with the nominal spacing starts when it exceeds ``zone_reset`` times it (DELSOL's and SolarPILOT's
      "slip planes").
    * **Between rings** the pitch is half the distance at which a heliostat straight ahead (two rings ahead,
      staggered) stops blocking at solar noon with the sun at ``design_sun_elevation_deg``: the beam from the
      lower edge, rising at the tower's elevation ``phi``, clears the upper edge of the one ahead when
      ``D >= h (sin e + cos e / tan phi)`` with ``e = (phi + design elevation) / 2`` the normal's elevation;
      and at least the distance at which two mirrors cannot collide (two half diagonals apart: against the
      staggered neighbours of the next ring and the one straight ahead two rings on). A new zone's first ring
      is not staggered against the last one: it keeps the full no-blocking distance and a full diagonal.

    Parameters
    ----------
    num_heliostats : int
        H >= 1.
    first_ring, tower_height, width, height : float
        [m]; ``tower_height`` is the receiver's height above the pivots.
    design_sun_elevation_deg, half_span_deg : float
        [deg].
    azimuth_pitch, zone_reset : float
        Arc spacing at a zone's start in mirror widths [1], and the ratio of arc spacing to it that starts a
        new zone [1].
    max_east : float, optional
        [m].

    Returns
    -------
    torch.Tensor, [H, 3], float64
        ENU [m] about the tower base (pivots on the ground, z = 0), ring by ring from the tower.
    """
    if isinstance(num_heliostats, bool) or not isinstance(num_heliostats, (int, np.integer)) or num_heliostats < 1:
        raise HeliotwinError(f"demo_field_positions: num_heliostats must be a positive int, got {num_heliostats!r}")
    out, r, ring, pitch = [], float(first_ring), 0, None
    collide = math.hypot(width, height)  # two half diagonals
    span = math.radians(half_span_deg)
    arc = azimuth_pitch * width
    while len(out) < num_heliostats:
        if pitch is None or r * pitch > zone_reset * arc:
            pitch, ring = arc / r, 0
        a = np.arange(-span + 0.5 * pitch * (1 + ring % 2), span, pitch)
        x, y = r * np.sin(a), r * np.cos(a)
        keep = np.abs(x) <= (np.inf if max_east is None else max_east)
        out.extend(zip(x[keep], y[keep], np.zeros(int(keep.sum()))))
        phi = math.atan2(tower_height, r)
        e = 0.5 * (phi + math.radians(design_sun_elevation_deg))
        clear = 0.5 * height * (math.sin(e) + math.cos(e) / math.tan(phi))
        stagger = math.sqrt(max(collide ** 2 - (0.5 * r * pitch) ** 2, 0.0))
        step = max(clear, stagger, 0.5 * collide)  # 0.5 collide: the one straight ahead is two rings ahead
        if (r + step) * pitch > zone_reset * arc:  # the next ring starts a zone: no stagger to rely on
            step = max(step, collide, 2.0 * clear)
        r += step
        ring += 1
        if r > 40.0 * tower_height:
            raise HeliotwinError(f"demo_field_positions: {num_heliostats} heliostats do not fit within "
                                 f"{40 * tower_height:.0f} m of the tower (widen half_span_deg or max_east)")
    return torch.tensor(np.asarray(out[:num_heliostats], dtype=np.float64))


def demo_field_plant(num_heliostats: int = 2000):
    """The embedded whole-field demo plant and its atmosphere: :func:`demo_field_positions` (Jülich's extent,
    ``|east| <= 135 m``, up to 2200 heliostats; the full +/-60 degree fan beyond) with Jülich-size
    heliostats (2 x 2 facets canted on-axis at their slant range, reflectivity 0.9, 1.53 mrad slope error)
    around an external 360-degree cylinder receiver (radius 4.1 m, height 5 m, centre 55 m up), the
    limb-darkened sun at DNI 900 W/m^2 and SolarPILOT's default atmosphere.

    Returns
    -------
    plant : Plant
    atmosphere : heliotwin.atmosphere.Atmosphere
    """
    pos = demo_field_positions(num_heliostats, max_east=135.0 if num_heliostats <= 2200 else None)
    ids = [f"R{i:05d}" for i in range(pos.shape[0])]
    sun = SunSettings(sunshape="limb-darkened", slope_error=1.53e-3, dni=900.0, reflectivity=0.9)
    receiver = {"type": "cylinder", "center": [0.0, 0.0, 55.0], "height": 5.0, "normal": None, "radius": 4.1,
                "opening_angle": 2 * math.pi}
    config = PlantConfig(Site(), HELIOSTAT_WIDTH, HELIOSTAT_HEIGHT, (2, 2), "on-axis", None, receiver, sun,
                         Atmosphere())
    return build_plant(Layout(ids, pos, list(range(len(ids))), "demo"), config), config.atmosphere
