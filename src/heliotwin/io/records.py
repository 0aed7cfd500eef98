"""The calibration record table: every camera-target record of a plant, validated once, as tensors.

A :class:`RecordTable` holds R records of H heliostats as a structure of arrays: the heliostat of each
record is ``heliostat_index[r]`` (into the kinematics' heliostat axis), so a model evaluates all records of
all heliostats in one call with ``kin.index(table.heliostat_index)``. The PAINT reader builds it once
(:func:`build_record_table`); ``validate``, ``calibrate`` and ``surfaces`` all consume it, choosing records
with :meth:`RecordTable.select` / :meth:`RecordTable.subset` and the centroid source with
:meth:`RecordTable.with_focal_spot`.

Every check a record must pass lives in :func:`build_record_table` and nowhere else: a record whose target
is unknown or not planar, that has no usable centroid, whose numbers are not finite, whose sun angles are beyond
a full turn (azimuth) or the zenith (elevation), that is dated in the future (later than the time of reading
plus a day), whose motor steps are outside the actuator range, or whose centroid lies off its target plane is
dropped with one reason string and the field concerned.
(What makes a *file* unreadable — a missing field, a sun at or below the horizon, an unknown target — is the
reader's job, :mod:`heliotwin.io.paint`, which names the file and field.) Duplicate record ids are an
error (one of them would silently shadow the other).
"""
from __future__ import annotations

import math
import re
import time as _time
from dataclasses import dataclass, field, fields
from datetime import datetime, timezone

import torch

from ..errors import HeliotwinError, InputFileError
from ..sunangles import direction_from_paint_angles

#: Focal-spot sources a record may carry, in PAINT's spelling.
SOURCES = ("HeliOS", "UTIS")


def normalise_source(name: str) -> str:
    """Accept ``heliOS``/``helios``/``utis`` (any case) and return PAINT's spelling."""
    for s in SOURCES:
        if name.lower() == s.lower():
            return s
    raise HeliotwinError(f"unknown focal-spot source {name!r}; known: {', '.join(SOURCES)}")


#: Time-zone names a PAINT time may end with that mean UTC (any other name -- ``CEST``, ``CET`` -- is refused:
#: an abbreviation is ambiguous and PAINT's DateTime is UTC).
UTC_NAMES = ("UTC", "GMT", "Z")
_ZONE_NAME = re.compile(r"^(?P<time>.*?\d)\s*(?P<zone>[A-Za-z][A-Za-z0-9+\-/_]*)$")


def parse_time(text: str | None) -> float:
    """A PAINT DateTime (UTC ISO 8601) -> POSIX seconds; NaN when missing (empty: the record has no time).

    Accepted: ISO 8601 with ``Z`` or an offset (``2023-05-01T10:00:00Z``, ``2023-05-01 10:00:00+02:00``), or
    naive (``2023-05-01 10:00:00``: UTC, PAINT's convention); a trailing ``UTC`` / ``GMT`` also means UTC.

    Raises
    ------
    ValueError
        Text that is not such a time, or that names another time zone (``2023-05-01 10:00:00 CEST``: an
        abbreviation is ambiguous; write the offset, ``+02:00``). The message is one line starting with the
        text; the PAINT reader adds the file, line and column.
    """
    if text is None or not str(text).strip():
        return float("nan")
    text = str(text).strip()
    body, zone = text, None
    m = _ZONE_NAME.match(text)
    if m and not _looks_iso(text):
        body, zone = m.group("time").strip(), m.group("zone")
        if zone.upper() not in UTC_NAMES:
            raise ValueError(f"{_short_text(text)} names the time zone {zone!r}; PAINT times are UTC (ISO 8601 with "
                             f"Z or an offset such as +02:00)")
    try:
        t = datetime.fromisoformat(body[:-1] + "+00:00" if body.endswith("Z") else body)
    except ValueError:
        raise ValueError(f"{_short_text(text)} is not an ISO 8601 time (e.g. 2023-05-01T10:00:00Z)") from None
    if t.tzinfo is None:  # PAINT's DateTime is UTC; a naive value is taken as UTC
        t = t.replace(tzinfo=timezone.utc)
    elif zone is not None:  # "10:00+02:00 UTC": two zones
        raise ValueError(f"{_short_text(text)} has both an offset and the zone name {zone!r}")
    try:
        return t.timestamp()
    except (OverflowError, ValueError):  # year 1 with a positive offset, year 9999 with a negative one
        raise ValueError(f"{_short_text(text)} is outside the representable times") from None


