"""Reader for a local PAINT download (the layout a user's download has), with validation.

Layout::

    <root>/WRI1030197-tower-measurements.json      (any ``*-tower-measurements.json``)
    <root>/metadata/calibration-metadata.csv        (optional: DateTime per record)
    <root>/metadata/calibration-weather.csv         (optional)
    <root>/<HID>/Properties/<HID>-heliostat-properties.json
    <root>/<HID>/Calibration/<id>-calibration-properties.json
    <root>/<HID>/Calibration/<id>-flux.png, <id>-flux-centered.png   (optional)

Every problem raises :class:`~heliotwin.errors.InputFileError` with the file and the JSON field.
Geodetic coordinates are lat-first WGS84 and become ENU about the plant reference (float64).

Only regular files are read (:func:`read_regular`): every file is opened non-blocking and checked with ``fstat``
before a byte is read, and read up to a size cap (:data:`MAX_JSON_BYTES`, :data:`MAX_RECORD_BYTES`,
:data:`MAX_CSV_BYTES`), so no FIFO, device or endless file can stall a command that holds the plant's lock. A
symbolic link to a regular file is read as that file (wherever it points: a download deduplicated with links
stays readable); a link to anything else, or a dangling one, is refused like the thing itself. A record file that
is refused so is dropped with its reason (``skipped``, field ``file`` or ``size``); the tower, properties and
metadata files are one-line errors naming the file. A record whose heliostat (its ``HeliostatId``, or its metadata
row's) is not its folder's is dropped too (field ``HeliostatId``).

A folder read onto a plant (:func:`load_paint_on_plant`, :meth:`PaintDataset.on_plant`) must be that plant's:
each heliostat's position in its Properties file within :data:`MAX_POSITION_MISMATCH_M` of the plant's, and no
record the plant saw under one heliostat lying under another.
"""
from __future__ import annotations

import csv
import glob
import io
import itertools
import json
import math
import os
import re
import stat
from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import InputFileError
from ..field import facets as facet_ops
from ..field.plant import Facets, Field, Kinematics, Plant, Site, SunSettings
from ..field.targets import CylinderTarget, PlanarTarget
from ..site import wgs84_to_enu
from . import record_index
from .readahead import read_ahead
from .records import (
    SOURCES,
    WEATHER_KEYS,
    RawRecords,
    RecordTable,
    build_record_table,
    parse_time,
    raw_from_records,
)

HELIOSTAT_DIR = re.compile(r"^[A-Z]{2}[0-9]{2}$")
FOCAL_SPOT_SOURCES = ("HeliOS", "UTIS")

# Plausibility bounds of a plant's geometry: the largest tower plants reach ~2 km from the tower, heliostats
# and their parts are metres in size. Beyond these a file holds a typo or corruption, not a plant.
#: Largest horizontal distance [m] of a target, heliostat or focal spot from the plant reference.
MAX_PLANT_RADIUS_M = 5000.0
#: Largest height difference [m] from the plant reference.
MAX_PLANT_HEIGHT_M = 1000.0
#: Largest heliostat-local length [m]: joint/concentrator/facet translations, canting vectors, actuator lengths.
MAX_HELIOSTAT_LENGTH_M = 50.0
#: Largest JSON file [bytes] a PAINT reader opens (PAINT's are a few kB) and its deepest nesting.
MAX_JSON_BYTES = 16 * 2**20
MAX_JSON_DEPTH = 32
#: Largest calibration record file [bytes] (PAINT's are 1-2 kB; a bigger one is not a record and is dropped).
MAX_RECORD_BYTES = 2**20
#: Largest metadata CSV [bytes] (about 80 bytes per record: 1 GiB is ten million records, 50 years of 10,000
#: heliostats at PAINT's rate).
MAX_CSV_BYTES = 2**30
#: Largest distance [m] of a heliostat's position in the folder's Properties file from the plant's position of
#: the same id: beyond it the folder is another plant's (surveys agree to centimetres).
MAX_POSITION_MISMATCH_M = 1.0

_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a directory"))


def _not_regular(mode: int) -> str | None:
    """Why a file of ``mode`` (an ``st_mode``) is not read, or None for a regular file."""
    if stat.S_ISREG(mode):
        return None
    kind = next((name for test, name in _KINDS if test(mode)), "of another kind")
    return f"not a regular file ({kind}; the reader opens only regular files)"


def _too_big(size: int, limit: int) -> str:
    return f"too large ({size} bytes; such a file holds at most {limit})"


def read_regular(path, limit: int, *, start: int = 0) -> bytes:
    """The bytes of the regular file ``path`` from byte ``start`` on, at most ``limit`` [bytes] in all.

    Opened with ``O_NONBLOCK`` (a FIFO or device neither blocks the open nor is read) and checked with ``fstat``
    on the open descriptor (no race between the check and the read); a symbolic link to a regular file is read as
    that file.

    Raises
    ------
    InputFileError
        Missing (or a dangling link), not a regular file (naming what it is), larger than ``limit``, unreadable.
    """
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise InputFileError(path, "not a regular file (a dangling symbolic link)" if os.path.islink(path)
                             else "file not found") from None
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        why = _not_regular(st.st_mode)
        if why is not None:
            raise InputFileError(path, why)
        if st.st_size > limit:
            raise InputFileError(path, _too_big(st.st_size, limit))
        if start:
            os.lseek(fd, start, os.SEEK_SET)
        chunks, left = [], limit - start + 1  # one byte more than allowed: a file that grew since fstat
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 22))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
        data = b"".join(chunks)
        if start + len(data) > limit:
            raise InputFileError(path, _too_big(start + len(data), limit))
        return data
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({exc.strerror})") from None
    finally:
        os.close(fd)


def regular_size(path) -> int | None:
    """Size [bytes] of ``path`` when it exists (following links); None when it does not exist.

    Raises
    ------
    InputFileError
        It exists but is not a regular file (or is a dangling link).
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        if os.path.islink(path):
            raise InputFileError(path, "not a regular file (a dangling symbolic link)") from None
        return None
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({exc.strerror})") from None
    why = _not_regular(st.st_mode)
    if why is not None:
        raise InputFileError(path, why)
    return int(st.st_size)


def _depth(obj, limit: int) -> int:
    """Nesting depth of parsed JSON, iteratively (no recursion), stopping once ``limit`` is exceeded."""
    deepest, stack = 0, [(obj, 1)]
    while stack:
        node, d = stack.pop()
        deepest = max(deepest, d)
        if deepest > limit:
            return deepest
        if isinstance(node, dict):
            stack.extend((v, d + 1) for v in node.values())
        elif isinstance(node, list):
            stack.extend((v, d + 1) for v in node)
    return deepest


def read_json(path, limit: int | None = None) -> dict:
    """Parse a JSON file; one-line :class:`InputFileError` when it is missing, not a regular file
    (:func:`read_regular`), malformed, not UTF-8, larger than ``limit`` [bytes] (default
    :data:`MAX_JSON_BYTES`) or nested deeper than :data:`MAX_JSON_DEPTH`."""
    raw = read_regular(path, MAX_JSON_BYTES if limit is None else limit)
    try:
        text = raw.decode("utf-8")
        data = json.loads(text)
    except UnicodeDecodeError as exc:
        raise InputFileError(path, f"not UTF-8 text (byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise InputFileError(path, f"malformed JSON ({exc})") from None
    except RecursionError:
        raise InputFileError(path, "malformed JSON (nested too deeply)") from None
    except ValueError as exc:  # e.g. an integer literal of more than 4300 digits
        raise InputFileError(path, f"malformed JSON ({' '.join(str(exc).split())})") from None
    # Nesting deeper than the limit needs more opening brackets than the limit: most files need no walk.
    if text.count("[") + text.count("{") > MAX_JSON_DEPTH and _depth(data, MAX_JSON_DEPTH) > MAX_JSON_DEPTH:
        raise InputFileError(path, f"nested deeper than {MAX_JSON_DEPTH} levels; not a PAINT file")
    if not isinstance(data, dict):
        raise InputFileError(path, "expected a JSON object at top level")
    return data


def _get(d: dict, key: str, path, prefix: str = ""):
    if not isinstance(d, dict) or key not in d:
        raise InputFileError(path, "missing key", field=f"{prefix}{key}")
    return d[key]


def _finite_number(x) -> bool:
    """An int/float (not bool) that is finite as a float; huge JSON integers (float() overflows) are not."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return False
    try:
        return math.isfinite(float(x))
    except OverflowError:
        return False


