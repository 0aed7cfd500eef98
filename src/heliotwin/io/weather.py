"""Measured or typical-year direct normal irradiance (DNI) as a time series, beside pvlib's clear sky.

:func:`read_dni_series` reads a weather file as sites and tools deliver it -- **TMY3**, **TMY2**, **EPW** and
**NSRDB PSM3** through ``pvlib.iotools``, **SAM CSV** (both two-line metadata layouts, a ``DNI`` or ``Beam``
column), **PAINT's** ``metadata/calibration-weather.csv`` and **any table** with a time column (``time``,
``timestamp``, ``datetime``, ``date``; ISO, naive = UTC) and a ``dni`` column -- its format found from its content
(:mod:`heliotwin.io.weather_formats`, which states each format's time convention). It returns UTC instants placed
where the sun stood while each row's energy was collected (the middle of an hour-ending hour of local standard time,
the stamp of an instantaneous value), their DNI [W/m^2], the convention in words (``convention``) and the file's
site (``info``). A file that is not weather (an image, an HDF5 file, a CSV of something else) is a one-line error
naming it; no pandas or pvlib warning reaches the user.

The checks a report states: :func:`site_offset_km` and :func:`site_warning` (the file's site against the plant's,
a warning beyond :data:`SITE_WARNING_KM`), :func:`dni_share_below_horizon` (the share of the DNI energy at
instants with the sun below the horizon: at most a few tenths of a percent for a correct time convention, tens of
percent for a file read hours off) and :func:`weather_checks` (all three for a report).

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

* a **typical year** (a file whose (month, day, time) keys are unique but whose rows name several years, e.g.
  months from 1977 to 2005, as TMY3, TMY2, EPW and SolarPILOT's climate files are) is always moved into the year
  asked for, whatever its Year column says;
* else the rows in that year are used; a file with no row in it but all (or all but the rows a UTC shift moves
  across New Year) in one other year is a typical year and is moved into it (month, day and time kept;
  29 February dropped when the year has none), which the report states; a file spanning other years only is
  an error;
* a moved year is a cycle: the rows its UTC shift moves across New Year (the first or last hours of local time)
  wrap to the other end of the year asked for, where the sun stands as it did; a typical year moved into a leap
  year has no 29 February: that day has no DNI (no energy), which the report states;
* each row stands for its interval (the file's step, the median spacing; less where the next row comes
  sooner), so the energy is that of the hours the file covers: **annual** only when they are at least
  :data:`ANNUAL_FRACTION` of the year, else the report says which part of the year it is.

Errors are one line naming the file and the field (:class:`heliotwin.errors.InputFileError`).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import InputFileError
from ..sun import solar_position
from .weather_formats import FORMATS, read_raw

__all__ = ["DniSeries", "WeatherYear", "read_dni_series", "weather_for_year", "site_offset_km", "site_warning",
           "dni_share_below_horizon", "weather_checks", "MAX_DNI_W_M2", "KW_THRESHOLD", "ANNUAL_FRACTION",
           "SITE_WARNING_KM"]

_MAX_BYTES = 200 * 1024 * 1024
MAX_DNI_W_M2 = 1500.0  #: [W/m^2] above any DNI at the ground (the solar constant is 1361 W/m^2)
KW_THRESHOLD = 2.0  #: [W/m^2] a file whose largest DNI is at most this is in kW/m^2, not W/m^2
ANNUAL_FRACTION = 0.98  #: share of the year's hours a file must cover for its energy to be called annual
_SAME_DNI = 0.5  #: [W/m^2] rows repeating an instant within this are one row
SITE_WARNING_KM = 50.0  #: [km] a weather file's site farther than this from the plant's is warned about
_EARTH_RADIUS_KM = 6371.0088  #: [km] mean Earth radius (IUGG)


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
        ``"tmy3"``, ``"tmy2"``, ``"epw"``, ``"sam"``, ``"psm3"``, ``"paint"`` or ``"table"``.
    path : str
    dropped : int
        Rows without a usable DNI (``missing + negative``; rows without a time are among ``missing``).
    info : dict
        The file's site where it names one: ``site_name``, ``latitude_deg``, ``longitude_deg`` [deg],
        ``elevation_m`` [m], ``time_zone_hours`` [h east of UTC].
    missing, negative, repeated : int
        Rows with no DNI (or no time), with a negative DNI (both gaps), and repeats of an instant (merged).
    convention : str
        The file's time convention and how it became UTC instants, in words (for the report).
    typical : bool
        A typical year (months of different years): always moved into the year asked for.
    file_years : tuple of int
        The first and last year the file's rows name (empty when it names none).
    sun_shift_s : numpy.ndarray, [T], float64, optional
        Each instant's shift [s] from the middle of its interval (the sunrise and sunset hours of an hour-ending
        file are at the middle of their sunlit part); the interval each row stands for is found from the
        middles. None: no instant shifted.
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
    convention: str = ""
    typical: bool = False
    file_years: tuple = ()
    sun_shift_s: np.ndarray | None = None


def read_dni_series(path) -> DniSeries:
    """Read a DNI time series (module docstring; the formats in :mod:`heliotwin.io.weather_formats`) from
    ``path``, its format detected from its content.

    Raises
    ------
    InputFileError
        Missing, unreadable, binary or huge file; not a weather file (no time or DNI column); unparsable times;
        no usable row.
    """
    path = Path(path)
    try:
        if path.stat().st_size > _MAX_BYTES:
            raise InputFileError(path, f"larger than {_MAX_BYTES // 2**20} MiB; not a weather file")
        with open(path, "rb") as fh:
            head_bytes = fh.read(4096)
        text = head_bytes.decode("utf-8-sig", errors="replace")
        lines = [ln + "\n" for ln in text.splitlines()[:3]]
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({exc})") from None
    try:
        raw = read_raw(path, head_bytes, lines)
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise InputFileError(path, f"malformed CSV ({' '.join(str(exc).split())[:160]}); not a weather file in "
                             f"one of the formats read ({FORMATS})") from None
    except UnicodeDecodeError as exc:
        raise InputFileError(path, f"not a text file ({exc.reason}); not a weather file") from None
    times, values = raw.times, np.asarray(raw.dni, dtype=np.float64)
    no_time = np.asarray(pd.isna(times))
    missing = ~np.isfinite(values) | no_time
    negative = ~missing & (values < 0)
    ok = ~missing & ~negative
    if not ok.any():
        raise InputFileError(path, "no row with a time and a non-negative DNI", field="dni")
    order = np.argsort(times[ok].asi8, kind="stable")
    t = times[ok][order]
    v = values[ok][order]
    shift = None if raw.sun_shift_s is None else np.asarray(raw.sun_shift_s, dtype=np.float64)[ok][order]
    t, v, repeated, first = _merge_repeats(path, t, v)
    shift = None if shift is None or not shift.any() else shift[first]
    _check_units(path, v)
    step = float(pd.Series(t).diff().median().total_seconds()) / 3600.0 if len(t) > 1 else 1.0
    return DniSeries(t, v, step, raw.kind, str(path), dropped=int((~ok).sum()), info=raw.info,
                     missing=int(missing.sum()), negative=int(negative.sum()), repeated=repeated,
                     convention=raw.convention, typical=raw.typical, file_years=tuple(raw.file_years),
                     sun_shift_s=shift)


def _merge_repeats(path, t: pd.DatetimeIndex, v: np.ndarray):
    """Sorted times and DNIs with the repeats of an instant merged (same DNI) or refused (different DNI); and the
    index of each instant's first row."""
    same = np.zeros(len(t), dtype=bool)
    same[1:] = t.asi8[1:] == t.asi8[:-1]
    if not same.any():
        return t, v, 0, np.arange(len(t))
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
    return t[first], 0.5 * (lo + hi), int(same.sum()), first


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
        ``rows_outside_year``, ``moved_from_year`` (None when not moved or a typical year), ``typical_year``,
        ``file_years``, ``time_convention`` and the file's site (``latitude_deg``, ``longitude_deg``,
        ``elevation_m``, ``time_zone_hours``, ``site_name``) where it names one.
    convention : str
        The file's time convention (:attr:`DniSeries.convention`), for the report.
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
    convention: str = ""

    def dni_at(self, times) -> np.ndarray:
        """DNI [W/m^2] at UTC ``times`` (T'): the row whose interval holds the instant (the nearest row within
        half the step), NaN where the file has no row (a gap: no energy there)."""
        at = pd.Series(self.dni, index=self.times)
        idx = pd.DatetimeIndex(pd.to_datetime(times, utc=True))
        near = at.reindex(idx, method="nearest", tolerance=pd.Timedelta(hours=0.5 * self.step_hours))
        return near.to_numpy(dtype=np.float64)