def _looks_iso(text: str) -> bool:
    """Whether ``text`` already parses as ISO 8601 (``...Z`` included), so a trailing letter is not a zone."""
    try:
        datetime.fromisoformat(text[:-1] + "+00:00" if text.endswith("Z") else text)
    except ValueError:
        return False
    return True


def _short_text(text: str, n: int = 60) -> str:
    return repr(text if len(text) <= n else text[:n] + "...")


@dataclass
class RecordTable:
    """R calibration records of H heliostats (structure of arrays, float64).

    Attributes
    ----------
    heliostat_ids : list of str
        The H heliostats, in the order of the kinematics' heliostat axis.
    heliostat_index : torch.Tensor, [R], long
        Heliostat of each record (index into ``heliostat_ids``).
    record_id : torch.Tensor, [R], long
    sun_azimuth, sun_elevation : torch.Tensor, [R]
        [rad], PAINT convention (azimuth 0 = south, +pi/2 = east).
    sun : torch.Tensor, [R, 3]
        Unit vector towards the sun, ENU.
    motor_steps : torch.Tensor, [R, 2]
        [steps].
    spot : torch.Tensor, [R, 3]
        Measured focal-spot centroid, ENU [m].
    plane_center, plane_normal, plane_right, plane_up : torch.Tensor, [R, 3]
        The record's target plane (normal towards the field).
    time : torch.Tensor, [R]
        UTC POSIX seconds; NaN where the record has no time.
    weather : torch.Tensor, [R, 5]
        wind speed [m/s], wind direction [deg], DNI [W/m^2], temperature [degC], humidity [%]; NaN where absent.
    target : list of str
        Target name per record.
    source : list of str
        Focal-spot source used per record.
    spot_other : torch.Tensor, [R, 3], optional
        The centroid of the *other* source (UTIS when ``spot`` is HeliOS and vice versa), NaN where the
        record has only one; ``None`` when not known (synthetic tables). Methods may fit on it; the metric
        always uses ``spot``.
    focal_spots : torch.Tensor, [R, 2, 3], optional
        Every source's centroid in :data:`SOURCES` order (HeliOS, UTIS), ENU [m]; NaN where the record has
        none or it is off the target plane. ``None`` for synthetic tables.
    flux_png, flux_centered_png : list of (str or None)
        Paths of the whole-target and the spot-centred measured image, ``None`` where the record has none.
    datetime : list of (str or None)
        UTC ISO time as the metadata CSV has it.
    path : list of (str or None)
        The record's properties file (for error messages).
    """

    heliostat_ids: list
    heliostat_index: torch.Tensor
    record_id: torch.Tensor
    sun_azimuth: torch.Tensor
    sun_elevation: torch.Tensor
    sun: torch.Tensor
    motor_steps: torch.Tensor
    spot: torch.Tensor
    plane_center: torch.Tensor
    plane_normal: torch.Tensor
    plane_right: torch.Tensor
    plane_up: torch.Tensor
    time: torch.Tensor
    weather: torch.Tensor
    target: list = field(default_factory=list)
    source: list = field(default_factory=list)
    spot_other: torch.Tensor | None = None
    focal_spots: torch.Tensor | None = None
    flux_png: list = field(default_factory=list)
    flux_centered_png: list = field(default_factory=list)
    datetime: list = field(default_factory=list)
    path: list = field(default_factory=list)

    def __post_init__(self):
        # Optional per-record lists default to "absent" so synthetic tables need not spell them out.
        n = len(self)
        for name in ("flux_png", "flux_centered_png", "datetime", "path"):
            if not getattr(self, name):
                setattr(self, name, [None] * n)

    def __len__(self) -> int:
        return int(self.record_id.shape[0])

    @property
    def num_heliostats(self) -> int:
        """H, the length of the table's heliostat axis (``heliostat_ids``), with or without records."""
        return len(self.heliostat_ids)

    def subset(self, idx) -> "RecordTable":
        """Records ``idx`` (bool mask of shape (R,), index list or tensor of shape (K,)); the heliostat axis is
        unchanged. Every per-record field keeps its trailing shape: ``spot`` (R, 3) becomes (K, 3)."""
        idx = torch.as_tensor(idx)
        if idx.dtype == torch.bool:
            idx = idx.nonzero().flatten()
        idx = idx.long()
        rows = idx.tolist()
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "heliostat_ids":
                out[f.name] = list(v)
            elif v is None:
                out[f.name] = None
            elif isinstance(v, list):
                out[f.name] = list(map(v.__getitem__, rows))
            else:
                out[f.name] = v[idx]
        return RecordTable(**out)

    def index_of(self, record_id: int) -> int:
        """Row of record ``record_id``; :class:`KeyError` naming the id when absent."""
        hit = (self.record_id == int(record_id)).nonzero().flatten()
        if not len(hit):
            raise KeyError(f"record {record_id} is not among the {len(self)} usable records")
        return int(hit[0])

    def select(self, *, heliostat: str | None = None, record_ids=None, with_centered_image: bool = False
               ) -> "RecordTable":
        """Rows of one heliostat and/or the given record ids (in table order), optionally only those with a
        flux-centred image; the heliostat axis is unchanged."""
        dev = self.heliostat_index.device  # a table on the GPU selects with masks there
        keep = torch.ones(len(self), dtype=torch.bool, device=dev)
        if heliostat is not None:
            if heliostat not in self.heliostat_ids:
                raise KeyError(f"heliostat {heliostat} has no records in this table")
            keep &= self.heliostat_index == self.heliostat_ids.index(heliostat)
        if record_ids is not None:
            keep &= torch.isin(self.record_id, torch.as_tensor(list(record_ids), dtype=torch.long,
                                                                device=self.record_id.device))
        if with_centered_image:
            keep &= torch.tensor([p is not None for p in self.flux_centered_png], dtype=torch.bool, device=dev)
        return self.subset(keep)

    def for_heliostats(self, heliostat_ids) -> "RecordTable":
        """The records of ``heliostat_ids`` only, re-indexed so that ``heliostat_index`` points into that list
        (the order a caller indexes its kinematics with)."""
        ids = list(heliostat_ids)
        at = {h: i for i, h in reversed(list(enumerate(self.heliostat_ids)))}  # first position, as list.index
        unknown = [h for h in ids if h not in at]
        if unknown:
            raise KeyError(f"heliostat(s) {', '.join(unknown)} not in the record table")
        dev = self.heliostat_index.device
        old = torch.tensor([at[h] for h in ids], dtype=torch.long, device=dev)
        out = self.subset(torch.isin(self.heliostat_index, old))
        remap = torch.full((max(len(self.heliostat_ids), 1),), -1, dtype=torch.long, device=dev)
        remap[old] = torch.arange(len(ids), device=dev)
        out.heliostat_index = remap[out.heliostat_index]
        out.heliostat_ids = ids
        return out

    def with_focal_spot(self, source: str) -> "RecordTable":
        """The same records with ``spot`` taken from ``source`` where the record has it (else the other
        source), ``spot_other`` the remaining one and ``source`` naming what ``spot`` is."""
        prefer = normalise_source(source)
        if self.focal_spots is None:
            raise HeliotwinError("this record table has no per-source centroids (synthetic records)")
        p = SOURCES.index(prefer)
        first, second = self.focal_spots[:, p], self.focal_spots[:, 1 - p]
        has = torch.isfinite(first).all(-1)
        out = self.subset(torch.arange(len(self)))
        out.spot = torch.where(has.unsqueeze(-1), first, second)
        out.spot_other = torch.where(has.unsqueeze(-1), second, torch.full_like(second, float("nan")))
        out.source = [prefer if h else SOURCES[1 - p] for h in has.tolist()]
        return out

    def on_target(self, name: str) -> torch.Tensor:
        """[R] bool: the records whose focal spot lies on target ``name``."""
        return torch.tensor([t == name for t in self.target], dtype=torch.bool, device=self.spot.device)

    def camera_offsets(self) -> dict:
        """Per target, how far the two cameras' centroids of the same spot lie apart.

        Returns
        -------
        dict
            Target name -> ``{"pairs", "heliostats", "offset"}``: the records with both centroids, the
            heliostats among them, and the median HeliOS - UTIS centroid over those records, [3] ENU [m]
            (componentwise, so one bad centroid cannot move it). Targets without a pair are left out, as is
            everything for tables without per-source centroids (synthetic records).
        """
        if self.focal_spots is None or len(self) == 0:
            return {}
        both = torch.isfinite(self.focal_spots).all(-1).all(-1)
        diff = self.focal_spots[:, 0] - self.focal_spots[:, 1]
        out = {}
        for name in dict.fromkeys(self.target):  # the few targets of a plant, not records or heliostats
            on = both & self.on_target(name)
            if bool(on.any()):
                out[name] = {"pairs": int(on.sum()), "heliostats": int(self.heliostat_index[on].unique().numel()),
                             "offset": diff[on].median(0).values}
        return out

    def of(self, h: int) -> torch.Tensor:
        """Indices (into this batch), shape (K,), long, of the K records of heliostat ``h``."""
        return (self.heliostat_index == h).nonzero().flatten()

    def rows_by_heliostat(self) -> list:
        """:meth:`of` for every heliostat at once: H index tensors, heliostat ``h``'s of shape (K_h,), long,
        ascending (one stable sort, O(R log R); a mask per heliostat is O(H R), 0.6 s at 2,000 heliostats and
        190,000 records)."""
        order = torch.argsort(self.heliostat_index, stable=True)
        return list(torch.split(order, self.counts().tolist()))

    def counts(self) -> torch.Tensor:
        """Records per heliostat, [H]."""
        return torch.bincount(self.heliostat_index, minlength=self.num_heliostats)

    @staticmethod
    def from_arrays(heliostat_ids, heliostat_index, sun_azimuth, sun_elevation, motor_steps, spot, target,
                    time=None, record_id=None) -> "RecordTable":
        """Build a batch from plain arrays (synthetic records, tests, aiming).

        Parameters
        ----------
        heliostat_ids : list of str (H)
        heliostat_index : array-like, shape (R,), int
        sun_azimuth, sun_elevation : array-like, shape (R,)
            [rad], PAINT convention (azimuth 0 = south, +pi/2 = east).
        motor_steps : array-like, shape (R, 2)
            [steps].
        spot : array-like, shape (R, 3)
            Focal-spot centroid, ENU [m].
        target : PlanarTarget
            The plane of every record.
        time : array-like, shape (R,), optional
            UTC POSIX seconds [s] (NaN = unknown).
        record_id : array-like, shape (R,), int, optional
            Default ``0 .. R-1``.
        """
        f64 = dict(dtype=torch.float64)
        hidx = torch.as_tensor(heliostat_index, dtype=torch.long).reshape(-1)
        r = len(hidx)
        az = torch.as_tensor(sun_azimuth, **f64).reshape(-1)
        el = torch.as_tensor(sun_elevation, **f64).reshape(-1)

        def rep(v):
            return torch.as_tensor(v, **f64).reshape(1, 3).expand(r, 3).clone()

        return RecordTable(
            heliostat_ids=list(heliostat_ids), heliostat_index=hidx,
            record_id=torch.arange(r) if record_id is None else torch.as_tensor(record_id, dtype=torch.long),
            sun_azimuth=az, sun_elevation=el, sun=direction_from_paint_angles(az, el, check_horizon=False),
            motor_steps=torch.as_tensor(motor_steps, **f64).reshape(r, 2),
            spot=torch.as_tensor(spot, **f64).reshape(r, 3),
            plane_center=rep(target.center), plane_normal=rep(target.normal), plane_right=rep(target.right),
            plane_up=rep(target.up),
            time=torch.full((r,), float("nan"), **f64) if time is None else torch.as_tensor(time, **f64).reshape(-1),
            weather=torch.full((r, len(WEATHER_KEYS)), float("nan"), **f64),
            target=[target.name] * r, source=["synthetic"] * r)

    @staticmethod
    def concatenate(items: list["RecordTable"]) -> "RecordTable":
        """Concatenate batches over the same heliostats."""
        out = {}
        for f in fields(RecordTable):
            vs = [getattr(b, f.name) for b in items]
            if f.name == "heliostat_ids":
                out[f.name] = list(vs[0])
            elif f.name in ("spot_other", "focal_spots"):
                out[f.name] = None if any(v is None for v in vs) else torch.cat(vs)
            elif isinstance(vs[0], list):
                out[f.name] = [x for v in vs for x in v]
            else:
                out[f.name] = torch.cat(vs)
        return RecordTable(**out)


