"""The calibrate workflow: a scenario and calibration records -> the calibrated scenario and its report.

``heliotwin calibrate`` (:func:`heliotwin.cli.calibrate.cmd_calibrate`) and :func:`heliotwin.api.calibrate`
are both :func:`calibrate` with their own way of taking options and of writing outputs:

* :class:`CalibrationSettings` holds the options, one field per command-line flag (named as its argparse
  ``dest``), with the command line's defaults; :func:`run_config` turns them into the run's
  :class:`~heliotwin.calibrate.protocol.config.RunConfig` (checked: one-line errors before any work).
* :func:`calibrate` loads the records (on the starting scenario's plant), runs the calibration
  (:func:`~heliotwin.calibrate.protocol.pipeline.run_calibration`), optionally the error-vs-training-size
  curve, and returns the calibrated scenario **in memory** (one ``calibrate`` provenance step, appended by
  :func:`heliotwin.io.scenario.next_scenario`) with the report; the caller writes what it wants where it
  wants (the scenario with :func:`heliotwin.io.scenario.write_scenario`, the plots with
  :func:`heliotwin.calibrate.report.write_plots`).
* :func:`calibration_checkpoint`: the checkpoint of a run of these settings (``--resume``).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import torch
import torch.distributed as dist

from ..calibrate import metrics
from ..calibrate.inputs import fit_spots
from ..calibrate.methods.batched import sharded
from ..calibrate.model import Calibrated
from ..calibrate.params import STONE8
from ..calibrate.priors import MIN_HELIOSTATS, plant_prior
from ..calibrate.protocol import pipeline, reduced, selection
from ..calibrate.protocol.archive import PriorArchive
from ..calibrate.protocol.config import (
    EVERY_RECORD,
    RunConfig,
    settings_mode,
    validate_config,
    validation_protocol,
)
from ..calibrate.protocol.suspicious import check_and_correct
from ..calibrate.scenario import calibrated_scenario
from ..calibrate.twinstate import with_alarm_threshold, with_process_noise_choice
from ..distributed import run_spawned
from ..errors import HeliotwinError
from ..io.checkpoint import Checkpoint
from ..io.paint import PaintDataset
from ..io.scenario import Scenario, load_records, load_scenario

__all__ = ["CalibrationSettings", "Calibration", "calibrate", "run_config", "resolved_settings_mode", "resolved_split",
           "calibration_checkpoint", "training_size_curves", "seen_records", "load_paint_records"]


@dataclass(frozen=True)
class CalibrationSettings:
    """The options of a calibration (``heliotwin calibrate``'s flags, same names, same defaults).

    Attributes
    ----------
    method : str
        ``lm``, ``gradient``, ``hybrid``, ``mlp`` or ``images``.
    heliostats : sequence of str or None
        Heliostat ids (None: every heliostat of the records).
    split : str or None
        None (default): ``"current"``, or ``"chrono"`` when ``train`` or ``validation`` is given (a study size
        names a study protocol, as it always did). ``"current"``: the plant as it is now, fitted on every usable
        record of each heliostat, its expected error from validation inside those records
        (:func:`calibrate`); or a study protocol's split type
        (:data:`heliotwin.calibrate.protocol.config.RUN_SPLITS`), whose written plant saw only the training part.
    train, validation, test : int or None
        Study splits: records per heliostat seen by the method (validation included; None: 30), carved out
        of ``train`` for validation (None: 20 % of it, 0 below 8), held out for the test (None: every other
        record). ``current``: ``train`` and ``validation`` must be None, ``test`` is how many of each
        heliostat's latest records the internal validation predicts (None:
        :data:`heliotwin.calibrate.protocol.config.CURRENT_HOLDOUT`).
    min_records : int
        Fewest usable records for the full model. A ``current`` lm run gives a heliostat with fewer the reduced
        model its records support (:func:`with_reduced_models`); study protocols and other methods skip it.
    focal_spot : str
        Centroid source scored on (``HeliOS`` or ``UTIS``).
    seed : int
    plane_tolerance : float
        Largest distance [m] of a focal spot from its target plane.
    keep_suspicious : bool
        Report suspicious property values but never replace them.
    prior, prior_from :
        lm's prior: ``"run"`` or ``"plant"``; ``prior_from`` a PAINT folder of the same plant or a scenario
        holding a prior learned from other heliostats.
    half_life_days : float or None
        lm drift tracking by recency weights [days].
    drift_mrad : float or None
        lm predictive interval: offset drift per component [mrad].
    drift, process_noise, drift_basis :
        lm drift model (``"auto"``: chosen by a current run's internal validation, none in a study protocol;
        ``"none"`` / ``"kalman"``), its process noise [mrad^2/day] or ``"auto"``, and what drifts (``"axes"`` /
        ``"rotation"``).
    settings : str
        ``"auto"``, ``"given"``, ``"cv"`` or ``"stored"`` (:func:`resolved_settings_mode`).
    online_step : int
        ``split="online"``: refit every this many test records.
    curve : bool
        Also run the error-vs-training-size experiment (lm refits) when something was calibrated.
    learn_settings : bool
        Also choose the lm settings, their plant prior and the interval calibration once for this plant, by
        leave-heliostats-out CV on every eligible heliostat of the records' folder, and store them in the
        scenario: later runs ``--prior-from`` it reuse them (``settings="stored"``) without recomputing.
    nproc : int
        Shard the heliostats' fits over this many local gloo processes (:func:`heliotwin.distributed.run_spawned`;
        the same result as one process). Under ``torchrun`` (a process group already initialised by the
        caller), every rank runs the calibration and fits its shard.
    """

    method: str = "lm"
    heliostats: tuple | list | None = None
    split: str | None = None
    train: int | None = None
    validation: int | None = None
    test: int | None = None
    min_records: int = 50
    focal_spot: str = "HeliOS"
    seed: int = 0
    plane_tolerance: float = 0.1
    keep_suspicious: bool = False
    prior: str = "run"
    prior_from: str | os.PathLike | None = None
    half_life_days: float | None = None
    drift_mrad: float | None = None
    drift: str = "auto"
    process_noise: str | float = "auto"
    drift_basis: str = "axes"
    settings: str = "auto"
    online_step: int = 5
    curve: bool = False
    learn_settings: bool = False
    nproc: int = 1


#: ``--train`` of the study splits when not given.
STUDY_TRAIN = 30


def resolved_split(s: "CalibrationSettings") -> str:
    """The run's split: as given, else ``current`` (the plant as it is now) unless a study size (``train``,
    ``validation``) is given, which names the chronological study protocol."""
    if s.split is not None:
        return s.split
    return "chrono" if (s.train is not None or s.validation is not None) else "current"


def _sizes(s: "CalibrationSettings") -> tuple:
    """(train, validation, test) of the run: ``current`` sees every record (``--train``/``--validation`` are
    a one-line error there), the study splits default to :data:`STUDY_TRAIN`."""
    if resolved_split(s) == "current":
        if s.train is not None or s.validation is not None:
            raise HeliotwinError("--train / --validation size the study splits (--split chrono, ...); --split current "
                                 "(the default) fits every record and validates inside them (--test: how many of "
                                 "each heliostat's latest records)")
        return EVERY_RECORD, 0, s.test
    return STUDY_TRAIN if s.train is None else s.train, s.validation, s.test


def _process_noise(value):
    """``process_noise``: ``auto`` or a number >= 0 [mrad^2/day] (one-line error otherwise)."""
    if value is None or str(value).strip().lower() == "auto":
        return "auto"
    try:
        q = float(value)
    except ValueError:
        q = float("nan")
    if not (math.isfinite(q) and q >= 0):
        raise HeliotwinError(f"--process-noise must be 'auto' or a number >= 0 [mrad^2/day], got {value!r}")
    return q


def _lm_options(settings: CalibrationSettings) -> dict:
    """``half_life_days`` / ``drift_mrad`` as lm method options (one-line error for other methods)."""
    opts = {}
    hl, drift = settings.half_life_days, settings.drift_mrad
    if hl is not None:
        if not (math.isfinite(hl) and hl > 0):
            raise HeliotwinError(f"--half-life-days must be a positive number, got {hl}")
        opts["half_life_days"] = hl
    if drift is not None:
        if not (math.isfinite(drift) and drift >= 0):
            raise HeliotwinError(f"--drift-mrad must be >= 0, got {drift}")
        opts["drift"] = 1e-3 * drift
    if opts and settings.method != "lm":
        raise HeliotwinError(f"--half-life-days / --drift-mrad apply to --method lm only, not {settings.method}")
    return opts


def resolved_settings_mode(settings: CalibrationSettings) -> str:
    """``settings.settings`` with ``auto`` resolved (:func:`~heliotwin.calibrate.protocol.config.settings_mode`):
    an lm setting fixed by hand (half-life, interval drift, drift model) keeps the given settings."""
    by_hand = settings.half_life_days is not None or settings.drift_mrad is not None \
        or settings.drift not in ("none", "auto")
    return settings_mode(settings.settings or "given", method=settings.method, prior_from=settings.prior_from,
                         fixed_by_hand=by_hand)


def _path(value):
    return os.fspath(value) if isinstance(value, os.PathLike) else value


def run_config(settings: CalibrationSettings, paint, *, progress: bool = False) -> RunConfig:
    """The checked :class:`~heliotwin.calibrate.protocol.config.RunConfig` of ``settings`` on the PAINT folder
    ``paint`` (one-line :class:`~heliotwin.errors.HeliotwinError` for a bad option); ``progress``: the
    methods' own tqdm bars."""
    s = settings
    train, validation, test = _sizes(s)
    cfg = RunConfig(paint=os.fspath(paint), method=s.method, split=resolved_split(s), train=train,
                    validation=validation, test=test, heliostats=None if s.heliostats is None else list(s.heliostats),
                    min_records=s.min_records, focal_spot=s.focal_spot, seed=s.seed, plane_tolerance=s.plane_tolerance,
                    correct_suspicious=not s.keep_suspicious, progress=progress is True, prior=s.prior,
                    prior_from=_path(s.prior_from), online_step=s.online_step, method_options=_lm_options(s),
                    drift_model="none" if s.drift == "auto" else s.drift,
                    process_noise=_process_noise(s.process_noise), drift_basis=s.drift_basis,
                    settings=resolved_settings_mode(s), learn_settings=bool(s.learn_settings))
    validate_config(cfg)
    return cfg


