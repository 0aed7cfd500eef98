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

from ..errors import HeliotwinError
from ..site import Site
from .actuators import steps_to_angle
from .facets import ideal_surfaces
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

#: Nominal PAINT/Jülich linear actuators, per axis.
ACTUATOR_NOMINAL = dict(increment=(154166.6667, 154166.6667), offset=(0.335308, 0.340771),
                        pivot_radius=(0.338095, 0.3191), initial_angle=(0.039009536, 0.943922248),
                        initial_stroke_length=(0.077412795, 0.077522286))
CONCENTRATOR_TRANSLATION = (0.0, 0.175, 0.0)  #: [m] joint 2 -> concentrator, heliostat frame

# Field layout
_ROW0_NORTH, _ROW_SPACING0, _ROW_SPACING_GROWTH = 22.0, 4.6, 0.04  # [m], [m], [m/m]
_COLUMN_SPACING, _HALF_WIDTH, _FIELD_DEPTH = 4.4, 60.0, 150.0  # [m]
_CENTRE_COLUMN = 36  # PAINT-like column number of the slot on the tower meridian


def receiver_canting(translation: torch.Tensor, half_width: float, half_height: float,
                     focal_length: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Canting span vectors of facets tilted to focus at ``focal_length`` (on-axis "receiver canting").

    Each flat facet's normal is set to the normal of the paraboloid ``z = (x^2 + y^2) / (4 f)`` at the
    facet centre, ``normalize(-t_x / (2 f), -t_y / (2 f), 1)``, by the rotation ``R_N(beta) R_E(alpha)``
    (PAINT's construction: ``canting_e`` keeps a zero north component).

    Parameters
    ----------
    translation : torch.Tensor, [..., F, 3]
        Facet centres, heliostat frame [m].
    half_width, half_height : float
        Half-spans along east / north [m].
    focal_length : torch.Tensor, [...]
        Focal distance per heliostat [m].

    Returns
    -------
    canting_e, canting_n : torch.Tensor, [..., F, 3]
        Half-span vectors [m] (lengths ``half_width`` / ``half_height``).
    """
    f = focal_length[..., None]
    n = torch.stack((-translation[..., 0] / (2 * f), -translation[..., 1] / (2 * f),
                     torch.ones_like(translation[..., 0])), dim=-1)
    n = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)
    sin_a = -n[..., 1]
    cos_a = torch.sqrt(1.0 - sin_a * sin_a)
    beta = torch.atan2(n[..., 0], n[..., 2])
    sin_b, cos_b = torch.sin(beta), torch.cos(beta)
    zero = torch.zeros_like(sin_a)
    e = torch.stack((cos_b, zero, -sin_b), dim=-1)  # R_N(beta) R_E(alpha) e_x
    nn = torch.stack((sin_b * sin_a, cos_a, cos_b * sin_a), dim=-1)  # R_N(beta) R_E(alpha) e_y
    return half_width * e, half_height * nn


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
        In mirror widths, and the ratio that starts a new zone.
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
    from ..atmosphere import Atmosphere
    from .layout import Layout, PlantConfig, build_plant

    pos = demo_field_positions(num_heliostats, max_east=135.0 if num_heliostats <= 2200 else None)
    ids = [f"R{i:05d}" for i in range(pos.shape[0])]
    sun = SunSettings(sunshape="limb-darkened", slope_error=1.53e-3, dni=900.0, reflectivity=0.9)
    receiver = {"type": "cylinder", "center": [0.0, 0.0, 55.0], "height": 5.0, "normal": None, "radius": 4.1,
                "opening_angle": 2 * math.pi}
    config = PlantConfig(Site(), HELIOSTAT_WIDTH, HELIOSTAT_HEIGHT, (2, 2), "on-axis", None, receiver, sun,
                         Atmosphere())
    return build_plant(Layout(ids, pos, list(range(len(ids))), "demo"), config), config.atmosphere


def run_field_demo(out, *, num_heliostats: int = 2000, time_utc: str = "2023-03-20T11:30:00Z",
                   peak_limit_fraction: float = 0.75, iterations: int | None = None,
                   progress: bool = False, device: str = "cpu") -> dict:
    """The demo as the whole field: efficiency map, loss breakdown, receiver flux before/after aim points.

    On :func:`demo_field_plant` at ``time_utc``: the field model with exact shading and blocking
    (:func:`heliotwin.raytrace.field.field_optics`, Gaussian footprints on the 48 x 20 receiver map) at
    equator aiming, then :func:`heliotwin.optimise.aimpoints.optimise_aimpoints` for a peak limit of
    ``peak_limit_fraction`` times equator aiming's peak (re-judged with exact occlusion).

    Parameters
    ----------
    out : path
        Folder (created when missing) for ``field_efficiency.png`` (per-heliostat efficiency),
        ``losses.png`` (power-weighted loss breakdown), ``flux_equator.png`` and ``flux_optimised.png``
        (receiver maps [kW/m^2]), ``heliostats.csv`` (per-heliostat factors, the ``field`` command's
        columns) and ``summary.json``.
    num_heliostats : int
    time_utc : str
        Instant of the sun position (pvlib at the Jülich reference); the sun must be up.
    peak_limit_fraction : float
        In (0, 1].
    iterations : int, optional
        Image-model steps per round of the aim-point optimiser (default: the optimiser's).
    progress : bool
        A progress bar over the stages.
    device : str
        Where the field model and the aim points run (``auto``: CUDA when present); results on the CPU.

    Returns
    -------
    dict
        The summary (also written as JSON): the ``field`` command's report (``field.efficiency`` unweighted as
        SolarPILOT and power-weighted, ``receiver``), ``losses`` (per factor: power-weighted fraction and
        [W]), ``aim_points`` (limit, peaks before/after, violation, power ratio), ``seconds`` per stage.
    """
    import time
    from pathlib import Path

    import pandas as pd
    from tqdm.auto import tqdm

    from ..io.report import write_json
    from ..optimise.aimpoints import optimise_aimpoints
    from ..raytrace.field import field_optics, per_heliostat_rows, summary
    from ..sun import direction_from_time

    if not 0.0 < float(peak_limit_fraction) <= 1.0:
        raise HeliotwinError(f"run_field_demo: peak_limit_fraction must be in (0, 1], got {peak_limit_fraction!r}")
    t_start = time.perf_counter()
    folder = Path(out)
    seconds = {}
    bar = tqdm(total=4, desc="demo: whole field", unit="stage", disable=not progress)
    from ..devices import resolve_device, to_device

    plant, atm = demo_field_plant(num_heliostats)
    s = plant.site
    sun = direction_from_time(pd.DatetimeIndex([pd.Timestamp(time_utc)]), s.latitude_deg, s.longitude_deg,
                              s.altitude_m)[0]
    device = resolve_device(device)
    plant_cpu, plant, sun = plant, to_device(plant, device), sun.to(device)
    t0 = time.perf_counter()
    with torch.no_grad():
        before = to_device(field_optics(plant, sun, atmosphere=atm), "cpu")
    seconds["field_model"] = time.perf_counter() - t0
    rep = summary(before, plant_cpu)
    bar.update()
    limit = float(peak_limit_fraction) * rep["receiver"]["peak_flux_w_m2"]
    t0 = time.perf_counter()
    steps = {} if iterations is None else {"iterations": int(iterations)}
    aimed = to_device(optimise_aimpoints(plant, sun, limit, atmosphere=atm, **steps), "cpu")
    seconds["aim_points"] = time.perf_counter() - t0
    bar.update()
    folder.mkdir(parents=True, exist_ok=True)
    rep["losses"] = _loss_breakdown(before)
    t0 = time.perf_counter()
    _demo_figures(folder, plant_cpu, before, aimed, rep, limit, time_utc)
    _write_rows(folder / "heliostats.csv", per_heliostat_rows(before, plant_cpu))
    seconds["outputs"] = time.perf_counter() - t0
    bar.update()
    seconds["total"] = time.perf_counter() - t_start
    rep.update({"plant": "embedded Jülich-like field (heliotwin.field.demo.demo_field_plant)", "time_utc": time_utc,
                "aim_points": {
                    "peak_limit_w_m2": limit, "equator_peak_w_m2": rep["receiver"]["peak_flux_w_m2"],
                    "optimised_peak_w_m2": aimed.peak_flux_w_m2, "violation": aimed.violation(limit),
                    "equator_power_w": rep["receiver"]["power_w"], "optimised_power_w": aimed.power_w,
                    "power_vs_equator": aimed.power_w / rep["receiver"]["power_w"], "iterations": aimed.iterations},
                "seconds": seconds,
                "files": ["field_efficiency.png", "losses.png", "flux_equator.png", "flux_optimised.png",
                          "heliostats.csv", "summary.json"]})
    write_json(folder / "summary.json", rep)
    bar.update()
    bar.close()
    return rep


def _loss_breakdown(result) -> dict:
    """Per factor of the chain (cosine, shading, blocking, attenuation, intercept, reflectance): the
    power-weighted fraction lost at that stage and the power [W] it costs (they add up to DNI x area - power)."""
    from ..raytrace.field import FACTORS

    stage = result.dni * result.mirror_area.to(torch.float64)
    out = {}
    for name in FACTORS:
        f = getattr(result, name).to(torch.float64)
        lost = float((stage * (1.0 - f)).sum())
        out[name] = {"fraction": lost / max(float(stage.sum()), 1e-30), "power_w": lost}
        stage = stage * f
    out["tower_shading_unweighted_mean"] = float(result.tower_shading.mean())
    return out


def _write_rows(path, rows: list[dict]) -> None:
    import csv

    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def _demo_figures(folder, plant, before, aimed, rep, limit: float, time_utc: str) -> None:
    """The four demo figures (colour bars, titles, units)."""
    from matplotlib.figure import Figure

    from ..io.report import save_figure
    from ..raytrace.field import FACTORS

    pos = plant.field.kinematics.position.numpy()
    sun = rep["sun"]
    e = rep["field"]["efficiency_power_weighted"]
    fig = Figure(figsize=(7, 6))
    ax = fig.add_subplot()
    sc = ax.scatter(pos[:, 0], pos[:, 1], c=before.efficiency.numpy(), s=5, cmap="viridis")
    ax.plot([0.0], [0.0], marker="^", color="k", markersize=8, linestyle="none", label="tower")
    fig.colorbar(sc, ax=ax, label="optical efficiency per heliostat [-]")
    ax.set(xlabel="east [m]", ylabel="north [m]", aspect="equal",
           title=f"{len(pos)} heliostats, {time_utc[:16]} UTC (sun el {sun['elevation_deg']:.1f} deg)\n"
                 f"field efficiency {e['total']:.3f} (power-weighted)")
    ax.legend(loc="lower right")
    save_figure(fig, folder / "field_efficiency.png")

    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    loss = [100.0 * rep["losses"][k]["fraction"] for k in FACTORS]
    bars = ax.bar(FACTORS, loss, color="tab:red")
    for b, v, k in zip(bars, loss, FACTORS):
        ax.annotate(f"{v:.1f} %\n{rep['losses'][k]['power_w'] / 1e6:.2f} MW", (b.get_x() + b.get_width() / 2, v),
                    ha="center", va="bottom", fontsize=8)
    ax.set(ylabel="share of DNI x mirror area lost [%]", ylim=(0, max(loss) * 1.3 + 1),
           title=f"loss breakdown: {rep['receiver']['power_w'] / 1e6:.2f} MW on the receiver "
                 f"(efficiency {e['total']:.3f})")
    save_figure(fig, folder / "losses.png")

    vmax = max(float(before.flux.max()), float(aimed.flux.max())) / 1e3
    ext = before.extent.tolist()
    for name, flux, label, power in (("flux_equator", before.flux, "equator aiming", rep["receiver"]["power_w"]),
                                     ("flux_optimised", aimed.flux, "optimised aim points", aimed.power_w)):
        fig = Figure(figsize=(8, 3))
        ax = fig.add_subplot()
        im = ax.imshow(flux.detach().numpy() / 1e3, extent=ext, aspect="auto", vmin=0, vmax=vmax, cmap="inferno")
        fig.colorbar(im, ax=ax, label="flux [kW/m²]")
        ax.set(xlabel="arc along the unrolled receiver [m]", ylabel="height [m]",
               title=f"{label}: peak {float(flux.max()) / 1e3:.0f} kW/m² (limit {limit / 1e3:.0f}), "
                     f"{power / 1e6:.2f} MW")
        save_figure(fig, folder / f"{name}.png")
