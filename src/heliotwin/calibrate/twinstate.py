"""The state of a calibrated twin as the scenario stores it, and what an update reads and writes there.

A rigid-body calibration (``calibrate --method lm``) stores under ``/learned/calibration`` its deviations,
their Laplace posterior and, with a drift model, the random-walk offset; this module turns that into the
:class:`~heliotwin.calibrate.assimilate.FilterState` an update starts from (:func:`filter_state`), and an
update's result back into ``/learned`` (:func:`updated_learned`). What is learned once per calibration and
reused by every update is chosen here on the records the calibration saw and stored with it:

* the random walk's process noise (:func:`process_noise_choice`: each heliostat's latest quarter of its
  records predicted by the walk run through its earlier ones), under ``/learned/calibration/
  process_noise_choice``;
* the step-alarm threshold (:func:`alarm_threshold_choice`: the target false-alarm rate and the normalised
  leave-one-out residuals of those records, :func:`heliotwin.calibrate.assimilate.alarm_threshold`), under
  ``/learned/calibration/alarm_threshold``.

``/learned/assimilation`` keeps every update's per-record history (:func:`state_history`), the step tests'
evidence window, the threshold in force, the **open alarms** (``open_alarms``: one row per heliostat whose alarm
no later record has settled yet, with the pre-alarm state and the settling evidence so far; :func:`open_alarms`)
and the **closed** ones (``closed_alarms``: confirmed, cleared or superseded, with the record that closed them).
Heliostats are indices into ``/learned/assimilation/heliostats`` in all three tables.
"""
from __future__ import annotations

import math
import os
from dataclasses import fields, replace

import numpy as np
import torch

from ..errors import HeliotwinError, InputFileError
from ..field.plant import Kinematics
from ..io.records import RecordTable
from ..io.scenario import Scenario, load_scenario
from ..timefmt import utc_text
from .assimilate import (
    ALARM_OUTCOMES,
    CONFIRM_RECORDS,
    FALSE_ALARMS_PER_HELIOSTAT_YEAR,
    WINDOW,
    FilterState,
    alarm_threshold,
    choose_process_noise,
    false_alarm_rate_for,
    leave_one_out_d2,
    no_open_alarms,
)
from .clock import latest_record_time
from .drift import BASES, DRIFT_NAMES, smooth, with_offset
from .inputs import FIT_FOCAL_SPOT, NOISE, fit_spots
from .params import STONE8, check_names

__all__ = ["ASSIMILATION_KEY", "HISTORY_VERSION", "DEFAULT_PROCESS_NOISE", "CHOICE_KEY", "THRESHOLD_KEY",
           "calibration_entry", "nominal_kinematics", "current_assimilation", "calibration_count", "seen_record_ids",
           "seen_record_owners",
           "stored_tensor", "filter_scale", "filter_state", "fit_posterior", "on_axis", "process_noise_choice",
           "with_process_noise_choice", "process_noise_source", "alarm_threshold_choice", "with_alarm_threshold",
           "threshold_in_force", "split_new", "merged_history", "updated_learned", "state_history", "open_alarms",
           "closed_alarms", "plant_clock", "OPEN_FIELDS", "CLOSED_FIELDS"]
#: Key of the calibration under ``Scenario.learned`` (:mod:`heliotwin.calibrate.scenario` writes it; defined here,
#: with what reads it back, so that an update does not import the calibration methods to find it).
KEY = "calibration"
#: Key of the assimilation state under ``Scenario.learned``.
ASSIMILATION_KEY = "assimilation"
#: Layout version of ``/learned/assimilation``: 2 adds ``open_alarms`` and ``closed_alarms`` (version 1 reads as
#: no open alarm and none closed).
HISTORY_VERSION = 2
#: q [mrad^2/day] of the drifting axis offsets when the calibration has no drift model and no choice could be
#: made on its records (:func:`process_noise_choice`): the random-walk setting chosen on the real PAINT
#: archive's online protocol by leave-heliostats-out CV (benchmarks/bench_carryover.py, kq0.03).
DEFAULT_PROCESS_NOISE = 0.03
#: Key under ``/learned/calibration`` of the q chosen on the calibration's records, with how it was chosen.
CHOICE_KEY = "process_noise_choice"
#: Key under ``/learned/calibration`` of the step-alarm threshold chosen on the calibration's records.
THRESHOLD_KEY = "alarm_threshold"
_HISTORY_FIELDS = ("heliostat", "record_id", "time", "mean", "variance", "innovation", "d2", "statistic", "window",
                   "alarm", "predicted_error", "update")

#: Stored types of the history's fields that are narrower than computed: float32 halves the state's columns
#: (~1e-7 relative), and the small counters fit int32 (:func:`state_history` hands them back as int64); the
#: rest keeps its type. Large arrays are also compressed on writing (:data:`heliotwin.io.scenario.COMPRESS_BYTES`).
_HISTORY_STORED = {"mean": torch.float32, "variance": torch.float32, "innovation": torch.float32,
                   "heliostat": torch.int32, "window": torch.int32, "update": torch.int32}


def calibration_count(scenario: Scenario) -> int:
    """How many ``calibrate`` steps the scenario's provenance holds (a new one restarts the update's state)."""
    return sum(1 for p in scenario.provenance or [] if isinstance(p, dict) and p.get("step") == "calibrate")


def current_assimilation(scenario: Scenario) -> dict | None:
    """``/learned/assimilation`` when it belongs to the scenario's current calibration (None after a
    recalibration: its threshold and step-test evidence were about the replaced one; the history stays)."""
    st = scenario.learned.get(ASSIMILATION_KEY)
    if not isinstance(st, dict):
        return None
    stamp = int(torch.as_tensor(st.get("calibrations", -1)).reshape(-1)[0])
    return st if stamp == calibration_count(scenario) else None


