"""Measured or typical-year direct normal irradiance (DNI) as a time series, beside pvlib's clear sky.

:func:`read_dni_series` reads three kinds of CSV and returns UTC instants with their DNI [W/m^2]:

* **SAM / typical meteorological year** (as NREL's SAM and SolarPILOT take it): two metadata lines
  (``Source,...,Latitude,Longitude,Time Zone,Elevation`` and their values), then a header with ``Year, Month,
  Day, Hour, Minute`` and ``DNI``; times are local standard time (``Time Zone`` hours east of UTC) and are
  converted to UTC.
* **PAINT's** ``metadata/calibration-weather.csv``: ``DateTime`` (UTC) and ``dni`` per calibration record
  (measured at the tower, at the records' instants only).
* **Any table** with a time column (``time``, ``timestamp``, ``datetime``, ``date``; ISO, naive = UTC) and a
  ``dni`` column (case-insensitive; also ``dni_w_m2``).

Rows with a missing or negative DNI are dropped and counted. Errors are one line naming the file and the
field (:class:`heliotwin.errors.InputFileError`).
"""
from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import InputFileError

__all__ = ["DniSeries", "read_dni_series"]

_TIME_COLUMNS = ("time", "timestamp", "datetime", "date_time", "date", "time_utc")
_DNI_COLUMNS = ("dni", "dni_w_m2", "dni [w/m2]", "dni (w/m2)")
_MAX_BYTES = 200 * 1024 * 1024


@dataclass
class DniSeries:
    """UTC instants and their DNI.

    Attributes
    ----------
    times : pandas.DatetimeIndex
        UTC, sorted, length T.
    dni : numpy.ndarray, [T], float64
        [W/m^2].
    step_hours : float
        The interval each instant stands for [h] (the median spacing; 1 for a single instant).
    kind : str
        ``"sam"``, ``"paint"`` or ``"table"``.
    path : str
    dropped : int
        Rows without a usable DNI.
    info : dict
        The SAM file's site metadata (latitude, longitude, time zone, elevation), when there is one.
    """

    times: pd.DatetimeIndex
    dni: np.ndarray
    step_hours: float
    kind: str
    path: str
    dropped: int = 0
    info: dict = field(default_factory=dict)


def _lower(names) -> dict:
    return {str(n).strip().lower(): n for n in names}


def _sam(path: Path, lines: list[str]) -> tuple[pd.DatetimeIndex, pd.Series, dict]:
    meta = dict(zip(next(csv.reader([lines[0]])), next(csv.reader([lines[1]]))))
    try:
        tz = float(meta.get("Time Zone", meta.get("Time zone", 0.0)) or 0.0)
    except ValueError:
        raise InputFileError(path, f"cannot read the time zone {meta.get('Time Zone')!r}", field="Time Zone") from None
    frame = pd.read_csv(path, skiprows=2)
    cols = _lower(frame.columns)
    for need in ("year", "month", "day", "hour"):
        if need not in cols:
            raise InputFileError(path, "missing column (a SAM weather file has Year, Month, Day, Hour, Minute, DNI)",
                                 field=need)
    parts = {k: pd.to_numeric(frame[cols[k]], errors="coerce") for k in ("year", "month", "day", "hour")}
    minute = pd.to_numeric(frame[cols["minute"]], errors="coerce") if "minute" in cols else 0
    try:
        local = pd.to_datetime(dict(year=parts["year"], month=parts["month"], day=parts["day"], hour=parts["hour"],
                                    minute=minute))
    except (ValueError, TypeError) as exc:
        raise InputFileError(path, f"cannot build times from Year/Month/Day/Hour/Minute ({exc})", field="Year") \
            from None
    times = pd.DatetimeIndex(local - pd.Timedelta(hours=tz)).tz_localize("UTC")
    dni_col = next((cols[c] for c in _DNI_COLUMNS if c in cols), None)
    if dni_col is None:
        raise InputFileError(path, "missing column", field="DNI")
    info = {k: meta[k] for k in ("Latitude", "Longitude", "Time Zone", "Elevation") if k in meta}
    return times, frame[dni_col], info


def _table(path: Path) -> tuple[pd.DatetimeIndex, pd.Series, str]:
    frame = pd.read_csv(path, comment="#")
    cols = _lower(frame.columns)
    tcol = next((cols[c] for c in _TIME_COLUMNS if c in cols), None)
    dcol = next((cols[c] for c in _DNI_COLUMNS if c in cols), None)
    if tcol is None:
        raise InputFileError(path, f"no time column (expected one of {', '.join(_TIME_COLUMNS)}, or a SAM weather "
                             "file)", field="time")
    if dcol is None:
        raise InputFileError(path, "no DNI column (expected 'dni' [W/m2])", field="dni")
    try:
        times = pd.DatetimeIndex(pd.to_datetime(frame[tcol], utc=True, format="mixed"))
    except (ValueError, TypeError) as exc:
        raise InputFileError(path, f"cannot parse the times ({exc})", field=str(tcol)) from None
    kind = "paint" if "heliostatid" in cols else "table"
    return times, frame[dcol], kind


def read_dni_series(path) -> DniSeries:
    """Read a DNI time series (module docstring) from ``path``.

    Raises
    ------
    InputFileError
        Missing, unreadable or huge file; no time or DNI column; unparsable times; no usable row.
    """
    path = Path(path)
    try:
        if path.stat().st_size > _MAX_BYTES:
            raise InputFileError(path, f"larger than {_MAX_BYTES // 2**20} MiB; not a weather file")
        with open(path, encoding="utf-8-sig") as fh:
            head = [fh.readline() for _ in range(3)]
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(path, f"cannot read ({exc})") from None
    info = {}
    try:
        if head[0].lower().startswith("source") and "time zone" in head[0].lower():
            times, dni, info = _sam(path, head)
            kind = "sam"
        else:
            times, dni, kind = _table(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise InputFileError(path, f"malformed CSV ({' '.join(str(exc).split())})") from None
    values = pd.to_numeric(dni, errors="coerce").to_numpy(dtype=np.float64)
    ok = np.isfinite(values) & (values >= 0) & ~pd.isna(times)
    if not ok.any():
        raise InputFileError(path, "no row with a time and a non-negative DNI", field="dni")
    order = np.argsort(times[ok].asi8, kind="stable")
    t = times[ok][order]
    v = values[ok][order]
    step = float(pd.Series(t).diff().median().total_seconds()) / 3600.0 if len(t) > 1 else 1.0
    return DniSeries(t, v, step, kind, str(path), dropped=int((~ok).sum()), info=info)