def calibration_checkpoint(settings: CalibrationSettings, paint, path, *, scenario=None, device: str = "cpu",
                           resume: bool = False, **options) -> Checkpoint:
    """The checkpoint at ``path`` of a calibration of ``settings`` on ``paint``, starting from ``scenario`` (a
    path is one of the run's inputs): :func:`heliotwin.calibrate.protocol.pipeline.calibration_checkpoint`.
    A checkpoint of other settings or inputs is refused (one line) before any work."""
    inputs = [scenario] if isinstance(scenario, (str, os.PathLike)) else []
    return pipeline.calibration_checkpoint(run_config(settings, paint), path, device=device, resume=resume,
                                           inputs=inputs, **options)


@dataclass(frozen=True)
class Calibration:
    """What :func:`calibrate` returns; unpacks as ``scenario, report = calibrate(...)``.

    Attributes
    ----------
    scenario : Scenario or None
        The calibrated scenario, in memory; None when no heliostat could be calibrated.
    report : dict
        The JSON report (:mod:`heliotwin.calibrate.report`).
    model : Calibrated or None
        The calibrated model over the run's heliostats, on the CPU (None when none could run).
    arrays : dict
        Per-record arrays for the plots (:func:`heliotwin.calibrate.report.write_plots`).
    curves : dict or None
        The error-vs-training-size curve (``settings.curve``): label -> [(records, median [mrad])].
    """

    scenario: Scenario | None
    report: dict
    model: Calibrated | None
    arrays: dict
    curves: dict | None = None

    def __iter__(self):
        return iter((self.scenario, self.report))