def _year_hours(year: int) -> float:
    return (pd.Timestamp(year + 1, 1, 1) - pd.Timestamp(year, 1, 1)).total_seconds() / 3600.0


def _shift_years(times: pd.DatetimeIndex, years: int) -> pd.DatetimeIndex:
    if years == 0 or len(times) == 0:
        return times
    with warnings.catch_warnings():  # pandas' PerformanceWarning on a non-vectorised offset: not the user's concern
        warnings.simplefilter("ignore")
        return pd.DatetimeIndex(times + pd.DateOffset(years=years))


def _move_into(series: DniSeries, times, dni, year: int, shift: np.ndarray):
    """``times`` (UTC) moved into ``year`` in the file's local standard time (``time_zone_hours``, else UTC):
    month, day and time kept, 29 February dropped when ``year`` has none, the rows the UTC shift puts across New
    Year wrapped to the other end (a typical year is a cycle). Returns (times sorted, dni, shift [s],
    assumptions, the year moved from); ``shift`` (T) goes with the rows."""
    tz = pd.Timedelta(hours=float(series.info.get("time_zone_hours") or 0.0))
    local = pd.DatetimeIndex(times + tz)
    values_y, counts = np.unique(np.asarray(local.year), return_counts=True)
    main = int(values_y[np.argmax(counts)])
    feb29 = np.asarray((local.month == 2) & (local.day == 29))
    leap = pd.Timestamp(year, 1, 1).is_leap_year
    keep = ~feb29 | leap
    shifted = _shift_years(pd.DatetimeIndex(local[keep]), year - main) - tz
    dni, shift = dni[keep], shift[keep]
    before, after = np.asarray(shifted.year < year), np.asarray(shifted.year > year)
    parts = [shifted[~before & ~after], _shift_years(shifted[before], 1), _shift_years(shifted[after], -1)]
    values = np.concatenate([dni[~before & ~after], dni[before], dni[after]])
    shift = np.concatenate([shift[~before & ~after], shift[before], shift[after]])
    moved = parts[0].append(parts[1]).append(parts[2])
    order = np.argsort(moved.asi8, kind="stable")
    moved, values, shift = moved[order], values[order], shift[order]
    span = tuple(series.file_years)
    what = (f"a typical year (its rows name {span[0]} to {span[-1]}: months of different years)"
            if series.typical and len(span) == 2 and span[0] != span[-1] else
            "a typical year" if series.typical else f"the file holds {main}, not {year}: read as a typical year")
    text = [f"{what}, moved into {year} (month, day and local time kept, the sun of {year})"
            + (f"; {int((~keep).sum())} rows of 29 February dropped" if (~keep).any() else "")]
    wrapped = int(before.sum() + after.sum())
    if wrapped:
        text.append(f"{wrapped} row{'s' if wrapped > 1 else ''} the UTC shift moved across New Year wrapped to the "
                    f"other end of {year} (a typical year is a cycle)")
    moved_local = moved + tz
    days = set(zip(np.asarray(moved_local.month), np.asarray(moved_local.day)))
    if leap and (2, 29) not in days and (2, 28) in days and (3, 1) in days:
        text.append(f"{year} is a leap year and the file has no 29 February: that day has no DNI (no energy)")
    return moved, values, shift, text, main


