"""The weather file formats :func:`heliotwin.io.weather.read_dni_series` reads, one reader each, and the detection
of a file's format from its content (never from its name alone).

Every reader returns a :class:`RawSeries`: the file's rows as **UTC instants at which the sun stands where the
row's energy was collected**, their DNI [W/m^2] (NaN where the file has none), the site the file names and its time
convention in words. The conventions (why each instant is where it is):

* **TMY3** (``pvlib.iotools.read_tmy3``), **TMY2** (``read_tmy2``), **EPW** (``read_epw``): local standard time
  (the file's fixed offset, no daylight saving), each value the irradiation of the hour *ending* at its stamp
  (TMY3 ``01:00`` and TMY2/EPW hour 1 = 00:00-01:00): the instant is the middle of that hour (00:30), where the
  sun stands at the hour's mean (to a few tenths of a degree); in the hour holding sunrise or sunset the instant is
  the middle of its sunlit part instead (SAM's rule, :func:`sunlit_middle`), where the middle of the hour may be
  below the horizon with a little DNI in the hour. The interval each row stands for stays the hour
  (``sun_shift_s`` records the move).
* **SAM CSV** (both two-line metadata layouts: ``Source,Location ID,City,...,Time Zone,Elevation`` and
  ``Location,City,Region,Country,Latitude,Longitude,Time Zone,Elevation[,Source]``): local standard time, read
  as SAM reads it (SAM help, "Time Convention and Sun Position"): with a ``Minute`` column the stamp
  ``Hour:Minute`` is the instant (SAM computes the sun there; NSRDB-made files stamp ``:30``, the middle of the
  hour); hourly rows with no ``Minute`` column stand for the hour *starting* at ``Hour`` (0-23: 0 = 00:00-01:00,
  TMY3's hour 1), so the instant is ``Hour:30``; without ``Minute`` and with hours 1-24 they are hour-ending
  (the instant ``Hour - 0:30``); without ``Minute`` the sunrise and sunset hours are moved as above.
* **NSRDB PSM3/PSM4 CSV** (``pvlib.iotools.read_nsrdb_psm4``, the installed pvlib's reader of the NSRDB's SAM-CSV
  files; pvlib >= 0.13 has no ``read_psm3``): instantaneous at the stamp in the file's ``Time Zone`` (hourly files
  are stamped at ``:30``, the middle of the hour they stand for).
* **PAINT** ``calibration-weather.csv`` and a plain ``time,dni`` table: instantaneous at the stamp, UTC unless the
  stamp carries an offset.

A file whose (month, day, time) keys are unique -- at most one year's worth of rows -- but whose rows name several
years (a typical year built from months of different years, as TMY3, TMY2, EPW and SolarPILOT's climate files are)
is a **typical year**: its Year column is ignored and it is placed in :data:`NOMINAL_YEAR` (or
:data:`NOMINAL_LEAP_YEAR` when it has a 29 February) until :func:`heliotwin.io.weather.weather_for_year` moves it.

Library warnings (pandas' ``DtypeWarning`` on mixed columns, pvlib's deprecations) are caught here: none reaches
the user.
"""
from __future__ import annotations

import csv
import importlib
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import InputFileError
from ..sun import solar_position

__all__ = ["RawSeries", "read_raw", "NOMINAL_YEAR", "NOMINAL_LEAP_YEAR", "FORMATS"]