def seen_records(arrays: dict) -> dict:
    """Heliostat id -> record ids a method saw (training + validation), for the provenance."""
    out: dict = {}
    for name in ("train", "validation"):
        t = arrays.get(name)
        if t is None:
            continue
        for h, rid in zip(t.heliostat_index.tolist(), t.record_id.tolist()):
            out.setdefault(t.heliostat_ids[h], []).append(int(rid))
    return out


def training_size_curves(cfg: RunConfig, dataset: PaintDataset, median_test_mrad) -> dict:
    """Error vs training size from cheap lm refits on the same split rule and test set. Unbagged: the
    curve's shape is what a plant engineer reads, and bagging would make it ~10x slower.

    Returns label -> [(training records, median over heliostats of the mean test error [mrad])]; ``cfg``'s
    own method at its ``train`` is ``median_test_mrad``."""
    sizes = sorted({n for n in (5, 10, 20, 30, 40, 60, 100) if n < cfg.train} | {cfg.train})
    pts = []
    for n in sizes:
        r, _, _ = pipeline.run_calibration(replace(cfg, method="lm", train=n, validation=None, progress=False,
                                                   method_options={"bags": 0}), dataset)
        pts.append((n, r["overall"]["median_of_mean_test_mrad"]))
    return {"lm (refits, unbagged)": pts, cfg.method: [(cfg.train, median_test_mrad)]}


def load_paint_records(paint, scenario=None, plane_tolerance: float = 0.1) -> tuple:
    """The records of the PAINT folder ``paint`` on ``scenario``'s plant (a Scenario, a path or None: the
    folder's nominal plant), :func:`heliotwin.io.scenario.load_records`; returns (dataset, Scenario or None).
    A missing folder is a one-line error."""
    if not os.path.isdir(paint):
        raise HeliotwinError(f"{paint}: PAINT folder not found")
    return load_records(paint, scenario, plane_tolerance=plane_tolerance)


def _calibrate_shard(job: dict, group):
    """One rank of a ``nproc`` calibration: the whole run, fitting this rank's shard of the heliostats."""
    with sharded(group):
        return pipeline.run_calibration(job["cfg"], job["dataset"])


