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
"""
from __future__ import annotations

import csv
import glob
import hashlib
import json
import math
import os
import re
import tempfile
from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import InputFileError
from ..field import facets as facet_ops
from ..field.plant import Facets, Field, Kinematics, Plant, Site, SunSettings
from ..field.targets import CylinderTarget, PlanarTarget
from ..site import wgs84_to_enu
from .records import SOURCES, WEATHER_KEYS, RawRecords, RecordTable, build_record_table, parse_time, raw_from_records

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


def read_json(path) -> dict:
    """Parse a JSON file; one-line :class:`InputFileError` when it is missing, malformed, not UTF-8, larger
    than :data:`MAX_JSON_BYTES` or nested deeper than :data:`MAX_JSON_DEPTH`."""
    try:
        size = os.path.getsize(path)
        if size > MAX_JSON_BYTES:
            raise InputFileError(path, f"{size} bytes; a PAINT JSON file is at most {MAX_JSON_BYTES} bytes")
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
        data = json.loads(text)
    except FileNotFoundError:
        raise InputFileError(path, "file not found") from None
    except UnicodeDecodeError as exc:
        raise InputFileError(path, f"not UTF-8 text (byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise InputFileError(path, f"malformed JSON ({exc})") from None
    except RecursionError:
        raise InputFileError(path, "malformed JSON (nested too deeply)") from None
    except ValueError as exc:  # e.g. an integer literal of more than 4300 digits
        raise InputFileError(path, f"malformed JSON ({' '.join(str(exc).split())})") from None
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({exc.strerror})") from None
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
    data = read_json(path)
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
                             png if os.path.exists(png) else None, cpng if os.path.exists(cpng) else None)


def read_metadata(root) -> tuple[dict, dict]:
    """DateTime and weather per record id from ``metadata/*.csv`` (empty dicts when absent).

    Raises
    ------
    InputFileError
        A CSV that is not UTF-8, malformed, lacks its columns, or has a bad Id, a duplicate Id or a
        non-finite weather value (file, line and column named).
    """
    meta = os.path.join(str(root), "metadata", "calibration-metadata.csv")
    wpath = os.path.join(str(root), "metadata", "calibration-weather.csv")
    times = _read_csv(meta, _metadata_row, ("Id", "DateTime")) if os.path.exists(meta) else {}
    weather = _read_csv(wpath, _weather_row, ("Id",)) if os.path.exists(wpath) else {}
    return times, weather


def _metadata_row(row: dict):
    return row["DateTime"] or None


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


def _read_csv(path: str, parse_row, columns) -> dict:
    """Record id -> ``parse_row(row)`` for every row of a PAINT metadata CSV."""
    out, line = {}, 1
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            if not all(c in (reader.fieldnames or []) for c in columns):
                raise InputFileError(path, f"needs columns {', '.join(columns)}", field="header")
            for line, row in enumerate(reader, start=2):
                try:
                    rid = int(row["Id"])
                except (TypeError, ValueError):
                    raise InputFileError(path, f"line {line}: bad Id {_short(row.get('Id'))}", field="Id") from None
                if rid in out:
                    raise InputFileError(path, f"line {line}: duplicate Id {rid}", field="Id")
                try:
                    out[rid] = parse_row(row)
                except (TypeError, ValueError) as exc:
                    raise InputFileError(path, f"line {line}: {' '.join(str(exc).split())}") from None
    except UnicodeDecodeError as exc:
        raise InputFileError(path, f"not UTF-8 text (byte {exc.start} after line {line})") from None
    except csv.Error as exc:
        raise InputFileError(path, f"line {line}: malformed CSV ({exc})") from None
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({exc.strerror})") from None
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
    """

    root: str
    plant: Plant
    records: RecordTable
    skipped: list = field(default_factory=list)
    properties: dict = field(default_factory=dict)

    def on_plant(self, plant: Plant, source: str = "scenario") -> "PaintDataset":
        """The same records on another plant of the same site (e.g. a calibrated scenario): the table's
        heliostat axis becomes ``plant.field.ids`` (each must be in this folder), records of other heliostats
        are left out. ``source`` names the plant in errors."""
        mine, theirs = self.plant.site, plant.site
        same_site = all(abs(float(getattr(mine, k)) - float(getattr(theirs, k))) <= tol for k, tol in
                        (("latitude_deg", 1e-9), ("longitude_deg", 1e-9), ("altitude_m", 1e-6)))
        if not same_site:
            raise InputFileError(source, f"site ({theirs.latitude_deg}, {theirs.longitude_deg}, {theirs.altitude_m}) "
                                         f"is not the PAINT folder's {self.root}", field="/site")
        missing = [h for h in plant.field.ids if h not in self.plant.field.ids]
        if missing:
            raise InputFileError(source, f"heliostat(s) {', '.join(missing[:5])} are not in the PAINT folder "
                                         f"{self.root}", field="/field/ids")
        ids = set(plant.field.ids)
        skipped = [s for s in self.skipped if s["heliostat_id"] in ids]
        return PaintDataset(self.root, plant, self.records.for_heliostats(plant.field.ids), skipped,
                            {h: p for h, p in self.properties.items() if h in ids})

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
               cache: bool | None = None) -> PaintDataset:
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
    focal_spot, plane_tolerance
        See :func:`heliotwin.io.records.build_record_table`, which judges every record (``plane_tolerance``
        [m]: largest distance of a centroid from its target plane).
    cache : bool or None
        Keep the parsed records in the record cache (:func:`record_cache_path`) and re-open them from it while
        no record, image, metadata or tower file of the folder changed. None: only for folders of at least
        :data:`CACHE_MIN_RECORDS` records (unless ``HELIOTWIN_CACHE=0``).
    """
    root = str(root)
    site, targets = read_tower(find_tower_file(root))
    available = list_heliostats(root)
    ids = available if heliostats is None else list(heliostats)
    missing = [h for h in ids if h not in available]
    if missing:
        raise InputFileError(root, f"heliostat(s) {', '.join(missing)} not found; available: {', '.join(available)}",
                             field="heliostats")
    if not ids:
        raise InputFileError(root, "no heliostats with a properties file")
    props = {h: read_heliostat_properties(os.path.join(root, h, "Properties", f"{h}-heliostat-properties.json"),
                                          site, h)
             for h in ids}
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
    raw = read_records(root, ids, site, targets, cache=cache) if with_records else []
    table, skipped = build_record_table(plant, raw, focal_spot=focal_spot, plane_tolerance=plane_tolerance)
    return PaintDataset(root, plant, table, skipped, props)


# ------------------------------------------------------------------------------------ fast record reading
#: Folders with at least this many record files keep a record cache by default (``load_paint(cache=None)``).
CACHE_MIN_RECORDS = 5000
#: Layout version of a record cache file; a file of another version is never read.
CACHE_VERSION = 1


def _listing(root: str, ids) -> list[tuple[str, list, set, list]]:
    """Per heliostat: its Calibration folder, the record files in reading order (ascending record id), every
    file name there, and ``(name, size, mtime_ns)`` of every file (the cache key's part)."""
    out = []
    for h in ids:
        folder = os.path.join(root, h, "Calibration")
        try:
            entries = list(os.scandir(folder))
        except (FileNotFoundError, NotADirectoryError):  # no records (what a glob of it finds)
            out.append((folder, [], set(), []))
            continue
        except OSError as exc:
            raise InputFileError(folder, f"cannot read ({exc.strerror})") from None
        names = {e.name for e in entries}
        files = sorted((e.name for e in entries if e.name.endswith("-calibration-properties.json")
                        and not e.name.startswith(".")), key=_record_number)
        stats = []
        for e in sorted(entries, key=lambda e: e.name):
            try:
                st = e.stat()
                stats.append((e.name, st.st_size, st.st_mtime_ns))
            except OSError:
                stats.append((e.name, -1, -1))
        out.append((folder, files, names, stats))
    return out


def _parse_record(data: dict, path: str, known_targets) -> tuple:
    """The fields of a parsed record file, validated like :func:`read_calibration_record` (raises a plain
    ``ValueError`` on anything it would reject; the caller then lets that function word the error)."""
    rid = int(os.path.basename(path).split("-")[0])
    mp = data["motor_position"]
    steps = (mp["axis_1_motor_position"], mp["axis_2_motor_position"])
    target = data["target_name"]
    spots = data["focal_spot"]
    az, el = data["sun_azimuth"], data["sun_elevation"]
    if not (all(_finite_number(x) for x in (*steps, az, el)) and isinstance(target, str) and isinstance(spots, dict)
            and (known_targets is None or target in known_targets) and 0.0 < float(el) <= 90.0):
        raise ValueError("invalid record")
    lla = [None, None]
    for k, src in enumerate(FOCAL_SPOT_SOURCES):
        v = spots.get(src)
        if v is not None:
            if not (isinstance(v, (list, tuple)) and len(v) == 3 and all(_finite_number(x) for x in v)
                    and -90.0 <= v[0] <= 90.0 and -180.0 <= v[1] <= 180.0):
                raise ValueError("invalid focal spot")
            lla[k] = [float(x) for x in v]
    if lla == [None, None]:
        raise ValueError("no focal spot")
    return rid, float(steps[0]), float(steps[1]), target, lla, math.radians(az), math.radians(el)


def _read_one_by_one(listing, ids, site: Site, targets: dict, times: dict, weather: dict) -> RawRecords:
    """Every record through :func:`read_calibration_record` (the reference reader: it words the first bad file
    in reading order)."""
    records = []
    for h, (folder, files, _, _) in zip(ids, listing):
        for name in files:
            r = read_calibration_record(os.path.join(folder, name), site, h, known_targets=targets)
            r.datetime = times.get(r.record_id)
            r.weather = weather.get(r.record_id)
            records.append(r)
    return raw_from_records(records)


def _parse_all(listing, ids, site: Site, targets: dict, times: dict, weather: dict) -> RawRecords:
    """Every record of ``ids`` as :class:`RawRecords`: parsed file by file, converted to ENU in one batch.

    Any file this fast path does not accept (or an implausibly far centroid) sends the whole folder through
    :func:`_read_one_by_one`, so errors and edge cases are exactly those of :func:`read_calibration_record`.
    """
    paths, hidx, rows = [], [], []
    try:
        for hi, (folder, files, _, _) in enumerate(listing):
            for name in files:
                path = os.path.join(folder, name)
                rows.append(_parse_record(read_json(path), path, targets))
                paths.append(path)
                hidx.append(hi)
    except (InputFileError, ValueError, KeyError, TypeError, AttributeError, OverflowError):
        return _read_one_by_one(listing, ids, site, targets, times, weather)
    n = len(rows)
    lla = np.full((n, len(SOURCES), 3), np.nan)
    for k in range(len(SOURCES)):
        have = [i for i, r in enumerate(rows) if r[4][k] is not None]
        if have:
            lla[have, k] = [rows[i][4][k] for i in have]
    present = ~np.isnan(lla[..., 0])
    enu = torch.full((n, len(SOURCES), 3), float("nan"), dtype=torch.float64)
    if present.any():
        enu[torch.from_numpy(present)] = wgs84_to_enu(torch.from_numpy(lla[present]), site.reference)
    far = (torch.hypot(enu[..., 0], enu[..., 1]) > MAX_PLANT_RADIUS_M) | (enu[..., 2].abs() > MAX_PLANT_HEIGHT_M)
    if bool(far.any()):
        return _read_one_by_one(listing, ids, site, targets, times, weather)
    rid = [r[0] for r in rows]
    dt = [times.get(x) for x in rid]
    nan5 = [float("nan")] * len(WEATHER_KEYS)
    wx = [[float(weather[x].get(k, float("nan"))) for k in WEATHER_KEYS] if weather.get(x) else nan5 for x in rid]
    f64 = dict(dtype=torch.float64)
    folders = [listing[h][0] for h in hidx]
    png = [os.path.join(f, f"{x}-flux.png") if f"{x}-flux.png" in listing[h][2] else None
           for f, x, h in zip(folders, rid, hidx)]
    cpng = [os.path.join(f, f"{x}-flux-centered.png") if f"{x}-flux-centered.png" in listing[h][2] else None
            for f, x, h in zip(folders, rid, hidx)]
    return RawRecords(
        heliostat_ids=list(ids), heliostat_index=torch.tensor(hidx, dtype=torch.long),
        record_id=torch.tensor(rid, dtype=torch.long), sun_azimuth=torch.tensor([r[5] for r in rows], **f64),
        sun_elevation=torch.tensor([r[6] for r in rows], **f64),
        motor_steps=torch.tensor([[r[1], r[2]] for r in rows], **f64).reshape(n, 2), target=[r[3] for r in rows],
        focal_spots=enu, present=torch.from_numpy(present), time=torch.tensor([parse_time(x) for x in dt], **f64),
        weather=torch.tensor(wx, **f64).reshape(n, len(WEATHER_KEYS)), datetime=dt, flux_png=png,
        flux_centered_png=cpng, path=paths)


def record_cache_path(root, ids) -> str:
    """Where the record cache of heliostats ``ids`` of the PAINT folder ``root`` lives: under
    ``$HELIOTWIN_CACHE_DIR`` (default ``$XDG_CACHE_HOME/heliotwin/paint-records``, ``~/.cache/...``), one
    ``.npz`` per folder and heliostat list."""
    base = os.environ.get("HELIOTWIN_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "heliotwin",
        "paint-records")
    name = hashlib.sha256("\0".join([os.path.abspath(str(root)), *ids]).encode()).hexdigest()[:32]
    return os.path.join(base, f"{name}.npz")


def _cache_key(root: str, ids, listing) -> str:
    """Digest of everything the parsed records depend on: the format version, the folder, the heliostats, and
    name, size and modification time of the tower file, the metadata CSVs and every file of every
    Calibration folder (records and images)."""
    def stat(path):
        try:
            st = os.stat(path)
            return [st.st_size, st.st_mtime_ns]
        except OSError:
            return None
    meta = [stat(os.path.join(root, "metadata", f)) for f in ("calibration-metadata.csv", "calibration-weather.csv")]
    tower = find_tower_file(root)
    parts = [CACHE_VERSION, os.path.abspath(root), list(ids), os.path.basename(tower), stat(tower), meta,
             [entry[3] for entry in listing]]
    return hashlib.sha256(json.dumps(parts).encode()).hexdigest()


def _save_cache(path: str, key: str, raw: RawRecords) -> None:
    """Write the cache atomically; a cache that cannot be written is simply not written."""
    strings = lambda v: np.array(["" if x is None else x for x in v], dtype=str)  # noqa: E731
    arrays = {"key": np.array(key), "heliostat_ids": np.array(raw.heliostat_ids, dtype=str)}
    for name in ("heliostat_index", "record_id", "sun_azimuth", "sun_elevation", "motor_steps", "focal_spots",
                 "present", "time", "weather"):
        arrays[name] = getattr(raw, name).numpy()
    for name in ("target", "datetime", "flux_png", "flux_centered_png", "path"):
        v = getattr(raw, name)
        arrays[name] = strings(v)
        arrays[name + "_none"] = np.array([x is None for x in v], dtype=bool)
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".records-", suffix=".npz", dir=os.path.dirname(path))
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, path)
    except OSError:
        try:
            os.unlink(tmp)
        except (OSError, UnboundLocalError):
            pass


def _load_cache(path: str, key: str) -> RawRecords | None:
    """The cached records when the file exists, reads cleanly and its key matches; None otherwise."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            d = {k: z[k] for k in z.files}
    except (OSError, ValueError, KeyError, EOFError):
        return None

    def strings(name):
        return [None if none else str(x) for x, none in zip(d[name].tolist(), d[name + "_none"].tolist())]
    try:
        return RawRecords(heliostat_ids=[str(x) for x in d["heliostat_ids"].tolist()],
                          **{k: torch.from_numpy(d[k]) for k in ("heliostat_index", "record_id", "sun_azimuth",
                                                                 "sun_elevation", "motor_steps", "focal_spots",
                                                                 "present", "time", "weather")},
                          **{k: strings(k) for k in ("target", "datetime", "flux_png", "flux_centered_png", "path")})
    except (KeyError, TypeError, ValueError):
        return None


def read_records(root, ids, site: Site, targets: dict, *, cache: bool | None = None) -> RawRecords:
    """Every calibration record of heliostats ``ids`` of a PAINT folder, parsed (not yet judged), with the
    metadata's time and weather: from the record cache when it matches the folder's files, else from the
    files (then the cache is written when ``cache`` allows, see :func:`load_paint`).

    Raises
    ------
    InputFileError
        As :func:`read_calibration_record` and :func:`read_metadata` (the first bad file in reading order).
    """
    root = str(root)
    listing = _listing(root, ids)
    files = sum(len(entry[1]) for entry in listing)
    use = cache if cache is not None else (files >= CACHE_MIN_RECORDS and os.environ.get("HELIOTWIN_CACHE") != "0")
    if use:
        key = _cache_key(root, ids, listing)
        path = record_cache_path(root, ids)
        hit = _load_cache(path, key)
        if hit is not None:
            return hit
    times, weather = read_metadata(root)
    raw = _parse_all(listing, ids, site, targets, times, weather)
    if use and _cache_key(root, ids, _listing(root, ids)) == key:  # nothing changed while reading
        _save_cache(path, key, raw)
    return raw