def seen_record_owners(scenario: Scenario) -> dict:
    """Record id -> the heliostat a provenance step lists it under (``calibrate``'s training records, updates'
    records)."""
    owners: dict = {}
    for step in scenario.provenance or []:
        recs = step.get("records") if isinstance(step, dict) else None
        if isinstance(recs, dict):
            for hid, ids in recs.items():
                if isinstance(ids, list):
                    owners.update((int(i), str(hid)) for i in ids if isinstance(i, (int, float)))
    return owners


def seen_record_ids(scenario: Scenario) -> set:
    """Record ids some provenance step lists as seen (:func:`seen_record_owners`' keys)."""
    return set(seen_record_owners(scenario))


def stored_tensor(cal: dict, where: str, path, *keys) -> torch.Tensor:
    """``cal[keys...]`` as a float64 tensor (shape as stored); a missing or malformed entry is a one-line
    :class:`~heliotwin.errors.InputFileError` naming ``path`` and ``where/keys``."""
    obj = cal
    try:
        for k in keys:
            obj = obj[k]
        return torch.as_tensor(obj, dtype=torch.float64)
    except (KeyError, TypeError, ValueError, RuntimeError):
        raise InputFileError(path, "missing or malformed (a rigid-body calibration with its posterior, "
                                   "calibrate --method lm)", field=f"{where}/{'/'.join(keys)}") from None


def calibration_entry(scenario: Scenario) -> tuple[dict, list, tuple]:
    """The ``/learned/calibration`` entry an update starts from, its heliostats and parameter names."""
    where = f"/learned/{KEY}"
    cal = scenario.learned.get(KEY)
    if not isinstance(cal, dict) or not cal.get("heliostats"):
        raise InputFileError(scenario.path, "no calibration to update (run heliotwin calibrate -o first)", field=where)
    if cal.get("networks") or not cal.get("posterior"):
        raise InputFileError(scenario.path, f"method {cal.get('method')!r} has no rigid-body posterior to update "
                                            "(calibrate --method lm)", field=f"{where}/posterior")
    ids = cal["heliostats"]
    if not isinstance(ids, list) or not all(isinstance(i, str) for i in ids):
        raise InputFileError(scenario.path, "expected a list of heliostat ids", field=f"{where}/heliostats")
    try:
        names = check_names(list(cal["parameter_names"]))
    except (KeyError, TypeError, HeliotwinError):
        raise InputFileError(scenario.path, "missing or unknown parameter names",
                             field=f"{where}/parameter_names") from None
    return cal, ids, names


def nominal_kinematics(cal: dict, path, n: int) -> Kinematics:
    """The nominal kinematics the calibration's deviations are relative to (``/learned/calibration/nominal``,
    ``n`` heliostats [1]); one-line error when missing, malformed or of another size."""
    try:
        kin = Kinematics(**{f.name: torch.as_tensor(cal["nominal"][f.name]) for f in fields(Kinematics)})
    except (KeyError, TypeError, ValueError, RuntimeError):
        raise InputFileError(path, "missing or malformed nominal kinematics", field=f"/learned/{KEY}/nominal") from None
    if kin.num_heliostats != n:
        raise InputFileError(path, f"expected {n} heliostats", field=f"/learned/{KEY}/nominal/position")
    return kin


def _state(cal: dict, names: tuple, path, n: int, q_given: float | None, seen_time: torch.Tensor, *,
           from_calibration: bool = False) -> FilterState:
    """The filter state of the calibration (module docstring); ``seen_time`` [H]: latest seen record time.
    ``from_calibration``: the stored posterior is still calibrate's (no update since), whose covariance is in
    the static residuals' noise: scaled to the walk's record noise the filter runs on (:func:`fit_posterior`)."""
    where = f"/learned/{KEY}"
    p = len(names)
    mean = stored_tensor(cal, where, path, "deviations")
    cov = stored_tensor(cal, where, path, "posterior", "covariance").clone()
    noise = stored_tensor(cal, where, path, "posterior", "noise_rad")
    if mean.shape != (n, p) or cov.shape != (n, p, p) or noise.shape != (n,):
        raise InputFileError(path, f"deviations / posterior must be [{n}, {p}] / [{n}, {p}, {p}] / [{n}]",
                             field=f"{where}/posterior")
    drift = cal.get("drift") or {}
    time = seen_time.clone()
    drift_names = tuple(drift.get("names") or DRIFT_NAMES)
    if any(d not in names for d in drift_names):
        raise InputFileError(path, f"drift names {list(drift_names)} not among the parameters", field=f"{where}/drift")
    cols = tuple(names.index(d) for d in drift_names)
    q = 1e-6 * DEFAULT_PROCESS_NOISE
    chosen = _stored_choice(cal, path)
    if chosen is not None:
        q = 1e-6 * chosen
    if drift:
        scale = filter_scale(cal, path)  # the walk's learned record noise (lm.laplace under the walk)
        p_l = scale * stored_tensor(cal, where, path, "drift", "covariance")
        t_l = stored_tensor(cal, where, path, "drift", "time")
        q = scale * float(stored_tensor(cal, where, path, "drift", "process_noise_rad2_per_day").reshape(-1)[0])
        if p_l.shape != (n, len(cols), len(cols)) or t_l.shape != (n,):
            raise InputFileError(path, "malformed drift state", field=f"{where}/drift")
        if "record_noise_rad" in drift:
            fit_noise, noise = noise, stored_tensor(cal, where, path, "drift", "record_noise_rad")
            if noise.shape != (n,):
                raise InputFileError(path, f"record noise must be [{n}]", field=f"{where}/drift/record_noise_rad")
            if from_calibration:
                cov = _in_record_units(cov, noise, fit_noise)
        idx = torch.tensor(cols)
        cov[:, idx[:, None], idx[None, :]] += p_l  # the offset's own uncertainty on top of the static posterior
        time = torch.where(torch.isfinite(t_l), t_l, time)
    if q_given is not None:
        q = 1e-6 * q_given
    return FilterState(mean=mean, covariance=cov, time=time, noise=noise, process_noise=q, drift_columns=cols,
                       names=names)