def _run(cfg: RunConfig, dataset: PaintDataset, nproc: int, device: str, progress, checkpoint) -> tuple:
    """One pipeline run of ``cfg`` (sharded over ``nproc`` local processes, or the caller's process group)."""
    if nproc > 1:
        if not str(device).startswith("cpu"):
            raise HeliotwinError("--nproc: the local process group is gloo on CPU; use --device cpu with --nproc")
        return run_spawned(_calibrate_shard, {"cfg": replace(cfg, progress=False), "dataset": dataset}, nproc)
    group = dist.group.WORLD if dist.is_available() and dist.is_initialized() else None  # e.g. torchrun
    with sharded(group):
        return pipeline.run_calibration(cfg, dataset, device=device, checkpoint=checkpoint,
                                        progress=progress if callable(progress) else None)


#: Heliostats the internal validation of a ``current`` run scores at most (a seeded sample of the eligible ones):
#: the median and 95th percentile of 200 heliostats' errors are known to a few percent, and a plant of 2,000
#: then pays a tenth of a second fit for its error estimate, not a whole one.
VALIDATION_HELIOSTATS = 200


def validation_sample(cfg: RunConfig, dataset: PaintDataset) -> list:
    """The heliostats a ``current`` run's internal validation scores: every one asked for that has at least
    ``cfg.min_records`` usable records, or a seeded sample (``cfg.seed``) of :data:`VALIDATION_HELIOSTATS` of
    them, in plant order."""
    ids = list(cfg.heliostats or dataset.plant.field.ids)
    counts = dataset.records.for_heliostats(ids).counts().tolist()
    eligible = [h for h, n in zip(ids, counts) if n >= max(1, cfg.min_records)]
    if len(eligible) <= VALIDATION_HELIOSTATS:
        return eligible or ids
    pick = np.random.default_rng(cfg.seed).choice(len(eligible), VALIDATION_HELIOSTATS, replace=False)
    return [eligible[i] for i in sorted(pick.tolist())]


#: Per-heliostat keys of a study run's report that describe its held-out records (the expected error).
_HELD_OUT_KEYS = ("test", "nominal_test", "mean_test_mrad", "median_test_mrad", "nominal_mean_test_mrad",
                  "interval_90_coverage", "expected_test_mrad", "interval_90_mrad")


def with_expected_error(report: dict, validation: dict, interval: dict | None = None) -> dict:
    """The report of a ``current`` run (every record fitted, nothing held out) with the expected error of the
    plant it wrote, from the validation run inside its records (``validation``: the report of the same
    calibration on each heliostat's earlier records, tested on its latest ones). The headline keys
    (``overall.median_of_mean_test_mrad``, each heliostat's ``mean_test_mrad``) are that expected error;
    ``expected_error`` says how it was measured; ``written_plant`` what the plant saw. ``interval``: the
    interval calibrated on those held-out records (``selection.choose_interval``'s ``coverage`` and
    ``uncalibrated_coverage``), the one the plant carries; without it the validation's own coverage."""
    v_overall = validation.get("overall") or {}
    holdout = (validation.get("config") or {}).get("test")
    out = dict(report)
    heliostats = {}
    for hid, entry in report["heliostats"].items():
        v = validation["heliostats"].get(hid) or {}
        held = {k: v[k] for k in _HELD_OUT_KEYS if k in v} if v.get("status") == "ok" else {}
        heliostats[hid] = {**entry, **held, "validation_split": v.get("split")}
    out["heliostats"] = heliostats
    mine = report.get("overall") or {}
    keep = ("n_heliostats", "fit_seconds", "seconds", "skipped_heliostats", "skipped_records",
            "median_of_mean_train_mrad", "method_info", "dropped_no_time")
    out["overall"] = {**{k: v for k, v in v_overall.items() if k not in keep},
                      **{k: mine[k] for k in keep if k in mine}, "split": "current",
                      "validation_seconds": v_overall.get("seconds")}
    out["test_records"] = validation.get("test_records", [])
    out["expected_error"] = {
        "protocol": f"validation inside the records: each heliostat's latest {holdout} records (chronological) "
                    "predicted by the same calibration fitted on its earlier records",
        "holdout_records": holdout, "median_of_mean_mrad": v_overall.get("median_of_mean_test_mrad"),
        "heliostats": f"{v_overall.get('n_heliostats')} of {mine.get('n_heliostats')} (at most "
                      f"{VALIDATION_HELIOSTATS}, a seeded sample)",
        "p95_of_mean_mrad": _quantile([e.get("mean_test_mrad") for e in heliostats.values()], 0.95),
        "interval_90_coverage": v_overall.get("interval_90_coverage"),
        "heliostats_validated": v_overall.get("n_heliostats")}
    if interval is not None:
        out["expected_error"].update(interval_90_coverage=interval["coverage"],
                                     interval_90_coverage_uncalibrated=interval["uncalibrated_coverage"])
        out["overall"]["interval_90_coverage"] = interval["coverage"]
    fitted = sum(int((e.get("split") or {}).get("train", 0)) for e in report["heliostats"].values()
                 if e.get("status") == "ok")
    out["written_plant"] = {"records": "every usable record of each calibrated heliostat", "records_fitted": fitted}
    return out