NOMINAL_YEAR = 2001  #: the year a typical year without 29 February is placed in while read
NOMINAL_LEAP_YEAR = 2000  #: the year a typical year with 29 February is placed in while read
FORMATS = "TMY3, TMY2, EPW, SAM CSV, NSRDB PSM3 CSV, PAINT calibration-weather.csv or a time,dni CSV"
_TIME_COLUMNS = ("time", "timestamp", "datetime", "date_time", "date", "time_utc")
_DNI_COLUMNS = ("dni", "dni_w_m2", "dni [w/m2]", "dni (w/m2)", "dni (w/m^2)")
_SAM_DNI = ("dni", "beam", "dn", "direct normal", "dni (w/m2)", "dni (w/m^2)", "beam (w/m2)")
_MISSING_9999 = 9999.0  #: [W/m^2] EPW's and TMY2's "missing" marker
_TMY2_HEAD = re.compile(r"^\s*\d{5}\s+\S.*\s-?\d{1,2}\s+[NS]\s+\d+\s+\d+\s+[EW]\s+\d+\s+\d+\s+-?\d+\s*$")
_TMY2_ROW = re.compile(r"^[ \d]\d[ \d]\d[ \d]\d[ \d]\d\d")
_BINARY = ((b"\x89PNG", "a PNG image"), (b"\x89HDF", "an HDF5 file"), (b"\xff\xd8\xff", "a JPEG image"),
           (b"PK\x03\x04", "a ZIP archive"), (b"%PDF", "a PDF document"), (b"\x1f\x8b", "a gzip archive"))


@dataclass
class RawSeries:
    """A weather file's rows as read (:func:`read_raw`).

    Attributes
    ----------
    times : pandas.DatetimeIndex
        UTC, length N, in the file's order; NaT where a row has no time.
    dni : numpy.ndarray, [N], float64
        [W/m^2]; NaN where the row has none (missing markers included); negatives kept (the caller's gaps).
    kind : str
        ``"tmy3"``, ``"tmy2"``, ``"epw"``, ``"sam"``, ``"psm3"``, ``"paint"`` or ``"table"``.
    convention : str
        The time convention read, in words (for the report).
    info : dict
        The file's site where it names one: ``site_name``, ``latitude_deg``, ``longitude_deg`` [deg],
        ``elevation_m`` [m], ``time_zone_hours`` [h east of UTC].
    typical : bool
        A typical year (module docstring): placed in the nominal year, its Year column ignored.
    file_years : tuple of int
        The first and last year the rows name (before a typical year is placed).
    sun_shift_s : numpy.ndarray, [N], float64, optional
        Each instant's shift from the middle of its interval [s] (:func:`sunlit_middle`); None: no shift.
    """

    times: pd.DatetimeIndex
    dni: np.ndarray
    kind: str
    convention: str
    info: dict = field(default_factory=dict)
    typical: bool = False
    file_years: tuple = ()
    sun_shift_s: np.ndarray | None = None


def _iotools():
    """``pvlib.iotools``, imported when a file in one of its formats is read: ``import pvlib`` costs ~0.5 s, which
    the library's other users (``heliotwin.api``, a table or SAM file) should not pay (see :mod:`heliotwin.sunspa`)."""
    return importlib.import_module("pvlib.iotools")


def _lower(names) -> dict:
    return {str(n).strip().lower(): n for n in names}


def _float(value):
    try:
        out = float(str(value).strip())
    except (TypeError, ValueError):
        return None
    return out if np.isfinite(out) else None


def _site(name, lat, lon, elevation, tz) -> dict:
    out = {"site_name": str(name).strip().strip('"') if name is not None else None, "latitude_deg": _float(lat),
           "longitude_deg": _float(lon), "elevation_m": _float(elevation), "time_zone_hours": _float(tz)}
    return {k: v for k, v in out.items() if v not in (None, "")}


def _offset_text(hours: float) -> str:
    sign = "+" if hours >= 0 else "-"
    h, m = divmod(round(abs(hours) * 60), 60)
    return f"UTC{sign}{h:02d}:{m:02d}"