def weather_for_year(series: DniSeries, year: int) -> WeatherYear:
    """The rows of ``series`` in ``year``, or the file moved into it when it is a typical year or another year's
    (module docstring); the interval each row stands for, the coverage and the assumptions made.

    Raises
    ------
    InputFileError
        No row in ``year`` and the rows span several other years.
    """
    year = int(year)
    times, dni = series.times, np.asarray(series.dni, dtype=np.float64)
    shift = np.zeros(len(times)) if series.sun_shift_s is None else np.asarray(series.sun_shift_s, dtype=np.float64)
    assumptions, moved, outside = [], None, 0
    years = np.asarray(times.year)
    if series.typical or not (years == year).any():
        values, counts = np.unique(years, return_counts=True)
        main = int(values[np.argmax(counts)])
        # a typical year: one year's rows (and a few a UTC shift moved across New Year)
        if not series.typical and (counts.max() < 0.95 * len(years) or (np.abs(values - main) > 1).any()):
            raise InputFileError(series.path, f"no row in {year} (the rows span {int(values.min())} to "
                                 f"{int(values.max())}); give that year's weather or a typical year", field="time")
        times, dni, shift, text, main = _move_into(series, times, dni, year, shift)
        moved = None if series.typical else main
        assumptions.extend(text)
    inside = np.asarray(times.year) == year
    outside = int((~inside).sum())
    if outside:
        assumptions.append(f"{outside} rows outside {year} not used")
    times, dni, shift = times[inside], dni[inside], shift[inside]
    if len(times) == 0:
        raise InputFileError(series.path, f"no row in {year}", field="time")
    step = float(series.step_hours)
    middles = times - pd.to_timedelta(shift, unit="s")  # a sunrise hour's instant moved, not its interval
    gaps = np.asarray((middles[1:] - middles[:-1]).total_seconds(), dtype=np.float64) / 3600.0
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
              "moved_from_year": moved, "typical_year": bool(series.typical),
              "file_years": list(series.file_years), "time_convention": series.convention, **series.info}
    return WeatherYear(year, times, dni, hours, step, annual, coverage, assumptions, source, series.convention)