def _number(d: dict, key: str, path, prefix: str = "", *, positive: bool = False) -> float:
    v = _get(d, key, path, prefix)
    if not _finite_number(v):
        raise InputFileError(path, f"expected a finite number, got {v!r}", field=f"{prefix}{key}")
    if positive and float(v) <= 0:
        raise InputFileError(path, f"expected a positive number, got {v!r}", field=f"{prefix}{key}")
    return float(v)


def _vector(d: dict, key: str, path, prefix: str = "", n: int = 3, *, bound: float | None = None) -> list[float]:
    v = _get(d, key, path, prefix)
    if (not isinstance(v, (list, tuple)) or len(v) != n
            or not all(_finite_number(x) for x in v)):
        raise InputFileError(path, f"expected a list of {n} finite numbers, got {_short(v)}", field=f"{prefix}{key}")
    out = [float(x) for x in v]
    if bound is not None and max(abs(x) for x in out) > bound:
        raise InputFileError(path, f"implausible: a component beyond {bound:g} m in {out}", field=f"{prefix}{key}")
    return out


def _short(v, n: int = 80) -> str:
    text = repr(v)
    return text if len(text) <= n else text[:n] + "..."


def _near_plant(enu: torch.Tensor, path, fld: str) -> torch.Tensor:
    """``enu`` [3] if within :data:`MAX_PLANT_RADIUS_M` / :data:`MAX_PLANT_HEIGHT_M` of the plant reference."""
    horizontal, up = float(torch.hypot(enu[0], enu[1])), float(enu[2])
    if horizontal > MAX_PLANT_RADIUS_M or abs(up) > MAX_PLANT_HEIGHT_M:
        raise InputFileError(path, f"implausible: {horizontal / 1e3:.1f} km from the plant reference and {up:.0f} m "
                                   f"above it (a plant spans at most {MAX_PLANT_RADIUS_M / 1e3:g} km, "
                                   f"{MAX_PLANT_HEIGHT_M:g} m)", field=fld)
    return enu


def _local_enu(d: dict, key: str, path, site, prefix: str = "") -> torch.Tensor:
    """A lat-first WGS84 point of the plant as ENU [3] about the reference, checked to be near the plant."""
    return _near_plant(wgs84_to_enu(_geodetic(d, key, path, prefix), site.reference), path, prefix + key)


def _geodetic(d: dict, key: str, path, prefix: str = "") -> list[float]:
    v = _vector(d, key, path, prefix)
    if not (-90.0 <= v[0] <= 90.0 and -180.0 <= v[1] <= 180.0):
        raise InputFileError(path, f"not a [latitude, longitude, altitude] (lat-first WGS84): {v}",
                             field=f"{prefix}{key}")
    return v


# ----------------------------------------------------------------------------------------------- tower
def find_tower_file(root) -> str:
    """The ``*-tower-measurements.json`` of a PAINT folder."""
    hits = sorted(glob.glob(os.path.join(str(root), "*tower-measurements.json")))
    if not hits:
        raise InputFileError(root, "no '*-tower-measurements.json' in this PAINT folder")
    return hits[0]


def read_tower(path) -> tuple[Site, dict]:
    """Read the tower file: plant reference and targets.

    Returns
    -------
    site : Site
        ENU origin = ``power_plant_properties.coordinates``.
    targets : dict of str -> PlanarTarget | CylinderTarget
        ENU geometry (float64).
    """
    data = read_json(path)
    plant = _get(data, "power_plant_properties", path)
    ref = _geodetic(plant, "coordinates", path, "power_plant_properties.")
    site = Site(ref[0], ref[1], ref[2], str(plant.get("ID", "")))
    targets = {}
    for name, spec in data.items():
        if name == "power_plant_properties":
            continue
        pre = f"{name}."
        kind = _get(spec, "type", path, pre)
        coords = _get(spec, "coordinates", path, pre)
        if not isinstance(spec, dict):
            raise InputFileError(path, f"expected an object, got {_short(spec)}", field=name)
        normal = _vector(spec, "normal_vector", path, pre)
        if math.hypot(*normal) < 1e-9:
            raise InputFileError(path, "zero-length normal vector", field=pre + "normal_vector")
        if kind == "planar":
            corners = {k: _local_enu(coords, k, path, site, pre + "coordinates.")
                       for k in ("upper_left", "upper_right", "lower_left", "lower_right")}
            center = _local_enu(coords, "center", path, site, pre + "coordinates.")
            targets[name] = PlanarTarget.from_corners(name, corners, normal, center)
        elif kind == "convex_cylinder":
            radius = _number(spec, "radius", path, pre, positive=True)
            if radius > MAX_HELIOSTAT_LENGTH_M:
                raise InputFileError(path, f"implausible receiver radius {radius} m", field=pre + "radius")
            opening_deg = _number(spec, "opening_angle", path, pre, positive=True)
            if opening_deg >= 360.0:
                raise InputFileError(path, f"opening angle must be below 360 deg, got {opening_deg}",
                                     field=pre + "opening_angle")
            opening = math.radians(opening_deg)
            corners = {k: _local_enu(coords, f"receiver_outer_{k}", path, site, pre + "coordinates.")
                       for k in ("upper_left", "upper_right", "lower_left", "lower_right")}
            targets[name] = CylinderTarget.from_outer_corners(name, corners, normal, radius, opening)
        else:
            raise InputFileError(path, f"unknown target type {kind!r} (known: planar, convex_cylinder)",
                                 field=pre + "type")
    return site, targets


# ------------------------------------------------------------------------------------------ heliostat
@dataclass
class HeliostatProperties:
    """One heliostat's properties file, as tensors with a leading heliostat axis of size 1."""

    heliostat_id: str
    kinematics: Kinematics
    facets: Facets
    width: float
    height: float
    renovation: str
    path: str


_ACTUATOR_KEYS = ("increment", "offset", "pivot_radius", "initial_angle", "initial_stroke_length")


