"""How a time and a sun position are written for people: on every figure, in the report and in the command line's
headlines, one format each.

* :func:`utc_text` -- a time as ISO 8601 UTC to the minute, ``2023-06-21T12:00Z`` (:data:`UTC_PATTERN`);
* :func:`sun_text` -- a sun position in PAINT's convention, the convention named: ``sun azimuth 12.3° (PAINT:
  0 = south, +90 = east), elevation 38.1°``. PAINT's is the convention of the command-line flags
  (``--sun-azimuth``) and of every JSON field ``sun_azimuth_deg``; SolarPILOT's (0 = north, clockwise) is never
  printed, so a number read off a figure can be typed back into a flag;

Machine-readable outputs (JSON, CSV, HDF5) keep their own full-precision ISO times.
"""
from __future__ import annotations

import datetime as _dt
import math

__all__ = ["UTC_PATTERN", "AZIMUTH_CONVENTION", "AZIMUTH_LABEL", "utc_text", "utc_or_label", "sun_text"]

#: The one time format of figures, the report and headlines (a regular expression).
UTC_PATTERN = r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}Z"
#: PAINT's sun azimuth convention, as printed beside every sun azimuth.
AZIMUTH_CONVENTION = "PAINT: 0 = south, +90 = east"
#: An axis label of a sun azimuth.
AZIMUTH_LABEL = f"sun azimuth [deg] ({AZIMUTH_CONVENTION})"


def utc_text(when) -> str | None:
    """``when`` as ``2023-06-21T12:00Z`` (seconds dropped, not rounded: the minute it falls in).

    ``when`` is POSIX seconds (float), a ``datetime`` / pandas ``Timestamp`` (naive = UTC) or ISO 8601 text
    (``Z``, an offset, or naive = UTC). None, NaN and empty text give None; unreadable text is a ValueError."""
    if when is None:
        return None
    if isinstance(when, str):
        text = when.strip()
        if not text:
            return None
        when = _dt.datetime.fromisoformat(text[:-1] + "+00:00" if text.endswith(("Z", "z")) else text)
    if isinstance(when, _dt.datetime):  # a pandas Timestamp is one
        t = when.replace(tzinfo=_dt.timezone.utc) if when.tzinfo is None else when.astimezone(_dt.timezone.utc)
    else:
        seconds = float(when)
        if not math.isfinite(seconds):
            return None
        t = _dt.datetime.fromtimestamp(seconds, _dt.timezone.utc)
    return t.strftime("%Y-%m-%dT%H:%MZ")


def utc_or_label(label) -> str:
    """:func:`utc_text` of a label that is a time; any other label (an instant named by its sun angles, a
    free-text name) as it is; ``"?"`` for none."""
    try:
        return utc_text(label) or "?"
    except (ValueError, TypeError):
        return str(label)


def sun_text(azimuth_deg: float, elevation_deg: float) -> str:
    """``sun azimuth 12.3° (PAINT: 0 = south, +90 = east), elevation 38.1°`` (PAINT's angles [deg])."""
    return f"sun azimuth {azimuth_deg:.1f}° ({AZIMUTH_CONVENTION}), elevation {elevation_deg:.1f}°"