def filter_scale(cal: dict, path) -> float:
    """The factor [1] from a drift calibration's stored offset covariance and q (in the 1 mrad record noise its
    fit assumed, what the predictive interval uses) to an update's filter (the walk's record noise learned from
    the records, ``/learned/calibration/drift/filter_scale``); 1 for plants written before it was learned."""
    drift = cal.get("drift") or {}
    if "filter_scale" not in drift:
        return 1.0
    return float(stored_tensor(cal, f"/learned/{KEY}", path, "drift", "filter_scale").reshape(-1)[0])


def _stored_choice(cal: dict, path) -> float | None:
    """q [mrad^2/day] of ``/learned/calibration/process_noise_choice`` (None: none stored or none made)."""
    choice = cal.get(CHOICE_KEY)
    if not isinstance(choice, dict):
        return None
    try:
        q = float(torch.as_tensor(choice["process_noise_mrad2_per_day"], dtype=torch.float64).reshape(-1)[0])
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError):
        raise InputFileError(path, "malformed process-noise choice",
                             field=f"/learned/{KEY}/{CHOICE_KEY}/process_noise_mrad2_per_day") from None
    if not (math.isfinite(q) and q >= 0):
        raise InputFileError(path, f"expected a number >= 0, got {q}",
                             field=f"/learned/{KEY}/{CHOICE_KEY}/process_noise_mrad2_per_day")
    return q


def _stored_choice_dict(choice: dict) -> dict:
    """The choice as stored (tensors for the numbers, text for how it was made)."""
    return {"process_noise_mrad2_per_day": torch.tensor([choice["process_noise_mrad2_per_day"]], dtype=torch.float64),
            "grid_mrad2_per_day": torch.tensor(choice["grid_mrad2_per_day"], dtype=torch.float64),
            "validation_error_mrad": torch.tensor(choice["validation_error_mrad"], dtype=torch.float64),
            "validation_records": torch.tensor([choice["validation_records"]]),
            "validation_heliostats": torch.tensor([choice["validation_heliostats"]]),
            "share": torch.tensor([choice["share"]], dtype=torch.float64), "method": choice["method"]}


def process_noise_choice(scenario: Scenario, records: RecordTable) -> dict | None:
    """The random walk's q [mrad^2/day] chosen on the records ``scenario``'s calibration saw, for a calibration
    without a drift model (:func:`heliotwin.calibrate.assimilate.choose_process_noise`: each heliostat's
    latest quarter of those records predicted by the walk run through its earlier ones).

    Parameters
    ----------
    scenario : Scenario
        With a rigid-body calibration (``calibrate --method lm``).
    records : RecordTable
        Records of the plant (any heliostat ids); only those the calibration lists as seen are used.

    Returns
    -------
    dict or None
        ``process_noise_mrad2_per_day`` (None: too few seen records), the grid, its validation errors [mrad]
        and counts, and ``method`` (how it was chosen); None when the calibration has a drift model (its q
        stands) or is not a rigid-body one.
    """
    cal = scenario.learned.get(KEY)
    if not isinstance(cal, dict) or cal.get("drift") or cal.get("networks") or not cal.get("posterior"):
        return None
    cal, ids, names = calibration_entry(scenario)
    table = fit_spots(on_axis(records, ids), FIT_FOCAL_SPOT)
    seen = seen_record_ids(scenario)
    rows = torch.as_tensor(np.isin(table.record_id.numpy(), np.array(sorted(seen), dtype=np.int64)))
    table = table.subset(rows)
    nominal = nominal_kinematics(cal, scenario.path, len(ids))
    state = _state(cal, names, scenario.path, len(ids), None, torch.full((len(ids),), float("nan")))
    choice = choose_process_noise(nominal, table, state)
    choice["method"] = ("chronological validation on the calibration's records: each heliostat's latest "
                        f"{choice['share']:.0%} predicted by the walk run through its earlier ones; median over "
                        "heliostats of the mean error; ties to the larger q")
    return choice


def with_process_noise_choice(scenario: Scenario, records: RecordTable) -> tuple[Scenario, dict | None]:
    """``scenario`` with :func:`process_noise_choice` stored under ``/learned/calibration`` (where the update
    reads it), and the choice; unchanged (and None) when there is nothing to choose or too few records."""
    made = process_noise_choice(scenario, records)
    if made is None or made["process_noise_mrad2_per_day"] is None:
        return scenario, None
    cal = {**scenario.learned[KEY], CHOICE_KEY: _stored_choice_dict(made)}
    return replace(scenario, learned={**scenario.learned, KEY: cal}), made


def filter_state(scenario: Scenario, records: RecordTable, process_noise: float | None = None, *,
                 seen: set | None = None) -> FilterState:
    """The filter state an update of ``scenario`` starts from (:class:`~heliotwin.calibrate.assimilate.FilterState`,
    heliostat axis = the calibrated heliostats): the deviations, their posterior covariance plus the random-walk
    offset's, the state's time (the drift state's, else the latest seen record's in ``records``), the residual
    noise and q.

    Parameters
    ----------
    records : RecordTable
        Records on the calibrated heliostats' axis (seen ones give the time when the calibration has none).
    process_noise : float, optional
        q [mrad^2/day] replacing the stored one.
    seen : set, optional
        :func:`seen_record_ids` of ``scenario``, when the caller has it already.
    """
    cal, ids, names = calibration_entry(scenario)
    seen = seen_record_ids(scenario) if seen is None else seen
    seen_rows = torch.as_tensor(np.isin(records.record_id.numpy(), np.array(sorted(seen), dtype=np.int64)))
    t = _with_time(records)
    ok = seen_rows & torch.isfinite(t)
    seen_time = torch.full((len(ids),), float("nan"), dtype=torch.float64)
    seen_time = seen_time.scatter_reduce(0, records.heliostat_index[ok], t[ok], reduce="amax", include_self=False)
    state = _state(cal, names, scenario.path, len(ids), process_noise, seen_time,
                   from_calibration=current_assimilation(scenario) is None)
    window = (current_assimilation(scenario) or {}).get("window") or {}
    if window.get("heliostats") == list(ids):  # the same calibration's heliostats: its evidence carries on
        try:
            g = torch.as_tensor(window["g"], dtype=torch.float64)
            f = torch.as_tensor(window["f"], dtype=torch.float64)
        except (KeyError, TypeError, ValueError, RuntimeError):
            raise InputFileError(scenario.path, "malformed step-test window",
                                 field=f"/learned/{ASSIMILATION_KEY}/window") from None
        state = replace(state, window_g=g, window_f=f)
    return replace(state, alarms=_stored_open_alarms(current_assimilation(scenario), ids, state))