WEATHER_KEYS = ("wind_speed", "wind_direction", "dni", "temperature", "humidity")


#: How far [s] a record's time may lie after the time of reading (clock skew, time zones of the writer) before
#: the record counts as dated in the future and is dropped.
FUTURE_TOLERANCE_S = 86400.0
#: Largest |sun azimuth| [deg] a record may name (PAINT's is in (-180, 180]; a full turn either way is allowed).
MAX_SUN_AZIMUTH_DEG = 360.0
#: Largest |sun elevation| [deg] a record may name (the reader refuses a sun at or below the horizon).
MAX_SUN_ELEVATION_DEG = 90.0


def _now_seconds(now) -> float:
    """``now`` (None = the current time, POSIX seconds, or an aware/naive-UTC ``datetime``) as POSIX seconds."""
    if now is None:
        return _time.time()
    if isinstance(now, datetime):
        return (now if now.tzinfo is not None else now.replace(tzinfo=timezone.utc)).timestamp()
    if isinstance(now, bool) or not isinstance(now, (int, float)) or not math.isfinite(float(now)):
        raise HeliotwinError(f"now must be POSIX seconds or a datetime, got {now!r}")
    return float(now)


def _utc_text(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, timezone.utc).isoformat(timespec="seconds").replace("+00:00", "Z")


