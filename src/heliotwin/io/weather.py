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

One rule for every command that takes ``--weather`` (``field --year``, ``predict``), in two steps:

:func:`read_dni_series` (the file as it is):

* a row whose DNI is missing (empty, not a number, NaN) **or negative** is a gap: its interval has no DNI and
  contributes no energy (sensors' night offsets and ``-9999`` markers alike); both are counted
  (``missing``, ``negative``);
* rows repeating an instant with the same DNI (within 0.5 W/m^2) are one row (counted, ``repeated``); an
  instant given two different DNIs is an error naming it;
* a DNI above :data:`MAX_DNI_W_M2` (no sun gives more: W/m^2 x 10^3 or x 10^6?) or a file whose largest DNI is
  at most :data:`KW_THRESHOLD` (kW/m^2 read as W/m^2?) is an error, as is a file whose every DNI is 0 or
  missing (no direct sun to make energy from).

:func:`weather_for_year` (the file placed in the year asked for):

* the rows in that year are used; a file with no row in it but all (or all but the rows a UTC shift moves
  across New Year) in one other year is a typical year and is moved into it (month, day and time kept;
  29 February dropped when the year has none), which the report states; a file spanning other years only is
  an error;
* each row stands for its interval (the file's step, the median spacing; less where the next row comes
  sooner), so the energy is that of the hours the file covers: **annual** only when they are at least
  :data:`ANNUAL_FRACTION` of the year, else the report says which part of the year it is.

Errors are one line naming the file and the field (:class:`heliotwin.errors.InputFileError`).
"""
from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import InputFileError

__all__ = ["DniSeries", "WeatherYear", "read_dni_series", "weather_for_year", "MAX_DNI_W_M2", "KW_THRESHOLD",
           "ANNUAL_FRACTION"]

_TIME_COLUMNS = ("time", "timestamp", "datetime", "date_time", "date", "time_utc")
_DNI_COLUMNS = ("dni", "dni_w_m2", "dni [w/m2]", "dni (w/m2)")
_MAX_BYTES = 200 * 1024 * 1024
MAX_DNI_W_M2 = 1500.0  #: [W/m^2] above any DNI at the ground (the solar constant is 1361 W/m^2)
KW_THRESHOLD = 2.0  #: [W/m^2] a file whose largest DNI is at most this is in kW/m^2, not W/m^2
ANNUAL_FRACTION = 0.98  #: share of the year's hours a file must cover for its energy to be called annual
_SAME_DNI = 0.5  #: [W/m^2] rows repeating an instant within this are one row


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
        Rows without a usable DNI (``missing + negative``; rows without a time are among ``missing``).
    info : dict
        The SAM file's site metadata (latitude, longitude, time zone, elevation), when there is one.
    missing, negative, repeated : int
        Rows with no DNI (or no time), with a negative DNI (both gaps), and repeats of an instant (merged).
    """

    times: pd.DatetimeIndex
    dni: np.ndarray
    step_hours: float
    kind: str
    path: str
    dropped: int = 0
    info: dict = field(default_factory=dict)
    missing: int = 0
    negative: int = 0
    repeated: int = 0


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
    no_time = np.asarray(pd.isna(times))
    missing = ~np.isfinite(values) | no_time
    negative = ~missing & (values < 0)
    ok = ~missing & ~negative
    if not ok.any():
        raise InputFileError(path, "no row with a time and a non-negative DNI", field="dni")
    order = np.argsort(times[ok].asi8, kind="stable")
    t = times[ok][order]
    v = values[ok][order]
    t, v, repeated = _merge_repeats(path, t, v)
    _check_units(path, v)
    step = float(pd.Series(t).diff().median().total_seconds()) / 3600.0 if len(t) > 1 else 1.0
    return DniSeries(t, v, step, kind, str(path), dropped=int((~ok).sum()), info=info, missing=int(missing.sum()),
                     negative=int(negative.sum()), repeated=repeated)


def _merge_repeats(path, t: pd.DatetimeIndex, v: np.ndarray):
    """Sorted times and DNIs with the repeats of an instant merged (same DNI) or refused (different DNI)."""
    same = np.zeros(len(t), dtype=bool)
    same[1:] = t.asi8[1:] == t.asi8[:-1]
    if not same.any():
        return t, v, 0
    first = np.flatnonzero(~same)
    group = np.cumsum(~same) - 1
    lo, hi = np.full(len(first), np.inf), np.full(len(first), -np.inf)
    np.minimum.at(lo, group, v)
    np.maximum.at(hi, group, v)
    bad = np.flatnonzero(hi - lo > _SAME_DNI)
    if bad.size:
        k = int(bad[0])
        raise InputFileError(path, f"the instant {t[first[k]].isoformat()} is given {int((group == k).sum())} "
                             f"different DNIs ({lo[k]:g} to {hi[k]:g} W/m2); one DNI per instant",
                             field="time")
    return t[first], 0.5 * (lo + hi), int(same.sum())


def _check_units(path, v: np.ndarray) -> None:
    """DNI in W/m^2: not above any sun's, not all in kW/m^2's range, not all zero."""
    top = float(v.max())
    if top > MAX_DNI_W_M2:
        raise InputFileError(path, f"DNI up to {top:g}: above the {MAX_DNI_W_M2:g} W/m2 no sun gives at the ground "
                             "(expected W/m2; is the column scaled?)", field="dni")
    if top == 0.0:
        raise InputFileError(path, f"every DNI of the {len(v)} rows is 0: no direct sun to make energy from (a "
                             "night-only or empty series?)", field="dni")
    if top <= KW_THRESHOLD:
        raise InputFileError(path, f"DNI at most {top:g}: looks like kW/m2 (expected W/m2, e.g. 850 not 0.85)",
                             field="dni")


@dataclass
class WeatherYear:
    """A DNI series placed in one calendar year (:func:`weather_for_year`).

    Attributes
    ----------
    year : int
    times : pandas.DatetimeIndex
        UTC instants in ``year``, sorted, unique, length T.
    dni : numpy.ndarray, [T], float64
        [W/m^2].
    hours : numpy.ndarray, [T], float64
        The interval each instant stands for [h]: the file's step, less where the next row comes sooner.
    step_hours : float
        The file's step [h].
    annual : bool
        The rows cover at least :data:`ANNUAL_FRACTION` of the year's hours.
    coverage : dict
        ``hours``, ``fraction_of_year``, ``first``, ``last`` (ISO), ``annual``.
    assumptions : list of str
        What was assumed or changed to place the file in the year (one sentence each).
    source : dict
        ``file``, ``kind``, ``rows`` (used), ``rows_missing``, ``rows_negative``, ``rows_repeated``,
        ``rows_outside_year``, ``moved_from_year`` and the SAM file's site metadata.
    """

    year: int
    times: pd.DatetimeIndex
    dni: np.ndarray
    hours: np.ndarray
    step_hours: float
    annual: bool
    coverage: dict
    assumptions: list
    source: dict

    def dni_at(self, times) -> np.ndarray:
        """DNI [W/m^2] at UTC ``times`` (T'): the row whose interval holds the instant (the nearest row within
        half the step), NaN where the file has no row (a gap: no energy there)."""
        at = pd.Series(self.dni, index=self.times)
        idx = pd.DatetimeIndex(pd.to_datetime(times, utc=True))
        near = at.reindex(idx, method="nearest", tolerance=pd.Timedelta(hours=0.5 * self.step_hours))
        return near.to_numpy(dtype=np.float64)


def _year_hours(year: int) -> float:
    return (pd.Timestamp(year + 1, 1, 1) - pd.Timestamp(year, 1, 1)).total_seconds() / 3600.0


def weather_for_year(series: DniSeries, year: int) -> WeatherYear:
    """The rows of ``series`` in ``year``, or the file moved into it when it is another year's (module
    docstring); the interval each row stands for, the coverage and the assumptions made.

    Raises
    ------
    InputFileError
        No row in ``year`` and the rows span several other years.
    """
    year = int(year)
    times, dni = series.times, np.asarray(series.dni, dtype=np.float64)
    assumptions, moved, outside = [], None, 0
    years = np.asarray(times.year)
    if not (years == year).any():
        values, counts = np.unique(years, return_counts=True)
        main = int(values[np.argmax(counts)])
        # a typical year: one year's rows (and a few a UTC shift moved across New Year)
        if counts.max() < 0.95 * len(years) or (np.abs(values - main) > 1).any():
            raise InputFileError(series.path, f"no row in {year} (the rows span {int(values.min())} to "
                                 f"{int(values.max())}); give that year's weather or a typical year", field="time")
        moved = main
        feb29 = (times.month == 2) & (times.day == 29)
        leap = pd.Timestamp(year, 1, 1).is_leap_year
        keep = ~feb29 | leap
        shifted = times[keep] + pd.DateOffset(years=year - main)
        times, dni = pd.DatetimeIndex(shifted), dni[np.asarray(keep)]
        assumptions.append(f"the file holds {main}, not {year}: read as a typical year and moved into {year} "
                           f"(month, day and time kept, the sun of {year})"
                           + (f"; {int((~keep).sum())} rows of 29 February dropped" if (~keep).any() else ""))
    inside = np.asarray(times.year) == year
    outside = int((~inside).sum())
    if outside:
        assumptions.append(f"{outside} rows outside {year} not used")
    times, dni = times[inside], dni[inside]
    if len(times) == 0:
        raise InputFileError(series.path, f"no row in {year}", field="time")
    step = float(series.step_hours)
    gaps = np.asarray((times[1:] - times[:-1]).total_seconds(), dtype=np.float64) / 3600.0
    hours = np.minimum(step, np.append(gaps, step))
    covered = float(hours.sum())
    fraction = covered / _year_hours(year)
    # The gap rows are dropped before the step is read from the rows left, so a file with every second DNI missing
    # looked like a complete year at twice the step: a file is annual only when its gaps are as rare as the hours
    # ANNUAL_FRACTION lets it miss.
    share = (series.missing + series.negative) / max(1, len(times) + series.missing + series.negative)
    annual = fraction >= ANNUAL_FRACTION and share <= 1.0 - ANNUAL_FRACTION
    if series.missing or series.negative:
        assumptions.append(f"{series.missing} rows without a DNI and {series.negative} with a negative DNI are gaps "
                           f"(no energy in their intervals; {100 * share:.1f} % of the rows)"
                           + ("" if share <= 1.0 - ANNUAL_FRACTION else ": too many for an annual energy"))
    if series.repeated:
        assumptions.append(f"{series.repeated} rows repeating an instant with the same DNI counted once")
    if not annual:
        assumptions.append(f"the file covers {covered:.1f} h, {100 * fraction:.2f} % of {year} "
                           f"({times[0].isoformat()} to {times[-1].isoformat()}): the energy is that of those hours, "
                           "not annual")
    coverage = {"hours": covered, "fraction_of_year": fraction, "first": times[0].isoformat(),
                "last": times[-1].isoformat(), "annual": annual}
    source = {"file": str(series.path), "kind": series.kind, "rows": int(len(times)), "rows_missing": series.missing,
              "rows_negative": series.negative, "rows_repeated": series.repeated, "rows_outside_year": outside,
              "moved_from_year": moved, **series.info}
    return WeatherYear(year, times, dni, hours, step, annual, coverage, assumptions, source)