#: Fields of ``/learned/assimilation/open_alarms`` (rows [A]; ``mean`` [A, P], ``covariance`` [A, P, P], ``g``
#: [A, B], ``f`` [A, B, B]) and of ``closed_alarms`` (rows [C]; :func:`heliotwin.calibrate.assimilate.assimilate`'s
#: ``closed`` plus the ``update`` that closed it).
OPEN_FIELDS = ("heliostat", "record_id", "time", "statistic", "window", "records", "mean", "covariance", "g", "f")
CLOSED_FIELDS = ("heliostat", "record_id", "opened", "statistic", "window", "closed_by", "closed_at", "outcome",
                 "evidence", "records", "update")


def _stored_open_alarms(assimilation: dict | None, ids: list, state: FilterState) -> dict:
    """The open-alarm slots [H] over the calibration's heliostats ``ids`` from ``open_alarms`` (none: a plant
    written before alarms were kept, or after a recalibration)."""
    h, p = state.mean.shape
    slots = no_open_alarms(h, p, len(state.drift_columns))
    table = (assimilation or {}).get("open_alarms")
    if not isinstance(table, dict) or not len(torch.as_tensor(table.get("heliostat", []))):
        return slots
    names = list(assimilation["heliostats"])
    pos = {hid: i for i, hid in enumerate(ids)}
    rows = torch.tensor([pos.get(names[int(k)], -1) for k in torch.as_tensor(table["heliostat"]).tolist()])
    ok = rows >= 0  # a heliostat the calibration no longer has: its alarm went with it
    for key in OPEN_FIELDS[1:]:
        slots[key][rows[ok]] = torch.as_tensor(table[key])[ok].to(slots[key].dtype)
    slots["open"][rows[ok]] = True
    return slots


def _open_table(alarms: dict | None, remap: torch.Tensor) -> dict:
    """``open_alarms`` as stored: one row per open slot (heliostat: index into the assimilation's heliostats)."""
    if alarms is None:
        return {}
    is_open = torch.as_tensor(alarms["open"]).cpu()
    out = {"heliostat": remap[is_open.nonzero().flatten()]}
    for key in OPEN_FIELDS[1:]:
        out[key] = torch.as_tensor(alarms[key]).detach().cpu()[is_open]
    return out


def open_alarms(scenario: Scenario, now: float | None = None) -> list[dict]:
    """The plant's open step alarms (``/learned/assimilation/open_alarms`` of the current calibration), oldest
    first: ``heliostat``, ``record_id``, ``opened`` (POSIX s) and ``opened_utc``, ``statistic``, ``window``,
    ``records`` (of :data:`~heliotwin.calibrate.assimilate.CONFIRM_RECORDS` that settle it) and, given ``now``
    (POSIX s), ``age_days``. Empty for a plant written before alarms were kept."""
    st = current_assimilation(scenario)
    table = (st or {}).get("open_alarms")
    if not isinstance(table, dict):
        return []
    names = list(st["heliostats"])
    rows = []
    for i, k in enumerate(torch.as_tensor(table["heliostat"]).tolist()):
        t = float(torch.as_tensor(table["time"])[i])
        row = {"heliostat": names[int(k)], "record_id": int(torch.as_tensor(table["record_id"])[i]), "opened": t,
               "opened_utc": utc_text(t), "statistic": float(torch.as_tensor(table["statistic"])[i]),
               "window": int(torch.as_tensor(table["window"])[i]),
               "records": int(torch.as_tensor(table["records"])[i]), "records_to_settle": CONFIRM_RECORDS}
        if now is not None and math.isfinite(t):
            row["age_days"] = (float(now) - t) / 86400.0
        rows.append(row)
    return sorted(rows, key=lambda r: (r["opened"], r["heliostat"]))


def closed_alarms(scenario: Scenario, update: int | None = None) -> list[dict]:
    """Closed step alarms (``/learned/assimilation/closed_alarms``), of one ``update`` (its number) or all: the
    alarm's ``heliostat``, ``record_id``, ``opened``, ``statistic``; ``closed_by`` (record id), ``closed_at``,
    ``outcome`` (text, :data:`~heliotwin.calibrate.assimilate.ALARM_OUTCOMES`), ``evidence``, ``records``."""
    st = scenario.learned.get(ASSIMILATION_KEY)
    table = (st or {}).get("closed_alarms") if isinstance(st, dict) else None
    if not isinstance(table, dict):
        return []
    names = list(st["heliostats"])
    col = {k: torch.as_tensor(table[k]).tolist() for k in CLOSED_FIELDS}
    out = []
    for i in range(len(col["heliostat"])):
        if update is not None and int(col["update"][i]) != int(update):
            continue
        code, n = int(col["outcome"][i]), int(col["records"][i])
        out.append({"heliostat": names[int(col["heliostat"][i])], "record_id": int(col["record_id"][i]),
                    "opened": col["opened"][i], "opened_utc": utc_text(col["opened"][i]),
                    "statistic": col["statistic"][i], "closed_by": int(col["closed_by"][i]),
                    "closed_at": col["closed_at"][i], "closed_utc": utc_text(col["closed_at"][i]),
                    "outcome": ALARM_OUTCOMES.get(code, "?").format(n=n), "confirmed": code == 1,
                    "evidence": col["evidence"][i], "records": n, "update": int(col["update"][i])})
    return out


