"""Calibration records as batched tensors, with validation of every record a method will see.

A :class:`RecordTable` holds R records of H heliostats as a structure of arrays: the heliostat of each
record is ``heliostat_index[r]`` (into the kinematics' heliostat axis), so a model evaluates all records of
all heliostats in one call with ``kin.index(batch.heliostat_index)``.

Bad input never crashes and never turns into a silent NaN: :func:`prepare_records` drops records whose
focal spot lies off its target plane, whose motor steps are outside the actuator range, whose target is
not planar, or whose numbers are not finite, and returns each drop with a reason.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from datetime import datetime, timezone

import torch

from ..errors import HeliotwinError
from ..sun import direction_from_paint_angles

#: Focal-spot sources a record may carry, in PAINT's spelling.
SOURCES = ("HeliOS", "UTIS")


def normalise_source(name: str) -> str:
    """Accept ``heliOS``/``helios``/``utis`` (any case) and return PAINT's spelling."""
    for s in SOURCES:
        if name.lower() == s.lower():
            return s
    raise HeliotwinError(f"unknown focal-spot source {name!r}; known: {', '.join(SOURCES)}")


def parse_time(text: str | None) -> float:
    """UTC ISO timestamp -> POSIX seconds; NaN when missing or unparsable (the record then has no time)."""
    if not text:
        return float("nan")
    try:
        t = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        return float("nan")
    if t.tzinfo is None:  # PAINT's DateTime is UTC; a naive value is taken as UTC
        t = t.replace(tzinfo=timezone.utc)
    return t.timestamp()


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
        record has only one; ``None`` when not known (synthetic batches). Methods may fit on it (see
        :func:`heliotwin.calibrate.methods.fit_spots`); the metric always uses ``spot``.
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

    def __len__(self) -> int:
        return int(self.record_id.shape[0])

    @property
    def num_heliostats(self) -> int:
        return len(self.heliostat_ids)

    def subset(self, idx) -> "RecordTable":
        """Records ``idx`` (bool mask, index list or tensor); the heliostat axis is unchanged."""
        idx = torch.as_tensor(idx)
        if idx.dtype == torch.bool:
            idx = idx.nonzero().flatten()
        idx = idx.long()
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "heliostat_ids":
                out[f.name] = list(v)
            elif v is None:
                out[f.name] = None
            elif isinstance(v, list):
                out[f.name] = [v[i] for i in idx.tolist()]
            else:
                out[f.name] = v[idx]
        return RecordTable(**out)

    def of(self, h: int) -> torch.Tensor:
        """Indices (into this batch) of the records of heliostat ``h``."""
        return (self.heliostat_index == h).nonzero().flatten()

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
        heliostat_index : [R] int
        sun_azimuth, sun_elevation : [R] rad
        motor_steps : [R, 2]
        spot : [R, 3] ENU m
        target : PlanarTarget
            The plane of every record.
        time : [R] POSIX s, optional (NaN = unknown)
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
            elif f.name == "spot_other":
                out[f.name] = None if any(v is None for v in vs) else torch.cat(vs)
            elif isinstance(vs[0], list):
                out[f.name] = [x for v in vs for x in v]
            else:
                out[f.name] = torch.cat(vs)
        return RecordTable(**out)


WEATHER_KEYS = ("wind_speed", "wind_direction", "dni", "temperature", "humidity")


