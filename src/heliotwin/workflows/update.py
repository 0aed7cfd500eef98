"""The update workflow: a calibrated scenario and the records it has not seen yet -> the updated scenario.

``heliotwin update`` (:func:`heliotwin.cli.update.cmd_update`) and :func:`heliotwin.api.update` are both
:func:`update`: the records a plant produced since its last calibration or update are *assimilated* into
each heliostat's Gaussian state (:mod:`heliotwin.calibrate.assimilate`), not refitted.

The workflow composes; the state logic is :mod:`heliotwin.calibrate.twinstate`'s, the filter
:mod:`heliotwin.calibrate.assimilate`'s, the reading :func:`heliotwin.io.paint.load_paint_on_plant`'s (the
folder's record index: a folder that grew by one day costs that day's files). :func:`update_plant_file` is the
whole command on files: the plant file is locked for the read-update-write, a plant replaced meanwhile is not
overwritten, and the write is atomic.

* The state is read from ``/learned/calibration`` (a rigid-body calibration with its Laplace posterior:
  ``calibrate --method lm``, with or without ``--drift kalman``) and written back there, so that every
  reader (``aim``, ``trace``, ``plan``) uses the current state; ``/field/kinematics`` become the updated
  kinematics.
* New records are those of calibrated heliostats whose ids no provenance step lists as seen (``calibrate``'s
  training records, earlier updates' records) and that are later than the heliostat's state (a record older
  than the state cannot be assimilated by a filter; it is counted, not used).
* The random walk of the axis offsets between records: the calibration's drift model's q; without one, q is
  chosen on the records the calibration saw
  (:func:`~heliotwin.calibrate.twinstate.process_noise_choice`: each heliostat's latest quarter
  predicted by the walk run through its earlier ones) by ``calibrate`` or, when it did not, by the first
  update given those records, and stored under ``/learned/calibration/process_noise_choice`` with how it was
  chosen; later updates read it. :data:`DEFAULT_PROCESS_NOISE` only when neither had the records.
* The step-alarm threshold: chosen by ``calibrate`` from the target false-alarm rate (by default the one that
  spends :data:`~heliotwin.calibrate.assimilate.FALSE_ALARMS_PER_HELIOSTAT_YEAR` at the plant's own record
  rate) and the normalised leave-one-out residuals of the records it saw, and stored with the calibration
  (:func:`~heliotwin.calibrate.twinstate.with_alarm_threshold`); an update reads it (it is chosen at the first
  update only for a plant calibrated before it was stored, or for another false-alarm rate or window).
* ``/learned/assimilation`` keeps the threshold in force and every update's per-record history
  (:func:`state_history` reads it back); each update is one ``update`` provenance step with the records it
  assimilated and its alarms.
* An alarm stays open there until the heliostat's next records settle it (confirmed: the state re-fitted on
  them is applied; cleared: not confirmed by them; :mod:`heliotwin.calibrate.assimilate`); the report lists
  the alarms this update closed (``closed_alarms``) and every one still open (``open_alarms``, with its age on
  the plant's latest record).
* What is not assimilated is counted by reason: seen before, older than the state, without a time, records
  the folder's reader dropped (out-of-range motor steps, a date in the future, ...: ``dropped``, by reason), and
  records of heliostats the plant does not know (``unknown_heliostats``).
"""
from __future__ import annotations

import math
import os
import time as _time
from dataclasses import dataclass, fields

import numpy as np
import torch

from ..calibrate.assimilate import REOPEN, WINDOW, AssimilationOptions, assimilate, confirm_threshold
from ..calibrate.inputs import FIT_FOCAL_SPOT, fit_spots
from ..calibrate.params import apply_deviations
from ..calibrate.twinstate import (
    ASSIMILATION_KEY,
    CHOICE_KEY,
    DEFAULT_PROCESS_NOISE,
    HISTORY_VERSION,
    THRESHOLD_KEY,
    calibration_entry,
    closed_alarms,
    current_assimilation,
    filter_state,
    fit_posterior,
    needs_seen_records,
    nominal_kinematics,
    on_axis,
    open_alarms,
    plant_clock,
    process_noise_choice,
    process_noise_source,
    seen_record_ids,
    seen_record_owners,
    split_new,
    state_history,
    threshold_in_force,
    updated_learned,
    with_alarm_threshold,
    with_process_noise_choice,
)
from ..devices import to_device
from ..errors import HeliotwinError
from ..field.update import select_heliostats, with_kinematics
from ..io.lock import check_unchanged, file_stamp, plant_lock
from ..io.paint import PaintDataset, list_heliostats, load_paint_on_plant
from ..io.records import RecordTable
from ..io.scenario import Scenario, load_scenario, next_scenario, provenance_entry, write_scenario