def plant_clock(scenario: Scenario) -> float | None:
    """The plant's own clock: its latest record time [POSIX s] (:func:`heliotwin.calibrate.clock.latest_record_time`:
    the calibration's state and fitted records, every assimilated record), None when the plant holds none."""
    return latest_record_time(scenario.learned)


def on_axis(table: RecordTable, ids: list) -> RecordTable:
    """The records of ``ids`` re-indexed onto that list (heliostats without records are fine)."""
    pos = {h: i for i, h in enumerate(ids)}
    remap = torch.tensor([pos.get(h, -1) for h in table.heliostat_ids], dtype=torch.long)
    new = remap[table.heliostat_index] if len(table) else table.heliostat_index
    out = table.subset(new >= 0)
    out.heliostat_index = new[new >= 0]
    out.heliostat_ids = list(ids)
    return out


def records_per_heliostat_year(table: RecordTable) -> float:
    """A plant's calibration record rate [1/year]: the median over heliostats (those with >= 2 timed records
    spanning >= 30 days) of their records per year of span; NaN when no heliostat qualifies."""
    t = _with_time(table).cpu().numpy()
    h = table.heliostat_index.cpu().numpy()
    ok = np.isfinite(t)
    t, h = t[ok], h[ok]
    if not len(t):
        return float("nan")
    n_h = int(h.max()) + 1
    n = np.bincount(h, minlength=n_h)
    lo, hi = np.full(n_h, np.inf), np.full(n_h, -np.inf)
    np.minimum.at(lo, h, t)
    np.maximum.at(hi, h, t)
    span = (hi - lo) / (365.25 * 86400.0)
    use = (n >= 2) & (span >= 30.0 / 365.25)
    return float(np.median((n[use] - 1) / span[use])) if use.any() else float("nan")


def _rate_of(false_alarm_rate: float | None, seen: RecordTable) -> dict:
    """The per-record rate in force and where it came from: given, or from the operator's budget per
    heliostat-year at the plant's record rate on ``seen`` (:func:`records_per_heliostat_year`)."""
    rate_per_year = records_per_heliostat_year(seen) if len(seen) else float("nan")
    if false_alarm_rate is None:
        false_alarm_rate = false_alarm_rate_for(rate_per_year)
        rule = (f"{FALSE_ALARMS_PER_HELIOSTAT_YEAR} false alarms per heliostat-year at the plant's record rate "
                "(median over heliostats)")
    else:
        rule = "given per record"
    out = {"false_alarm_rate": float(false_alarm_rate), "rate_rule": rule}
    if math.isfinite(rate_per_year):
        out.update(records_per_heliostat_year=rate_per_year,
                   false_alarms_per_heliostat_year=float(false_alarm_rate) * rate_per_year)
    return out


def alarm_threshold_choice(scenario: Scenario, records: RecordTable, false_alarm_rate: float | None = None,
                           window: int = WINDOW) -> dict | None:
    """The step-alarm threshold of ``scenario``'s rigid-body calibration, chosen on the records it saw
    (:func:`~heliotwin.calibrate.assimilate.alarm_threshold` of the target ``false_alarm_rate`` per record,
    ``window`` step tests per record, and the normalised leave-one-out residuals of those records under the
    fit's own posterior, :func:`~heliotwin.calibrate.assimilate.leave_one_out_d2`).

    Parameters
    ----------
    records : RecordTable
        Records of the plant (any heliostat ids); only those the calibration lists as seen are used.
    false_alarm_rate : float, optional
        Target share of clean records that raise an alarm [1]; None (default): the one that spends
        :data:`~heliotwin.calibrate.assimilate.FALSE_ALARMS_PER_HELIOSTAT_YEAR` at the plant's own record rate.
    window : int
        Step tests per record [1].

    Returns
    -------
    dict or None
        ``threshold`` (d^2), ``kappa``, ``false_alarm_rate``, ``tests``, ``validation_records``, ``method``,
        ``rate_rule``, ``records_per_heliostat_year`` and ``false_alarms_per_heliostat_year`` (when the record
        rate is known); None for a calibration without a rigid-body posterior (nothing to update).
    """
    cal = scenario.learned.get(KEY)
    if not isinstance(cal, dict) or cal.get("networks") or not cal.get("posterior"):
        return None
    cal, ids, names = calibration_entry(scenario)
    table = fit_spots(on_axis(records, ids), FIT_FOCAL_SPOT)
    seen = seen_record_ids(scenario)
    rows = torch.as_tensor(np.isin(table.record_id.numpy(), np.array(sorted(seen), dtype=np.int64)))
    nominal = nominal_kinematics(cal, scenario.path, len(ids))
    state = _state(cal, names, scenario.path, len(ids), None, torch.full((len(ids),), float("nan")))
    # validation under the fit's own posterior (the Laplace posterior of those records, without the walk's)
    state = fit_posterior(state, cal, scenario.path)
    seen_table = table.subset(rows)
    d2 = leave_one_out_d2(nominal, seen_table, state, _judged_at(cal, names, nominal, seen_table, scenario.path)) \
        if bool(rows.any()) else None
    rate = _rate_of(false_alarm_rate, seen_table)
    made = {**rate, **alarm_threshold(rate["false_alarm_rate"], d2, tests=window)}
    made["method"] = ("chi-square quantile of the false-alarm rate per step test, widened by the 90 % quantile of "
                      "the leave-one-out normalised residuals of the calibration's records (under a drift model, "
                      "each at the offset smoothed to its time)")
    return made


