"""Fields as input: a heliostat layout CSV (as SolarPILOT writes it) plus a small TOML plant description.

Layout CSV
----------
``x, y, z`` = east, north, up [m] of each heliostat's pivot, tower base at the origin; lines starting with
``#`` are comments; the first other line is the header (column names ``x``, ``y``, ``z``, optionally
``id``; SolarPILOT's ``x_location``/``y_location``/``z_location`` are accepted too; other columns are
ignored). Without an ``id`` column heliostats are named ``H0000``, ``H0001``, ... in file order. An optional
``focal_length`` column [m] gives each heliostat's on-axis canting distance (default: the TOML's, else the
slant range); ``heliotwin scenario export`` writes it for plants whose facets are canted at another distance.

Plant description (TOML)
------------------------
::

    [site]        latitude, longitude [deg], altitude [m]
    [heliostat]   width, height [m], facets = [nx, ny], canting = "flat" | "on-axis" (focal_length [m],
                  default: each heliostat's slant range to the receiver), reflectivity [-],
                  slope_error_mrad (per in-plane direction); optional facet_centers = [[x, y, z], ...]
                  (nx * ny facet centres in the heliostat frame [m], row by row from the top left; default:
                  the facets tile the mirror) and facet_size = [w, h] (one facet [m]; default: the tile)
    [receiver]    type = "cylinder" (radius, height [m], center = [e, n, u] of the axis at mid-height,
                  opening_angle_deg, optional horizontal normal: default the field's mean direction, for a
                  full cylinder the nearest of N/E/S/W; it only fixes where the unrolled map starts;
                  optional axis = [e, n, u], the cylinder's unit axis (default vertical): with it the
                  normal may tilt (a PAINT tower's receiver), perpendicular to the axis)
                  | "planar" (width, height, center, normal)
    [receiver.flux_limit]  optional allowable flux, read by ``aimpoints``/``daily --flux-limit plant.toml``:
                  panels_w_m2 = [...] (one limit per panel [W/m^2], equal-width panels left to right along the
                  unrolled map), flow_path = [...] (0-based panel indices in the fluid's order; default in order),
                  derating = [...] (factor in (0, 1] at each flow-path step, e.g. falling to 0.33 at the hot
                  outlet; default 1), top_bottom_w_m2 (a lower limit on the map's top and bottom rows)
                  (:mod:`heliotwin.field.flux_limit`, :mod:`heliotwin.optimise.fluxmap`)
    [sun]         shape = "limb-darkened" | "buie" (csr) | "gaussian" (sigma_mrad) | "pillbox"
                  (radius_mrad, also the limb-darkened disc), dni [W/m^2]
    [atmosphere]  model = "polynomial", coefficients = [c0, c1, c2, c3] (loss in slant range [km])

Every key has a unit in its name or above; unknown keys are errors (a typo must not silently fall back to a
default). Errors are one line naming the file and the field (``plant.toml [receiver.type]: ...``,
``layout.csv [line 7, y]: ...``), raised before anything is written.

The heliostats become a :class:`~heliotwin.field.plant.Plant` with nominal Jülich linear actuators (the
kinematics only matter to commands that convert aim points to motor steps), the facets tiling the mirror
(flat or canted on-axis, :func:`heliotwin.field.facets.receiver_canting`), ideal NURBS surfaces, the receiver
as the target named ``"receiver"``, and the sun/mirror optics in :class:`~heliotwin.field.plant.SunSettings`.
The atmosphere is returned separately (:class:`heliotwin.atmosphere.Atmosphere`; scenario files keep it in
``/extras/atmosphere``).
"""
from __future__ import annotations

import csv
import math
import os
import stat
import sys
from dataclasses import dataclass
from pathlib import Path

import torch

from ..atmosphere import ATMOSPHERE_MODELS, Atmosphere, attenuation
from ..errors import InputFileError
from ..site import Site
from ..sunshape import SUNSHAPES
from .actuators import ACTUATOR_NOMINAL
from .facets import ideal_surfaces, receiver_canting
from .flux_limit import parse_flux_limit_table
from .plant import Facets, Field, Kinematics, Plant, SunSettings
from .targets import CylinderTarget, PlanarTarget

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10 only
    import tomli as tomllib