def site_offset_km(series, latitude_deg, longitude_deg=None) -> float | None:
    """Great-circle distance [km] from the weather file's site to the plant's (``latitude_deg``,
    ``longitude_deg`` [deg], or a site object with ``latitude_deg`` / ``longitude_deg`` as the one argument);
    None when the file names no site (PAINT's CSV, a plain table).

    ``series``: a :class:`DniSeries` or :class:`WeatherYear` (its ``source`` holds the site)."""
    if longitude_deg is None and hasattr(latitude_deg, "latitude_deg"):
        latitude_deg, longitude_deg = latitude_deg.latitude_deg, latitude_deg.longitude_deg
    info = getattr(series, "info", None)
    info = info if info is not None else getattr(series, "source", {})
    lat, lon = info.get("latitude_deg"), info.get("longitude_deg")
    if lat is None or lon is None:
        return None
    p1, p2 = math.radians(float(lat)), math.radians(float(latitude_deg))
    dp, dl = p2 - p1, math.radians(float(longitude_deg) - float(lon))
    h = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2.0 * _EARTH_RADIUS_KM * math.asin(min(1.0, math.sqrt(h)))


def _where(lat: float, lon: float) -> str:
    return f"{abs(lat):.3f} {'N' if lat >= 0 else 'S'}, {abs(lon):.3f} {'E' if lon >= 0 else 'W'}"


def site_warning(series, latitude_deg: float, longitude_deg: float, limit_km: float = SITE_WARNING_KM) -> str | None:
    """One line when the weather file's site is more than ``limit_km`` [km] from the plant's (its sun and its DNI
    are another place's), naming the file and both sites; None when within it or when the file names no site."""
    km = site_offset_km(series, latitude_deg, longitude_deg)
    if km is None or km <= limit_km:
        return None
    info = getattr(series, "info", None)
    info = info if info is not None else getattr(series, "source", {})
    path = getattr(series, "path", None) or info.get("file", "the weather file")
    name = f" ({info['site_name']})" if info.get("site_name") else ""
    return (f"{path}: the weather file's site {_where(info['latitude_deg'], info['longitude_deg'])}{name} is "
            f"{km:.0f} km from the plant at {_where(float(latitude_deg), float(longitude_deg))} (more than "
            f"{limit_km:g} km): its DNI is another place's weather")


def _share_below(wy: WeatherYear, elevation) -> float:
    energy = np.asarray(wy.dni, dtype=np.float64) * np.asarray(wy.hours, dtype=np.float64)
    total = float(energy.sum())
    below = ~np.asarray(elevation > 0)
    return float(energy[below].sum()) / total if total > 0 else 0.0


def dni_share_below_horizon(weather_year: WeatherYear, latitude, longitude, altitude=0.0) -> float:
    """Share of the file's DNI energy (DNI x hours) at instants with the sun below the horizon (apparent
    elevation <= 0, :func:`heliotwin.sun.solar_position`) at the site ``latitude``, ``longitude`` [deg],
    ``altitude`` [m]: at most a few tenths of a percent when the time convention was read right (the sunrise and
    sunset hours' little DNI), tens of percent when the file is read hours off (UTC taken for local time)."""
    _, el = solar_position(weather_year.times, float(latitude), float(longitude), float(altitude))
    return _share_below(weather_year, el.numpy())


def weather_checks(weather_year: WeatherYear, series, site, elevation=None) -> dict:
    """What a report states about a weather file at the plant's ``site`` (``latitude_deg``, ``longitude_deg``,
    ``altitude_m``): ``time_convention``, ``weather_site`` (the file's, or None), ``site_offset_km`` (or None),
    ``dni_share_below_horizon`` and ``warnings`` (one-line texts: the site beyond :data:`SITE_WARNING_KM`).
    ``elevation``: the sun's elevation [rad] at ``weather_year.times`` when already computed (T)."""
    if elevation is None:
        _, el = solar_position(weather_year.times, site.latitude_deg, site.longitude_deg, site.altitude_m)
        elevation = el.numpy()
    share = _share_below(weather_year, np.asarray(elevation))
    warning = site_warning(series, site.latitude_deg, site.longitude_deg)
    keys = ("site_name", "latitude_deg", "longitude_deg", "elevation_m", "time_zone_hours")
    info = {k: series.info[k] for k in keys if k in series.info}
    return {"time_convention": series.convention, "weather_site": info or None,
            "site_offset_km": site_offset_km(series, site.latitude_deg, site.longitude_deg),
            "dni_share_below_horizon": share, "warnings": [warning] if warning else []}