def fit_posterior(state: FilterState, cal: dict, path) -> FilterState:
    """``state`` with the calibration fit's own Laplace posterior covariance [H, P, P] (without the walk's; what
    the leave-one-out residuals of the records it saw are judged under), in the units of ``state.noise``: scaled
    per heliostat by (state noise / the posterior's noise)^2 when the filter runs on the walk's learned record
    noise (the posterior's comes from the static residuals; a data-dominated Laplace covariance scales with the
    noise squared)."""
    cov = stored_tensor(cal, f"/learned/{KEY}", path, "posterior", "covariance")
    if "record_noise_rad" in (cal.get("drift") or {}):
        cov = _in_record_units(cov, state.noise, stored_tensor(cal, f"/learned/{KEY}", path, "posterior", "noise_rad"))
    return replace(state, covariance=cov)


def _in_record_units(cov: torch.Tensor, noise: torch.Tensor, fit_noise: torch.Tensor) -> torch.Tensor:
    """A Laplace covariance [H, P, P] of a fit with residual noise ``fit_noise`` [H] [rad] rescaled to the record
    noise ``noise`` [H] [rad] (a data-dominated posterior covariance scales with the noise squared)."""
    return cov * ((noise / fit_noise.clamp_min(1e-12)) ** 2)[:, None, None]


def _judged_at(cal: dict, names: tuple, nominal: Kinematics, records: RecordTable, path) -> torch.Tensor | None:
    """Per record [R, P] the deviations a drift calibration had at the record's time: the static part plus the
    random-walk offset smoothed there (:func:`heliotwin.calibrate.drift.smooth`); None without a drift model."""
    drift = cal.get("drift") or {}
    if not drift or "static_deviations" not in drift or tuple(names) != STONE8:
        return None
    where = f"/learned/{KEY}"
    static = stored_tensor(cal, where, path, "drift", "static_deviations").double()
    q = float(stored_tensor(cal, where, path, "drift", "process_noise_rad2_per_day").reshape(-1)[0])
    drift_names = tuple(drift.get("names") or DRIFT_NAMES)
    basis = next((b for b, n in BASES.items() if n == drift_names), None)
    if basis is None or static.shape != (nominal.num_heliostats, len(names)):
        return None
    offset = smooth(nominal, records, static, q, NOISE, basis=basis)["smoothed"]
    return with_offset(static[records.heliostat_index], offset, basis)


def with_alarm_threshold(scenario: Scenario, records: RecordTable, false_alarm_rate: float | None = None,
                         window: int = WINDOW) -> tuple[Scenario, dict | None]:
    """``scenario`` with :func:`alarm_threshold_choice` (``false_alarm_rate`` [1] per record or None: from the
    budget per heliostat-year, ``window`` [1] step tests) stored under ``/learned/calibration/alarm_threshold``
    (where every update reads it), and the choice; unchanged (and None) when there is nothing to update."""
    made = alarm_threshold_choice(scenario, records, false_alarm_rate, window)
    if made is None:
        return scenario, None
    f64 = dict(dtype=torch.float64)
    stored = {"threshold": torch.tensor([made["threshold"]], **f64), "kappa": torch.tensor([made["kappa"]], **f64),
              "false_alarm_rate": torch.tensor([made["false_alarm_rate"]], **f64),
              "tests": torch.tensor([made["tests"]]), "validation_records": torch.tensor([made["validation_records"]]),
              "method": made["method"], "rate_rule": made["rate_rule"]}
    for key in ("records_per_heliostat_year", "false_alarms_per_heliostat_year"):
        if key in made:
            stored[key] = torch.tensor([made[key]], **f64)
    cal = {**scenario.learned[KEY], THRESHOLD_KEY: stored}
    return replace(scenario, learned={**scenario.learned, KEY: cal}), made


def _first(value, default=None) -> float:
    return float(torch.as_tensor(value if value is not None else default).reshape(-1)[0])


def _stored_threshold(assimilation: dict | None, cal: dict, false_alarm_rate: float | None,
                      window: int) -> dict | None:
    """The stored step-alarm threshold that applies (an earlier update's of the same calibration, else the one
    ``calibrate`` stored for the same window and the same rate, or any rate when ``false_alarm_rate`` is None:
    the rate calibrate chose), or None."""
    if assimilation and "threshold" in assimilation:
        return {"threshold": _first(assimilation["threshold"]), "kappa": _first(assimilation.get("kappa"), 1.0),
                "false_alarm_rate": _first(assimilation.get("false_alarm_rate"), 0.0), "stored": True,
                "source": "stored by an earlier update of this calibration"}
    chosen = cal.get(THRESHOLD_KEY)
    if isinstance(chosen, dict):
        rate, tests = _first(chosen["false_alarm_rate"]), int(_first(chosen["tests"]))
        same_rate = false_alarm_rate is None or math.isclose(rate, float(false_alarm_rate), rel_tol=1e-12)
        if same_rate and tests == max(1, int(window)):
            extra = {k: _first(chosen[k]) for k in ("records_per_heliostat_year", "false_alarms_per_heliostat_year")
                     if k in chosen}
            return {"threshold": _first(chosen["threshold"]), "kappa": _first(chosen["kappa"]),
                    "false_alarm_rate": rate, "tests": tests,
                    "validation_records": int(_first(chosen["validation_records"])), "stored": True,
                    "source": "stored by calibrate (chosen on the records it saw)", **extra}
    return None


def threshold_in_force(assimilation: dict | None, cal: dict, false_alarm_rate: float | None, window: int, nominal,
                       seen: RecordTable, state: FilterState) -> dict:
    """The step-alarm threshold an update applies: an earlier update's of the same calibration, else the one
    ``calibrate`` stored for the same ``false_alarm_rate`` [1] (None: the rate it chose) and ``window`` [1]
    (:func:`with_alarm_threshold`), else chosen now on ``seen`` (the seen records, fit centroids) under
    ``state`` (the fit's posterior; None rate: from the budget per heliostat-year at ``seen``'s record rate).
    ``source`` says which."""
    stored = _stored_threshold(assimilation, cal, false_alarm_rate, window)
    if stored is not None:
        return stored
    d2 = leave_one_out_d2(nominal, seen, state) if len(seen) else None
    rate = _rate_of(false_alarm_rate, seen)
    return {**rate, **alarm_threshold(rate["false_alarm_rate"], d2, tests=window), "stored": False,
            "source": "chosen now on the calibration's records"}