__all__ = ["UpdateSettings", "Update", "update", "update_plant_file", "locked_plant_write", "state_history",
           "seen_record_ids", "filter_state", "ASSIMILATION_KEY", "HISTORY_VERSION", "DEFAULT_PROCESS_NOISE",
           "CHOICE_KEY", "THRESHOLD_KEY", "process_noise_choice", "with_process_noise_choice", "with_alarm_threshold"]


@dataclass(frozen=True)
class UpdateSettings:
    """The options of an update (``heliotwin update``'s flags, same names, same defaults).

    Attributes
    ----------
    false_alarm_rate : float, optional
        Target share of clean records that raise a step alarm [1]; None (default): the threshold ``calibrate``
        stored (its rate spends :data:`~heliotwin.calibrate.assimilate.FALSE_ALARMS_PER_HELIOSTAT_YEAR` at the
        plant's record rate). Later updates keep the threshold in force.
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

    false_alarm_rate: float | None = None
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
    if s.false_alarm_rate is not None and not (0.0 < float(s.false_alarm_rate) < 1.0):
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


def _records(records_or_paint, scenario: Scenario, ids: list, plane_tolerance: float, skip=None) -> tuple:
    """The record table (calibrated heliostats' axis), where it came from, and how it was read (the folder's
    reading counts and the records its reader dropped, by field). A folder may hold some of the calibrated
    heliostats only (their records are read); none of them is a one-line error. ``skip``: record ids a folder's
    reader leaves out (given records are taken as they are)."""
    if isinstance(records_or_paint, RecordTable):
        return on_axis(records_or_paint, ids), "records", {}
    if isinstance(records_or_paint, PaintDataset):
        ds = records_or_paint
    else:
        paint = os.fspath(records_or_paint)
        if not os.path.isdir(paint):
            raise HeliotwinError(f"{paint}: PAINT folder not found")
        present = set(list_heliostats(paint))
        use = [h for h in ids if h in present]
        if not use:
            raise HeliotwinError(f"{paint}: none of the scenario's {len(ids)} calibrated heliostats is in this "
                                 "PAINT folder")
        ds = load_paint_on_plant(paint, select_heliostats(scenario.plant, use), source=scenario.path or "scenario",
                                 plane_tolerance=plane_tolerance, skip_record_ids=skip,
                                 seen_owners=seen_record_owners(scenario))
    reading = {**ds.reading, **_dropped(ds.skipped)}
    if not isinstance(records_or_paint, PaintDataset):
        reading.update(_known_but_nominal(scenario, ids, reading))
    return on_axis(ds.records, ids), os.path.abspath(ds.root), reading


def _known_but_nominal(scenario: Scenario, ids: list, reading: dict) -> dict:
    """The folder's records of heliostats the plant knows but its calibration left nominal: counted as such
    (``nominal_*``), not among those of heliostats the plant does not know (``unknown_*``); from the reader's
    per-heliostat ``unknown_counts`` (the reader saw only the calibrated heliostats' plant)."""
    calibrated, known = set(ids), set(scenario.plant.field.ids)
    counts = {h: n for h, n in (reading.get("unknown_counts") or {}).items() if h in known and h not in calibrated}
    if not counts:
        return {}
    return {"unknown_heliostats": max(0, reading.get("unknown_heliostats", 0) - len(counts)),
            "unknown_records": max(0, reading.get("unknown_records", 0) - sum(counts.values())),
            "unknown_ids": [h for h in reading.get("unknown_ids", []) if h not in counts],
            "nominal_heliostats": len(counts), "nominal_records": sum(counts.values()),
            "nominal_ids": sorted(counts)[:20]}


def _dropped(skipped: list) -> dict:
    """How many records the reader dropped, grouped by the file field that made them unusable (one key per field:
    the field and the first such record's reason without its values)."""
    by_field: dict = {}
    for s in skipped:
        key = by_field.setdefault(s["field"], [f"{s['field']}: {s['reason'].split(' = ')[0].split(' (')[0]}", 0])
        key[1] += 1
    return {"dropped": len(skipped), "dropped_by_reason": dict(sorted(by_field.values(), key=lambda kv: -kv[1]))}


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
    cal, ids, names = calibration_entry(previous)
    nominal = nominal_kinematics(cal, previous.path, len(ids))
    seen = seen_record_ids(previous)
    # a plant that has stored all it starts from reads only the records it has not seen (most of a folder has been)
    skip = None if needs_seen_records(previous, cal, q_given, settings.false_alarm_rate, settings.window) else \
        np.fromiter(seen, dtype=np.int64, count=len(seen))
    table, source, reading = _records(records_or_paint, previous, ids, settings.plane_tolerance, skip)
    t0 = _time.perf_counter()
    previous, cal, noise = process_noise_source(previous, cal, table, q_given)
    state = filter_state(previous, table, q_given, seen=seen)
    new_rows, seen_idx, counts = split_new(table, seen, state.time)
    skipped = int(reading.get("skipped", 0)) if reading else 0
    counts.update(records=counts["records"] + skipped, seen=counts["seen"] + skipped)  # left out when read
    if reading:
        counts.update(dropped=reading["dropped"], dropped_by_reason=reading["dropped_by_reason"],
                      unknown_heliostats=reading.get("unknown_heliostats", 0),
                      unknown_heliostat_records=reading.get("unknown_records", 0),
                      unknown_heliostat_ids=reading.get("unknown_ids", []),
                      nominal_heliostats=reading.get("nominal_heliostats", 0),
                      nominal_heliostat_records=reading.get("nominal_records", 0),
                      nominal_heliostat_ids=reading.get("nominal_ids", []))
    fit_table = fit_spots(table, settings.fit_focal_spot)
    # validation under the fit's own posterior (the Laplace posterior of those records, without the walk's)
    fit_post = fit_posterior(state, cal, previous.path)
    threshold = threshold_in_force(current_assimilation(previous), cal, settings.false_alarm_rate, settings.window,
                                   nominal, fit_table.subset(seen_idx), fit_post)
    options = AssimilationOptions(threshold=threshold["threshold"], reopen=1e-3 * settings.reopen_mrad,
                                  iterations=int(settings.iterations), robust=bool(settings.robust),
                                  window=int(settings.window),
                                  confirm_threshold=confirm_threshold(float(threshold.get("kappa", 1.0))))
    new = fit_table.subset(new_rows)
    on = (lambda x: x) if torch.device(device).type == "cpu" else (lambda x: to_device(x, device))
    new_state, hist = assimilate(on(nominal), on(new), on(state), options, score_spot=on(table.spot[new_rows]))
    new_state, hist = to_device(new_state, "cpu"), to_device(hist, "cpu")
    seconds = _time.perf_counter() - t0
    learned = updated_learned(previous, cal, ids, new_state, state, threshold, hist)
    plant = with_kinematics(previous.plant, ids, apply_deviations(nominal, new_state.mean, names))
    records = {}
    for j, rid in zip(hist["heliostat"].tolist(), hist["record_id"].tolist()):
        records.setdefault(ids[j], []).append(int(rid))
    report = _report(ids, counts, threshold, hist, new_state, seconds, source)
    report["threshold"]["confirm_threshold"] = options.confirm_threshold
    report["threshold"]["confirm_records"] = options.confirm_records
    report["process_noise"] = {"mrad2_per_day": 1e6 * float(new_state.process_noise), **noise}
    if reading:
        report["reading"] = {k: reading[k] for k in ("files", "parsed", "indexed", "skipped") if k in reading}
    step = provenance_entry("update", source=str(source), records=records, alarms=report["alarms"],
                            settings={f.name: getattr(settings, f.name) for f in fields(UpdateSettings)},
                            threshold=float(threshold["threshold"]))
    scenario = next_scenario(previous, plant, learned=learned, step=step)
    number = int(torch.as_tensor(learned[ASSIMILATION_KEY]["updates"]).reshape(-1)[0])
    # the alarms this update settled, and those still open (age on the plant's own clock, its latest record)
    report["closed_alarms"] = closed_alarms(scenario, update=number)
    report["open_alarms"] = open_alarms(scenario, now=plant_clock(scenario))
    return Update(scenario, report, hist)


def locked_plant_write(output, make, timeout: float | None = None):
    """``make()`` (a workflow's result with a ``scenario``) written to the plant file ``output`` the way a
    scheduled command must: ``output`` locked for the whole read-compute-write (a second command on the same
    plant refuses at once, or waits ``timeout`` [s]), not replaced when another process changed it meanwhile,
    and written atomically (an error leaves the old file as it was). A symlinked plant is updated through its
    target (the link stays a link, and both names share the target's lock). Returns the result."""
    output = os.path.realpath(output)
    with plant_lock(output, timeout=timeout):
        stamp = file_stamp(output)
        result = make()
        check_unchanged(output, stamp)
        write_scenario(result.scenario, output)
    return result


def update_plant_file(scenario_path, paint, output, settings: UpdateSettings = UpdateSettings(), *,
                      device: str = "cpu", timeout: float | None = None) -> Update:
    """:func:`update` from and to files, as a scheduled command runs it (:func:`locked_plant_write`; ``output``
    may be ``scenario_path``: in place)."""
    return locked_plant_write(output, lambda: update(scenario_path, paint, settings, device=device), timeout)
