"""The plant's own clock: when its state was last informed by a record, and how its pointing uncertainty grows
with the time since.

A plant file is often worked on long after its records were taken (a study of last year's data, a test plant,
a backup restored): planning "tomorrow" by the wall clock, or quoting the pointing spread of the records' day for
an instant years later, misleads. Everything that asks "when is this plant now?" or "how uncertain is it at t?"
asks here:

* :func:`state_times` -- each calibrated heliostat's state time [s] (POSIX UTC): the drift state's time (an
  update's or ``calibrate --drift kalman``'s), else the latest record the calibration fitted (its stored
  residuals), else unknown (NaN);
* :func:`walk_process_noise` -- the random walk of the axis offsets q [rad^2/day] that the update filter uses
  (the drift model's, else the choice stored with the calibration);
* :func:`grown_covariance` -- the posterior covariance at an instant: q x days since the state time added to the
  axis offsets' variances (the walk's prediction step; nothing is subtracted before the state time);
* :func:`latest_record_time` and :func:`planned_day` -- the plant's latest record and the day a daily run plans
  (the day after it when the plant is more than :data:`BEHIND_DAYS` behind the wall clock).
"""
from __future__ import annotations

import datetime as _dt
import math

import torch

__all__ = ["BEHIND_DAYS", "state_times", "walk_process_noise", "grown_covariance", "latest_record_time",
           "planned_day", "OFFSET_NAMES"]

#: A plant whose latest record is more than this many days [d] older than the wall clock plans on its own clock.
BEHIND_DAYS = 3.0
#: The axis offsets the random walk moves (the drift model's default names).
OFFSET_NAMES = ("initial_angle_1", "initial_angle_2")
_DAY_S = 86400.0


def _tensor(value) -> torch.Tensor:
    return torch.as_tensor(value, dtype=torch.float64).reshape(-1)


def state_times(cal: dict, n: int) -> torch.Tensor:
    """Each of the ``n`` calibrated heliostats' state time [n] [s] (module docstring; NaN: unknown).

    ``cal`` is ``/learned/calibration`` as loaded (a dict of tensors)."""
    t = torch.full((n,), float("nan"), dtype=torch.float64)
    res = cal.get("residuals")
    if isinstance(res, dict) and "time" in res and "heliostat" in res:
        times, rows = _tensor(res["time"]), torch.as_tensor(res["heliostat"]).reshape(-1).long()
        ok = torch.isfinite(times) & (rows >= 0) & (rows < n)
        if bool(ok.any()):
            latest = torch.full((n,), -math.inf, dtype=torch.float64).scatter_reduce(
                0, rows[ok], times[ok], reduce="amax")
            t = torch.where(torch.isfinite(latest), latest, t)
    drift = cal.get("drift") or {}
    if "time" in drift:
        td = _tensor(drift["time"])
        if td.shape == (n,):
            t = torch.where(torch.isfinite(td), td, t)
    return t


def walk_process_noise(cal: dict) -> float | None:
    """q [rad^2/day] of the axis offsets' random walk stored with the calibration (None: none stored)."""
    drift = cal.get("drift") or {}
    if "process_noise_rad2_per_day" in drift:
        return float(_tensor(drift["process_noise_rad2_per_day"])[0])
    choice = cal.get("process_noise_choice")
    if isinstance(choice, dict) and "process_noise_mrad2_per_day" in choice:
        q = float(_tensor(choice["process_noise_mrad2_per_day"])[0])
        return 1e-6 * q if math.isfinite(q) and q >= 0 else None
    return None


def grown_covariance(cal: dict, names: list, when_s) -> tuple[torch.Tensor, torch.Tensor]:
    """The posterior covariance [H, P, P] at ``when_s`` [s] (POSIX; a float or [H]) and the days [H] it was grown
    by: q x max(when - state time, 0) / 1 day added to the variance of each axis offset present in ``names``.

    Heliostats without a known state time, or a calibration without a stored walk, are not grown (days 0)."""
    cov = torch.as_tensor(cal["posterior"]["covariance"], dtype=torch.float64).clone()
    h = cov.shape[0]
    drift = cal.get("drift") or {}
    offset = [n for n in (drift.get("names") or OFFSET_NAMES) if n in names]
    q = walk_process_noise(cal)
    when = torch.as_tensor(when_s, dtype=torch.float64).expand(h)
    days = ((when - state_times(cal, h)) / _DAY_S).clamp_min(0.0).nan_to_num(0.0)
    if q is None or not offset:
        return cov, torch.zeros(h, dtype=torch.float64)
    cols = torch.tensor([names.index(n) for n in offset], dtype=torch.long)
    cov[:, cols, cols] += (q * days)[:, None]
    return cov, days


def latest_record_time(learned: dict) -> float | None:
    """The plant's latest record time [s] (POSIX UTC) over what its ``/learned`` stores: the calibration's state
    times and every assimilated record (None: the file stores no record time)."""
    cal = (learned or {}).get("calibration") or {}
    times = []
    if cal.get("posterior") is not None and cal.get("heliostats") is not None:
        t = state_times(cal, len(cal["heliostats"]))
        times += t[torch.isfinite(t)].tolist()
    hist = (((learned or {}).get("assimilation") or {}).get("history") or {}).get("time")
    if hist is not None:
        th = _tensor(hist)
        times += th[torch.isfinite(th)].tolist()
    return max(times) if times else None


def planned_day(learned: dict, day: str | None, now: _dt.datetime | None = None) -> tuple[str, str]:
    """The day a daily run plans (UTC date, ISO) and why, in one sentence.

    ``day`` given: that day. Else the day after the wall clock's ``now`` (default: the current UTC time) --
    unless the plant's latest record (:func:`latest_record_time`) is more than :data:`BEHIND_DAYS` before
    ``now``: then the day after that record, since planning the wall clock's tomorrow for a plant whose records
    ended years ago plans for a state years of random walk away from anything measured."""
    if day is not None:
        return day, "given (--day)"
    now = now or _dt.datetime.now(_dt.timezone.utc)
    latest = latest_record_time(learned)
    if latest is not None and now.timestamp() - latest > BEHIND_DAYS * _DAY_S:
        last = _dt.datetime.fromtimestamp(latest, _dt.timezone.utc).date()
        planned = (last + _dt.timedelta(days=1)).isoformat()
        return planned, (f"the day after the plant's latest record ({last.isoformat()}); the wall clock is "
                         f"{now.date().isoformat()}: give --day to plan another day")
    return (now.date() + _dt.timedelta(days=1)).isoformat(), "tomorrow by the wall clock (UTC)"
