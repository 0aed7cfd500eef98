"""The update workflow: a calibrated scenario and the records it has not seen yet -> the updated scenario.

``heliotwin update`` (:func:`heliotwin.cli.update.cmd_update`) and :func:`heliotwin.api.update` are both
:func:`update`: the records a plant produced since its last calibration or update are *assimilated* into
each heliostat's Gaussian state (:mod:`heliotwin.calibrate.assimilate`), not refitted.

* The state is read from ``/learned/calibration`` (a rigid-body calibration with its Laplace posterior:
  ``calibrate --method lm``, with or without ``--drift kalman``) and written back there, so that every
  reader (``aim``, ``trace``, ``plan``) uses the current state; ``/field/kinematics`` become the updated
  kinematics.
* New records are those of calibrated heliostats whose ids no provenance step lists as seen (``calibrate``'s
  training records, earlier updates' records) and that are later than the heliostat's state (a record older
  than the state cannot be assimilated by a filter; it is counted, not used).
* The random walk of the axis offsets between records: the calibration's drift model's q; without one, q is
  chosen on the records the calibration saw (:func:`process_noise_choice`: each heliostat's latest quarter
  predicted by the walk run through its earlier ones) by ``calibrate`` or, when it did not, by the first
  update given those records, and stored under ``/learned/calibration/process_noise_choice`` with how it was
  chosen; later updates read it. :data:`DEFAULT_PROCESS_NOISE` only when neither had the records.
* ``/learned/assimilation`` keeps the step-alarm threshold (chosen at the first update from the target
  false-alarm rate and the normalised leave-one-out residuals of the records the calibration saw, when the
  folder holds them) and every update's per-record history (:func:`state_history` reads it back); each
  update is one ``update`` provenance step with the records it assimilated and its alarms.
"""
from __future__ import annotations

import math
import os
import time as _time
from dataclasses import dataclass, fields, replace

import numpy as np
import torch

from ..calibrate.assimilate import (
    FALSE_ALARM_RATE,
    REOPEN,
    WINDOW,
    AssimilationOptions,
    FilterState,
    alarm_threshold,
    assimilate,
    choose_process_noise,
    leave_one_out_d2,
)
from ..calibrate.inputs import FIT_FOCAL_SPOT, fit_spots
from ..calibrate.params import apply_deviations, check_names
from ..calibrate.scenario import KEY
from ..devices import to_device
from ..errors import HeliotwinError, InputFileError
from ..field.plant import Kinematics
from ..field.update import with_kinematics
from ..io.paint import PaintDataset, list_heliostats
from ..io.records import RecordTable
from ..io.scenario import Scenario, load_records, load_scenario, next_scenario, provenance_entry

__all__ = ["UpdateSettings", "Update", "update", "state_history", "seen_record_ids", "filter_state", "ASSIMILATION_KEY",
           "HISTORY_VERSION", "DEFAULT_PROCESS_NOISE", "CHOICE_KEY", "process_noise_choice",
           "with_process_noise_choice"]

#: Key of the assimilation state under ``Scenario.learned``.
ASSIMILATION_KEY = "assimilation"
#: Layout version of ``/learned/assimilation``.
HISTORY_VERSION = 1
#: q [mrad^2/day] of the drifting axis offsets when the calibration has no drift model and no choice could be
#: made on its records (:func:`process_noise_choice`): the random-walk setting chosen on the real PAINT
#: archive's online protocol by leave-heliostats-out CV (benchmarks/bench_carryover.py, kq0.03).
DEFAULT_PROCESS_NOISE = 0.03
#: Key under ``/learned/calibration`` of the q chosen on the calibration's records, with how it was chosen.
CHOICE_KEY = "process_noise_choice"
_DRIFT_NAMES = ("initial_angle_1", "initial_angle_2")
_HISTORY_FIELDS = ("heliostat", "record_id", "time", "mean", "variance", "innovation", "d2", "statistic", "window",
                   "alarm", "predicted_error", "update")

#: Stored types of the history's fields that are narrower than computed: float32 halves the state's columns
#: (~1e-7 relative), and the small counters fit int32 (:func:`state_history` hands them back as int64); the
#: rest keeps its type. Large arrays are also compressed on writing (:data:`heliotwin.io.scenario.COMPRESS_BYTES`).
_HISTORY_STORED = {"mean": torch.float32, "variance": torch.float32, "innovation": torch.float32,
                   "heliostat": torch.int32, "window": torch.int32, "update": torch.int32}