def _reason_to_skip(rec, target, kin, h: int, plane_tolerance: float, now: float = math.inf
                    ) -> tuple[str, str] | None:
    """Why ``rec`` cannot be used (one line) and the file field concerned, or None. The only place a record
    is judged. ``now`` [POSIX s]: the time of reading (a record later than ``now + FUTURE_TOLERANCE_S`` is
    dated in the future)."""
    if target is None:
        return f"unknown target {rec.target!r}", "target_name"
    if getattr(target, "kind", "") != "planar":
        return f"target {rec.target!r} is not planar (a centroid is measured on a flat target)", "target_name"
    if not rec.focal_spot:
        return "no focal-spot centroid", "focal_spot"
    steps = torch.tensor(rec.motor_steps, dtype=torch.float64)
    if not (bool(torch.isfinite(steps).all()) and math.isfinite(rec.sun_azimuth) and math.isfinite(rec.sun_elevation)
            and all(bool(torch.isfinite(torch.as_tensor(v)).all()) for v in rec.focal_spot.values())):
        return "non-finite value", "motor_position"
    for name, value, bound in (("sun_azimuth", rec.sun_azimuth, MAX_SUN_AZIMUTH_DEG),
                               ("sun_elevation", rec.sun_elevation, MAX_SUN_ELEVATION_DEG)):
        if abs(value) > math.radians(bound):
            return f"{name} {math.degrees(value):.6g} deg outside [-{bound:g}, {bound:g}] deg", name
    t = getattr(rec, "time", math.nan)
    if t > now + FUTURE_TOLERANCE_S:  # NaN (no time) is not in the future
        return (f"time {rec.datetime or _utc_text(t)} is in the future (read at {_utc_text(now)}; a record may be "
                f"at most {FUTURE_TOLERANCE_S / 3600:g} h ahead)", "DateTime")
    lo, hi = kin.min_steps[h], kin.max_steps[h]
    bad = (steps < lo) | (steps > hi)
    if bool(bad.any()):
        a = int(bad.nonzero()[0])
        return (f"motor steps axis {a + 1} = {steps[a].item():.0f} outside actuator range "
                f"[{lo[a].item():.0f}, {hi[a].item():.0f}]", f"motor_position.axis_{a + 1}_motor_position")
    offsets = {src: float(target.distance_to_plane(torch.as_tensor(v, dtype=torch.float64)))
               for src, v in rec.focal_spot.items()}
    if all(abs(d) > plane_tolerance for d in offsets.values()):
        src, d = min(offsets.items(), key=lambda kv: abs(kv[1]))
        return (f"focal spot ({src}) {d:+.3f} m off the plane of target {rec.target!r} (tolerance "
                f"{plane_tolerance} m)", f"focal_spot.{src}")
    return None


