"""One calibration run: read, validate, split, check properties, fit, evaluate, report.

:func:`run_calibration` is what ``heliotwin calibrate`` does; benchmarks and tests call it directly.
Every heliostat or record that cannot be used is reported with a reason, never dropped silently.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import HeliotwinError
from ..io.paint import load_paint
from . import metrics
from .inputs import MIN_TRAIN
from .methods import get_method
from .model import Calibrated, nominal_model
from ..io.records import RecordTable, normalise_source, prepare_records
from .splits import SPLIT_TYPES, split_records
from .suspicious import check_and_correct


@dataclass
class RunConfig:
    """Options of a calibration run (the CLI's flags)."""

    paint: str
    method: str = "lm"
    split: str = "chrono"
    train: int = 30
    validation: int | None = None
    test: int | None = 30
    heliostats: list | None = None
    min_records: int = 50
    focal_spot: str = "HeliOS"
    seed: int = 0
    plane_tolerance: float = 0.1
    correct_suspicious: bool = True
    progress: bool = False
    method_options: dict = field(default_factory=dict)

    def n_validation(self) -> int:
        """Validation records carved out of ``train``: default 20 % (at least 2 when train >= 8, else 0)."""
        if self.validation is not None:
            return int(self.validation)
        return max(2, int(round(0.2 * self.train))) if self.train >= 8 else 0


def validate_config(cfg: RunConfig) -> None:
    if cfg.split not in SPLIT_TYPES:
        raise HeliotwinError(f"unknown split type {cfg.split!r}; known: {', '.join(SPLIT_TYPES)}")
    get_method(cfg.method)
    normalise_source(cfg.focal_spot)
    if cfg.train < 1:
        raise HeliotwinError(f"--train must be >= 1, got {cfg.train}")
    v = cfg.n_validation()
    if v < 0 or v >= cfg.train:
        raise HeliotwinError(f"--validation must be in [0, train) (validation is carved out of --train {cfg.train}), got {v}")
    if cfg.test is not None and cfg.test < 1:
        raise HeliotwinError(f"--test must be >= 1, got {cfg.test}")
    if cfg.min_records < 0:
        raise HeliotwinError(f"--min-records must be >= 0, got {cfg.min_records}")


def _per_heliostat(values: torch.Tensor, batch: RecordTable, h: int) -> torch.Tensor:
    return values[batch.heliostat_index == h]


def _stats(err: torch.Tensor, miss: torch.Tensor | None = None) -> dict:
    return metrics.summarize(err, miss)


def _median(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.median(xs)) if xs else None


def _mean(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.mean(xs)) if xs else None


def _image_context(ds, plant, all_ids, run_ids) -> dict:
    """What the ``images`` method needs beyond records: flux-image paths, surfaces, targets, sun."""
    from ..field.plant import Surfaces

    srf = plant.field.surfaces
    idx = torch.tensor([all_ids.index(h) for h in run_ids])
    surfaces = Surfaces(control_points=srf.control_points[idx], degree_u=srf.degree_u, degree_v=srf.degree_v,
                        weights=None if srf.weights is None else srf.weights[idx])
    images = {int(r.record_id): r.flux_png for r in ds.records if r.heliostat_id in run_ids and r.flux_png}
    return {"images": images, "surfaces": surfaces, "targets": plant.targets, "sun": plant.sun}


def run_calibration(cfg: RunConfig, dataset=None) -> tuple[dict, Calibrated | None, dict]:
    """Run one calibration.

    Parameters
    ----------
    cfg : RunConfig
    dataset : heliotwin.io.paint.PaintDataset, optional
        Already loaded PAINT folder (every heliostat, with records); read from ``cfg.paint`` otherwise.

    Returns
    -------
    report : dict
        The JSON report (see module :mod:`heliotwin.calibrate.report`).
    model : Calibrated or None
        The calibrated model over the heliostats that were run (None when none could be).
    arrays : dict
        Per-record arrays for the plots (test records: azimuth, elevation, heliostat, nominal and calibrated
        error [mrad]).
    """
    validate_config(cfg)
    t_start = time.perf_counter()
    ds = dataset if dataset is not None else load_paint(cfg.paint)
    plant = ds.plant
    all_ids = list(plant.field.ids)
    if cfg.heliostats:
        unknown = [h for h in cfg.heliostats if h not in all_ids]
        if unknown:
            raise HeliotwinError(f"heliostat(s) {', '.join(unknown)} not in {cfg.paint}; available: {', '.join(all_ids)}")
        wanted = list(dict.fromkeys(cfg.heliostats))
    else:
        wanted = all_ids
    batch_all, skipped_records = prepare_records(plant, ds.records, wanted, focal_spot=cfg.focal_spot,
                                                 plane_tolerance=cfg.plane_tolerance)
    counts = batch_all.counts()
    skipped_heliostats = {}
    run_ids = []
    for h, hid in enumerate(wanted):
        n = int(counts[h])
        if n < max(cfg.min_records, 1):
            skipped_heliostats[hid] = f"too few usable records ({n} < --min-records {max(cfg.min_records, 1)})"
        else:
            run_ids.append(hid)
    heliostat_reports: dict = {hid: {"status": "skipped", "reason": r} for hid, r in skipped_heliostats.items()}
    report = {"config": {k: v for k, v in cfg.__dict__.items() if k not in ("progress",)},
              "skipped_records": skipped_records, "heliostats": heliostat_reports}
    report["config"]["validation"] = cfg.n_validation()
    arrays: dict = {}
    if not run_ids:
        report["overall"] = {"n_heliostats": 0, "median_test_mrad": None, "mean_test_mrad": None,
                             "nominal_median_test_mrad": None, "seconds": time.perf_counter() - t_start,
                             "note": "no heliostat with enough records"}
        return report, None, arrays
    # Re-batch over the heliostats that run (their index = position in run_ids).
    keep = torch.tensor([wanted.index(h) for h in run_ids])
    sel = torch.isin(batch_all.heliostat_index, keep)
    batch = batch_all.subset(sel)
    remap = torch.full((len(wanted),), -1, dtype=torch.long)
    remap[keep] = torch.arange(len(run_ids))
    batch.heliostat_index = remap[batch.heliostat_index]
    batch.heliostat_ids = list(run_ids)
    field_kin = plant.field.kinematics
    nominal_raw = field_kin.index([all_ids.index(h) for h in run_ids])

    tr_idx, va_idx, te_idx, split_info = split_records(batch, cfg.split, cfg.train, cfg.n_validation(), cfg.test, seed=cfg.seed)
    train, val, test = batch.subset(tr_idx), batch.subset(va_idx), batch.subset(te_idx)
    seen = RecordTable.concatenate([train, val])

    if cfg.correct_suspicious:
        nominal, findings = check_and_correct(nominal_raw, run_ids, field_kin, seen)
    else:
        nominal, findings = nominal_raw, {}

    fit = get_method(cfg.method)
    options = dict(cfg.method_options)
    if cfg.method == "images":
        options.update(_image_context(ds, plant, all_ids, run_ids))
    t_fit = time.perf_counter()
    model = fit(nominal, train, val, seed=cfg.seed, progress=cfg.progress, **options)
    fit_seconds = time.perf_counter() - t_fit
    model.corrections = {h: f for h, f in findings.items() if f.get("corrected")}

    nominal_m = nominal_model(run_ids, nominal_raw)
    with torch.no_grad():
        ev = {}
        for name, b in (("train", train), ("validation", val), ("test", test)):
            ev[name] = (model.pointing_error(b), model.miss_distance(b)) if len(b) else (torch.zeros(0), torch.zeros(0))
        nom_test = (nominal_m.pointing_error(test), nominal_m.miss_distance(test)) if len(test) else (torch.zeros(0), torch.zeros(0))
    per_h_seconds = fit_seconds / max(1, len(run_ids))
    names = list(model.names)
    for h, hid in enumerate(run_ids):
        info = split_info[hid]
        rep = {"status": "ok" if bool(model.ok[h]) else "skipped", "split": info}
        if not bool(model.ok[h]):
            rep["reason"] = model.reasons.get(hid, f"too few training records ({info['train']} < {MIN_TRAIN})")
        for name in ("train", "validation", "test"):
            b = {"train": train, "validation": val, "test": test}[name]
            e, m = ev[name]
            rep[name] = _stats(_per_heliostat(e, b, h), _per_heliostat(m, b, h))
        rep["nominal_test"] = _stats(_per_heliostat(nom_test[0], test, h), _per_heliostat(nom_test[1], test, h))
        if rep["status"] != "ok":
            # An uncalibrated heliostat has no calibrated error; do not let nominal numbers pass as one.
            rep["test"] = {k: None for k in rep["test"]}
        rep["mean_test_mrad"] = rep["test"]["mean_mrad"]
        rep["median_test_mrad"] = rep["test"]["median_mrad"]
        rep["nominal_mean_test_mrad"] = rep["nominal_test"]["mean_mrad"]
        rep["seconds"] = per_h_seconds
        if names and bool(model.ok[h]):
            rep["parameters"] = {n: float(model.delta[h, j]) for j, n in enumerate(names)}
        if hid in findings:
            rep["suspicious"] = findings[hid]
        if model.extras.get("per_heliostat", {}).get(hid):
            rep["method_info"] = model.extras["per_heliostat"][hid]
        heliostat_reports[hid] = rep
    ran = [heliostat_reports[h] for h in run_ids if heliostat_reports[h]["status"] == "ok"]
    report["overall"] = {
        "method": cfg.method, "split": cfg.split, "n_heliostats": len(ran),
        "median_test_mrad": _median([r["mean_test_mrad"] for r in ran]),
        "mean_test_mrad": _mean([r["mean_test_mrad"] for r in ran]),
        "median_of_median_test_mrad": _median([r["median_test_mrad"] for r in ran]),
        "nominal_median_test_mrad": _median([r["nominal_mean_test_mrad"] for r in ran]),
        "nominal_mean_test_mrad": _mean([r["nominal_mean_test_mrad"] for r in ran]),
        "median_train_mrad": _median([r["train"]["mean_mrad"] for r in ran]),
        "median_test_miss_m": _median([r["test"].get("median_miss_m") for r in ran]),
        "mean_train_test_distance_rad": _mean([r["split"].get("mean_train_test_distance_rad") for r in ran]),
        "fit_seconds": fit_seconds,
        "seconds": time.perf_counter() - t_start,
        "skipped_heliostats": len(skipped_heliostats) + sum(1 for h in run_ids if heliostat_reports[h]["status"] != "ok"),
        "skipped_records": len(skipped_records),
        "dropped_no_time": int(sum(split_info[h]["dropped_no_time"] for h in run_ids)),
    }
    if model.extras.get("summary"):
        report["overall"]["method_info"] = model.extras["summary"]
    arrays = {"heliostat_ids": run_ids,
              "test_heliostat": test.heliostat_index.numpy(), "test_azimuth": test.sun_azimuth.numpy(),
              "test_elevation": test.sun_elevation.numpy(), "test_error_mrad": ev["test"][0].numpy() * 1e3,
              "test_nominal_mrad": nom_test[0].numpy() * 1e3, "train": train, "validation": val, "test": test,
              "nominal": nominal}
    return report, model, arrays