def _place(local: pd.DatetimeIndex, offset_hours: float, force_typical: bool = False):
    """Local standard (wall, naive) instants -> (UTC instants, typical, file years); a typical year is rebuilt in
    the nominal year first (its Year column ignored)."""
    local = pd.DatetimeIndex(local)
    ok = ~np.asarray(local.isna())
    good = local[ok]
    years = np.unique(np.asarray(good.year)) if len(good) else np.array([], dtype=int)
    file_years = (int(years.min()), int(years.max())) if len(years) else ()
    keys = (((np.asarray(good.month) * 100 + np.asarray(good.day)) * 100 + np.asarray(good.hour)) * 100
            + np.asarray(good.minute)) * 100 + np.asarray(good.second)
    typical = bool(len(good)) and (force_typical or (len(years) > 1 and len(np.unique(keys)) == len(keys)))
    if typical:
        leap = bool(((good.month == 2) & (good.day == 29)).any())
        rebuilt = pd.to_datetime(pd.DataFrame({"year": NOMINAL_LEAP_YEAR if leap else NOMINAL_YEAR,
                                               "month": good.month, "day": good.day, "hour": good.hour,
                                               "minute": good.minute, "second": good.second}))
        values = np.full(len(local), np.datetime64("NaT"), dtype="datetime64[ns]")
        values[ok] = rebuilt.to_numpy(dtype="datetime64[ns]")
        local = pd.DatetimeIndex(values)
    utc = pd.DatetimeIndex(local - pd.Timedelta(hours=float(offset_hours))).tz_localize("UTC")
    return utc, typical, file_years


def sunlit_middle(times: pd.DatetimeIndex, hours: float, info: dict) -> tuple[pd.DatetimeIndex, np.ndarray]:
    """Mid-interval UTC instants (T) of intervals ``hours`` [h] long moved, in the hour holding sunrise or
    sunset at the file's site (``info``), to the middle of the interval's sunlit part (SAM's rule for hourly
    files): the little DNI of that hour was collected with the sun up, where the middle of the hour may be below
    the horizon. Sunrise and sunset are placed by interpolating the sun's apparent elevation linearly within the
    interval (seconds off near the horizon). Unchanged without a site. Returns the instants and each one's
    shift from its interval's middle [s] (T; 0 but at sunrise and sunset)."""
    lat, lon = info.get("latitude_deg"), info.get("longitude_deg")
    ok = ~np.asarray(times.isna())
    if lat is None or lon is None or not ok.any():
        return times, np.zeros(len(times))
    half = pd.Timedelta(hours=hours / 2)
    t = times[ok]
    alt = info.get("elevation_m") or 0.0
    el0 = solar_position(t - half, lat, lon, alt)[1].numpy()
    el1 = solar_position(t + half, lat, lon, alt)[1].numpy()
    rise, sets = (el0 <= 0) & (el1 > 0), (el0 > 0) & (el1 <= 0)
    cross = np.where(rise | sets, el0 / np.where(el0 != el1, el0 - el1, 1.0), 0.5)  # [0, 1] of the interval
    frac = np.where(rise, 0.5 * (cross + 1.0), np.where(sets, 0.5 * cross, 0.5))
    shift = np.zeros(len(times))
    shift[ok] = np.round((frac - 0.5) * 2 * half.value) / 1e9
    moved = pd.DatetimeIndex(times + pd.to_timedelta(shift, unit="s"))
    return moved, shift


_SUNLIT = "; the sunrise and sunset hours at the middle of their sunlit part (SAM's rule)"