def read_heliostat_properties(path, site: Site, heliostat_id: str | None = None) -> HeliostatProperties:
    """Read ``<HID>-heliostat-properties.json``.

    Accepts both ``kinematics_properties`` and the older ``kinematic_properties`` key.
    """
    data = read_json(path)
    hid = heliostat_id or os.path.basename(str(path)).split("-")[0]
    position = _local_enu(data, "heliostat_position", path, site)
    key = "kinematics_properties" if "kinematics_properties" in data else "kinematic_properties"
    kin = _get(data, key, path)
    pre = key + "."
    acts = _get(kin, "actuators", path, pre)
    if not isinstance(acts, list) or len(acts) != 2:
        raise InputFileError(path, "expected a list of 2 actuators", field=pre + "actuators")
    per_axis = {k: [] for k in _ACTUATOR_KEYS + ("min_increment", "max_increment", "min_movement_angle",
                                                 "max_movement_angle")}
    clockwise, linear = [], []
    for i, act in enumerate(acts):
        ap = f"{pre}actuators[{i}]."
        kind = _get(act, "type_axis", path, ap)
        if kind not in ("linear", "ideal"):
            raise InputFileError(path, f"unknown actuator type {kind!r} (known: linear, ideal)", field=ap + "type_axis")
        for k in per_axis:
            if k in ("min_movement_angle", "max_movement_angle") and k not in act:
                per_axis[k].append(float("nan"))
                continue
            per_axis[k].append(_number(act, k, path, ap, positive=(k == "increment")))
        cw = _get(act, "clockwise_axis_movement", path, ap)
        if cw not in (0, 1, True, False):
            raise InputFileError(path, f"expected 0 or 1, got {cw!r}", field=ap + "clockwise_axis_movement")
        clockwise.append(bool(cw))
        linear.append(kind == "linear")
        if kind == "linear":
            for k in ("offset", "pivot_radius", "initial_stroke_length"):
                v = per_axis[k][-1]
                if not (v > 0 if k != "initial_stroke_length" else v >= 0) or v > MAX_HELIOSTAT_LENGTH_M:
                    raise InputFileError(path, f"implausible for a linear actuator: {v} m (expected "
                                               f"{'0' if k == 'initial_stroke_length' else '> 0'} to "
                                               f"{MAX_HELIOSTAT_LENGTH_M:g} m)", field=ap + k)
        for k in ("initial_angle", "min_movement_angle", "max_movement_angle"):
            if abs(per_axis[k][-1]) > 4 * math.pi:  # NaN (absent) passes
                raise InputFileError(path, f"implausible angle {per_axis[k][-1]} rad", field=ap + k)
        if per_axis["max_increment"][-1] < per_axis["min_increment"][-1]:
            raise InputFileError(path, "max_increment < min_increment", field=ap + "max_increment")

    def num(k):
        v = _number(kin, k, path, pre) if k in kin else 0.0
        if abs(v) > MAX_HELIOSTAT_LENGTH_M:
            raise InputFileError(path, f"implausible translation {v} m (at most {MAX_HELIOSTAT_LENGTH_M:g} m)",
                                 field=pre + k)
        return v

    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    joint_translation = t([[[num(f"joint_translation_{a}_{j}") for a in "enu"] for j in (1, 2)]])
    kinematics = Kinematics(
        position=position.reshape(1, 3),
        joint_translation=joint_translation,
        concentrator_translation=t([[num(f"concentrator_translation_{a}") for a in "enu"]]),
        joint_tilt=torch.zeros(1, 2, 3, dtype=torch.float64),
        concentrator_tilt=torch.zeros(1, 3, dtype=torch.float64),
        **{k: t([per_axis[k]]) for k in _ACTUATOR_KEYS},
        clockwise=torch.tensor([clockwise]), linear=torch.tensor([linear]),
        min_steps=t([per_axis["min_increment"]]), max_steps=t([per_axis["max_increment"]]),
        min_angle=t([per_axis["min_movement_angle"]]), max_angle=t([per_axis["max_movement_angle"]]),
    )
    fp = _get(data, "facet_properties", path)
    facets = _get(fp, "facets", path, "facet_properties.")
    if not isinstance(facets, list) or not facets:
        raise InputFileError(path, "expected a non-empty list of facets", field="facet_properties.facets")
    tr, ce, cn = [], [], []
    for i, f in enumerate(facets):
        fpre = f"facet_properties.facets[{i}]."
        tr.append(_vector(f, "translation_vector", path, fpre, bound=MAX_HELIOSTAT_LENGTH_M))
        ce.append(_vector(f, "canting_e", path, fpre, bound=MAX_HELIOSTAT_LENGTH_M))
        cn.append(_vector(f, "canting_n", path, fpre, bound=MAX_HELIOSTAT_LENGTH_M))
        if math.hypot(*ce[-1]) == 0 or math.hypot(*cn[-1]) == 0:
            raise InputFileError(path, "zero-length canting span vector", field=fpre + "canting_e")
    fac = Facets(t([tr]), t([ce]), t([cn]))
    width = _number(data, "width", path, positive=True) if "width" in data else float("nan")
    height = _number(data, "height", path, positive=True) if "height" in data else float("nan")
    for k, v in (("width", width), ("height", height)):
        if v > MAX_HELIOSTAT_LENGTH_M:
            raise InputFileError(path, f"implausible heliostat {k} {v} m", field=k)
    return HeliostatProperties(hid, kinematics, fac, width, height, str(data.get("renovation", "")), str(path))


# ---------------------------------------------------------------------------------------- calibration
@dataclass
class CalibrationRecord:
    """One camera-target calibration record.

    Attributes
    ----------
    record_id : int
    heliostat_id : str
    sun_azimuth, sun_elevation : float
        [rad], PAINT convention (azimuth 0 = south, +pi/2 = east).
    motor_steps : tuple of 2 float
        [steps].
    target : str
        Target name.
    focal_spot : dict of str -> torch.Tensor (3,)
        ENU [m] per source present (``"HeliOS"``, ``"UTIS"``).
    focal_spot_wgs84 : dict of str -> list of 3 float
    flux_png, flux_centered_png : str or None
        Image paths when present.
    datetime : str or None
        UTC ISO time from the metadata CSV.
    weather : dict or None
    path : str
    claim : str
        The heliostat the file names itself (``HeliostatId``; '' when it names none).
    """

    record_id: int
    heliostat_id: str
    sun_azimuth: float
    sun_elevation: float
    motor_steps: tuple[float, float]
    target: str
    focal_spot: dict
    focal_spot_wgs84: dict
    path: str
    flux_png: str | None = None
    flux_centered_png: str | None = None
    datetime: str | None = None
    weather: dict | None = None
    claim: str = ""

    def spot(self, prefer: str = "HeliOS") -> torch.Tensor:
        """Focal spot ENU (3,) from ``prefer``, falling back to the other source."""
        if prefer in self.focal_spot:
            return self.focal_spot[prefer]
        for s in FOCAL_SPOT_SOURCES:
            if s in self.focal_spot:
                return self.focal_spot[s]
        raise InputFileError(self.path, "no focal spot", field="focal_spot")


def read_calibration_record(path, site: Site, heliostat_id: str, known_targets=None) -> CalibrationRecord:
    """Read ``<id>-calibration-properties.json``; validates every field it uses."""
    data = read_json(path, MAX_RECORD_BYTES)
    base = os.path.basename(str(path))
    try:
        rid = int(base.split("-")[0])
    except ValueError:
        raise InputFileError(path, "file name does not start with a numeric record id") from None
    mp = _get(data, "motor_position", path)
    steps = (_number(mp, "axis_1_motor_position", path, "motor_position."),
             _number(mp, "axis_2_motor_position", path, "motor_position."))
    target = _get(data, "target_name", path)
    if not isinstance(target, str):
        raise InputFileError(path, f"expected a string, got {target!r}", field="target_name")
    if known_targets is not None and target not in known_targets:
        raise InputFileError(path, f"unknown target {target!r}; known: {', '.join(sorted(known_targets))}",
                             field="target_name")
    spots = _get(data, "focal_spot", path)
    if not isinstance(spots, dict):
        raise InputFileError(path, "expected an object", field="focal_spot")
    enu, lla = {}, {}
    for src in FOCAL_SPOT_SOURCES:
        if spots.get(src) is not None:
            lla[src] = _geodetic(spots, src, path, "focal_spot.")
            enu[src] = _near_plant(wgs84_to_enu(lla[src], site.reference), path, f"focal_spot.{src}")
    if not enu:
        raise InputFileError(path, "neither a HeliOS nor a UTIS centroid", field="focal_spot")
    az = _number(data, "sun_azimuth", path)
    el = _number(data, "sun_elevation", path)
    if not 0.0 < el <= 90.0:
        raise InputFileError(path, f"sun elevation {el} deg is at or below the horizon", field="sun_elevation")
    folder = os.path.dirname(str(path))
    png = os.path.join(folder, f"{rid}-flux.png")
    cpng = os.path.join(folder, f"{rid}-flux-centered.png")
    return CalibrationRecord(rid, heliostat_id, math.radians(az), math.radians(el), steps, target, enu, lla, str(path),
                             png if os.path.exists(png) else None, cpng if os.path.exists(cpng) else None,
                             claim=_claim(data))


def read_metadata(root) -> tuple[dict, dict]:
    """DateTime and weather per record id from ``metadata/*.csv`` (empty dicts when absent).

    Raises
    ------
    InputFileError
        A CSV that is not UTF-8, malformed, lacks its columns, or has a bad Id, a duplicate Id, a DateTime that
        is not a UTC ISO 8601 time (unparsable, or naming a zone such as ``CEST``; empty is allowed: no time) or
        a non-finite weather value (file, line and column named).
    """
    meta = os.path.join(str(root), "metadata", "calibration-metadata.csv")
    wpath = os.path.join(str(root), "metadata", "calibration-weather.csv")
    times = _read_csv(meta, _metadata_row, ("Id", "DateTime")) if regular_size(meta) is not None else {}
    weather = _read_csv(wpath, _weather_row, ("Id",)) if regular_size(wpath) is not None else {}
    return times, weather


def _metadata_row(row: dict):
    """A record's DateTime (None when empty: PAINT has records without one), checked to be a UTC ISO 8601 time
    (:func:`~heliotwin.io.records.parse_time`: a zone name such as ``CEST`` or unparsable text is refused)."""
    text = row["DateTime"]
    if not text or not text.strip():
        return None
    try:
        parse_time(text)
    except ValueError as exc:
        raise ValueError(f"column DateTime: {exc}") from None
    return text