def _quantile(values, q: float):
    xs = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    if not xs:
        return None
    return float(np.quantile(np.asarray(xs), q))


def _settings_to_choose(cfg: RunConfig) -> bool:
    """Whether a ``current`` run chooses lm's bagging and drift model by its internal validation
    (:func:`heliotwin.calibrate.protocol.selection.choose_current`): lm with the given settings (a settings CV or a
    stored choice chooses among its own candidates), bags and drift model not fixed by the caller. A
    ``--learn-settings`` run chooses so too: what it learns is stored for later runs, and the plant it writes
    is fitted as its own validation says."""
    return cfg.method == "lm" and cfg.settings == "given" and "bags" not in cfg.method_options \
        and cfg.drift_model == "none"


def calibrate(scenario, records_or_paint, settings: CalibrationSettings = CalibrationSettings(), *,
              device: str = "cpu", progress: bool | Callable = False, checkpoint: Checkpoint | None = None,
              stage: Callable[[str], None] | None = None) -> Calibration:
    """Calibrate the kinematics of ``scenario``'s plant from calibration records.

    Parameters
    ----------
    scenario : Scenario, str, os.PathLike or None
        The plant to start from (a scenario file's path is read); None: the PAINT folder's nominal plant.
    records_or_paint : str, os.PathLike or heliotwin.io.paint.PaintDataset
        The PAINT folder (its records are put on the scenario's plant,
        :func:`heliotwin.io.scenario.load_records`), or its records already loaded on that plant.
    settings : CalibrationSettings
    device : str
        Where to compute (``"cpu"``, ``"cuda"``, ``"auto"``); the model comes back on the CPU.
    progress : bool or callable
        tqdm bars, or ``progress(step_name, index, total)`` before each step of the run.
    checkpoint : heliotwin.io.checkpoint.Checkpoint, optional
        From :func:`calibration_checkpoint`; the caller removes it once its outputs are written.
    stage : callable, optional
        ``stage(text)`` names each stage reached (reading, calibrating, training-size curve).

    Returns
    -------
    Calibration
        ``scenario, report = calibrate(...)``; also ``model``, ``arrays`` (plots) and ``curves``.
    """
    stage = stage or (lambda text: None)
    paint = records_or_paint.root if isinstance(records_or_paint, PaintDataset) else os.fspath(records_or_paint)
    cfg = run_config(settings, paint, progress=progress)
    if isinstance(records_or_paint, PaintDataset):
        dataset = records_or_paint
        previous = load_scenario(scenario) if isinstance(scenario, (str, os.PathLike)) else scenario
    else:
        stage(f"reading {paint}")
        dataset, previous = load_paint_records(paint, scenario, cfg.plane_tolerance)
    validation, study_cfg, choice = None, cfg, None
    if cfg.split == "current":
        study_cfg = replace(validation_protocol(cfg), learn_settings=False,
                            heliostats=validation_sample(cfg, dataset))
        stage(f"validating inside the records ({cfg.method}): each heliostat's latest {study_cfg.test} records "
              f"predicted from its earlier ones ({len(study_cfg.heliostats)} heliostats)")
        if _settings_to_choose(cfg):  # bagged or not, a random walk or not: the records decide
            chosen, validation, choice = selection.choose_current(
                study_cfg, dataset, runner=lambda c, d: _run(c, d, settings.nproc, device, progress, None),
                drift=settings.drift == "auto" and "half_life_days" not in cfg.method_options, log=stage)
            cfg = replace(cfg, method_options=chosen.method_options, drift_model=chosen.drift_model,
                          process_noise=chosen.process_noise)
        else:
            validation = _run(study_cfg, dataset, settings.nproc, device, progress, None)
        stage(f"current plant: fitting ({cfg.method}) on every record on {device}")
    else:
        stage(f"study run: calibrating ({cfg.method}, {cfg.split} split) on {device}")
    report, model, arrays = _run(cfg, dataset, settings.nproc, device, progress, checkpoint)
    seen = seen_records(arrays)  # what the written plant saw (the update treats every other record as new)
    if validation is not None:
        report = with_expected_error(report, validation[0], (choice or {}).get("interval"))
        arrays = validation[2]
        if choice is not None:
            report["current_settings_choice"] = choice
    else:
        report["written_plant"] = {"records": f"the training part of the {cfg.split} split only",
                                   "note": "a study protocol: the plant written saw only its training records; "
                                           "--split current (the default) fits every record"}
    full_ids = [] if model is None else [h for h, ok in zip(model.heliostat_ids, model.ok.tolist()) if ok]
    if cfg.split == "current" and cfg.method == "lm":
        stage("reduced models: the heliostats with fewer than --min-records records (the rule chosen by validation "
              "on the fully calibrated ones)")
        model, extra_seen = with_reduced_models(cfg, dataset, model, report)
        seen.update(extra_seen)
    with_headline(report)
    if model is None or not bool(model.ok.any()):
        return Calibration(None, report, model, arrays)
    curves = None
    if settings.curve:
        stage("training-size curve (lm refits)")
        curves = training_size_curves(study_cfg, dataset, report["overall"]["median_of_mean_test_mrad"])
    # The run's settings, method options included (half-life, drift: they shape the result).
    new = calibrated_scenario(dataset.plant, model, previous=previous, focal_spot=cfg.focal_spot,
                              records=seen, settings=dict(report["config"]),
                              source=os.path.abspath(paint), settings_choice=report.get("settings_choice"),
                              coverage=run_coverage(report, model, dataset, cfg))
    # without a drift model, the update's random walk is chosen here, where the records the fit saw are at hand
    # (an update is often given only the new ones)
    # (both chosen on the fully calibrated heliostats' records: a reduced heliostat's few records cannot tell a
    # walk from noise, and their thresholds stay those of the plant)
    chosen_on = _rows_of(dataset.records, full_ids)
    new, choice = with_process_noise_choice(new, chosen_on)
    if choice is not None:
        report["update_process_noise"] = choice
    # the updates' step-alarm threshold too: its leave-one-out residuals need every record the fit saw
    new, threshold = with_alarm_threshold(new, chosen_on)
    if threshold is not None:
        report["update_alarm_threshold"] = threshold
    return Calibration(new, report, model, arrays, curves)