@dataclass(frozen=True)
class UpdateSettings:
    """The options of an update (``heliotwin update``'s flags, same names, same defaults).

    Attributes
    ----------
    false_alarm_rate : float
        Target share of clean records that raise a step alarm (chooses the threshold at the first update;
        later updates keep the stored one).
    process_noise : str or float
        ``"stored"``: the calibration's random-walk q, else the one chosen on its records (module docstring;
        :data:`DEFAULT_PROCESS_NOISE` when neither exists), or a number >= 0 [mrad^2/day].
    reopen_mrad : float
        Smallest re-opening of the axis offsets at an alarm [mrad].
    iterations : int
        Linearisations per record (iterated extended Kalman filter).
    robust : bool
        Down-weight moderate outliers (Huber), as the batch fit's robust loss does.
    window : int
        Step tests over each heliostat's latest 1..window records (1: a record far out on its own only).
    fit_focal_spot : str or None
        Centroids assimilated (as the ``lm`` fit: :data:`~heliotwin.calibrate.inputs.FIT_FOCAL_SPOT`); the
        prediction error is scored on the calibration's ``focal_spot``.
    plane_tolerance : float
        Largest distance [m] of a focal spot from its target plane.
    """

    false_alarm_rate: float = FALSE_ALARM_RATE
    process_noise: str | float = "stored"
    reopen_mrad: float = 1e3 * REOPEN
    iterations: int = 2
    robust: bool = True
    window: int = WINDOW
    fit_focal_spot: str | None = FIT_FOCAL_SPOT
    plane_tolerance: float = 0.1


@dataclass(frozen=True)
class Update:
    """What :func:`update` returns; unpacks as ``scenario, report = update(...)``.

    Attributes
    ----------
    scenario : Scenario
        The updated scenario, in memory (:func:`heliotwin.io.scenario.write_scenario` writes it).
    report : dict
        JSON report: counts, threshold, per-heliostat predicted errors and alarms.
    history : dict
        This update's per-record history (tensors, :func:`state_history`'s fields).
    """

    scenario: Scenario
    report: dict
    history: dict

    def __iter__(self):
        return iter((self.scenario, self.report))


def _check_settings(s: UpdateSettings) -> float | None:
    if not (0.0 < float(s.false_alarm_rate) < 1.0):
        raise HeliotwinError(f"--false-alarm-rate must be in (0, 1), got {s.false_alarm_rate}")
    if not (math.isfinite(s.reopen_mrad) and s.reopen_mrad >= 0):
        raise HeliotwinError(f"--reopen-mrad must be a number >= 0, got {s.reopen_mrad}")
    if int(s.iterations) < 1:
        raise HeliotwinError(f"--iterations must be >= 1, got {s.iterations}")
    if int(s.window) < 1:
        raise HeliotwinError(f"--window must be >= 1, got {s.window}")
    if s.process_noise is None or str(s.process_noise).strip().lower() == "stored":
        return None
    try:
        q = float(s.process_noise)
    except ValueError:
        q = float("nan")
    if not (math.isfinite(q) and q >= 0):
        raise HeliotwinError(f"--process-noise must be 'stored' or a number >= 0 [mrad^2/day], got {s.process_noise!r}")
    return q


def _calibrations(scenario: Scenario) -> int:
    """How many ``calibrate`` steps the scenario's provenance holds (a new one restarts the update's state)."""
    return sum(1 for p in scenario.provenance or [] if isinstance(p, dict) and p.get("step") == "calibrate")


def _current(scenario: Scenario) -> dict | None:
    """``/learned/assimilation`` when it belongs to the scenario's current calibration (None after a
    recalibration: its threshold and step-test evidence were about the replaced one; the history stays)."""
    st = scenario.learned.get(ASSIMILATION_KEY)
    if not isinstance(st, dict):
        return None
    stamp = int(torch.as_tensor(st.get("calibrations", -1)).reshape(-1)[0])
    return st if stamp == _calibrations(scenario) else None


def seen_record_ids(scenario: Scenario) -> set:
    """Record ids some provenance step lists as seen (``calibrate``'s training records, updates' records)."""
    seen = set()
    for step in scenario.provenance or []:
        recs = step.get("records") if isinstance(step, dict) else None
        if isinstance(recs, dict):
            for ids in recs.values():
                if isinstance(ids, list):
                    seen.update(int(i) for i in ids if isinstance(i, (int, float)))
    return seen


def _tensor(cal: dict, where: str, path, *keys) -> torch.Tensor:
    obj = cal
    try:
        for k in keys:
            obj = obj[k]
        return torch.as_tensor(obj, dtype=torch.float64)
    except (KeyError, TypeError, ValueError, RuntimeError):
        raise InputFileError(path, "missing or malformed (a rigid-body calibration with its posterior, "
                                   "calibrate --method lm)", field=f"{where}/{'/'.join(keys)}") from None