def _library(path, what: str, reader, *args, **kwargs):
    """A pvlib/pandas reader called with its warnings silenced; its errors become one line naming the file."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return reader(*args, **kwargs)
    except (ValueError, KeyError, IndexError, TypeError, AttributeError, pd.errors.ParserError,
            pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise InputFileError(path, f"cannot read as {what} ({' '.join(str(exc).split())[:160]})") from None


def _values(frame, column) -> np.ndarray:
    return np.array(pd.to_numeric(frame[column], errors="coerce"), dtype=np.float64)  # a writable copy


def _from_pvlib(path, kind: str, data, meta: dict, column: str, shift_h: float, tz: float, name, what: str,
                force_typical: bool = False, missing_9999: bool = False) -> RawSeries:
    if column not in data.columns:
        raise InputFileError(path, f"no DNI column in the {what} file", field=column)
    local = pd.DatetimeIndex(data.index).tz_localize(None) + pd.Timedelta(hours=shift_h)
    dni = _values(data, column)
    if missing_9999:
        dni[dni >= _MISSING_9999] = np.nan
    times, typical, years = _place(local, tz, force_typical)
    info = _site(name, meta.get("latitude"), meta.get("longitude"), meta.get("altitude"), tz)
    times, shift = sunlit_middle(times, 1.0, info)
    return RawSeries(times, dni, kind, "", info, typical, years, shift)


def _tmy3(path: Path) -> RawSeries:
    data, meta = _library(path, "TMY3", _iotools().read_tmy3, str(path), map_variables=True)
    tz = float(meta["TZ"])
    # The stamps from the file's own Date and Time columns: pvlib moves a leap year's "02/28 24:00" (the hour
    # ending at midnight, 23:00-24:00 on 28 February) to 1 March 00:00 by its 29-February rule, a day late.
    try:
        date = pd.to_datetime(data["Date (MM/DD/YYYY)"], format="%m/%d/%Y")
        hh_mm = data["Time (HH:MM)"].astype(str).str.split(":", expand=True).astype(int)
    except (KeyError, ValueError, TypeError) as exc:
        raise InputFileError(path, f"cannot read the TMY3 Date/Time ({' '.join(str(exc).split())[:120]})",
                             field="Time (HH:MM)") from None
    stamp = date + pd.to_timedelta(hh_mm[0], unit="h") + pd.to_timedelta(hh_mm[1], unit="min")
    data.index = pd.DatetimeIndex(stamp)
    raw = _from_pvlib(path, "tmy3", data, meta, "dni", -0.5, tz, meta.get("Name"), "TMY3")
    raw.convention = _hour_ending("TMY3", tz, "01:00")
    return raw


def _hour_ending(name: str, tz: float, first: str) -> str:
    """The convention of an hourly local-standard-time file of hour-ending values (``first``: how the file names
    its first hour), as the reading turns it into UTC instants."""
    return (f"{name}: local standard time ({_offset_text(tz)}, no DST), hour-ending values ({first} = 00:00-01:00) "
            "-> UTC at the middle of each hour" + _SUNLIT)


def _tmy2(path: Path) -> RawSeries:
    data, meta = _library(path, "TMY2", _iotools().read_tmy2, str(path))
    tz = float(meta["TZ"])
    # pvlib stamps TMY2's hour h at h-1 (the hour's start): the middle is 30 min later
    raw = _from_pvlib(path, "tmy2", data, meta, "DNI", 0.5, tz, meta.get("City"), "TMY2", force_typical=True,
                      missing_9999=True)
    raw.convention = _hour_ending("TMY2", tz, "hour 1")
    return raw


def _epw(path: Path) -> RawSeries:
    data, meta = _library(path, "EPW", _iotools().read_epw, str(path))
    tz = float(meta["TZ"])
    # pvlib stamps EPW's hour h at h-1 (the hour's start): the middle is 30 min later
    raw = _from_pvlib(path, "epw", data, meta, "dni", 0.5, tz, meta.get("city"), "EPW", missing_9999=True)
    raw.convention = _hour_ending("EPW", tz, "hour 1")
    return raw


def _meta(lines: list[str]) -> dict:
    fields = next(csv.reader([lines[0]]), [])
    values = next(csv.reader([lines[1]]), [])
    return {str(f).strip().lower(): str(v).strip() for f, v in zip(fields, values)}


def _meta_tz(path, meta: dict, key: str = "time zone") -> float:
    raw = meta.get(key, meta.get("timezone", meta.get("time_zone", "0")))
    tz = _float(raw or 0)
    if tz is None or not -14 <= tz <= 14:
        raise InputFileError(path, f"cannot read the time zone {raw!r} (hours east of UTC, -14 to 14)",
                             field="Time Zone")
    return tz


def _psm3(path: Path, lines: list[str]) -> RawSeries:
    meta_text = _meta(lines)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data, meta = _iotools().read_nsrdb_psm4(str(path), map_variables=True)
    except (ValueError, KeyError, IndexError, TypeError, pd.errors.ParserError):
        # pvlib's reader wants integer zones and elevation; anything else is read as SAM CSV, instantaneous
        raw = _sam(path, lines, instantaneous=True)
        raw.kind = "psm3"
        return raw
    tz = float(meta["Time Zone"])
    local = pd.DatetimeIndex(data.index).tz_localize(None)
    times, typical, years = _place(local, tz)
    info = _site(meta_text.get("city") or meta_text.get("location id"), meta.get("latitude"), meta.get("longitude"),
                 meta.get("altitude"), meta.get("Local Time Zone", tz))
    if "dni" not in data.columns:
        raise InputFileError(path, "no DNI column in the NSRDB file", field="DNI")
    conv = (f"NSRDB PSM3: instantaneous at the stamp ({_offset_text(tz)}; hourly files are stamped at :30, the "
            "middle of their hour) -> UTC at the stamp")
    return RawSeries(times, _values(data, "dni"), "psm3", conv, info, typical, years)


def _sam(path: Path, lines: list[str], instantaneous: bool = False) -> RawSeries:
    meta = _meta(lines)
    tz = _meta_tz(path, meta)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        frame = pd.read_csv(path, skiprows=2, low_memory=False, encoding="utf-8-sig")
    cols = _lower(frame.columns)
    for need in ("month", "day", "hour"):
        if need not in cols:
            raise InputFileError(path, "missing column (a SAM weather file has Year, Month, Day, Hour[, Minute] and "
                                 "DNI or Beam)", field=need.capitalize())
    dni_col = next((cols[c] for c in _SAM_DNI if c in cols), None)
    if dni_col is None:
        raise InputFileError(path, "no DNI column (a SAM weather file has DNI or Beam [W/m2])", field="DNI")
    part = {k: pd.to_numeric(frame[cols[k]], errors="coerce") for k in ("month", "day", "hour")}
    year = (pd.to_numeric(frame[cols["year"]], errors="coerce") if "year" in cols
            else pd.Series(NOMINAL_YEAR, index=frame.index))
    minute = (pd.to_numeric(frame[cols["minute"]], errors="coerce").fillna(0) if "minute" in cols
              else pd.Series(0, index=frame.index))
    hour = part["hour"]
    ending = bool(hour.max() == 24 and hour.min() >= 1)
    try:
        day_start = pd.to_datetime(pd.DataFrame({"year": year, "month": part["month"], "day": part["day"]}),
                                   errors="raise")
    except (ValueError, TypeError) as exc:
        raise InputFileError(path, f"cannot build dates from Year/Month/Day ({' '.join(str(exc).split())[:120]})",
                             field="Day") from None
    stamp = pd.DatetimeIndex(day_start + pd.to_timedelta(hour, unit="h") + pd.to_timedelta(minute, unit="min"))
    step = pd.Series(stamp).diff().median()
    hourly = pd.notna(step) and step == pd.Timedelta(hours=1)
    where = _offset_text(tz)
    # SAM's own rule (SAM help, "Time Convention and Sun Position"): hourly data with no Minute column stand for
    # the hour whose middle is Hour:30 (Hour 0 = 00:00-01:00); with a Minute column the sun is at Hour:Minute
    if instantaneous:
        local, conv = stamp, f"NSRDB PSM3 (SAM CSV): instantaneous at the stamp ({where}) -> UTC at the stamp"
    elif "minute" not in cols and ending:
        local = stamp - pd.Timedelta(minutes=30)
        conv = (f"SAM CSV: local standard time ({where}), no Minute column, Hour 1-24 hour-ending (1 = "
                "00:00-01:00) -> UTC at the middle of each hour")
    elif "minute" not in cols and hourly:
        local = stamp + pd.Timedelta(minutes=30)
        conv = (f"SAM CSV: local standard time ({where}), no Minute column: each row the hour starting at its Hour "
                "(0 = 00:00-01:00) -> UTC at the middle of the hour (SAM's sun position)")
    else:
        local = stamp
        conv = (f"SAM CSV: local standard time ({where}), the sun at Hour:Minute (SAM's sun position; NSRDB "
                "files stamp :30, the middle of the hour) -> UTC at the stamp")
    times, typical, years = _place(local, tz, force_typical="year" not in cols)  # no Year: a typical year
    info = _site(meta.get("city") or meta.get("location") or meta.get("location id"), meta.get("latitude"),
                 meta.get("longitude"), meta.get("elevation"), tz)
    if "minute" not in cols and (ending or hourly) and not instantaneous:
        (times, shift), conv = sunlit_middle(times, 1.0, info), conv + _SUNLIT
        return RawSeries(times, _values(frame, dni_col), "sam", conv, info, typical, years, shift)
    return RawSeries(times, _values(frame, dni_col), "sam", conv, info, typical, years)


def _table(path: Path) -> RawSeries:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        frame = pd.read_csv(path, comment="#", low_memory=False, encoding="utf-8-sig")
    cols = _lower(frame.columns)
    tcol = next((cols[c] for c in _TIME_COLUMNS if c in cols), None)
    dcol = next((cols[c] for c in _DNI_COLUMNS if c in cols), None)
    if tcol is None:
        raise InputFileError(path, f"not a weather file: no time column (expected one of {', '.join(_TIME_COLUMNS)}"
                             f"; or a {FORMATS.split(', PAINT')[0]} file)", field="time")
    if dcol is None:
        raise InputFileError(path, "not a weather file: no DNI column (expected 'dni' [W/m2])", field="dni")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            times = pd.DatetimeIndex(pd.to_datetime(frame[tcol], utc=True, format="mixed"))
    except (ValueError, TypeError) as exc:
        raise InputFileError(path, f"cannot parse the times ({exc})", field=str(tcol)) from None
    kind = "paint" if "heliostatid" in cols else "table"
    conv = ("PAINT calibration weather: measured at each record's instant (UTC)" if kind == "paint" else
            "time,dni table: instantaneous at each stamp (UTC where the stamp has no offset)")
    return RawSeries(times, _values(frame, dcol), kind, conv, {}, False, ())


def _not_text(head: bytes) -> str | None:
    for magic, what in _BINARY:
        if head.startswith(magic):
            return what
    if b"\x00" in head:
        return "binary data"
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 4:  # not a multi-byte character cut by the read's end
            try:
                head.decode("latin-1")
            except UnicodeDecodeError:  # pragma: no cover - latin-1 decodes every byte
                return "binary data"
    return None


def detect_format(path: Path, head_bytes: bytes, lines: list[str]) -> str:
    """The format of a file from its first bytes and lines: ``"tmy3"``, ``"tmy2"``, ``"epw"``, ``"psm3"``,
    ``"sam"`` or ``"table"`` (PAINT's CSV is a table); a binary file is a one-line error naming it."""
    what = _not_text(head_bytes)
    if what is not None:
        raise InputFileError(path, f"not a weather file ({what}); expected {FORMATS}")
    first = lines[0].strip().lower() if lines else ""
    second = lines[1].strip().lower() if len(lines) > 1 else ""
    if not first:
        raise InputFileError(path, f"empty; not a weather file (expected {FORMATS})")
    if first.startswith("location,") and len(first.split(",")) >= 10 and "latitude" not in first:
        return "epw"
    if second.startswith("date (mm/dd/yyyy)"):
        return "tmy3"
    if _TMY2_HEAD.match(lines[0].rstrip("\n")) and _TMY2_ROW.match(lines[1] if len(lines) > 1 else ""):
        return "tmy2"
    if "latitude" in first and "longitude" in first and ("time zone" in first or "timezone" in first):
        meta = _meta(lines)
        if "local time zone" in meta or meta.get("source", "").upper().startswith("NSRDB"):
            return "psm3"
        return "sam"
    return "table"


def read_raw(path: Path, head_bytes: bytes, lines: list[str]) -> RawSeries:
    """Read ``path`` in the format its content shows (:func:`detect_format`); module docstring."""
    kind = detect_format(path, head_bytes, lines)
    if kind == "tmy3":
        return _tmy3(path)
    if kind == "tmy2":
        return _tmy2(path)
    if kind == "epw":
        return _epw(path)
    if kind == "psm3":
        return _psm3(path, lines)
    if kind == "sam":
        return _sam(path, lines)
    return _table(path)