def _weather_row(row: dict) -> dict:
    out = {}
    for k, v in row.items():
        if k in ("Id", "HeliostatId", "DateTime") or v in (None, ""):
            continue
        if k is None or not isinstance(v, str):
            raise ValueError("more fields than columns")
        x = float(v)
        if not math.isfinite(x):
            raise ValueError(f"column {k}: {v!r} is not a finite number")
        out[k] = x
    return out


def _read_csv(path: str, parse_row, columns, *, text: str | None = None, header: str | None = None,
              first_line: int = 2, known=()) -> dict:
    """Record id -> ``parse_row(row)`` for every row of a PAINT metadata CSV.

    ``text``: only this part of the file (from a line start on; ``header`` is then its header line and
    ``first_line`` the file's line number of the part's first row, ``known`` the ids of the rows before it,
    for the duplicate check); default: the whole file."""
    out, line = {}, first_line - 1
    if text is None:
        data = read_regular(path, MAX_CSV_BYTES)
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            lines_before = data.count(b"\n", 0, exc.start)
            raise InputFileError(path, f"not UTF-8 text (byte {exc.start} after line {lines_before})") from None
    try:
        with io.StringIO(text, newline="") as fh:
            lines = fh if header is None else itertools.chain([header], fh)
            reader = csv.DictReader(lines)
            if not all(c in (reader.fieldnames or []) for c in columns):
                raise InputFileError(path, f"needs columns {', '.join(columns)}", field="header")
            for line, row in enumerate(reader, start=first_line):
                try:
                    rid = int(row["Id"])
                except (TypeError, ValueError):
                    raise InputFileError(path, f"line {line}: bad Id {_short(row.get('Id'))}", field="Id") from None
                if rid in out or rid in known:
                    raise InputFileError(path, f"line {line}: duplicate Id {rid}", field="Id")
                try:
                    out[rid] = parse_row(row)
                except (TypeError, ValueError) as exc:
                    raise InputFileError(path, f"line {line}: {' '.join(str(exc).split())}") from None
    except UnicodeDecodeError as exc:
        raise InputFileError(path, f"not UTF-8 text (byte {exc.start} after line {line})") from None
    except csv.Error as exc:
        raise InputFileError(path, f"line {line}: malformed CSV ({exc})") from None
    return out


# ------------------------------------------------------------------------------------------- dataset
@dataclass
class PaintDataset:
    """A PAINT folder read into a plant and its validated record table.

    Attributes
    ----------
    root : str
    plant : Plant
        Nominal kinematics, ideal surfaces.
    records : RecordTable
        Every usable calibration record, heliostat axis = ``plant.field.ids``.
    skipped : list of dict
        ``{"record_id", "heliostat_id", "reason"}`` per record that could not be used.
    properties : dict
        Heliostat id -> :class:`HeliostatProperties`.
    reading : dict
        How the records were read (:func:`read_records`' ``stats``: files listed, parsed now, from the index).
    """

    root: str
    plant: Plant
    records: RecordTable
    skipped: list = field(default_factory=list)
    properties: dict = field(default_factory=dict)
    reading: dict = field(default_factory=dict)

    def on_plant(self, plant: Plant, source: str = "scenario") -> "PaintDataset":
        """The same records on another plant of the same site (e.g. a calibrated scenario): the table's
        heliostat axis becomes ``plant.field.ids`` (each must be in this folder), records of other heliostats
        are left out. ``source`` names the plant in errors."""
        _check_same_site(self.plant.site, plant.site, source, self.root)
        mine = set(self.plant.field.ids)
        missing = [h for h in plant.field.ids if h not in mine]
        if missing:
            raise InputFileError(source, f"heliostat(s) {', '.join(missing[:5])} are not in the PAINT folder "
                                         f"{self.root}", field="/field/ids")
        if self.properties:
            check_positions(self.root, list(plant.field.ids),
                            torch.cat([self.properties[h].kinematics.position for h in plant.field.ids]),
                            plant.field.kinematics.position, source)
        ids = set(plant.field.ids)
        skipped = [s for s in self.skipped if s["heliostat_id"] in ids]
        return PaintDataset(self.root, plant, self.records.for_heliostats(plant.field.ids), skipped,
                            {h: p for h, p in self.properties.items() if h in ids}, dict(self.reading))

    def records_of(self, heliostat_id: str) -> RecordTable:
        """Usable records of one heliostat, in reading order (ascending record id)."""
        return self.records.select(heliostat=heliostat_id)

    def record(self, record_id: int) -> RecordTable:
        """One record as a one-row table; a skipped record raises with its reason."""
        for s in self.skipped:
            if s["record_id"] == int(record_id):
                raise InputFileError(s["path"], f"record {record_id} of {s['heliostat_id']} cannot be used: "
                                                f"{s['reason']}", field=s["field"])
        try:
            return self.records.subset([self.records.index_of(record_id)])
        except KeyError:
            raise InputFileError(self.root, f"record {record_id} not found for heliostat(s) "
                                            f"{', '.join(self.plant.field.ids)}", field="record") from None


def _check_same_site(mine: Site, theirs: Site, source, root) -> None:
    """A plant of another site than the folder's is a one-line error naming ``source``."""
    same_site = all(abs(float(getattr(mine, k)) - float(getattr(theirs, k))) <= tol for k, tol in
                    (("latitude_deg", 1e-9), ("longitude_deg", 1e-9), ("altitude_m", 1e-6)))
    if not same_site:
        raise InputFileError(source, f"site ({theirs.latitude_deg}, {theirs.longitude_deg}, {theirs.altitude_m}) "
                                     f"is not the PAINT folder's {root}", field="/site")


def load_paint_on_plant(root, plant: Plant, *, source: str = "scenario", focal_spot: str = "HeliOS",
                        plane_tolerance: float = 0.1, cache: bool | None = None,
                        skip_record_ids=None, seen_owners=None, require_times: bool = True) -> PaintDataset:
    """The records of ``plant``'s heliostats in the PAINT folder ``root``, judged on ``plant`` (its targets and
    motor ranges): what a learner that starts from a scenario needs from a folder that grows
    (:func:`read_records` with the record index; ``skip_record_ids``, ``seen_owners`` and ``require_times``
    as there: by default a folder without its metadata CSV is refused, an update needs the records' times [s];
    ``plane_tolerance`` [m] as in :func:`heliotwin.io.records.build_record_table`).
    Of the folder's heliostat properties only the positions are read, to check that the folder is this plant's
    (:func:`check_positions`). The dataset's ``properties`` are empty; ``reading`` also counts
    ``unknown_heliostats`` and ``unknown_records`` (heliostat folders with records that ``plant`` does not
    hold, listed in ``unknown_ids``, first 20; ``unknown_counts``: every such heliostat's record count).

    Raises
    ------
    InputFileError
        The folder's site is not ``plant``'s, a heliostat of ``plant`` has no folder there (``source`` names
        the plant), a heliostat's position there is not the plant's, a record lies under another heliostat than
        the plant saw it under, or as :func:`read_records`.
    """
    root = str(root)
    site, targets = read_tower(find_tower_file(root))
    _check_same_site(site, plant.site, source, root)
    available = list_heliostats(root)
    ids = list(plant.field.ids)
    have = set(available)
    missing = [h for h in ids if h not in have]
    if missing:
        raise InputFileError(source, f"heliostat(s) {', '.join(missing[:5])} are not in the PAINT folder {root}",
                             field="/field/ids")
    positions = _folder_positions(root, ids, site)
    check_positions(root, ids, positions, plant.field.kinematics.position, source)
    reading: dict = {}
    raw = read_records(root, ids, site, targets, cache=cache, stats=reading, skip_record_ids=skip_record_ids,
                       seen_owners=seen_owners, require_times=require_times)
    table, skipped = build_record_table(plant, raw, focal_spot=focal_spot, plane_tolerance=plane_tolerance)
    known = set(ids)
    unknown = [h for h in available if h not in known]
    counts = {h: len(f) for h, f in zip(unknown, (_record_names(os.path.join(root, h, "Calibration"))
                                                  for h in unknown)) if f}
    reading.update(unknown_heliostats=len(counts), unknown_records=int(sum(counts.values())),
                   unknown_ids=sorted(counts)[:20], unknown_counts=counts)
    return PaintDataset(root, plant, table, skipped, {}, reading)


def _properties_path(root: str, heliostat_id: str) -> str:
    return os.path.join(root, heliostat_id, "Properties", f"{heliostat_id}-heliostat-properties.json")