def _calibration(scenario: Scenario) -> tuple[dict, list, tuple]:
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


def _nominal(cal: dict, path, n: int) -> Kinematics:
    try:
        kin = Kinematics(**{f.name: torch.as_tensor(cal["nominal"][f.name]) for f in fields(Kinematics)})
    except (KeyError, TypeError, ValueError, RuntimeError):
        raise InputFileError(path, "missing or malformed nominal kinematics", field=f"/learned/{KEY}/nominal") from None
    if kin.num_heliostats != n:
        raise InputFileError(path, f"expected {n} heliostats", field=f"/learned/{KEY}/nominal/position")
    return kin


def _state(cal: dict, names: tuple, path, n: int, q_given: float | None, seen_time: torch.Tensor) -> FilterState:
    """The filter state of the calibration (module docstring); ``seen_time`` [H]: latest seen record time."""
    where = f"/learned/{KEY}"
    p = len(names)
    mean = _tensor(cal, where, path, "deviations")
    cov = _tensor(cal, where, path, "posterior", "covariance").clone()
    noise = _tensor(cal, where, path, "posterior", "noise_rad")
    if mean.shape != (n, p) or cov.shape != (n, p, p) or noise.shape != (n,):
        raise InputFileError(path, f"deviations / posterior must be [{n}, {p}] / [{n}, {p}, {p}] / [{n}]",
                             field=f"{where}/posterior")
    drift = cal.get("drift") or {}
    time = seen_time.clone()
    drift_names = tuple(drift.get("names") or _DRIFT_NAMES)
    if any(d not in names for d in drift_names):
        raise InputFileError(path, f"drift names {list(drift_names)} not among the parameters", field=f"{where}/drift")
    cols = tuple(names.index(d) for d in drift_names)
    q = 1e-6 * DEFAULT_PROCESS_NOISE
    chosen = _stored_choice(cal, path)
    if chosen is not None:
        q = 1e-6 * chosen
    if drift:
        p_l = _tensor(cal, where, path, "drift", "covariance")
        t_l = _tensor(cal, where, path, "drift", "time")
        q = float(_tensor(cal, where, path, "drift", "process_noise_rad2_per_day").reshape(-1)[0])
        if p_l.shape != (n, len(cols), len(cols)) or t_l.shape != (n,):
            raise InputFileError(path, "malformed drift state", field=f"{where}/drift")
        idx = torch.tensor(cols)
        cov[:, idx[:, None], idx[None, :]] += p_l  # the offset's own uncertainty on top of the static posterior
        time = torch.where(torch.isfinite(t_l), t_l, time)
    if q_given is not None:
        q = 1e-6 * q_given
    return FilterState(mean=mean, covariance=cov, time=time, noise=noise, process_noise=q, drift_columns=cols,
                       names=names)


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
    cal, ids, names = _calibration(scenario)
    table = fit_spots(_on_axis(records, ids), FIT_FOCAL_SPOT)
    seen = seen_record_ids(scenario)
    rows = torch.as_tensor(np.isin(table.record_id.numpy(), np.array(sorted(seen), dtype=np.int64)))
    table = table.subset(rows)
    nominal = _nominal(cal, scenario.path, len(ids))
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