def _rows_of(records, ids):
    """The rows of ``records`` on the heliostats ``ids`` (same heliostat axis)."""
    keep = torch.tensor([records.heliostat_ids.index(h) for h in ids if h in records.heliostat_ids],
                        dtype=torch.long, device=records.heliostat_index.device)
    return records.subset(torch.isin(records.heliostat_index, keep))


def with_reduced_models(cfg: RunConfig, dataset: PaintDataset, model: Calibrated | None, report: dict) -> tuple:
    """The heliostats a ``current`` lm run left out for having fewer than ``--min-records`` usable records, each
    with the reduced model its records support (:mod:`heliotwin.calibrate.protocol.reduced`: the rule validated on
    the fully calibrated heliostats, the plant prior learned from them); only a heliostat without a usable record
    (or below the rule's first step) stays nominal. Updates ``report`` in place (their entries, ``reduced``);
    returns (the model over every calibrated heliostat, plant order; {heliostat id: record ids fitted})."""
    wanted = list(cfg.heliostats or dataset.plant.field.ids)
    ran = set(model.heliostat_ids) if model is not None else set()
    left = [h for h in wanted if h not in ran]
    if not left:
        return model, {}
    ok_rows = [] if model is None else model.ok.nonzero().flatten().tolist()
    full_ids = [model.heliostat_ids[i] for i in ok_rows]
    records = dataset.records.for_heliostats(full_ids).with_focal_spot(cfg.focal_spot)
    prior, rule, noise = None, None, NOISE_DEFAULT
    if full_ids:
        kin = model.nominal.index(ok_rows)  # property corrections applied, as the full fits saw them
        archive = PriorArchive.fit(kin, records, min_records=1)
        if len(full_ids) >= MIN_HELIOSTATS:
            prior = plant_prior(archive.deviations, STONE8, full_ids)
        rule = reduced.choose_rule(kin, records, archive.deviations, cfg.min_records, cfg.seed, prior)
        noise = reduced.plant_noise(kin, fit_spots(records), archive.deviations)
    else:
        rule = reduced.Rule(((1, "axis offsets"),), False, {"protocol": "not validated: no fully calibrated heliostat"})
    mine = dataset.records.for_heliostats(left).with_focal_spot(cfg.focal_spot)
    all_ids = list(dataset.plant.field.ids)
    kin_left = dataset.plant.field.kinematics.index([all_ids.index(h) for h in left])
    findings = {}
    if cfg.correct_suspicious:  # as the full run checks its heliostats (a wrong actuator value is tens of mrad)
        fallback = None if prior is None else (prior.mean, prior.sigma)
        kin_left, findings = check_and_correct(kin_left, left, dataset.plant.field.kinematics, mine,
                                               fallback_prior=fallback)
    small, info = reduced.fit_reduced(kin_left, mine, rule, prior, noise)
    small.corrections = {h: f for h, f in findings.items() if f.get("corrected")}
    heliostats = _reduced_entries(small, mine, info, rule, cfg)
    held = _reduced_held_out(kin_left, mine, rule, prior, noise)
    for hid, entry in heliostats.items():
        if hid in held:
            entry["held_out"] = held[hid]
    for hid, found in findings.items():
        heliostats[hid]["suspicious"] = found
    report["heliostats"].update(heliostats)
    nominal = [h for h in left if not heliostats[h]["status"] == "ok"]
    scored = [v for v in held.values() if v.get("mean_mrad") is not None]
    report["reduced"] = {
        "rule": rule.json(), "min_records": cfg.min_records,
        "prior": ("plant prior of the fully calibrated heliostats" if prior is not None else "nominal prior"),
        "heliostats": {h: info[h] for h in left}, "calibrated": [h for h in left if h not in nominal],
        "nominal": nominal,
        "held_out": {"protocol": "each reduced heliostat's latest records (a third of them, at most "
                                 f"{reduced.HOLDOUT}) predicted by the rule's model fitted on its earlier ones",
                     "heliostats": len(scored),
                     "median_mrad": _quantile([v["mean_mrad"] for v in scored], 0.5),
                     "nominal_median_mrad": _quantile([v["nominal_mean_mrad"] for v in scored], 0.5),
                     "better_than_nominal": sum(1 for v in scored if v["mean_mrad"] < v["nominal_mean_mrad"])}}
    combined = reduced.merged(model, small, [h for h in all_ids if h in ran or h in set(left)])
    fitted = {h: [int(r) for r in mine.record_id[mine.heliostat_index == i].tolist()]
              for i, h in enumerate(left) if heliostats[h]["status"] == "ok"}
    return combined, fitted