def _folder_positions(root: str, ids: list, site: Site) -> torch.Tensor:
    """The ENU positions [H, 3] [m] of heliostats ``ids`` in their Properties files (only that field read and
    checked): one file read per heliostat, the WGS84 -> ENU conversion batched over all of them."""
    if not ids:
        return torch.zeros(0, 3, dtype=torch.float64)
    paths = [_properties_path(root, h) for h in ids]
    lla = torch.tensor([_geodetic(read_json(p), "heliostat_position", p) for p in paths], dtype=torch.float64)
    enu = wgs84_to_enu(lla, site.reference)
    far = (torch.hypot(enu[:, 0], enu[:, 1]) > MAX_PLANT_RADIUS_M) | (enu[:, 2].abs() > MAX_PLANT_HEIGHT_M)
    if bool(far.any()):  # the first implausible one, refused as every point the reader converts
        i = int(far.nonzero()[0])
        _near_plant(enu[i], paths[i], "heliostat_position")
    return enu


def check_positions(root, ids, folder_positions: torch.Tensor, plant_positions: torch.Tensor, source) -> None:
    """Refuse a folder whose heliostats stand elsewhere than the plant's of the same ids.

    Parameters
    ----------
    root : str
        The PAINT folder (its Properties files are named in the error).
    ids : list of str, H
    folder_positions, plant_positions : torch.Tensor, [H, 3]
        ENU [m] about the site's reference, from the folder's Properties and from the plant.
    source : str
        Names the plant in the error.

    Raises
    ------
    InputFileError
        The first heliostat farther than :data:`MAX_POSITION_MISMATCH_M` from the plant's (the folder is
        another plant's: ids repeat between plants, positions do not).
    """
    if not len(ids):
        return
    d = torch.linalg.vector_norm(folder_positions.to(torch.float64) - plant_positions.to(torch.float64), dim=-1)
    far = (~(d <= MAX_POSITION_MISMATCH_M)).nonzero().flatten()
    if len(far):
        i = int(far[0])
        h = ids[i]
        where = ", ".join(f"{x:.1f}" for x in plant_positions[i].tolist())
        more = f" (and {len(far) - 1} more)" if len(far) > 1 else ""
        raise InputFileError(_properties_path(str(root), h),
                             f"heliostat {h} is {float(d[i]):.1f} m from {source}'s {h} (ENU {where} m){more}; "
                             "is this another plant's folder?", field="heliostat_position")


def _record_names(folder: str) -> list:
    """Names of the record files in a Calibration folder (none when it is missing)."""
    try:
        return [e.name for e in os.scandir(folder) if e.name.endswith(RECORD_SUFFIX) and not e.name.startswith(".")]
    except OSError:
        return []


def _record_number(path: str) -> int:
    """Numeric record id of a calibration file name (-1 for a name that does not start with one)."""
    head = os.path.basename(path).split("-")[0]
    return int(head) if head.isdigit() else -1


def list_heliostats(root) -> list[str]:
    """Heliostat folders (``AA39``-style names with a Properties file) of a PAINT download, sorted."""
    root = str(root)
    if not os.path.isdir(root):
        raise InputFileError(root, "PAINT folder not found")
    return sorted(d for d in os.listdir(root) if HELIOSTAT_DIR.match(d)
                  and os.path.exists(os.path.join(root, d, "Properties", f"{d}-heliostat-properties.json")))


def load_paint(root, heliostats=None, *, surface_control_points=(4, 4), surface_degree=(2, 2),
               with_records: bool = True, focal_spot: str = "HeliOS", plane_tolerance: float = 0.1,
               cache: bool | None = None, now=None, require_times: bool = False) -> PaintDataset:
    """Read a PAINT folder into a :class:`Plant` (ideal flat canted surfaces) and its records.

    Parameters
    ----------
    root : path
        The PAINT download folder.
    heliostats : list of str, optional
        Heliostat ids to read (default: all with a properties file). Unknown ids raise.
    surface_control_points, surface_degree : tuple of int
        NURBS resolution of the ideal facets: ``(nu, nv)`` control points and
        ``(p, q)`` degrees per facet [1].
    with_records : bool
        Also read every calibration record.
    focal_spot, plane_tolerance, now
        See :func:`heliotwin.io.records.build_record_table`, which judges every record (``plane_tolerance``
        [m]: largest distance of a centroid from its target plane; ``now``: the time of reading, default the
        current time, after which a record is dated in the future).
    require_times : bool
        Refuse a folder without ``metadata/calibration-metadata.csv`` (:func:`read_records`).
    cache : bool or None
        Use the folder's incremental record index (:mod:`heliotwin.io.record_index`): files unchanged since
        they were indexed are not parsed again, new ones are parsed and appended. None: for folders of at least
        :data:`CACHE_MIN_RECORDS` record files (``HELIOTWIN_CACHE=1``: every folder, ``=0``: none).
    """
    root = str(root)
    site, targets = read_tower(find_tower_file(root))
    available = list_heliostats(root)
    ids = available if heliostats is None else list(heliostats)
    have = set(available)
    missing = [h for h in ids if h not in have]
    if missing:
        raise InputFileError(root, f"heliostat(s) {', '.join(missing)} not found; available: {', '.join(available)}",
                             field="heliostats")
    if not ids:
        raise InputFileError(root, "no heliostats with a properties file")
    props = {h: read_heliostat_properties(_properties_path(root, h), site, h) for h in ids}
    nfac = {p.facets.translation.shape[1] for p in props.values()}
    if len(nfac) != 1:
        raise InputFileError(root, f"heliostats have different facet counts {sorted(nfac)}; load them separately",
                             field="facet_properties.number_of_facets")
    kin = Kinematics.concatenate([props[h].kinematics for h in ids])
    fac = Facets(*(torch.cat([getattr(props[h].facets, a) for h in ids])
                   for a in ("translation", "canting_e", "canting_n")))
    surfaces = facet_ops.ideal_surfaces(fac, num_control_points=surface_control_points, degree=surface_degree)
    fld = Field(ids, kin, fac, surfaces, torch.tensor([props[h].width for h in ids], dtype=torch.float64),
                torch.tensor([props[h].height for h in ids], dtype=torch.float64), [props[h].renovation for h in ids])
    plant = Plant(site, targets, fld, SunSettings())
    reading: dict = {}
    raw = read_records(root, ids, site, targets, cache=cache, stats=reading,
                       require_times=require_times) if with_records else []
    table, skipped = build_record_table(plant, raw, focal_spot=focal_spot, plane_tolerance=plane_tolerance, now=now)
    return PaintDataset(root, plant, table, skipped, props, reading)


# ------------------------------------------------------------------------------------ fast record reading
#: Folders with at least this many record files keep a record index by default (``load_paint(cache=None)``;
#: ``HELIOTWIN_CACHE=1`` indexes every folder, ``HELIOTWIN_CACHE=0`` none).
CACHE_MIN_RECORDS = 5000
#: Suffix of a calibration record file's name.
RECORD_SUFFIX = "-calibration-properties.json"


@dataclass
class Listing:
    """The record files of some heliostats of a PAINT folder, as listed now (arrays over F files, in reading
    order: heliostat by heliostat, ascending record id).

    Attributes
    ----------
    folders : list of str
        Each heliostat's Calibration folder.
    names : list of set
        The image (``.png``) file names in each of those folders (a record's images are looked up there).
    heliostat : np.ndarray [F] int
        Index of each file's heliostat.
    name : np.ndarray [F] bytes
        File names.
    size, mtime_ns, ctime_ns, inode : np.ndarray [F] int64
        The index key's part of each file (of a link: of its target). The status-change time and inode catch a
        rewrite whose size and modification time were restored (``touch -d``, ``cp -p``, ``rsync -a``).
    skipped : int
        Record files left out by id before they were stat'ed (:func:`_listing`'s ``skip``).
    refused : list of dict
        Record files that are not read: not a regular file (a FIFO, a device, a directory, a link to one or a
        dangling link) or larger than :data:`MAX_RECORD_BYTES`, or whose heliostat contradicts the folder; as
        :func:`heliotwin.io.records.build_record_table`'s ``skipped`` (``field``: ``file``, ``size`` or
        ``HeliostatId``).
    """

    folders: list
    names: list
    heliostat: np.ndarray
    name: np.ndarray
    size: np.ndarray
    mtime_ns: np.ndarray
    ctime_ns: np.ndarray = None
    inode: np.ndarray = None
    skipped: int = 0
    refused: list = field(default_factory=list)

    def __post_init__(self):
        n = len(self.name)
        if self.ctime_ns is None:
            self.ctime_ns = np.full(n, -1, dtype=np.int64)
        if self.inode is None:
            self.inode = np.full(n, -1, dtype=np.int64)

    def subset(self, keep: np.ndarray, *, left_out_by_id: bool = True) -> "Listing":
        """The files of ``keep`` ([F] bool), folders, images and refusals unchanged; the others count as left out
        by id (``left_out_by_id``) or simply go (refused: the caller adds them to ``refused``)."""
        gone = int((~keep).sum()) if left_out_by_id else 0
        return Listing(self.folders, self.names, self.heliostat[keep], self.name[keep], self.size[keep],
                       self.mtime_ns[keep], self.ctime_ns[keep], self.inode[keep], self.skipped + gone,
                       list(self.refused))

    def files(self, rows=None) -> list:
        """(heliostat index, Calibration folder, file name) per file (of ``rows``, default all)."""
        rows = range(len(self.name)) if rows is None else rows
        return [(int(self.heliostat[i]), self.folders[int(self.heliostat[i])], self.name[i].decode()) for i in rows]