def prepare_records(plant, records, heliostat_ids=None, *, focal_spot: str = "HeliOS",
                    plane_tolerance: float = 0.1) -> tuple[RecordTable, list[dict]]:
    """Validate PAINT records and batch the good ones.

    Parameters
    ----------
    plant : heliotwin.field.plant.Plant
        Provides targets and the kinematics' motor ranges.
    records : list of heliotwin.io.paint.CalibrationRecord
    heliostat_ids : list of str, optional
        Heliostats to keep, in this order (default: the plant's field order). Their index in this list is
        ``heliostat_index``; the caller indexes the kinematics the same way.
    focal_spot : str
        Preferred centroid source (``HeliOS`` or ``UTIS``); a record without it falls back to the other.
    plane_tolerance : float
        Largest distance [m] of a focal spot from its target plane (the multi-focus tower's records lie
        up to 9 cm behind it; beyond 0.1 m the centroid is not on the target the record names).

    Returns
    -------
    batch : RecordTable
    skipped : list of dict
        ``{"record_id", "heliostat_id", "reason"}`` per dropped record.
    """
    prefer = normalise_source(focal_spot)
    ids = list(plant.field.ids if heliostat_ids is None else heliostat_ids)
    pos = {h: i for i, h in enumerate(ids)}
    kin = plant.field.kinematics
    cols = {k: [] for k in ("hidx", "rid", "az", "el", "steps", "spot", "other", "c", "n", "r", "u", "t", "w", "target",
                            "source")}
    skipped = []
    for rec in records:
        if rec.heliostat_id not in pos:
            continue

        def skip(reason):
            skipped.append({"record_id": int(rec.record_id), "heliostat_id": rec.heliostat_id, "reason": reason})

        h = plant.field.index_of(rec.heliostat_id)
        target = plant.targets.get(rec.target)
        if target is None:
            skip(f"unknown target {rec.target!r}")
            continue
        if getattr(target, "kind", "") != "planar":
            skip(f"target {rec.target!r} is not planar (centroid calibration needs a flat target)")
            continue
        src = prefer if prefer in rec.focal_spot else next((s for s in SOURCES if s in rec.focal_spot), None)
        if src is None:
            skip("no focal-spot centroid")
            continue
        spot = torch.as_tensor(rec.focal_spot[src], dtype=torch.float64)
        steps = torch.tensor(rec.motor_steps, dtype=torch.float64)
        if not (bool(torch.isfinite(spot).all()) and bool(torch.isfinite(steps).all())
                and math.isfinite(rec.sun_azimuth) and math.isfinite(rec.sun_elevation)):
            skip("non-finite value")
            continue
        if rec.sun_elevation <= 0:
            skip(f"sun elevation {math.degrees(rec.sun_elevation):.2f} deg at or below the horizon")
            continue
        lo, hi = kin.min_steps[h], kin.max_steps[h]
        bad = (steps < lo) | (steps > hi)
        if bool(bad.any()):
            a = int(bad.nonzero()[0])
            skip(f"motor steps axis {a + 1} = {steps[a].item():.0f} outside actuator range "
                 f"[{lo[a].item():.0f}, {hi[a].item():.0f}]")
            continue
        dist = float(target.distance_to_plane(spot))
        if abs(dist) > plane_tolerance:
            skip(f"focal spot {dist:+.3f} m off the plane of target {rec.target!r} (tolerance {plane_tolerance} m)")
            continue
        cols["hidx"].append(pos[rec.heliostat_id])
        cols["rid"].append(int(rec.record_id))
        cols["az"].append(rec.sun_azimuth)
        cols["el"].append(rec.sun_elevation)
        cols["steps"].append(steps)
        cols["spot"].append(spot)
        other = next((s for s in SOURCES if s != src and s in rec.focal_spot), None)
        o = torch.as_tensor(rec.focal_spot[other], dtype=torch.float64) if other is not None else None
        ok_other = o is not None and bool(torch.isfinite(o).all()) and abs(float(target.distance_to_plane(o))) <= plane_tolerance
        cols["other"].append(o if ok_other else torch.full((3,), float("nan"), dtype=torch.float64))
        cols["c"].append(target.center)
        cols["n"].append(target.normal)
        cols["r"].append(target.right)
        cols["u"].append(target.up)
        cols["t"].append(parse_time(rec.datetime))
        w = rec.weather or {}
        cols["w"].append([float(w.get(k, float("nan"))) for k in WEATHER_KEYS])
        cols["target"].append(rec.target)
        cols["source"].append(src)
    f64 = dict(dtype=torch.float64)
    n = len(cols["rid"])

    def stack3(key):
        return torch.stack(cols[key]).to(torch.float64) if n else torch.zeros(0, 3, **f64)

    az = torch.tensor(cols["az"], **f64)
    el = torch.tensor(cols["el"], **f64)
    batch = RecordTable(
        heliostat_ids=ids,
        heliostat_index=torch.tensor(cols["hidx"], dtype=torch.long),
        record_id=torch.tensor(cols["rid"], dtype=torch.long),
        sun_azimuth=az, sun_elevation=el,
        sun=direction_from_paint_angles(az, el, check_horizon=False) if n else torch.zeros(0, 3, **f64),
        motor_steps=torch.stack(cols["steps"]) if n else torch.zeros(0, 2, **f64),
        spot=stack3("spot"), plane_center=stack3("c"), plane_normal=stack3("n"),
        plane_right=stack3("r"), plane_up=stack3("u"),
        time=torch.tensor(cols["t"], **f64),
        weather=torch.tensor(cols["w"], **f64) if n else torch.zeros(0, len(WEATHER_KEYS), **f64),
        target=cols["target"], source=cols["source"], spot_other=stack3("other"),
    )
    return batch, skipped