def filter_state(scenario: Scenario, records: RecordTable, process_noise: float | None = None) -> FilterState:
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
    """
    cal, ids, names = _calibration(scenario)
    seen = seen_record_ids(scenario)
    seen_rows = torch.as_tensor(np.isin(records.record_id.numpy(), np.array(sorted(seen), dtype=np.int64)))
    t = _with_time(records)
    ok = seen_rows & torch.isfinite(t)
    seen_time = torch.full((len(ids),), float("nan"), dtype=torch.float64)
    seen_time = seen_time.scatter_reduce(0, records.heliostat_index[ok], t[ok], reduce="amax", include_self=False)
    state = _state(cal, names, scenario.path, len(ids), process_noise, seen_time)
    window = (_current(scenario) or {}).get("window") or {}
    if window.get("heliostats") == list(ids):  # the same calibration's heliostats: its evidence carries on
        try:
            g = torch.as_tensor(window["g"], dtype=torch.float64)
            f = torch.as_tensor(window["f"], dtype=torch.float64)
        except (KeyError, TypeError, ValueError, RuntimeError):
            raise InputFileError(scenario.path, "malformed step-test window",
                                 field=f"/learned/{ASSIMILATION_KEY}/window") from None
        state = replace(state, window_g=g, window_f=f)
    return state


def _on_axis(table: RecordTable, ids: list) -> RecordTable:
    """The records of ``ids`` re-indexed onto that list (heliostats without records are fine)."""
    pos = {h: i for i, h in enumerate(ids)}
    remap = torch.tensor([pos.get(h, -1) for h in table.heliostat_ids], dtype=torch.long)
    new = remap[table.heliostat_index] if len(table) else table.heliostat_index
    out = table.subset(new >= 0)
    out.heliostat_index = new[new >= 0]
    out.heliostat_ids = list(ids)
    return out


def _records(records_or_paint, scenario: Scenario, ids: list, plane_tolerance: float) -> tuple[RecordTable, str]:
    """The record table (calibrated heliostats' axis) and where it came from."""
    if isinstance(records_or_paint, RecordTable):
        return _on_axis(records_or_paint, ids), "records"
    if isinstance(records_or_paint, PaintDataset):
        return _on_axis(records_or_paint.records, ids), os.path.abspath(records_or_paint.root)
    paint = os.fspath(records_or_paint)
    if not os.path.isdir(paint):
        raise HeliotwinError(f"{paint}: PAINT folder not found")
    present = set(list_heliostats(paint))
    use = [h for h in ids if h in present]
    if not use:
        raise HeliotwinError(f"{paint}: none of the scenario's {len(ids)} calibrated heliostats is in this "
                             "PAINT folder")
    ds, _ = load_records(paint, scenario, use, plane_tolerance=plane_tolerance)
    return _on_axis(ds.records, ids), os.path.abspath(paint)


def _threshold(previous: dict | None, settings: UpdateSettings, nominal, seen: RecordTable, state) -> dict:
    if previous and "threshold" in previous:
        t = float(torch.as_tensor(previous["threshold"]).reshape(-1)[0])
        return {"threshold": t, "kappa": float(torch.as_tensor(previous.get("kappa", 1.0)).reshape(-1)[0]),
                "false_alarm_rate": float(torch.as_tensor(previous.get("false_alarm_rate", 0.0)).reshape(-1)[0]),
                "stored": True}
    d2 = leave_one_out_d2(nominal, seen, state) if len(seen) else None
    return {**alarm_threshold(settings.false_alarm_rate, d2, tests=settings.window), "stored": False}


def _with_time(table: RecordTable) -> torch.Tensor:
    return table.time.double() if table.time is not None else torch.full((len(table),), float("nan"))


def _split(table: RecordTable, seen: set, state_time: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Rows (new, seen) of ``table`` and the counts of what is skipped."""
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


def _merged_history(previous: dict | None, ids: list, hist: dict, number: int) -> dict:
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


def _learned(previous: Scenario, cal: dict, ids: list, state: FilterState, old_state: FilterState,
             threshold: dict, hist: dict) -> dict:
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
                        "process_noise_rad2_per_day": torch.tensor([float(state.process_noise)], dtype=torch.float64)}
    prev = previous.learned.get(ASSIMILATION_KEY)
    number = int(torch.as_tensor(prev.get("updates", 0)).reshape(-1)[0]) + 1 if prev else 1
    merged = _merged_history(prev, ids, hist, number)
    learned = dict(previous.learned)
    learned[KEY] = new_cal
    learned[ASSIMILATION_KEY] = {"version": torch.tensor([HISTORY_VERSION]), "updates": torch.tensor([number]),
                                 "threshold": torch.tensor([threshold["threshold"]], dtype=torch.float64),
                                 "kappa": torch.tensor([threshold["kappa"]], dtype=torch.float64),
                                 "false_alarm_rate": torch.tensor([threshold["false_alarm_rate"]], dtype=torch.float64),
                                 "calibrations": torch.tensor([_calibrations(previous)]),
                                 "parameter_names": names, **merged}
    if state.window_g is not None:  # the step tests' evidence of each heliostat's latest records
        learned[ASSIMILATION_KEY]["window"] = {"heliostats": list(ids), "g": state.window_g.detach().cpu(),
                                               "f": state.window_f.detach().cpu()}
    return learned


def _report(ids, counts, threshold, hist, state, seconds, source) -> dict:
    hh = hist["heliostat"].cpu()
    n = torch.bincount(hh, minlength=len(ids))
    err = torch.zeros(len(ids), dtype=torch.float64).index_add_(0, hh, 1e3 * hist["predicted_error"].cpu().double())
    alarm = hist["alarm"].cpu()
    count = torch.bincount(hh[alarm], minlength=len(ids))
    per = {ids[j]: {"records": int(n[j]), "mean_predicted_error_mrad": float(err[j] / n[j]), "alarms": int(count[j])}
           for j in n.nonzero().flatten().tolist()}  # the report's one entry per updated heliostat
    alarms = [{"heliostat": ids[int(hh[i])], "record_id": int(hist["record_id"][i]), "time": float(hist["time"][i]),
               "d2": float(hist["d2"][i]), "statistic": float(hist["statistic"][i]), "window": int(hist["window"][i])}
              for i in alarm.nonzero().flatten().tolist()]
    means = [v["mean_predicted_error_mrad"] for v in per.values()]
    return {"source": source, "counts": counts, "heliostats_updated": len(per),
            "threshold": {k: v for k, v in threshold.items()}, "alarms": alarms,
            "overall": {"median_of_mean_predicted_error_mrad": float(np.median(means)) if means else None,
                        "records": int(len(hh)), "alarms": len(alarms)},
            "process_noise_mrad2_per_day": 1e6 * float(state.process_noise), "seconds": seconds, "heliostats": per}


def _process_noise(previous: Scenario, cal: dict, table: RecordTable, q_given: float | None) -> tuple:
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


def update(scenario, records_or_paint, settings: UpdateSettings = UpdateSettings(), *, device: str = "cpu") -> Update:
    """Assimilate the records a calibrated plant has not seen yet (module docstring).

    Parameters
    ----------
    scenario : Scenario, str or os.PathLike
        A scenario with a rigid-body calibration (``calibrate --method lm -o``) or an earlier update.
    records_or_paint : str, os.PathLike, PaintDataset or RecordTable
        The PAINT folder (old and new records may both be there: seen ones are recognised by id), or records
        already loaded (heliostat ids as in the scenario).
    settings : UpdateSettings
    device : str
        Where to compute (``"cpu"`` or ``"cuda"``); the scenario comes back on the CPU.

    Returns
    -------
    Update
        ``scenario, report = update(...)``; also ``history`` (this update's rows).
    """
    q_given = _check_settings(settings)
    previous = load_scenario(scenario) if isinstance(scenario, (str, os.PathLike)) else scenario
    cal, ids, names = _calibration(previous)
    nominal = _nominal(cal, previous.path, len(ids))
    table, source = _records(records_or_paint, previous, ids, settings.plane_tolerance)
    t0 = _time.perf_counter()
    previous, cal, noise = _process_noise(previous, cal, table, q_given)
    seen_ids = seen_record_ids(previous)
    state = filter_state(previous, table, q_given)
    new_rows, seen_idx, counts = _split(table, seen_ids, state.time)
    fit_table = fit_spots(table, settings.fit_focal_spot)
    assim_prev = _current(previous)
    # validation under the fit's own posterior (the Laplace posterior of those records, without the walk's)
    fit_posterior = replace(state, covariance=_tensor(cal, f"/learned/{KEY}", previous.path, "posterior", "covariance"))
    threshold = _threshold(assim_prev, settings, nominal, fit_table.subset(seen_idx), fit_posterior)
    options = AssimilationOptions(threshold=threshold["threshold"], reopen=1e-3 * settings.reopen_mrad,
                                  iterations=int(settings.iterations), robust=bool(settings.robust),
                                  window=int(settings.window))
    new = fit_table.subset(new_rows)
    on = (lambda x: x) if torch.device(device).type == "cpu" else (lambda x: to_device(x, device))
    new_state, hist = assimilate(on(nominal), on(new), on(state), options, score_spot=on(table.spot[new_rows]))
    new_state, hist = to_device(new_state, "cpu"), to_device(hist, "cpu")
    seconds = _time.perf_counter() - t0
    learned = _learned(previous, cal, ids, new_state, state, threshold, hist)
    plant = with_kinematics(previous.plant, ids, apply_deviations(nominal, new_state.mean, names))
    records = {}
    for j, rid in zip(hist["heliostat"].tolist(), hist["record_id"].tolist()):
        records.setdefault(ids[j], []).append(int(rid))
    report = _report(ids, counts, threshold, hist, new_state, seconds, source)
    report["process_noise"] = {"mrad2_per_day": 1e6 * float(new_state.process_noise), **noise}
    step = provenance_entry("update", source=str(source), records=records, alarms=report["alarms"],
                            settings={f.name: getattr(settings, f.name) for f in fields(UpdateSettings)},
                            threshold=float(threshold["threshold"]))
    return Update(next_scenario(previous, plant, learned=learned, step=step), report, hist)


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