def _refusal(path: str, heliostat_id: str, reason: str, fld: str = "file") -> dict:
    """A record left out by the reader, as :func:`heliotwin.io.records.build_record_table` words a dropped one."""
    return {"record_id": _record_number(path), "heliostat_id": heliostat_id, "reason": reason, "path": path,
            "field": fld}


def _listing(root: str, ids, skip=None, owners=None) -> Listing:
    """The record files of heliostats ``ids`` of ``root`` with their size, times and inode; those whose record id
    (the name's head) is in ``skip`` (a set of int, optional) are left out before they are stat'ed (an update of
    a plant that has seen most of a folder: one stat per file was most of its reading). A file that is not a
    regular file (following links) or larger than :data:`MAX_RECORD_BYTES` is refused (:attr:`Listing.refused`),
    never opened.

    ``owners`` (record id -> heliostat id, optional): the heliostat a plant saw each record id under; a file
    under another heliostat with such an id is a one-line error (another plant's folder, or a record moved).
    """
    skip = skip or set()
    owners = owners or {}
    left_out = 0
    refused = []
    folders, names, hidx, fnames, sizes, mtimes, ctimes, inodes = [], [], [], [], [], [], [], []
    for h, hid in enumerate(ids):
        folder = os.path.join(root, hid, "Calibration")
        folders.append(folder)
        try:
            entries = list(os.scandir(folder))
        except (FileNotFoundError, NotADirectoryError):  # no records (what a glob of it finds)
            names.append(set())
            continue
        except OSError as exc:
            raise InputFileError(folder, f"cannot read ({exc.strerror})") from None
        files, images = [], set()
        for e in entries:  # one pass: record files, and the images a record may have
            name = e.name
            if name.endswith(RECORD_SUFFIX):
                if not name.startswith("."):
                    head = name.split("-", 1)[0]
                    rid = int(head) if head.isdigit() else -1
                    if owners and owners.get(rid, hid) != hid:
                        raise InputFileError(os.path.join(folder, name), f"record {rid} is under heliostat {hid} "
                                             f"but the plant saw it under {owners[rid]}; is this another plant's "
                                             "folder?", field="id")
                    if rid in skip:
                        left_out += 1
                        continue
                    files.append((rid, name, e))
            elif name.endswith(".png"):
                images.add(name)
        names.append(images)
        files.sort(key=lambda item: item[0])  # ascending record id (stable: ties keep the folder's order)
        for _, name, e in files:
            try:
                st = e.stat()  # follows a link: its target is what is read
            except FileNotFoundError:
                refused.append(_refusal(os.path.join(folder, name), hid,
                                        "not a regular file (a dangling symbolic link)"))
                continue
            except OSError as exc:
                refused.append(_refusal(os.path.join(folder, name), hid, f"cannot stat ({exc.strerror})"))
                continue
            why, fld = _not_regular(st.st_mode), "file"
            if why is None and st.st_size > MAX_RECORD_BYTES:
                why, fld = _too_big(st.st_size, MAX_RECORD_BYTES), "size"
            if why is not None:
                refused.append(_refusal(os.path.join(folder, name), hid, why, fld))
                continue
            sizes.append(st.st_size)
            mtimes.append(st.st_mtime_ns)
            ctimes.append(st.st_ctime_ns)
            inodes.append(st.st_ino)
            fnames.append(name.encode())
            hidx.append(h)
    i64 = dict(dtype=np.int64)
    return Listing(folders, names, np.asarray(hidx, **i64), np.asarray(fnames, dtype="S"), np.asarray(sizes, **i64),
                   np.asarray(mtimes, **i64), np.asarray(ctimes, **i64), np.asarray(inodes, dtype=np.uint64).astype(
                       np.int64), left_out, refused)


def _parse_record(data: dict, path: str) -> tuple:
    """The fields of a parsed record file (focal spots lat-first WGS84, NaN where absent), checked like
    :func:`read_calibration_record` (raises a plain ``ValueError`` on anything it would reject; the caller
    then lets that function word the error). The target is checked against the tower at assembly."""
    rid = int(os.path.basename(path).split("-")[0])
    mp = data["motor_position"]
    steps = (mp["axis_1_motor_position"], mp["axis_2_motor_position"])
    target = data["target_name"]
    spots = data["focal_spot"]
    az, el = data["sun_azimuth"], data["sun_elevation"]
    if not (all(_finite_number(x) for x in (*steps, az, el)) and isinstance(target, str) and isinstance(spots, dict)
            and 0.0 < float(el) <= 90.0):
        raise ValueError("invalid record")
    lla = [[math.nan] * 3, [math.nan] * 3]
    for k, src in enumerate(FOCAL_SPOT_SOURCES):
        v = spots.get(src)
        if v is not None:
            if not (isinstance(v, (list, tuple)) and len(v) == 3 and all(_finite_number(x) for x in v)
                    and -90.0 <= v[0] <= 90.0 and -180.0 <= v[1] <= 180.0):
                raise ValueError("invalid focal spot")
            lla[k] = [float(x) for x in v]
    if math.isnan(lla[0][0]) and math.isnan(lla[1][0]):
        raise ValueError("no focal spot")
    return rid, float(steps[0]), float(steps[1]), target, lla, math.radians(az), math.radians(el), _claim(data)


#: Keys under which a record file may name its heliostat (PAINT's files do not; some exports do).
CLAIM_KEYS = ("HeliostatId", "heliostat_id")


def _claim(data: dict) -> str:
    """The heliostat a record file names itself ('' when it names none)."""
    for k in CLAIM_KEYS:
        v = data.get(k)
        if isinstance(v, str) and v.strip():
            return v.strip()
    return ""


def _parse_files(root: str, ids, listing: Listing, rows, site: Site, targets: dict) -> dict:
    """Index entries (:mod:`heliotwin.io.record_index`) of the listed files ``rows``, parsed now. A file the
    fast parser does not accept is read by :func:`read_calibration_record`, which words its error."""
    out = []
    files = listing.files(rows)
    paths = [os.path.join(folder, name) for _, folder, name in files]
    with read_ahead(paths):  # many files from a disk: the kernel reads them while this loop parses
        for (h, _, _), path in zip(files, paths):
            try:
                data = read_json(path, MAX_RECORD_BYTES)
                out.append(_parse_record(data, path))
            except (InputFileError, ValueError, KeyError, TypeError, AttributeError, OverflowError):
                r = read_calibration_record(path, site, ids[h], known_targets=targets)  # words the error, if any
                lla = [r.focal_spot_wgs84.get(src, [math.nan] * 3) for src in FOCAL_SPOT_SOURCES]
                out.append((r.record_id, *map(float, r.motor_steps), r.target, lla, r.sun_azimuth,
                            r.sun_elevation, r.claim))
    n = len(out)
    return {"heliostat": np.asarray([ids[int(listing.heliostat[i])] for i in rows], dtype="U").reshape(n),
            "name": listing.name[rows].reshape(n), "size": listing.size[rows].reshape(n),
            "mtime_ns": listing.mtime_ns[rows].reshape(n), "ctime_ns": listing.ctime_ns[rows].reshape(n),
            "inode": listing.inode[rows].reshape(n),
            "record_id": np.asarray([r[0] for r in out], dtype=np.int64).reshape(n),
            "motor_steps": np.asarray([[r[1], r[2]] for r in out], dtype=np.float64).reshape(n, 2),
            "target": np.asarray([r[3] for r in out], dtype="U").reshape(n),
            "lla": np.asarray([r[4] for r in out], dtype=np.float64).reshape(n, 2, 3),
            "sun_azimuth": np.asarray([r[5] for r in out], dtype=np.float64).reshape(n),
            "sun_elevation": np.asarray([r[6] for r in out], dtype=np.float64).reshape(n),
            "claim": np.asarray([r[7] for r in out] or [""], dtype="U")[:n]}