__all__ = ["Layout", "PlantConfig", "read_layout", "read_plant_config", "plant_from_layout", "build_plant",
           "RECEIVER_TYPES", "CANTINGS", "require_regular_file", "check_spacing", "check_attenuation", "check_memory"]

RECEIVER_TYPES = ("cylinder", "planar")
CANTINGS = ("flat", "on-axis")
_REQUIRED = object()
_ALIASES = {"x": ("x", "x_location"), "y": ("y", "y_location"), "z": ("z", "z_location"), "id": ("id",),
            "focal_length": ("focal_length",)}
_OPTIONAL_COLUMNS = ("id", "focal_length")
#: Physical bounds of a plant description: beyond them a value is a typo or a unit mistake.
MIN_MIRROR_M, MAX_MIRROR_M = 0.05, 50.0  # heliostat width/height [m] (the largest built are about 12 m)
MIN_RECEIVER_M, MAX_RECEIVER_M = 0.1, 1000.0  # receiver radius/width/height [m]
MAX_DISTANCE_M = 20_000.0  # heliostats and receiver from the tower base [m] (the attenuation model holds to a few km)
MAX_FACETS_PER_SIDE = 64


def require_regular_file(path, what: str = "file") -> None:
    """Refuse a FIFO, device or socket before opening it (reading one could block forever); one line.

    A missing path or a folder passes: the reader's own ``open`` says what is wrong with those.
    """
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise InputFileError(path, f"is not a regular file (a FIFO, device or socket); expected a {what}")


def check_spacing(position: torch.Tensor, min_distance: float, path, ids=None, lines=None) -> None:
    """Refuse two heliostats whose pivots are closer than ``min_distance`` [m] (their mirrors would collide).

    ``position``: (H, 3) pivots, ENU [m]. Uses a grid of cells ``min_distance / sqrt(2)`` wide in (east,
    north): two pivots in one cell are always too close, so a valid field has at most one pivot per cell and
    each pivot is compared with the pivots of the 5 x 5 cells around it only (sorted cell keys and a binary
    search: O(H log H), no all-pairs distance matrix).
    """
    h = position.shape[0]
    if h < 2 or not min_distance > 0:
        return
    cell = min_distance / math.sqrt(2.0)
    xy = position[:, :2].to(torch.float64)
    ij = torch.floor((xy - xy.min(0).values) / cell).to(torch.int64)
    span = int(ij[:, 1].max()) + 5
    key = ij[:, 0] * span + ij[:, 1]
    order = torch.argsort(key)
    sorted_key = key[order]
    pairs = []
    same = torch.nonzero(sorted_key[1:] == sorted_key[:-1]).flatten()
    if same.numel():
        pairs.append(torch.stack((order[same], order[same + 1]), dim=-1))
    for di in range(-2, 3):
        for dj in range(-2, 3):
            if (di, dj) <= (0, 0):  # each neighbour pair once; the cell itself is covered above
                continue
            want = key + di * span + dj
            at = torch.searchsorted(sorted_key, want).clamp_max(h - 1)
            hit = sorted_key[at] == want
            if bool(hit.any()):
                pairs.append(torch.stack((torch.nonzero(hit).flatten(), order[at[hit]]), dim=-1))
    if not pairs:
        return
    pairs = torch.cat(pairs)
    dist = torch.linalg.vector_norm(xy[pairs[:, 0]] - xy[pairs[:, 1]], dim=-1)
    bad = torch.nonzero(dist < min_distance).flatten()
    if bad.numel():
        k = int(bad[torch.argmin(dist[bad])])
        a, b = sorted(int(v) for v in pairs[k])
        def name(i: int) -> str:
            return ids[i] if ids is not None else f"#{i}"

        where = f"line {lines[b]}" if lines is not None else None
        raise InputFileError(path, f"heliostats {name(a)} and {name(b)} are {float(dist[k]):.2f} m apart: their "
                             f"mirrors would collide (pivots must be at least {min_distance:.2f} m apart, the "
                             "mirror's smaller side)", field=where)