@dataclass
class RawRecords:
    """Parsed, not yet judged calibration records as arrays (what :func:`build_record_table` judges).

    The PAINT reader fills it straight from the files (and its cache stores it); :func:`raw_from_records`
    makes it from :class:`~heliotwin.io.paint.CalibrationRecord` objects.

    Attributes
    ----------
    heliostat_ids : list of str
        The heliostats the records belong to (``heliostat_index`` points into it).
    heliostat_index, record_id : [R] long
    sun_azimuth, sun_elevation : [R] float64
        [rad], PAINT convention.
    motor_steps : [R, 2] float64
    target : list of str, R
    focal_spots : [R, 2, 3] float64
        ENU [m] per source of :data:`SOURCES`; NaN where ``present`` is False.
    present : [R, 2] bool
        Which sources the record has.
    time : [R] float64
        UTC POSIX seconds of ``datetime`` (NaN without one).
    weather : [R, 5] float64
        :data:`WEATHER_KEYS`, NaN where absent.
    datetime, flux_png, flux_centered_png, path : list of (str or None), R
    refused : list of dict
        Records the reader left out before parsing (a file that is not a regular file, too large, or under
        another heliostat than it names), worded as :func:`build_record_table`'s ``skipped``; they join it.
    """

    heliostat_ids: list
    heliostat_index: torch.Tensor
    record_id: torch.Tensor
    sun_azimuth: torch.Tensor
    sun_elevation: torch.Tensor
    motor_steps: torch.Tensor
    target: list
    focal_spots: torch.Tensor
    present: torch.Tensor
    time: torch.Tensor
    weather: torch.Tensor
    datetime: list
    flux_png: list
    flux_centered_png: list
    path: list
    refused: list = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.record_id.shape[0])