def _read_one_by_one(listing, ids, site: Site, targets: dict, times: dict, weather: dict) -> RawRecords:
    """Every record through :func:`read_calibration_record` (the reference reader: it words the first bad file
    in reading order)."""
    records = []
    for h, folder, name in listing.files():
        r = read_calibration_record(os.path.join(folder, name), site, ids[h], known_targets=targets)
        r.datetime = times.get(r.record_id)
        r.weather = weather.get(r.record_id)
        records.append(r)
    return raw_from_records(records)


def _assemble(entries: dict, listing: Listing, ids, site: Site, targets: dict, meta: dict) -> RawRecords | None:
    """:class:`RawRecords` of the entries of the listed files (one per file, in listing order): focal spots to
    ENU in one batch, times and weather joined by record id, images looked up in the listing. None when a
    record names a target the tower lacks or a centroid lies implausibly far (the one-by-one reader then
    words the error)."""
    n = len(entries["record_id"])
    if n and not bool(np.isin(entries["target"], np.asarray(list(targets), dtype="U")).all()):
        return None
    lla = entries["lla"]
    present = ~np.isnan(lla[..., 0])
    enu = torch.full((n, len(SOURCES), 3), float("nan"), dtype=torch.float64)
    if present.any():
        enu[torch.from_numpy(present)] = wgs84_to_enu(torch.from_numpy(lla[present]), site.reference)
    far = (torch.hypot(enu[..., 0], enu[..., 1]) > MAX_PLANT_RADIUS_M) | (enu[..., 2].abs() > MAX_PLANT_HEIGHT_M)
    if bool(far.any()):
        return None
    rid = entries["record_id"]
    dt, t = _join(rid, meta["ids"], meta["datetime"], meta["time"], None)
    wx = _join(rid, meta["weather_ids"], None, meta["weather"], len(WEATHER_KEYS))[1]
    hidx = listing.heliostat
    names = listing.name.astype("U").tolist() if n else []
    prefix = [folder + os.sep for folder in listing.folders]
    paths = [prefix[h] + nm for h, nm in zip(hidx.tolist(), names)]
    rid_list = rid.tolist()
    png, cpng = [], []
    for h, x in zip(hidx.tolist(), rid_list):
        have = listing.names[h]
        if not have:  # most folders hold no image
            png.append(None)
            cpng.append(None)
            continue
        png.append(prefix[h] + f"{x}-flux.png" if f"{x}-flux.png" in have else None)
        cpng.append(prefix[h] + f"{x}-flux-centered.png" if f"{x}-flux-centered.png" in have else None)
    f64 = dict(dtype=torch.float64)
    return RawRecords(
        heliostat_ids=list(ids), heliostat_index=torch.from_numpy(hidx.astype(np.int64)),
        record_id=torch.from_numpy(rid.astype(np.int64)), sun_azimuth=torch.tensor(entries["sun_azimuth"], **f64),
        sun_elevation=torch.tensor(entries["sun_elevation"], **f64),
        motor_steps=torch.tensor(entries["motor_steps"], **f64).reshape(n, 2), target=entries["target"].tolist(),
        focal_spots=enu, present=torch.from_numpy(present), time=torch.from_numpy(t),
        weather=torch.from_numpy(wx).reshape(n, len(WEATHER_KEYS)), datetime=dt, flux_png=png, flux_centered_png=cpng,
        path=paths)


def _join(rid: np.ndarray, ids: np.ndarray, text, values: np.ndarray, width: int | None):
    """Per record id: the text (list, None where absent) and values (NaN where absent) of the CSV rows ``ids``."""
    n = len(rid)
    shape = (n,) if width is None else (n, width)
    out = np.full(shape, np.nan)
    have = np.zeros(n, dtype=bool)
    pos = np.zeros(n, dtype=np.int64)
    if len(ids):
        order = np.argsort(ids, kind="stable")
        at = np.searchsorted(ids[order], rid).clip(max=len(ids) - 1)
        have = ids[order][at] == rid
        pos = order[at]
        out[have] = values[pos[have]]
    words = None
    if text is not None:
        words = [None] * n
        for i in np.nonzero(have)[0].tolist():
            words[i] = text[pos[i]]
    return words, out


def _stored_text(stored: dict) -> list:
    """The text column of a stored CSV parse (None where the row had none)."""
    return [None if none else str(x) for x, none in zip(stored["text"].tolist(), stored["text_none"].tolist())]


def _csv_columns(root: str, name: str, parse_row, columns, to_row, width: int | None, use_index: bool) -> dict:
    """The rows of ``root/metadata/<name>`` as columns: ``ids`` [M] int64, ``text`` (str or None per row, or
    absent), ``values`` [M] or [M, width] float64, ``heliostat`` [M] str (the row's HeliostatId, '' without
    one; ``to_row`` returns ``(text, values)`` or ``(text, values, heliostat)``); parsed from the record index
    where it holds the file's bytes (only the rows appended since are parsed,
    :func:`heliotwin.io.record_index.csv_cached`). A missing file has no rows; one that is not a regular file
    or larger than :data:`MAX_CSV_BYTES` is a one-line error (:func:`read_regular`)."""
    path = os.path.join(root, "metadata", name)
    empty = {"ids": np.zeros(0, dtype=np.int64), "text": [],
             "values": np.zeros((0,) if width is None else (0, width)), "heliostat": np.zeros(0, dtype="U1")}
    if regular_size(path) is None:
        return empty
    stored, covered = record_index.csv_cached(root, path) if use_index else (None, 0)
    data = read_regular(path, MAX_CSV_BYTES, start=covered)
    if stored is not None and not data:
        return {"ids": stored["ids"], "values": stored["values"], "text": _stored_text(stored),
                "heliostat": stored["heliostat"]}
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(path, f"not UTF-8 text (byte {covered + exc.start})") from None
    header = None if stored is None else str(stored["header"])
    first = 2 if stored is None else int(stored["lines"]) + 1
    known = set() if stored is None else set(stored["ids"].tolist())
    rows = _read_csv(path, parse_row, columns, text=text, header=header, first_line=first, known=known)
    new_ids = np.fromiter(rows, dtype=np.int64, count=len(rows))
    parsed = [to_row(v) for v in rows.values()]
    new_text = [p[0] for p in parsed]
    new_values = np.asarray([p[1] for p in parsed], dtype=np.float64).reshape((len(rows),) + empty["values"].shape[1:])
    new_hid = np.asarray([p[2] if len(p) > 2 else "" for p in parsed] or [""], dtype="U")[:len(parsed)]
    if stored is None:
        out = {"ids": new_ids, "text": new_text, "values": new_values, "heliostat": new_hid}
        header = text.splitlines(keepends=True)[0] if text else ""
    else:
        out = {"ids": np.concatenate([stored["ids"], new_ids]),
               "values": np.concatenate([stored["values"], new_values]), "text": _stored_text(stored) + new_text,
               "heliostat": np.concatenate([stored["heliostat"], new_hid])}
    if use_index and text.endswith("\n"):
        lines = (first - 1) + text.count("\n") - (1 if stored is None else 0)
        record_index.store_csv(root, path, covered + len(data), {
            "ids": out["ids"], "values": out["values"], "header": np.array(header), "lines": np.array(lines),
            "text": np.asarray(["" if x is None else x for x in out["text"]], dtype="U"),
            "text_none": np.asarray([x is None for x in out["text"]], dtype=bool),
            "heliostat": np.asarray(out["heliostat"], dtype="U")})
    return out


def _metadata_with_heliostat(row: dict):
    """A metadata row's DateTime (:func:`_metadata_row`) and its HeliostatId ('' without one)."""
    return _metadata_row(row), str(row.get("HeliostatId") or "").strip()