#: Record noise per component [rad] of a reduced fit when no fully calibrated heliostat gives the plant's.
NOISE_DEFAULT = 1e-3


def _reduced_entries(small: Calibrated, records, info: dict, rule, cfg: RunConfig) -> dict:
    """Report entries of the reduced heliostats: the set fitted, the Laplace expected error over their own
    records' sun positions (``mean_test_mrad``: what the headline counts), the nominal error on those records."""
    err = small.pointing_error(records).double()
    nom = metrics.pointing_error(small.nominal, records).double()
    pred, _ = pipeline.record_intervals(small, records, err, cfg.seed)
    h = len(small.heliostat_ids)
    hidx = records.heliostat_index

    def mean(v):
        return metrics.per_heliostat_mean(v, hidx, h).tolist()

    fit_m, nom_m = mean(err), mean(nom)
    exp_m = mean(pred["expected"].to(err)) if pred is not None else [None] * h
    up_m = mean(pred["upper"].to(err)) if pred is not None else [None] * h
    out = {}
    for i, hid in enumerate(small.heliostat_ids):
        n = info[hid]["records"]
        split = {"n_records": n, "train": n if bool(small.ok[i]) else 0, "validation": 0, "test": 0,
                 "dropped_no_time": 0}
        if not bool(small.ok[i]):
            least = rule.fewest
            out[hid] = {"status": "nominal", "split": split, "model": "nominal",
                        "reason": ("no usable record" if n == 0 else f"too few usable records ({n}) for any model "
                                   f"the validation supports (fewest {least})"),
                        "nominal_records": n}
            continue
        finite = math.isfinite(nom_m[i])
        out[hid] = {"status": "ok", "split": split, "model": f"reduced: {info[hid]['parameters']}",
                    "reason": f"{n} usable record(s) < --min-records {cfg.min_records}: reduced model, "
                              f"{reduced.DESCRIPTIONS[info[hid]['parameters']]}",
                    "mean_test_mrad": 1e3 * exp_m[i] if exp_m[i] is not None else None,
                    "expected_test_mrad": 1e3 * exp_m[i] if exp_m[i] is not None else None,
                    "interval_90_mrad": [0.0, 1e3 * up_m[i]] if up_m[i] is not None else None,
                    "expected_error_source": "Laplace posterior of the reduced fit (interval drift chosen on the "
                                             "validation's held-out records)",
                    "train": {"mean_mrad": 1e3 * fit_m[i] if finite else None},
                    "nominal_mean_test_mrad": 1e3 * nom_m[i] if finite else None,
                    "nominal_mean_records_mrad": 1e3 * nom_m[i] if finite else None,
                    "parameters": {p: float(small.delta[i, j]) for j, p in enumerate(STONE8)}}
    return out