def raw_from_records(records) -> RawRecords:
    """:class:`RawRecords` of a list of :class:`~heliotwin.io.paint.CalibrationRecord` (reading order)."""
    f64 = dict(dtype=torch.float64)
    n = len(records)
    hids = list(dict.fromkeys(r.heliostat_id for r in records))
    at = {h: i for i, h in enumerate(hids)}
    spots = torch.full((n, len(SOURCES), 3), float("nan"), **f64)
    present = torch.zeros(n, len(SOURCES), dtype=torch.bool)
    for k, src in enumerate(SOURCES):
        rows = [i for i, r in enumerate(records) if src in r.focal_spot]
        if rows:
            spots[rows, k] = torch.stack([torch.as_tensor(records[i].focal_spot[src], **f64).reshape(3)
                                          for i in rows])
            present[rows, k] = True
    return RawRecords(
        heliostat_ids=hids, heliostat_index=torch.tensor([at[r.heliostat_id] for r in records], dtype=torch.long),
        record_id=torch.tensor([int(r.record_id) for r in records], dtype=torch.long),
        sun_azimuth=torch.tensor([r.sun_azimuth for r in records], **f64),
        sun_elevation=torch.tensor([r.sun_elevation for r in records], **f64),
        motor_steps=torch.tensor([list(r.motor_steps) for r in records], **f64).reshape(n, 2),
        target=[r.target for r in records], focal_spots=spots, present=present,
        time=torch.tensor([_record_time(r) for r in records], **f64),
        weather=torch.tensor([[float((r.weather or {}).get(k, float("nan"))) for k in WEATHER_KEYS]
                              for r in records], **f64).reshape(n, len(WEATHER_KEYS)),
        datetime=[r.datetime for r in records], flux_png=[r.flux_png for r in records],
        flux_centered_png=[r.flux_centered_png for r in records], path=[str(r.path) for r in records])