def _metadata_columns(root: str, use_index: bool) -> dict:
    """Times, heliostats and weather of the folder's records as columns (:func:`_csv_columns`)."""
    meta = _csv_columns(root, "calibration-metadata.csv", _metadata_with_heliostat, ("Id", "DateTime"),
                        lambda v: (v[0], parse_time(v[0]), v[1]), None, use_index)
    wx = _csv_columns(root, "calibration-weather.csv", _weather_row, ("Id",),
                      lambda d: (None, [float(d.get(k, float("nan"))) for k in WEATHER_KEYS]), len(WEATHER_KEYS),
                      use_index)
    return {"ids": meta["ids"], "datetime": meta["text"], "time": meta["values"], "heliostat": meta["heliostat"],
            "weather_ids": wx["ids"], "weather": wx["values"]}


#: A metadata CSV of at least this many bytes (~2,600 rows of a simulated folder's ~76 bytes) is parsed through
#: the record index even when few record files are read: it holds every record of the folder, so reading one
#: heliostat of a large folder parsed all of its rows (2,000 heliostats, 187,000 rows: 3 s per heliostat in
#: ``reconstruct --heliostats``).
CACHE_MIN_METADATA_BYTES = 200_000


def _metadata_worth_index(root: str, cache: bool | None) -> bool:
    """Whether the folder's metadata CSVs go through the record index: :func:`_use_index`'s rules (``cache``,
    ``HELIOTWIN_CACHE``), with a large metadata CSV counting as a large folder."""
    try:
        size = os.path.getsize(os.path.join(root, "metadata", "calibration-metadata.csv"))
    except OSError:
        size = 0
    return _use_index(cache, CACHE_MIN_RECORDS if size >= CACHE_MIN_METADATA_BYTES else 0)


def _use_index(cache: bool | None, files: int) -> bool:
    if cache is not None:
        return bool(cache)
    flag = os.environ.get("HELIOTWIN_CACHE")
    return flag != "0" and (flag == "1" or files >= CACHE_MIN_RECORDS)


def read_records(root, ids, site: Site, targets: dict, *, cache: bool | None = None,
                 stats: dict | None = None, skip_record_ids=None, seen_owners=None,
                 require_times: bool = False) -> RawRecords:
    """Every calibration record of heliostats ``ids`` of a PAINT folder, parsed (not yet judged), with the
    metadata's time and weather. With the record index (``cache``, see :func:`load_paint`) only files that
    are new or changed since they were indexed are parsed (:mod:`heliotwin.io.record_index`), and they are
    appended to it.

    ``stats``, when given, receives ``files`` (record files listed), ``parsed`` (read from the files now),
    ``indexed`` (taken from the index), ``skipped`` (records left out by id) and ``refused`` (left out by the
    reader: :attr:`Listing.refused`).

    ``skip_record_ids`` (an int array, optional): records left out once their ids are known, before they are
    assembled (an update that needs only the records its plant has not seen; seen ones are most of a folder).
    ``seen_owners`` (record id -> heliostat id, optional): where a plant saw its records (:func:`_listing`).
    ``require_times``: a folder without ``metadata/calibration-metadata.csv`` is a one-line error (the records'
    times [s] are there; a command that orders records in time cannot use them without).

    A record file that is not a regular file, is too large, or whose heliostat (its ``HeliostatId``, or its
    metadata row's) is not the folder's, is left out and returned in ``RawRecords.refused``.

    Raises
    ------
    InputFileError
        As :func:`read_calibration_record` and :func:`read_metadata` (the first bad file in reading order).
    """
    root = str(root)
    meta_path = os.path.join(root, "metadata", "calibration-metadata.csv")
    if require_times and regular_size(meta_path) is None:
        raise InputFileError(meta_path, "missing: the records' times (DateTime) are there; without it no record "
                                        "can be placed in time")
    skip = None if skip_record_ids is None else np.asarray(skip_record_ids, dtype=np.int64)
    listing = _listing(root, ids, None if skip is None else set(skip.tolist()), seen_owners)
    n = len(listing.name)
    use = _use_index(cache, n + listing.skipped)
    rows = np.full(n, -1, dtype=np.int64)
    if use:
        known, segments = record_index.read_entries(root)
        rows = record_index.match(known, [ids[h] for h in listing.heliostat.tolist()], listing.name.tolist(),
                                  listing.size, listing.mtime_ns, listing.ctime_ns, listing.inode)
    else:
        known, segments = record_index.empty_entries(), []
    todo = np.nonzero(rows < 0)[0]
    fresh = _parse_files(root, ids, listing, todo, site, targets)
    if use and len(todo):
        record_index.append_entries(root, fresh)
    if use:
        valid = np.zeros(len(known["record_id"]), dtype=bool)
        valid[rows[rows >= 0]] = True
        if skip is not None and listing.skipped:  # left out unlisted, not gone: their entries stay
            valid |= np.isin(known["record_id"], skip)
        listed = np.isin(known["heliostat"], np.asarray(list(ids), dtype="U"))
        record_index.compact(root, known, valid | ~listed, segments)
    order = np.concatenate([rows[rows >= 0], len(known["record_id"]) + np.arange(len(todo))])
    place = np.concatenate([np.nonzero(rows >= 0)[0], todo])
    both = record_index.concat_entries([known, fresh])
    rows_in_listing_order = order[np.argsort(place, kind="stable")]
    listed_files = n + listing.skipped + len(listing.refused)
    if skip is not None and n:  # a file whose name does not carry its record id
        keep = ~np.isin(both["record_id"][rows_in_listing_order], skip)
        rows_in_listing_order, listing = rows_in_listing_order[keep], listing.subset(keep)
    entries = {k: v[rows_in_listing_order] for k, v in both.items()}
    meta = _metadata_columns(root, use or _metadata_worth_index(root, cache))
    entries, listing = _refuse_foreign(entries, listing, ids, meta, meta_path)
    if stats is not None:
        stats.update(files=listed_files, parsed=int(len(todo)), indexed=int(n - len(todo)), skipped=listing.skipped,
                     refused=len(listing.refused))
    raw = _assemble(entries, listing, ids, site, targets, meta)
    if raw is None:  # a record the batch refuses: the reference reader words the first such file
        times, weather = read_metadata(root)
        raw = _read_one_by_one(listing, ids, site, targets, times, weather)
    raw.refused = list(listing.refused)
    return raw


def _refuse_foreign(entries: dict, listing: Listing, ids, meta: dict, meta_path: str) -> tuple[dict, Listing]:
    """The entries and listing without the records whose heliostat contradicts their folder: the file names
    another heliostat (``HeliostatId``), or its metadata row does (those go to ``listing.refused``)."""
    n = len(entries["record_id"])
    if not n:
        return entries, listing
    folder_hid = np.asarray(list(ids), dtype="U")[listing.heliostat]
    claim = entries["claim"].astype("U")
    by_file = (claim != "") & (claim != folder_hid)
    row_hid = np.full(n, "", dtype=object)
    if len(meta["ids"]):
        order = np.argsort(meta["ids"], kind="stable")
        at = np.searchsorted(meta["ids"][order], entries["record_id"]).clip(max=len(order) - 1)
        have = meta["ids"][order][at] == entries["record_id"]
        row_hid[have] = np.asarray(meta["heliostat"], dtype="U")[order[at[have]]]
    row_hid = row_hid.astype("U")
    by_row = ~by_file & (row_hid != "") & (row_hid != folder_hid)
    bad = by_file | by_row
    if not bool(bad.any()):
        return entries, listing
    refused = list(listing.refused)
    for i in np.nonzero(bad)[0].tolist():
        path = os.path.join(listing.folders[int(listing.heliostat[i])], listing.name[i].decode())
        rid, here = int(entries["record_id"][i]), str(folder_hid[i])
        if by_file[i]:
            why = f"another heliostat than its folder (the file names {claim[i]}; it lies under {here})"
        else:
            why = (f"another heliostat than its folder ({meta_path} names {row_hid[i]} for record {rid}; its file "
                   f"lies under {here})")
        refused.append({"record_id": rid, "heliostat_id": here, "reason": why, "path": path, "field": "HeliostatId"})
    keep = ~bad
    out = listing.subset(keep, left_out_by_id=False)
    out.refused = refused
    return {k: v[keep] for k, v in entries.items()}, out