def _reduced_held_out(nominal, records, rule, prior, noise) -> dict:
    """Held-out check on the reduced heliostats themselves (evidence, never used to choose anything): each one's
    latest third of its records (at most :data:`reduced.HOLDOUT`, at least one; heliostats with >= 3 records)
    predicted by the rule's model fitted on its earlier ones. Heliostat id -> mean errors [mrad]."""
    counts = records.counts().cpu()
    k = torch.clamp(counts // 3, 1, reduced.HOLDOUT)
    rank = reduced.rank_from_latest(records).cpu()
    scored = counts >= 3
    row_h = records.heliostat_index.cpu()
    test_rows = (rank < k[row_h]) & scored[row_h]
    train = records.subset((~test_rows & scored[row_h]).to(records.heliostat_index.device))
    test = records.subset(test_rows.to(records.heliostat_index.device))
    if len(test) == 0:
        return {}
    model, info = reduced.fit_reduced(nominal, train, rule, prior, noise)
    err = metrics.per_heliostat_mean(model.pointing_error(test).double(), test.heliostat_index, len(counts)).tolist()
    nom = metrics.per_heliostat_mean(metrics.pointing_error(nominal, test).double(), test.heliostat_index,
                                     len(counts)).tolist()
    out = {}
    for i, hid in enumerate(records.heliostat_ids):
        if bool(scored[i]) and bool(model.ok[i]) and math.isfinite(err[i]):
            out[hid] = {"records": int(k[i]), "fitted_on": int(counts[i] - k[i]), "parameters": info[hid]["parameters"],
                        "mean_mrad": 1e3 * err[i], "nominal_mean_mrad": 1e3 * nom[i]}
    return out


def with_headline(report: dict) -> dict:
    """``report["headline"]``: calibrated N of M heliostats, the expected error's median and p95 over every
    calibrated one (full: the validation inside the records; reduced: their Laplace posterior), the nominal
    ones named with why. Also the line that says it (``text``)."""
    entries = report.get("heliostats") or {}
    ok = {h: e for h, e in entries.items() if e.get("status") == "ok"}
    errors = [e.get("mean_test_mrad") for e in ok.values()]
    n_reduced = sum(1 for e in ok.values() if str(e.get("model", "")).startswith("reduced"))
    nominal = {h: e.get("reason", "") for h, e in entries.items() if e.get("status") != "ok"}
    med, p95 = _quantile(errors, 0.5), _quantile(errors, 0.95)
    least = ((report.get("reduced") or {}).get("rule") or {}).get("steps")
    first = next((n for n, s in least if s != "nominal"), None) if least else None
    text = (f"calibrated {len(ok)} of {len(entries)} heliostats ({len(ok) - n_reduced} full model, {n_reduced} "
            f"reduced); expected error {_fmt(med)} mrad median, {_fmt(p95)} p95 over them")
    if nominal:
        least = first if first else (report.get("config") or {}).get("min_records")
        why = ("no usable record" if least == 1 else f"fewer than {least} usable records") if least else \
            "not calibrated"
        text += f"; {nominal_line(list(nominal), why)}"
    report["headline"] = {"calibrated": len(ok), "heliostats": len(entries), "reduced": n_reduced,
                          "full": len(ok) - n_reduced, "expected_median_mrad": med, "expected_p95_mrad": p95,
                          "nominal": list(nominal), "nominal_reasons": nominal, "text": text}
    return report


def nominal_line(ids: list, why: str, limit: int = 12) -> str:
    """``"3 heliostats nominal: fewer than 1 usable records: AA12, AB01, ..."`` (at most ``limit`` named)."""
    shown = ", ".join(ids[:limit]) + (f", ... ({len(ids) - limit} more)" if len(ids) > limit else "")
    return f"{len(ids)} heliostat{'s' if len(ids) != 1 else ''} nominal: {why}: {shown}"


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.2f}"


def run_coverage(report: dict, model: Calibrated, dataset: PaintDataset, cfg: RunConfig) -> dict:
    """What the run did with every heliostat, for the scenario (:func:`heliotwin.calibrate.scenario.
    calibration_state`): each calibrated one's expected error, the reduced ones' parameter set, the nominal ones
    with why, and the calibrated model's residual on every usable record of its heliostats."""
    entries = report.get("heliostats") or {}
    red = report.get("reduced") or {}
    ok = [h for h, o in zip(model.heliostat_ids, model.ok.tolist()) if o]
    records = dataset.records.for_heliostats(model.heliostat_ids).with_focal_spot(cfg.focal_spot)
    records = records.subset(model.ok.to(records.heliostat_index.device)[records.heliostat_index])
    err = model.pointing_error(records).double().cpu() if len(records) else torch.zeros(0, dtype=torch.float64)
    t = records.time.double().cpu() if records.time is not None else torch.full((len(records),), float("nan"))
    return {"expected_error_mrad": {h: entries.get(h, {}).get("mean_test_mrad") for h in ok},
            "reduced": {h: v["parameters"] for h, v in (red.get("heliostats") or {}).items() if h in set(ok)},
            "nominal": (report.get("headline") or {}).get("nominal_reasons") or {},
            "min_records": cfg.min_records, "rule": (red.get("rule") or {}).get("rule"),
            "residuals": {"record_id": records.record_id.cpu().tolist(),
                          "heliostat": [records.heliostat_ids[i] for i in records.heliostat_index.cpu().tolist()],
                          "time": t.tolist(), "error_mrad": (1e3 * err).tolist()}}