def _record_time(record) -> float:
    """POSIX time of a record's ``datetime`` (NaN without one); a malformed one names the record's file."""
    try:
        return parse_time(record.datetime)
    except ValueError as exc:
        raise InputFileError(record.path, f"DateTime {exc}", field="DateTime") from None


def build_record_table(plant, records, *, focal_spot: str = "HeliOS", plane_tolerance: float = 0.1, now=None
                       ) -> tuple[RecordTable, list[dict]]:
    """Validate raw records once and put the usable ones into one table over the plant's heliostats.

    Parameters
    ----------
    plant : heliotwin.field.plant.Plant
        Provides targets and the kinematics' motor ranges; the table's heliostat axis is ``plant.field.ids``.
    records : list of heliotwin.io.paint.CalibrationRecord, or RawRecords
        As read from the files (parsed, not yet judged).
    focal_spot : str
        Preferred centroid source for ``spot`` (``HeliOS`` or ``UTIS``); a record without a usable one falls
        back to the other (:meth:`RecordTable.with_focal_spot` changes it later without re-reading).
    plane_tolerance : float
        Largest distance [m] of a centroid from its target plane (the multi-focus tower's records lie up to
        9 cm behind it; beyond 0.1 m the centroid is not on the target the record names). A source beyond
        it is treated as absent; a record with no source within it is dropped.
    now : float or datetime.datetime, optional
        The time of reading (POSIX seconds [s] or a datetime; naive = UTC); default: the current time. A
        record dated more than :data:`FUTURE_TOLERANCE_S` after it is dropped ("time ... is in the future"):
        assimilated, it would date the heliostat's state after every real record to come.

    Returns
    -------
    table : RecordTable
        Usable records in reading order.
    skipped : list of dict
        ``{"record_id", "heliostat_id", "reason", "path", "field"}`` per dropped record (the file and the
        field that made it unusable).

    Raises
    ------
    InputFileError
        Two records with the same id (naming both files), or a non-finite / negative tolerance.

    Notes
    -----
    Judged in batch (tensors of shape (R,) over all R records); only the dropped records go one by one through
    :func:`_reason_to_skip`, which words why.
    """
    if not (isinstance(plane_tolerance, (int, float)) and math.isfinite(plane_tolerance) and plane_tolerance >= 0):
        raise HeliotwinError(f"plane tolerance must be a finite number >= 0 m, got {plane_tolerance!r}")
    prefer = normalise_source(focal_spot)
    raw = records if isinstance(records, RawRecords) else raw_from_records(list(records))
    table, skipped = _table_from_raw(plant, raw, float(plane_tolerance), _now_seconds(now))
    return table.with_focal_spot(prefer), skipped


class _Record:
    """The fields of one raw record that :func:`_reason_to_skip` reads (for the dropped ones only)."""

    def __init__(self, raw: RawRecords, i: int):
        self.target = raw.target[i]
        self.motor_steps = tuple(raw.motor_steps[i].tolist())
        self.sun_azimuth, self.sun_elevation = float(raw.sun_azimuth[i]), float(raw.sun_elevation[i])
        self.time, self.datetime = float(raw.time[i]), raw.datetime[i]
        self.focal_spot = {src: raw.focal_spots[i, k] for k, src in enumerate(SOURCES) if bool(raw.present[i, k])}


def _check_duplicates(raw: RawRecords) -> None:
    first: dict = {}
    for i, rid in enumerate(raw.record_id.tolist()):
        if rid in first:
            raise InputFileError(raw.path[i], f"duplicate record id {rid} (also in {raw.path[first[rid]]})", field="id")
        first[rid] = i