def needs_seen_records(scenario: Scenario, cal: dict, q_given: float | None, false_alarm_rate: float | None,
                       window: int) -> bool:
    """Whether an update of ``scenario`` needs the records its plant has already seen, or only the new ones
    (``q_given`` [mrad^2/day] or None, ``false_alarm_rate`` per record [1] or None, ``window`` in records [1]): it needs
    them while something it starts from is not stored yet -- the state's time per heliostat (stored
    with the drift state from the first update on), the process noise (:func:`process_noise_source`), the
    step-alarm threshold (:func:`threshold_in_force`). Every later update of a plant reads only new records."""
    drift = cal.get("drift") or {}
    t = drift.get("time")
    timed = t is not None and bool(torch.isfinite(torch.as_tensor(t, dtype=torch.float64)).all())
    noise = q_given is not None or isinstance(cal.get(CHOICE_KEY), dict) or bool(drift)
    threshold = _stored_threshold(current_assimilation(scenario), cal, false_alarm_rate, window) is not None
    return not (timed and noise and threshold)


def _with_time(table: RecordTable) -> torch.Tensor:
    return table.time.double() if table.time is not None else torch.full((len(table),), float("nan"))


def split_new(table: RecordTable, seen: set, state_time: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Rows (new [N], seen [S]) of ``table`` and the counts of what is skipped: ``seen`` holds record ids a
    provenance step lists, ``state_time`` [H] each heliostat's state time [s] (POSIX; a record not later than
    it cannot be assimilated)."""
    ids = table.record_id
    is_seen = torch.as_tensor(np.isin(ids.cpu().numpy(), np.fromiter(seen, dtype=np.int64, count=len(seen))),
                              dtype=torch.bool)
    t = _with_time(table)
    timed = torch.isfinite(t)
    st = state_time[table.heliostat_index]
    late = timed & torch.isfinite(st) & (t <= st)
    new = ~is_seen & timed & ~late
    counts = {"records": len(table), "seen": int(is_seen.sum()), "without_time": int((~is_seen & ~timed).sum()),
              "older_than_state": int((~is_seen & late).sum()), "new": int(new.sum())}
    return new.nonzero().flatten(), is_seen.nonzero().flatten(), counts


def merged_history(previous: dict | None, ids: list, hist: dict, number: int) -> dict:
    """The stored history with this update's rows appended (heliostat index into ``heliostats``)."""
    old_ids = list((previous or {}).get("heliostats") or [])
    all_ids = old_ids + [h for h in ids if h not in set(old_ids)]
    pos = {h: i for i, h in enumerate(all_ids)}
    remap = torch.tensor([pos[h] for h in ids], dtype=torch.long)
    rows = {"heliostat": remap[hist["heliostat"]], "record_id": hist["record_id"].long(), "time": hist["time"],
            "mean": hist["mean"], "variance": hist["variance"], "innovation": hist["innovation"], "d2": hist["d2"],
            "statistic": hist["statistic"], "window": hist["window"].long(), "alarm": hist["alarm"],
            "predicted_error": hist["predicted_error"],
            "update": torch.full((len(hist["d2"]),), number, dtype=torch.long)}
    old = (previous or {}).get("history") or {}
    merged = {}
    for k, v in rows.items():
        v = v.detach().cpu()
        v = v.to(_HISTORY_STORED.get(k, v.dtype))
        merged[k] = torch.cat([torch.as_tensor(old[k]).to(v.dtype), v]) if k in old else v
    return {"heliostats": all_ids, "history": merged}


def updated_learned(previous: Scenario, cal: dict, ids: list, state: FilterState, old_state: FilterState,
             threshold: dict, hist: dict) -> dict:
    """``previous.learned`` with the update's result: the calibration's deviations [Hc, P] and posterior
    [Hc, P, P] now ``state``'s, its drift state (offset [Hc, 2] from the static deviations, time [s]), and
    ``/learned/assimilation`` with the threshold in force and the history (this update's rows ``hist``
    appended)."""
    names = list(state.names)
    cols = list(state.drift_columns)
    mean, cov = state.mean.detach().cpu(), state.covariance.detach().cpu()
    new_cal = dict(cal)
    new_cal["deviations"] = mean
    new_cal["posterior"] = dict(cal["posterior"], covariance=cov)
    drift = dict(cal.get("drift") or {})
    static = torch.as_tensor(drift.get("static_deviations", old_state.mean), dtype=torch.float64)
    new_cal["drift"] = {**drift, "model": "kalman", "names": [names[c] for c in cols],
                        "offset": (mean - static)[:, cols], "covariance": torch.zeros(len(ids), len(cols), len(cols),
                                                                                      dtype=torch.float64),
                        "time": state.time.detach().cpu(), "static_deviations": static,
                        # q stored as calibrate stores it (the interval's units), the filter's divided by its scale
                        "process_noise_rad2_per_day": torch.tensor(
                            [float(state.process_noise) / filter_scale(cal, None)], dtype=torch.float64)}
    prev = previous.learned.get(ASSIMILATION_KEY)
    number = int(torch.as_tensor(prev.get("updates", 0)).reshape(-1)[0]) + 1 if prev else 1
    merged = merged_history(prev, ids, hist, number)
    pos = {hid: i for i, hid in enumerate(merged["heliostats"])}
    remap = torch.tensor([pos[hid] for hid in ids], dtype=torch.long)
    alarms = {"open_alarms": _open_table(state.alarms, remap),
              "closed_alarms": _closed_table(_current_closed(previous), hist.get("closed"), remap, number)}
    learned = dict(previous.learned)
    learned[KEY] = new_cal
    learned[ASSIMILATION_KEY] = {"version": torch.tensor([HISTORY_VERSION]), "updates": torch.tensor([number]),
                                 "threshold": torch.tensor([threshold["threshold"]], dtype=torch.float64),
                                 "kappa": torch.tensor([threshold["kappa"]], dtype=torch.float64),
                                 "false_alarm_rate": torch.tensor([threshold["false_alarm_rate"]], dtype=torch.float64),
                                 "calibrations": torch.tensor([calibration_count(previous)]),
                                 "parameter_names": names, **merged, **alarms}
    if state.window_g is not None:  # the step tests' evidence of each heliostat's latest records
        learned[ASSIMILATION_KEY]["window"] = {"heliostats": list(ids), "g": state.window_g.detach().cpu(),
                                               "f": state.window_f.detach().cpu()}
    return learned