def check_attenuation(atmosphere: Atmosphere, slant_range: torch.Tensor, path, field: str, ids=None) -> None:
    """Refuse an atmosphere whose transmitted fraction leaves [0, 1] at some heliostat's slant range.

    ``slant_range``: (H,) heliostat-to-receiver distances [m]; ``field`` names the coefficients in ``path``.
    """
    if slant_range.numel() == 0:
        return
    values = attenuation(slant_range.to(torch.float64), atmosphere)
    bad = torch.nonzero(~((values >= 0.0) & (values <= 1.0))).flatten()
    if bad.numel():
        i = int(bad[0])
        who = f"heliostat {ids[i]}" if ids is not None else f"heliostat #{i}"
        raise InputFileError(path, f"attenuation {float(values[i]):.4g} at {who}'s slant range "
                             f"{float(slant_range[i]):.1f} m is outside [0, 1] (coefficients "
                             f"{list(atmosphere.coefficients)}, slant range in km)", field=field)


def check_memory(heliostats: int, facets, num_control_points, path) -> None:
    """Raise ``MemoryError`` (the command line's out-of-memory message) for a plant that cannot fit in memory.

    A plant's mirrors alone take ``H x F x (nu x nv + 9) x 3`` float64 values; the field model needs several
    times that. Refused when that estimate exceeds the machine's physical memory.
    """
    f = int(facets[0]) * int(facets[1])
    need = 8 * 8 * 3 * int(heliostats) * f * (int(num_control_points[0]) * int(num_control_points[1]) + 9)
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = 64 * 2**30
    if need > total:
        raise MemoryError(f"{path}: {heliostats} heliostats x {f} facets need about {need / 2**30:.0f} GiB "
                          f"(this machine has {total / 2**30:.0f} GiB)")


def _check_far(layout: Layout) -> None:
    far = torch.nonzero(torch.linalg.vector_norm(layout.position, dim=-1) > MAX_DISTANCE_M).flatten()
    if far.numel():
        i = int(far[0])
        raise InputFileError(layout.path, f"heliostat {layout.ids[i]} is {float(layout.position[i].norm()):.3g} m "
                             f"from the tower base (at most {MAX_DISTANCE_M:g} m)", field=f"line {layout.lines[i]}")


@dataclass
class Layout:
    """Heliostat positions read from a layout CSV.

    Attributes
    ----------
    ids : list of str
        Heliostat names, length H.
    position : torch.Tensor, [H, 3], float64
        Pivot positions, ENU [m] about the tower base.
    lines : list of int
        Source line of each heliostat (for error messages).
    path : str
    focal_length : torch.Tensor, [H], float64, optional
        On-axis canting distance per heliostat [m] (the optional ``focal_length`` column).
    """

    ids: list
    position: torch.Tensor
    lines: list
    path: str
    focal_length: torch.Tensor | None = None