def _table_from_raw(plant, raw: RawRecords, tolerance: float, now: float = math.inf
                    ) -> tuple[RecordTable, list[dict]]:
    """The usable records of ``raw`` as a table on ``plant`` (HeliOS in ``spot``) and the dropped ones (``now``
    [POSIX s]: the time of reading)."""
    f64 = dict(dtype=torch.float64)
    _check_duplicates(raw)
    ids = list(plant.field.ids)
    pos = {h: i for i, h in enumerate(ids)}
    kin = plant.field.kinematics
    n = len(raw)
    to_plant = torch.tensor([pos.get(h, -1) for h in raw.heliostat_ids] or [0], dtype=torch.long)
    h = to_plant[raw.heliostat_index] if n else torch.zeros(0, dtype=torch.long)
    names = list(dict.fromkeys(raw.target))
    tix = torch.tensor([names.index(t) for t in raw.target] if len(names) > 1 else [0] * n, dtype=torch.long)
    targets = [plant.targets.get(t) for t in names]
    planar = [t is not None and getattr(t, "kind", "") == "planar" for t in targets]
    zero = torch.zeros(3, **f64)
    centers = torch.stack([t.center.to(**f64) if p else zero for t, p in zip(targets, planar)] or [zero])
    normals = torch.stack([t.normal.to(**f64) if p else zero for t, p in zip(targets, planar)] or [zero])
    in_plant = h >= 0
    hp = h.clamp_min(0)
    usable_target = torch.tensor(planar or [False], dtype=torch.bool)[tix] if n else torch.zeros(0, dtype=torch.bool)
    has_spot = raw.present.any(-1)
    finite = (torch.isfinite(raw.motor_steps).all(-1) & torch.isfinite(raw.sun_azimuth)
              & torch.isfinite(raw.sun_elevation) & (torch.isfinite(raw.focal_spots).all(-1) | ~raw.present).all(-1))
    sun_ok = ((raw.sun_azimuth.abs() <= math.radians(MAX_SUN_AZIMUTH_DEG))
              & (raw.sun_elevation.abs() <= math.radians(MAX_SUN_ELEVATION_DEG)))
    not_future = ~(raw.time > now + FUTURE_TOLERANCE_S)  # NaN (no time) passes
    steps = raw.motor_steps
    in_range = ((steps >= kin.min_steps[hp].to(**f64)) & (steps <= kin.max_steps[hp].to(**f64))).all(-1)
    dist = ((raw.focal_spots - centers[tix].unsqueeze(1)) * normals[tix].unsqueeze(1)).sum(-1)
    within = raw.present & (dist.abs() <= tolerance)
    ok = usable_target & has_spot & finite & sun_ok & not_future & in_range & within.any(-1)
    skipped = []
    for i in (in_plant & ~ok).nonzero().flatten().tolist():  # the dropped records only: word why
        why = _reason_to_skip(_Record(raw, i), targets[int(tix[i])], kin, int(h[i]), tolerance, now)
        if why is None:  # the batch and the reasons disagree on an edge case: the reasons decide
            ok[i] = True
            continue
        skipped.append({"record_id": int(raw.record_id[i]), "heliostat_id": ids[int(h[i])], "reason": why[0],
                        "path": str(raw.path[i]), "field": why[1]})
    skipped += [dict(r) for r in raw.refused if r["heliostat_id"] in pos]  # left out by the reader, named there
    keep = (in_plant & ok).nonzero().flatten()
    rows = keep.tolist()
    spots = torch.where(within[keep].unsqueeze(-1), raw.focal_spots[keep], torch.full_like(raw.focal_spots[keep],
                                                                                          float("nan")))
    tk = tix[keep]
    m = len(rows)

    def plane(attr):
        return torch.stack([getattr(t, attr).to(**f64) if p else zero for t, p in zip(targets, planar)] or [zero])[tk]

    az, el = raw.sun_azimuth[keep], raw.sun_elevation[keep]
    table = RecordTable(
        heliostat_ids=ids, heliostat_index=h[keep], record_id=raw.record_id[keep], sun_azimuth=az, sun_elevation=el,
        sun=direction_from_paint_angles(az, el, check_horizon=False) if m else torch.zeros(0, 3, **f64),
        motor_steps=raw.motor_steps[keep], spot=spots[:, 0].clone(), plane_center=plane("center"),
        plane_normal=plane("normal"), plane_right=plane("right"), plane_up=plane("up"), time=raw.time[keep],
        weather=raw.weather[keep], target=[raw.target[i] for i in rows], source=[SOURCES[0]] * m,
        spot_other=spots[:, 1].clone(), focal_spots=spots, flux_png=[raw.flux_png[i] for i in rows],
        flux_centered_png=[raw.flux_centered_png[i] for i in rows], datetime=[raw.datetime[i] for i in rows],
        path=[raw.path[i] for i in rows])
    return table, skipped