def _current_closed(previous: Scenario) -> dict | None:
    """The stored ``closed_alarms`` (kept across recalibrations: they are the plant's record of what happened)."""
    st = previous.learned.get(ASSIMILATION_KEY)
    table = st.get("closed_alarms") if isinstance(st, dict) else None
    return table if isinstance(table, dict) else None


def _closed_table(old: dict | None, new: dict | None, remap: torch.Tensor, number: int) -> dict:
    """``closed_alarms`` with this update's closed alarms (``new``, heliostats on the calibration's axis)
    appended."""
    floats = ("opened", "statistic", "closed_at", "evidence")
    rows = {}
    new = new or {}
    c = len(new.get("heliostat", []))
    for key in CLOSED_FIELDS:
        dtype = torch.float64 if key in floats else torch.long
        if key == "update":
            v = torch.full((c,), number, dtype=dtype)
        elif key == "heliostat":
            v = remap[torch.as_tensor(new[key]).long().cpu()] if c else torch.zeros(0, dtype=dtype)
        else:
            v = torch.as_tensor(new[key]).detach().cpu().to(dtype) if c else torch.zeros(0, dtype=dtype)
        if old is not None and key in old:
            v = torch.cat([torch.as_tensor(old[key]).to(dtype), v])
        rows[key] = v
    return rows


def process_noise_source(previous: Scenario, cal: dict, table: RecordTable, q_given: float | None) -> tuple:
    """Where this update's q comes from: given, the calibration's drift model (or an earlier update's), the
    choice stored with the calibration, or -- the first time a calibration without a drift model is updated --
    chosen now on the seen records in ``table`` (:func:`process_noise_choice`) and stored with the calibration
    so that later updates read it; :data:`DEFAULT_PROCESS_NOISE` when ``table`` holds too few seen records.
    Returns (scenario, calibration entry, report's ``process_noise`` entry)."""
    choice = cal.get(CHOICE_KEY)
    if q_given is not None:
        return previous, cal, {"source": "given"}
    if isinstance(choice, dict):
        return previous, cal, {"source": "stored choice (made on the calibration's records)",
                               "method": str(choice.get("method", "")),
                               "validation_error_mrad": torch.as_tensor(choice["validation_error_mrad"]).tolist(),
                               "grid_mrad2_per_day": torch.as_tensor(choice["grid_mrad2_per_day"]).tolist()}
    if cal.get("drift"):
        return previous, cal, {"source": "the stored drift state (the calibration's drift model or an earlier update)"}
    previous, made = with_process_noise_choice(previous, table)
    if made is None:
        return previous, cal, {"source": "default (too few seen records to choose on)"}
    return previous, previous.learned[KEY], {"source": "chosen now on the calibration's records (stored)",
                                             "method": made["method"],
                                             "validation_error_mrad": made["validation_error_mrad"],
                                             "grid_mrad2_per_day": made["grid_mrad2_per_day"]}


def state_history(scenario, heliostat_id: str) -> dict:
    """One heliostat's state history across every update of ``scenario`` (a Scenario or a path).

    Returns
    -------
    dict
        ``heliostat``, ``parameter_names`` [P], and per assimilated record in time order: ``record_id`` [n],
        ``time`` [n] (POSIX s), ``update`` [n] (which update), ``mean`` [n, P] and ``variance`` [n, P] of the
        deviations after the record, ``innovation`` [n, 2] [rad], ``d2`` [n], ``alarm`` [n] (bool),
        ``predicted_error`` [n] [rad] (numpy arrays). Empty arrays for a heliostat never updated.
    """
    sc = load_scenario(scenario) if isinstance(scenario, (str, os.PathLike)) else scenario
    where = f"/learned/{ASSIMILATION_KEY}"
    st = sc.learned.get(ASSIMILATION_KEY)
    if not isinstance(st, dict):
        raise InputFileError(sc.path, "no update history (run heliotwin update first)", field=where)
    try:
        names = list(st["parameter_names"])
        ids = list(st["heliostats"])
        h = {k: np.asarray(st["history"][k]) for k in _HISTORY_FIELDS}
    except (KeyError, TypeError, ValueError):
        raise InputFileError(sc.path, "malformed update history", field=f"{where}/history") from None
    if heliostat_id not in ids:
        cal_ids = (sc.learned.get(KEY) or {}).get("heliostats") or []
        if heliostat_id not in cal_ids:
            raise HeliotwinError(f"{sc.path}: heliostat {heliostat_id} was never calibrated or updated")
        rows = np.zeros(0, dtype=np.int64)
    else:
        rows = np.nonzero(h["heliostat"] == ids.index(heliostat_id))[0]
        rows = rows[np.argsort(h["time"][rows], kind="stable")]
    out = {k: h[k][rows] for k in _HISTORY_FIELDS if k != "heliostat"}
    out.update(window=out["window"].astype(np.int64), update=out["update"].astype(np.int64))
    return {"heliostat": heliostat_id, "parameter_names": names, **out}