def read_layout(path) -> Layout:
    """Read a layout CSV (module docstring).

    Raises
    ------
    InputFileError
        Missing/unreadable file, no header, missing ``x``/``y``/``z`` column, a value that is not a finite
        number, a short row, duplicate ids, no heliostat (message names the line and column).
    """
    path = Path(path)
    require_regular_file(path, "layout")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else " ".join(str(exc).split())
        raise InputFileError(path, f"cannot read layout ({exc.__class__.__name__}: {reason})") from None
    rows = [(n, line) for n, line in enumerate(text.splitlines(), start=1)
            if line.strip() and not line.lstrip().startswith("#")]
    if not rows:
        raise InputFileError(path, "no header and no heliostats (expected a header line x,y,z)")
    header_line, header = rows[0]
    names = [c.strip().lower() for c in next(csv.reader([header]))]
    column = {}
    for key, aliases in _ALIASES.items():
        found = [i for i, c in enumerate(names) if c in aliases]
        if found:
            column[key] = found[0]
        elif key not in _OPTIONAL_COLUMNS:
            raise InputFileError(path, f"missing column {key!r} in header {header.strip()!r} (expected x,y,z[,id])",
                                 field=f"line {header_line}")
    values, ids, lines = [], [], []
    numeric = ("x", "y", "z") + (("focal_length",) if "focal_length" in column else ())
    for n, line in rows[1:]:
        cells = [c.strip() for c in next(csv.reader([line]))]
        xyz = []
        for key in numeric:
            i = column[key]
            if i >= len(cells) or not cells[i]:
                raise InputFileError(path, f"missing value (row has {len(cells)} columns)", field=f"line {n}, {key}")
            try:
                v = float(cells[i])
            except ValueError:
                raise InputFileError(path, f"expected a number, got {cells[i]!r}", field=f"line {n}, {key}") from None
            if not math.isfinite(v) or (key == "focal_length" and not 0.0 < v <= 1e5):
                want = "a focal length in (0, 1e5] m" if key == "focal_length" else "a finite number"
                raise InputFileError(path, f"expected {want}, got {cells[i]!r}", field=f"line {n}, {key}")
            xyz.append(v)
        if "id" in column:
            i = column["id"]
            if i >= len(cells) or not cells[i]:
                raise InputFileError(path, "missing id", field=f"line {n}, id")
            if not cells[i].isprintable():
                raise InputFileError(path, f"id {cells[i]!r} holds a control character", field=f"line {n}, id")
            ids.append(cells[i])
        else:
            ids.append(f"H{len(ids):04d}")
        values.append(xyz)
        lines.append(n)
    if not values:
        raise InputFileError(path, "no heliostats after the header")
    seen = {}
    for hid, n in zip(ids, lines):
        if hid in seen:
            raise InputFileError(path, f"duplicate id {hid!r} (first on line {seen[hid]})", field=f"line {n}, id")
        seen[hid] = n
    table = torch.tensor(values, dtype=torch.float64)
    return Layout(ids, table[:, :3].contiguous(), lines, str(path),
                  table[:, 3].contiguous() if "focal_length" in column else None)


# ------------------------------------------------------------------------------------------------ TOML
class _Table:
    """One TOML table with typed, unit-checked access; every failure names ``[section.key]``."""

    def __init__(self, path, section: str, data):
        self.path, self.section = path, section
        if not isinstance(data, dict):
            self.fail(None, f"expected a table [{section}], got {type(data).__name__}")
        self.data, self.used = data, set()

    def fail(self, key, message: str):
        field = self.section if key is None else f"{self.section}.{key}"
        raise InputFileError(self.path, message, field=field)

    def _lookup(self, key: str, default, missing: str = "missing") -> tuple[bool, object]:
        """(present, value): marks ``key`` as used; a required key that is absent fails with ``missing``."""
        self.used.add(key)
        if key in self.data:
            return True, self.data[key]
        if default is _REQUIRED:
            self.fail(key, missing)
        return False, default

    def number(self, key: str, default=_REQUIRED, *, lo=None, hi=None, lo_open=False) -> float:
        present, v = self._lookup(key, default)
        if not present:
            return v
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            self.fail(key, f"expected a finite number, got {v!r}")
        v = float(v)
        if lo is not None and (v < lo or (lo_open and v == lo)):
            self.fail(key, f"expected a value {'>' if lo_open else '>='} {lo:g}, got {v:g}")
        if hi is not None and v > hi:
            self.fail(key, f"expected a value <= {hi:g}, got {v:g}")
        return v

    def vector(self, key: str, length: int | None, default=_REQUIRED, *, integer=False, nested: int = 0) -> list:
        present, v = self._lookup(key, default)
        if not present:
            return v
        if nested:  # a list of vectors of ``nested`` numbers each
            if not isinstance(v, list) or not v or not all(isinstance(x, list) for x in v):
                self.fail(key, f"expected a list of [{', '.join(['x'] * nested)}] lists, got {v!r}")
            return [self._numbers(key, x, nested, integer) for x in v]
        return self._numbers(key, v, length, integer)

    def _numbers(self, key: str, v, length: int | None, integer: bool) -> list:
        kinds = (int,) if integer else (int, float)
        if not isinstance(v, list) or (length is not None and len(v) != length) or not v or \
                not all(isinstance(x, kinds) and not isinstance(x, bool) and math.isfinite(float(x)) for x in v):
            want = f"{length} " if length else ""
            self.fail(key, f"expected a list of {want}{'integers' if integer else 'numbers'}, got {v!r}")
        return [int(x) if integer else float(x) for x in v]

    def choice(self, key: str, options, default=_REQUIRED) -> str:
        present, v = self._lookup(key, default, f"missing (one of {', '.join(options)})")
        if not present:
            return v
        if not isinstance(v, str) or v.lower() not in options:
            self.fail(key, f"unknown value {v!r}; expected one of {', '.join(options)}")
        return v.lower()

    def done(self):
        extra = sorted(set(self.data) - self.used)
        if extra:
            self.fail(extra[0], "unknown key (check the spelling; see heliotwin.field.layout)")


@dataclass
class PlantConfig:
    """The validated plant description (all SI units; angles in rad)."""

    site: Site
    width: float
    height: float
    facets: tuple
    canting: str
    focal_length: float | None
    receiver: dict
    sun: SunSettings
    atmosphere: Atmosphere
    facet_centers: tuple | None = None
    facet_size: tuple | None = None


def read_plant_config(path) -> PlantConfig:
    """Read and validate the TOML plant description (module docstring).

    Raises
    ------
    InputFileError
        Missing or malformed file, missing/unknown/mistyped key, out-of-range value, unknown receiver
        type, sunshape, canting or atmosphere model (one line naming ``[section.key]``).
    """
    path = Path(path)
    require_regular_file(path, "plant description")
    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({exc.__class__.__name__}: {exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise InputFileError(path, "not UTF-8 text (expected a TOML plant description)") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputFileError(path, f"malformed TOML ({' '.join(str(exc).split())})") from None
    except RecursionError:
        raise InputFileError(path, "malformed TOML (nested too deeply)") from None
    for section in doc:
        if section not in ("site", "heliostat", "receiver", "sun", "atmosphere"):
            raise InputFileError(path, "unknown section (expected site, heliostat, receiver, sun, atmosphere)",
                                 field=section)
    t = _Table(path, "site", doc.get("site", {}))
    site = Site(t.number("latitude", lo=-90, hi=90), t.number("longitude", lo=-180, hi=180),
                t.number("altitude", 0.0, lo=-500, hi=9000), str(t.data.get("name", path.stem)))
    t.used.add("name")
    t.done()

    t = _Table(path, "heliostat", doc.get("heliostat", {}))
    width = t.number("width", lo=MIN_MIRROR_M, hi=MAX_MIRROR_M)
    height = t.number("height", lo=MIN_MIRROR_M, hi=MAX_MIRROR_M)
    facets = t.vector("facets", 2, [1, 1], integer=True)
    if min(facets) < 1 or max(facets) > MAX_FACETS_PER_SIDE:
        t.fail("facets", f"expected two integers in 1..{MAX_FACETS_PER_SIDE}, got {facets}")
    canting = t.choice("canting", CANTINGS, "flat")
    focal = t.number("focal_length", None, lo=0, lo_open=True, hi=1e5)
    centers = t.vector("facet_centers", None, None, nested=3)
    if centers is not None and len(centers) != facets[0] * facets[1]:
        t.fail("facet_centers", f"expected {facets[0] * facets[1]} facet centres (facets = {facets}), "
                                f"got {len(centers)}")
    if centers is not None and max(abs(c) for xyz in centers for c in xyz) > MAX_MIRROR_M:
        t.fail("facet_centers", f"expected centres within {MAX_MIRROR_M:g} m of the pivot")
    facet_size = t.vector("facet_size", 2, None)
    if facet_size is not None and not all(MIN_MIRROR_M / 64 <= v <= MAX_MIRROR_M for v in facet_size):
        t.fail("facet_size", f"expected two sizes in [{MIN_MIRROR_M / 64:g}, {MAX_MIRROR_M:g}] m, got {facet_size}")
    reflectivity = t.number("reflectivity", 0.9, lo=0, hi=1)
    slope = t.number("slope_error_mrad", 1.53, lo=0, hi=100) * 1e-3
    t.done()

    if "receiver" not in doc:
        raise InputFileError(path, "missing table (type = \"cylinder\" or \"planar\")", field="receiver")
    receiver = _receiver_config(_Table(path, "receiver", doc["receiver"]))

    t = _Table(path, "sun", doc.get("sun", {}))
    shape = t.choice("shape", SUNSHAPES, "limb-darkened")
    sun = SunSettings(sunshape=shape, sigma=t.number("sigma_mrad", 2.51, lo=0, lo_open=True, hi=100) * 1e-3,
                      radius=t.number("radius_mrad", 4.65, lo=0, lo_open=True, hi=100) * 1e-3,
                      csr=t.number("csr", 0.05, lo=0, lo_open=True, hi=0.999), slope_error=slope,
                      dni=t.number("dni", 1000.0, lo=0, hi=1500), reflectivity=reflectivity)
    t.done()

    t = _Table(path, "atmosphere", doc.get("atmosphere", {}))
    coefficients = t.vector("coefficients", None, list(Atmosphere().coefficients))
    if len(coefficients) > 8:
        t.fail("coefficients", f"expected at most 8 polynomial coefficients, got {len(coefficients)}")
    atmosphere = Atmosphere(t.choice("model", ATMOSPHERE_MODELS, "polynomial"), tuple(coefficients))
    t.done()
    return PlantConfig(site, width, height, tuple(facets), canting, focal, receiver, sun, atmosphere,
                       None if centers is None else tuple(tuple(c) for c in centers),
                       None if facet_size is None else tuple(facet_size))


def _receiver_config(t: _Table) -> dict:
    kind = t.choice("type", RECEIVER_TYPES)
    out = {"type": kind, "center": t.vector("center", 3), "height": t.number("height", lo=MIN_RECEIVER_M,
                                                                              hi=MAX_RECEIVER_M)}
    if max(abs(c) for c in out["center"]) > MAX_DISTANCE_M:
        t.fail("center", f"expected a point within {MAX_DISTANCE_M:g} m of the tower base, got {out['center']}")
    if out["center"][2] - out["height"] / 2 <= 0:
        t.fail("center", f"the receiver reaches below the ground (centre height {out['center'][2]:g} m, half height "
                         f"{out['height'] / 2:g} m)")
    normal = t.vector("normal", 3, None)
    if normal is not None and math.hypot(*normal) == 0.0:
        t.fail("normal", "expected a non-zero vector")
    out["normal"] = normal
    if kind == "cylinder":
        out["radius"] = t.number("radius", lo=MIN_RECEIVER_M, hi=MAX_RECEIVER_M)
        out["opening_angle"] = math.radians(t.number("opening_angle_deg", 360.0, lo=1, hi=360))
        axis = t.vector("axis", 3, None)
        if axis is not None and (math.hypot(*axis) == 0.0 or axis[2] <= 0.0):
            t.fail("axis", f"expected a non-zero vector pointing up (positive up component), got {axis}")
        out["axis"] = axis
        if axis is None and normal is not None and abs(normal[2]) > 1e-9 * math.hypot(*normal):
            t.fail("normal", "a cylinder's aperture normal must be horizontal (the axis is vertical; give `axis` "
                             "for a tilted receiver)")
        if axis is not None and normal is not None and \
                abs(sum(a * b for a, b in zip(axis, normal))) > 1e-6 * math.hypot(*axis) * math.hypot(*normal):
            t.fail("normal", f"must be perpendicular to the cylinder's axis {axis}")
    else:
        out["width"] = t.number("width", lo=MIN_RECEIVER_M, hi=MAX_RECEIVER_M)
        if normal is None:
            t.fail("normal", "missing (planar receivers need their normal, towards the field)")
    present, limits = t._lookup("flux_limit", None)
    if present:  # the allowable flux per panel (read by aimpoints/daily --flux-limit plant.toml): checked here too
        out["flux_limit"] = parse_flux_limit_table(limits, t.path, f"{t.section}.flux_limit")
    t.done()
    return out


# ------------------------------------------------------------------------------------------------ plant
def _receiver(config: dict, towards_field: torch.Tensor):
    f64 = dict(dtype=torch.float64)
    center = torch.tensor(config["center"], **f64)
    if config["type"] == "planar":
        return PlanarTarget.from_center_normal("receiver", center, config["normal"], config["width"], config["height"])
    normal = torch.tensor(config["normal"], **f64) if config["normal"] is not None else towards_field
    normal = normal / torch.linalg.vector_norm(normal)
    up = torch.tensor(config.get("axis") or [0.0, 0.0, 1.0], **f64)
    up = up / torch.linalg.vector_norm(up)
    if config.get("axis") is not None and config["normal"] is None:  # default normal: made perpendicular to the axis
        normal = torch.nn.functional.normalize(normal - (normal @ up) * up, dim=0)
    right = torch.linalg.cross(up, normal)
    r = float(config["radius"])
    return CylinderTarget("receiver", center + r * normal, normal, right, up, r, float(config["height"]),
                          float(config["opening_angle"]))


def _check_outside_tower(layout: Layout, config: PlantConfig, config_path) -> None:
    """Heliostats whose mirror would reach into the tower's footprint (the receiver's horizontal extent)."""
    rc = config.receiver
    reach = rc["radius"] if rc["type"] == "cylinder" else 0.5 * rc["width"]
    centre = torch.tensor(rc["center"][:2], dtype=torch.float64)
    clearance = reach + 0.5 * math.hypot(config.width, config.height)
    dist = torch.linalg.vector_norm(layout.position[:, :2] - centre, dim=-1)
    bad = torch.nonzero(dist < clearance).flatten()
    if bad.numel():
        i = int(bad[0])
        raise InputFileError(layout.path, f"heliostat {layout.ids[i]} at {dist[i]:.2f} m from the tower axis is inside "
                             f"the tower (receiver reach + half mirror diagonal = {clearance:.2f} m, from "
                             f"{config_path})", field=f"line {layout.lines[i]}")


def _nominal_kinematics(position: torch.Tensor) -> Kinematics:
    """Nominal Jülich linear actuators at every pivot (zero joint offsets, concentrator at the pivot)."""
    h = position.shape[0]
    f64 = dict(dtype=torch.float64)

    def const(values):
        return torch.tensor(values, **f64).expand(h, len(values)).clone()

    act = {k: const(v) for k, v in ACTUATOR_NOMINAL.items()}
    zeros3 = torch.zeros(h, 3, **f64)
    return Kinematics(position=position.clone(), joint_translation=torch.zeros(h, 2, 3, **f64),
                      concentrator_translation=zeros3.clone(), joint_tilt=torch.zeros(h, 2, 3, **f64),
                      concentrator_tilt=zeros3.clone(), clockwise=torch.tensor([[False, True]]).expand(h, 2).clone(),
                      linear=torch.ones(h, 2, dtype=torch.bool), min_steps=torch.zeros(h, 2, **f64),
                      max_steps=const((69000.0, 75000.0)), min_angle=const((-math.pi / 2, -math.pi)),
                      max_angle=const((math.pi / 2, math.pi)), **act)


def _facets(config: PlantConfig, h: int, focal_length: torch.Tensor) -> Facets:
    nx, ny = config.facets
    hw, hh = config.width / (2 * nx), config.height / (2 * ny)
    if config.facet_size is not None:
        hw, hh = config.facet_size[0] / 2, config.facet_size[1] / 2
    ex = [(-config.width / 2 + (2 * i + 1) * config.width / (2 * nx)) for i in range(nx)]
    ny_ = [(config.height / 2 - (2 * j + 1) * config.height / (2 * ny)) for j in range(ny)]
    centres = torch.tensor(config.facet_centers or [(x, y, 0.0) for y in ny_ for x in ex], dtype=torch.float64)
    translation = centres.expand(h, -1, -1).clone()
    if config.canting == "on-axis":
        ce, cn = receiver_canting(translation, hw, hh, focal_length)
    else:
        ce = torch.tensor([hw, 0.0, 0.0], dtype=torch.float64).expand_as(translation).clone()
        cn = torch.tensor([0.0, hh, 0.0], dtype=torch.float64).expand_as(translation).clone()
    return Facets(translation, ce, cn)


def plant_from_layout(layout_path, config_path, *, num_control_points=(4, 4)) -> tuple[Plant, Atmosphere]:
    """A plant from a layout CSV and a TOML plant description.

    Parameters
    ----------
    layout_path, config_path : path
    num_control_points : (int, int)
        NURBS control net of each ideal facet.

    Returns
    -------
    plant : Plant
        H heliostats (float64), target ``"receiver"``, sun/optics from the description.
    atmosphere : Atmosphere

    Raises
    ------
    InputFileError
        Any problem of either file (one line naming file and field), including heliostats inside the tower.
    """
    config = read_plant_config(config_path)
    layout = read_layout(layout_path)
    _check_far(layout)
    _check_outside_tower(layout, config, config_path)
    check_spacing(layout.position, min(config.width, config.height), layout.path, layout.ids, layout.lines)
    check_memory(len(layout.ids), config.facets, num_control_points, layout.path)
    plant = build_plant(layout, config, num_control_points=num_control_points)
    rec = plant.targets["receiver"]
    slant = torch.linalg.vector_norm((rec.center if rec.kind == "planar" else rec.axis_point) - layout.position, dim=-1)
    check_attenuation(config.atmosphere, slant, config_path, "atmosphere.coefficients", layout.ids)
    return plant, config.atmosphere


def build_plant(layout: Layout, config: PlantConfig, *, num_control_points=(4, 4)) -> Plant:
    """The plant of validated inputs (:func:`plant_from_layout` without the files; also the demo field's)."""
    pos = layout.position
    towards = pos[:, :2].mean(0) - torch.tensor(config.receiver["center"][:2], dtype=torch.float64)
    towards = torch.cat((towards, towards.new_zeros(1)))
    if float(torch.linalg.vector_norm(towards)) < 1e-9:  # surround field: aperture reference faces north
        towards = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    if config.receiver["type"] == "cylinder" and config.receiver["opening_angle"] >= 2 * math.pi - 1e-9:
        # A full cylinder's normal only fixes where its unrolled map starts: snap it to the nearest of N, E, S,
        # W so that the map does not move with the layout's asymmetries.
        k = round(math.atan2(float(towards[0]), float(towards[1])) / (math.pi / 2)) % 4
        towards = torch.tensor([(0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (-1.0, 0.0, 0.0)][k],
                               dtype=torch.float64)
    receiver = _receiver(config.receiver, towards / torch.linalg.vector_norm(towards))
    aim_centre = receiver.center if receiver.kind == "planar" else receiver.axis_point
    slant = torch.linalg.vector_norm(aim_centre - pos, dim=-1)
    focal = torch.full_like(slant, config.focal_length) if config.focal_length else slant
    if layout.focal_length is not None:
        focal = layout.focal_length.to(slant)
    h = len(layout.ids)
    facets = _facets(config, h, focal)
    surfaces = ideal_surfaces(facets, num_control_points=num_control_points)
    fld = Field(list(layout.ids), _nominal_kinematics(pos), facets, surfaces,
                torch.full((h,), config.width, dtype=torch.float64),
                torch.full((h,), config.height, dtype=torch.float64),
                [""] * h)
    return Plant(config.site, {"receiver": receiver}, fld, config.sun)
