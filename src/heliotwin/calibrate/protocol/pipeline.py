"""One calibration run as a pipeline of named steps (:data:`STEPS`).

:func:`run_calibration` is what ``heliotwin calibrate`` does; benchmarks and tests call it directly. It
runs, in order, on one :class:`Run` state: ``select`` (heliostats asked for), ``prepare`` (validated
records; heliostats with too few are skipped), ``rebatch`` (the run's heliostat axis), ``split``
(train/validation/test), ``choose_settings`` (``--settings cv|stored``), ``learn_prior`` (a plant prior
from other heliostats, when asked for), ``check_properties`` (suspicious property values, corrected where
the training records support it), ``fit`` (the
method), ``evaluate`` (pointing error and miss distance of calibrated
and nominal model), ``online_refit`` (``--split online``: test errors of refits as records arrive),
``predict_intervals`` (predictive error and its 90 % interval per test record, for
methods with a posterior), ``report_heliostats``, ``report_overall`` and ``plot_arrays``. Every heliostat or
record that cannot be used is reported with a reason, never dropped silently.

Devices: ``run_calibration(..., device="cuda")`` moves the plant and the record table there (the methods follow
the device of their inputs) and hands the model and the plot arrays back on the CPU. Progress: a tqdm bar
over the steps, titled ``calibrate <method>`` with the step's name, plus the methods' own loop bars
(``cfg.progress``; or a callable ``progress(step, index, total)``). Checkpoints: under a
:class:`~heliotwin.io.checkpoint.Checkpoint` (:func:`calibration_checkpoint`) every fit loop of the run
saves its state and a resumed run restores it (:mod:`.fitloop`).

Report keys mean one thing each: per heliostat, ``mean_test_mrad``/``median_test_mrad`` are the mean and
median over its test records; over the run, ``median_of_mean_test_mrad`` is the median over heliostats of
those per-heliostat means (the headline figure), ``median_of_median_test_mrad`` the median of the medians.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm.auto import tqdm

from ...devices import resolve_device, to_device
from ...errors import HeliotwinError
from ...field.plant import Kinematics, Surfaces
from ...io import checkpoint as _checkpoint
from ...io.paint import load_paint
from ...io.records import RecordTable
from .. import metrics
from ..drift import predicted_covariance
from ..inputs import MIN_TRAIN
from ..methods import get_method
from ..metrics import record_jacobian
from ..model import Calibrated, nominal_model
from ..uncertainty import predictive
from .archive import PriorArchive, load_prior_source, reference_kinematics, resolve_prior
from .config import RunConfig, validate_config
from .online import online_errors, online_split
from .selection import choose_for_run, stored_choice
from .splits import split_records
from .suspicious import check_and_correct


def _median(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.median(xs)) if xs else None


def _mean(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.mean(xs)) if xs else None


@dataclass
class Run:
    """State of one calibration run, filled in by the steps of :data:`STEPS` (each sets what it names)."""

    cfg: RunConfig
    dataset: object = None
    t_start: float = field(default_factory=time.perf_counter)
    stop: bool = False
    report: dict = field(default_factory=dict)
    arrays: dict = field(default_factory=dict)
    wanted: list = field(default_factory=list)
    run_ids: list = field(default_factory=list)
    batch_all: RecordTable | None = None
    skipped_records: list = field(default_factory=list)
    skipped_heliostats: dict = field(default_factory=dict)
    batch: RecordTable | None = None
    nominal_raw: object = None
    nominal: object = None
    findings: dict = field(default_factory=dict)
    train: RecordTable | None = None
    validation: RecordTable | None = None
    test: RecordTable | None = None
    #: Indices of the test records into ``batch`` (the online protocol refits on the records before them).
    test_rows: torch.Tensor | None = None
    split_info: dict = field(default_factory=dict)
    model: Calibrated | None = None
    fit_seconds: float = 0.0
    errors: dict = field(default_factory=dict)
    plant_prior: object = None
    #: ``cfg.prior_from`` as given: ``choose_settings`` may replace the config by one without it, but the
    #: prior's plant still judges the run's property values (``check_properties``).
    prior_source: object = None
    intervals: dict = field(default_factory=dict)
    interval_inputs: dict = field(default_factory=dict)
    device: str = "cpu"

    @property
    def parts(self) -> dict:
        return {"train": self.train, "validation": self.validation, "test": self.test}


def select(run: Run) -> None:
    """The heliostats asked for (``--heliostats``, default all); an unknown id is a one-line error."""
    cfg = run.cfg
    run.prior_source = cfg.prior_from
    if run.dataset is None:
        run.dataset = load_paint(cfg.paint, plane_tolerance=cfg.plane_tolerance)
    if run.device != "cpu":
        run.dataset = to_device(run.dataset, run.device)
    all_ids = list(run.dataset.plant.field.ids)
    if cfg.heliostats:
        unknown = [h for h in cfg.heliostats if h not in all_ids]
        if unknown:
            raise HeliotwinError(f"heliostat(s) {', '.join(unknown)} not in {cfg.paint}; "
                                 f"available: {', '.join(all_ids)}")
        run.wanted = list(dict.fromkeys(cfg.heliostats))
    else:
        run.wanted = all_ids


def prepare(run: Run) -> None:
    """Validated records of the wanted heliostats; heliostats with fewer than ``--min-records`` are skipped."""
    cfg = run.cfg
    # The dataset's record table already judged every record (with the tolerance it was loaded with).
    run.batch_all = run.dataset.records.for_heliostats(run.wanted).with_focal_spot(cfg.focal_spot)
    run.skipped_records = [s for s in run.dataset.skipped if s["heliostat_id"] in run.wanted]
    counts = run.batch_all.counts()
    need = max(cfg.min_records, 1)
    for h, hid in enumerate(run.wanted):
        if int(counts[h]) < need:
            run.skipped_heliostats[hid] = f"too few usable records ({int(counts[h])} < --min-records {need})"
        else:
            run.run_ids.append(hid)
    run.report = {"config": _config_report(cfg, run.device), "skipped_records": run.skipped_records,
                  "heliostats": {hid: {"status": "skipped", "reason": r} for hid, r in run.skipped_heliostats.items()}}
    if not run.run_ids:
        run.report["overall"] = {"n_heliostats": 0, "median_of_mean_test_mrad": None, "mean_of_mean_test_mrad": None,
                                 "nominal_median_of_mean_test_mrad": None, "note": "no heliostat with enough records",
                                 "seconds": time.perf_counter() - run.t_start}
        run.stop = True


def _config_report(cfg: RunConfig, device) -> dict:
    config = {k: v for k, v in cfg.__dict__.items() if k not in ("progress",)}
    config["paint"] = os.fspath(cfg.paint)
    pf = cfg.prior_from
    config["prior_from"] = pf if pf is None or isinstance(pf, str) else (getattr(pf, "source", "") or type(pf).__name__)
    config["validation"] = cfg.n_validation()
    config["device"] = device
    return config


def rebatch(run: Run) -> None:
    """Records and nominal kinematics over the heliostats that run (heliostat index = position in run_ids)."""
    dev = run.batch_all.heliostat_index.device
    keep = torch.tensor([run.wanted.index(h) for h in run.run_ids], device=dev)
    batch = run.batch_all.subset(torch.isin(run.batch_all.heliostat_index, keep))
    remap = torch.full((len(run.wanted),), -1, dtype=torch.long, device=dev)
    remap[keep] = torch.arange(len(run.run_ids), device=dev)
    batch.heliostat_index = remap[batch.heliostat_index]
    batch.heliostat_ids = list(run.run_ids)
    run.batch = batch
    all_ids = list(run.dataset.plant.field.ids)
    run.nominal_raw = run.dataset.plant.field.kinematics.index([all_ids.index(h) for h in run.run_ids])


def split(run: Run) -> None:
    """Train/validation/test records per heliostat (validation carved out of ``--train``)."""
    cfg = run.cfg
    if cfg.split == "online":
        tr, va, te, run.split_info = online_split(run.batch, cfg.train, cfg.test)
    else:
        tr, va, te, run.split_info = split_records(run.batch, cfg.split, cfg.train, cfg.n_validation(), cfg.test,
                                                   seed=cfg.seed)
    run.train, run.validation, run.test = run.batch.subset(tr), run.batch.subset(va), run.batch.subset(te)
    run.test_rows = te


def check_properties(run: Run) -> None:
    """Suspicious property values, corrected where the training + validation records support it.

    The field medians the values are judged against come from every heliostat of the run's plant and, with
    ``prior_from``, of the prior's plant too (:func:`~heliotwin.calibrate.archive.reference_kinematics`):
    a run on a folder of a few heliostats would otherwise have no field to compare with. For the same reason
    the run's plant prior (``learn_prior`` runs first) judges a correction when the run's own heliostats are
    too few for a field prior.
    """
    if run.cfg.correct_suspicious:
        seen = RecordTable.concatenate([run.train, run.validation])
        field_kin = run.dataset.plant.field.kinematics
        _, extra = reference_kinematics(run.prior_source, skip=run.dataset.plant.field.ids)
        if extra is not None:
            field_kin = Kinematics.concatenate([field_kin, extra.to(device=field_kin.initial_angle.device)])
        pp = run.plant_prior
        fallback = None if pp is None else (pp.mean, pp.sigma)
        run.nominal, run.findings = check_and_correct(run.nominal_raw, run.run_ids, field_kin, seen,
                                                      fallback_prior=fallback)
    else:
        run.nominal, run.findings = run.nominal_raw, {}


def choose_settings(run: Run) -> None:
    """``--settings cv``: replace the run's lm settings by those leave-heliostats-out CV chooses on the
    ``--prior-from`` folder (:func:`~heliotwin.calibrate.selection.choose_for_run`); ``--settings stored``:
    by the choice stored in the ``--prior-from`` scenario where it applies
    (:func:`~heliotwin.calibrate.selection.stored_choice`). The report keeps the choice (``settings_choice``)
    and ``config`` shows the settings that ran. The CV scores every candidate with :func:`run_calibration`,
    handed down as its ``runner``."""
    cfg = run.cfg
    if cfg.settings not in ("cv", "stored"):
        return
    if cfg.settings == "stored":
        chosen, record = stored_choice(cfg, _held_out(run))
    else:
        # The CV runs are not the run's fit: they stay out of its checkpoint (a resumed run repeats them, seeded).
        with _checkpoint.active(None):
            chosen, record = choose_for_run(cfg, _held_out(run), runner=run_calibration, progress=bool(cfg.progress),
                                            run_size=len(run.run_ids))
    run.cfg = chosen
    run.report["config"] = _config_report(chosen, run.device)
    run.report["settings_choice"] = record


def _held_out(run: Run) -> list:
    """Heliostats no prior and no settings choice of the run may learn from: its own and ``prior_exclude``."""
    return list(run.run_ids) + list(run.cfg.prior_exclude)


def learn_prior(run: Run) -> None:
    """The plant prior of a run that asks for one, from heliostats that are neither calibrated nor tested.

    Leakage rule (:mod:`.archive`): the run's heliostats (and ``prior_exclude``) never enter the prior.
    """
    cfg = run.cfg
    if not cfg.uses_plant_prior():
        return
    source, excluded = cfg.prior_from, _held_out(run)
    if source is None:
        source = PriorArchive.from_dataset(run.dataset, focal_spot=cfg.focal_spot, source=os.fspath(cfg.paint),
                                           exclude=excluded)
    elif isinstance(source, (str, os.PathLike)):
        source = load_prior_source(os.fspath(source), cfg.plane_tolerance, exclude=excluded)
    run.plant_prior = resolve_prior(source, excluded, settings=cfg.prior_options)


def _image_context(ds, run_ids) -> dict:
    """What the ``images`` method needs beyond records: flux-image paths, surfaces, targets, sun."""
    plant = ds.plant
    all_ids = list(plant.field.ids)
    srf = plant.field.surfaces
    idx = torch.tensor([all_ids.index(h) for h in run_ids], device=srf.control_points.device)
    surfaces = Surfaces(control_points=srf.control_points[idx], degree_u=srf.degree_u, degree_v=srf.degree_v,
                        weights=None if srf.weights is None else srf.weights[idx])
    table = ds.records.for_heliostats(run_ids)
    images = {rid: png for rid, png in zip(table.record_id.tolist(), table.flux_png) if png}
    return {"images": images, "surfaces": surfaces, "targets": plant.targets, "sun": plant.sun}


def fit(run: Run) -> None:
    """The method on the training (and validation) records; ``fit_seconds`` is its wall time alone."""
    cfg = run.cfg
    options = cfg.fit_options()
    if cfg.method == "images":
        options.update(_image_context(run.dataset, run.run_ids))
    if run.plant_prior is not None:
        options["plant_prior"] = run.plant_prior
    t_fit = time.perf_counter()
    run.model = get_method(cfg.method)(run.nominal, run.train, run.validation, seed=cfg.seed, progress=cfg.progress,
                                       **options)
    run.fit_seconds = time.perf_counter() - t_fit
    run.model.corrections = {h: f for h, f in run.findings.items() if f.get("corrected")}


def evaluate(run: Run) -> None:
    """Per-record pointing error [rad] and miss distance [m]: calibrated on every part, nominal on test.

    The nominal model is the *uncorrected* one: what the plant would do without this calibration.
    """
    def of(model, b):
        empty = b.spot.new_zeros(0)
        return (model.pointing_error(b), model.miss_distance(b)) if len(b) else (empty, empty)

    with torch.no_grad():
        run.errors = {name: of(run.model, b) for name, b in run.parts.items()}
        run.errors["nominal_test"] = of(nominal_model(run.run_ids, run.nominal_raw), run.test)


def online_refit(run: Run) -> None:
    """``--split online``: replace the test errors by those of refits on the records before each test block."""
    if run.cfg.split != "online" or run.test is None or len(run.test) == 0:
        return
    cfg = run.cfg
    options = cfg.fit_options()
    if run.plant_prior is not None:
        options["plant_prior"] = run.plant_prior
    method = get_method(cfg.method)

    def fit_one(train):
        return method(run.nominal, train, None, seed=cfg.seed, progress=False, **options)

    blocks = []

    def interval_of_block(model, records, where, err):
        pred, inputs = record_intervals(model, records, err, cfg.seed)
        if pred is not None:
            blocks.append((where, pred, inputs))

    run.errors["test"] = online_errors(fit_one, run.batch, run.test_rows, cfg.train, cfg.online_step,
                                       on_block=interval_of_block)
    if blocks:
        run.intervals, run.interval_inputs = _assemble_blocks(blocks, len(run.test_rows))


def _assemble_blocks(blocks, n: int) -> tuple[dict, dict]:
    """The online protocol's intervals in test order from its blocks ``(positions, intervals, inputs)``;
    records of no block stay NaN / outside."""
    out = {k: torch.full((n,), float("nan"), dtype=torch.float64) for k in ("expected", "median", "lower", "upper")}
    out["inside"] = torch.zeros(n, dtype=torch.bool)
    for where, pred, _ in blocks:
        at = torch.as_tensor(where, dtype=torch.long)
        for k, v in pred.items():
            out[k][at] = v.to(out[k].dtype)
    inputs = {k: torch.cat([b[2][k] for b in blocks]) for k in blocks[0][2] if k != "heliostat"}
    inputs["heliostat"] = [h for b in blocks for h in b[2]["heliostat"]]
    return out, inputs


def record_intervals(model: Calibrated, records: RecordTable, err: torch.Tensor, seed: int = 0):
    """Predictive pointing error of ``records`` from ``model``'s Laplace posterior (when it has one).

    Parameters
    ----------
    model : Calibrated
        A fitted model whose ``extras["posterior"]`` holds the per-heliostat covariance (lm); its random-walk
        offset state (``extras["drift_state"]``), when present, grows the offset's covariance from the latest
        training record to each record's time (:func:`heliotwin.calibrate.drift.predicted_covariance`).
    records : RecordTable
        The R records to predict (heliostat axis = the model's).
    err : torch.Tensor, [R]
        Their measured pointing error [rad] (for ``inside``).
    seed : int
        Seed of the predictive samples.

    Returns
    -------
    intervals : dict or None
        ``expected``, ``median``, ``lower`` (0), ``upper`` (the 90 % quantile) [R] [rad] and ``inside`` [R] bool;
        None when the model has no posterior.
    inputs : dict
        What :func:`heliotwin.calibrate.selection.coverage` needs to re-draw the interval with another offset
        drift or walk scale (rows of the records whose heliostat the model calibrated): ``jacobian``
        [R', 3, P], ``normal`` [R', 3], ``covariance`` / ``walk`` [R', P, P], ``noise`` [R'] [rad], ``error``
        [R'] [rad], ``heliostat`` (R' ids).
    """
    post = model.extras.get("posterior")
    if not post or len(records) == 0:
        return None, {}
    hidx = records.heliostat_index
    _, jac = record_jacobian(model.nominal.index(hidx), records, model.delta.detach()[hidx], model.names)
    normal, _ = model.normals(records)
    err = err.double()
    keep = model.ok[hidx]
    cov = post["covariance"][hidx]
    state = model.extras.get("drift_state")
    if state is not None:  # the offset's uncertainty at the latest training time, grown by q dt (drift.py)
        rows = state["columns"].to(cov.device)
        walk = torch.zeros_like(cov)
        walk[:, rows[:, None], rows[None, :]] = predicted_covariance(state, hidx, records.time).to(cov)
    else:
        walk = torch.zeros_like(cov)
    inputs = {"jacobian": jac[keep], "normal": normal.detach()[keep], "covariance": cov[keep], "walk": walk[keep],
              "noise": post["noise_rad"][hidx][keep], "error": err[keep],
              "heliostat": [model.heliostat_ids[h] for h in hidx[keep].tolist()]}
    # The posterior predictive samples on the CPU (its draws take a CPU generator): a few thousand numbers.
    jac, normal, err, hidx = jac.cpu(), normal.detach().cpu(), err.cpu(), hidx.cpu()
    full = (cov + float(post.get("walk_scale", 1.0)) * walk).cpu()
    pred = predictive(jac, normal, full, post["noise_rad"].cpu()[hidx],
                      drift=post.get("drift_rad", 0.0), generator=torch.Generator().manual_seed(seed))
    pred["inside"] = (err >= pred["lower"]) & (err <= pred["upper"])
    return pred, inputs


def predict_intervals(run: Run) -> None:
    """Predictive pointing error of every test record from the model's Laplace posterior (when it has one):
    ``run.intervals`` = {"expected", "median", "lower", "upper"} [R] (rad, interval ``[0, q_0.9]``),
    "inside" [R] bool; ``run.interval_inputs`` (:func:`record_intervals`). ``--split online`` has them from
    :func:`online_refit` already: each block of test records is predicted by the refit before it."""
    test = run.test
    if test is None or len(test) == 0 or run.cfg.split == "online":
        return
    pred, inputs = record_intervals(run.model, test, run.errors["test"][0], run.cfg.seed)
    if pred is not None:
        run.intervals, run.interval_inputs = pred, inputs


def _heliostat_report(run: Run, h: int, hid: str, per_h_seconds: float) -> dict:
    model, info = run.model, run.split_info[hid]
    ok = bool(model.ok[h])
    rep = {"status": "ok" if ok else "skipped", "split": info}
    if not ok:
        why = f"too few training records ({info['train']} < {MIN_TRAIN})"
        if info.get("dropped_no_time"):
            # a time-ordered split cannot place a record without a time (metadata/calibration-metadata.csv)
            why += (f"; {info['dropped_no_time']} record(s) have no DateTime in metadata/calibration-metadata.csv, "
                    f"which the {run.cfg.split} split needs")
        rep["reason"] = model.reasons.get(hid, why)
    for name, b in list(run.parts.items()) + [("nominal_test", run.test)]:
        e, m = run.errors[name]
        mine = b.heliostat_index == h
        rep[name] = metrics.summarize(e[mine], m[mine])
    if not ok:
        # An uncalibrated heliostat has no calibrated error; do not let nominal numbers pass as one.
        rep["test"] = {k: None for k in rep["test"]}
    rep["mean_test_mrad"] = rep["test"]["mean_mrad"]
    rep["median_test_mrad"] = rep["test"]["median_mrad"]
    rep["nominal_mean_test_mrad"] = rep["nominal_test"]["mean_mrad"]
    rep["fit_seconds_share"] = per_h_seconds
    if run.intervals and ok:
        mine = (run.test.heliostat_index == h).cpu()
        iv = run.intervals
        rep["interval_90_coverage"] = float(iv["inside"][mine].double().mean()) if bool(mine.any()) else None
        rep["expected_test_mrad"] = float(1e3 * iv["expected"][mine].mean()) if bool(mine.any()) else None
        rep["interval_90_mrad"] = ([float(1e3 * iv["lower"][mine].median()), float(1e3 * iv["upper"][mine].median())]
                                   if bool(mine.any()) else None)
    if model.names and ok:
        rep["parameters"] = {n: float(model.delta[h, j]) for j, n in enumerate(model.names)}
    if hid in run.findings:
        rep["suspicious"] = run.findings[hid]
    if model.extras.get("per_heliostat", {}).get(hid):
        rep["method_info"] = model.extras["per_heliostat"][hid]
    return rep


def report_heliostats(run: Run) -> None:
    """One entry per heliostat that ran; ``fit_seconds_share`` = the run's ``fit_seconds`` / H (the fit is batched,
    a heliostat has no time of its own; ``overall.seconds`` is the whole run's wall time)."""
    per_h_seconds = run.fit_seconds / max(1, len(run.run_ids))
    for h, hid in enumerate(run.run_ids):
        run.report["heliostats"][hid] = _heliostat_report(run, h, hid, per_h_seconds)


def report_overall(run: Run) -> None:
    """Statistics over the calibrated heliostats (each key: which statistic over heliostats of which one)."""
    cfg, reps = run.cfg, run.report["heliostats"]
    ran = [reps[h] for h in run.run_ids if reps[h]["status"] == "ok"]
    run.report["overall"] = {
        "method": cfg.method, "split": cfg.split, "n_heliostats": len(ran),
        "median_of_mean_test_mrad": _median([r["mean_test_mrad"] for r in ran]),
        "mean_of_mean_test_mrad": _mean([r["mean_test_mrad"] for r in ran]),
        "median_of_median_test_mrad": _median([r["median_test_mrad"] for r in ran]),
        "nominal_median_of_mean_test_mrad": _median([r["nominal_mean_test_mrad"] for r in ran]),
        "nominal_mean_of_mean_test_mrad": _mean([r["nominal_mean_test_mrad"] for r in ran]),
        "median_of_mean_train_mrad": _median([r["train"]["mean_mrad"] for r in ran]),
        "median_of_median_test_miss_m": _median([r["test"].get("median_miss_m") for r in ran]),
        "mean_of_mean_train_test_distance_rad": _mean([r["split"].get("mean_train_test_distance_rad") for r in ran]),
        "fit_seconds": run.fit_seconds,
        "seconds": time.perf_counter() - run.t_start,
        "skipped_heliostats": len(run.skipped_heliostats) + sum(1 for h in run.run_ids if reps[h]["status"] != "ok"),
        "skipped_records": len(run.skipped_records),
        "dropped_no_time": int(sum(run.split_info[h]["dropped_no_time"] for h in run.run_ids)),
    }
    if run.intervals:
        mine = run.model.ok[run.test.heliostat_index].cpu()
        inside = run.intervals["inside"][mine]
        run.report["overall"]["interval_90_coverage"] = float(inside.double().mean()) if len(inside) else None
        run.report["overall"]["median_of_expected_test_mrad"] = _median([r.get("expected_test_mrad") for r in ran])
    if run.model.extras.get("summary"):
        run.report["overall"]["method_info"] = run.model.extras["summary"]


def report_records(run: Run) -> None:
    """Per test record: heliostat, id, calibrated and nominal pointing error [mrad] (report ``test_records``),
    the numbers ``heliotwin validate --scenario`` reproduces record by record."""
    test = run.test
    ok = run.model.ok
    cal, nom = run.errors["test"][0].tolist(), run.errors["nominal_test"][0].tolist()
    run.report["test_records"] = [
        {"record": int(rid), "heliostat": run.run_ids[h], "pointing_error_mrad": 1e3 * cal[i] if bool(ok[h]) else None,
         "nominal_pointing_error_mrad": 1e3 * nom[i]}
        for i, (rid, h) in enumerate(zip(test.record_id.tolist(), test.heliostat_index.tolist()))]


def plot_arrays(run: Run) -> None:
    """Per-record arrays of the test records for the plots (errors in mrad)."""
    test = run.test
    run.arrays = {"heliostat_ids": run.run_ids,
                  "test_heliostat": test.heliostat_index.cpu().numpy(), "test_azimuth": test.sun_azimuth.cpu().numpy(),
                  "test_elevation": test.sun_elevation.cpu().numpy(),
                  "test_error_mrad": run.errors["test"][0].cpu().numpy() * 1e3,
                  "test_nominal_mrad": run.errors["nominal_test"][0].cpu().numpy() * 1e3,
                  "train": run.train, "validation": run.validation, "test": test, "nominal": run.nominal,
                  "interval_inputs": run.interval_inputs}


#: The steps of :func:`run_calibration`, in order (name, function of :class:`Run`).
STEPS = (("select", select), ("prepare", prepare), ("rebatch", rebatch), ("split", split),
         ("choose_settings", choose_settings), ("learn_prior", learn_prior),
         ("check_properties", check_properties), ("fit", fit), ("evaluate", evaluate),
         ("online_refit", online_refit), ("predict_intervals", predict_intervals),
         ("report_heliostats", report_heliostats), ("report_overall", report_overall),
         ("report_records", report_records), ("plot_arrays", plot_arrays))


def run_calibration(cfg: RunConfig, dataset=None, *, device: str = "cpu", progress=None,
                    checkpoint=None) -> tuple[dict, Calibrated | None, dict]:
    """Run one calibration: the steps of :data:`STEPS` in order (stopping early when no heliostat can run).

    Parameters
    ----------
    cfg : RunConfig
    dataset : heliotwin.io.paint.PaintDataset, optional
        Already loaded PAINT folder (its record table, possibly on a scenario's plant via
        :meth:`~heliotwin.io.paint.PaintDataset.on_plant`); read from ``cfg.paint`` with
        ``cfg.plane_tolerance`` otherwise.
    device : str or torch.device
        Where to compute (``"cpu"``, ``"cuda"``, ``"auto"`` = CUDA when present); results come back on the CPU.
    progress : bool or callable, optional
        tqdm bars (default ``cfg.progress``), or ``progress(step_name, index, total)`` called before each step.
    checkpoint : heliotwin.io.checkpoint.Checkpoint, optional
        Save every fit loop's state there; a resumed checkpoint continues where the run stopped
        (:func:`calibration_checkpoint`). The caller removes it once its outputs are written.

    Returns
    -------
    report : dict
        The JSON report (see module :mod:`heliotwin.calibrate.report`).
    model : Calibrated or None
        The calibrated model over the heliostats that were run (None when none could be), on the CPU.
    arrays : dict
        Per-record arrays for the plots (test records: azimuth, elevation, heliostat, nominal and calibrated
        error [mrad]), on the CPU.
    """
    validate_config(cfg)
    run = Run(cfg, dataset, device=resolve_device(device))
    show = cfg.progress if progress is None else progress
    bar = _StageBar(f"calibrate {cfg.method}", len(STEPS), show)
    try:
        with _checkpoint.active(checkpoint):
            for name, step in STEPS:
                bar.stage(name)
                step(run)
                if run.stop:
                    break
    finally:
        bar.close()
    if run.device == "cpu":
        return run.report, run.model, run.arrays
    return run.report, to_device(run.model, "cpu"), to_device(run.arrays, "cpu")


class _StageBar:
    """Progress over the steps of a run: a tqdm bar titled ``desc`` showing the step's name, a callable
    ``progress(step, index, total)``, or nothing."""

    def __init__(self, desc: str, total: int, progress):
        self.callback = progress if callable(progress) else None
        self.total, self.index, self.bar = total, 0, None
        if progress is True:
            self.bar = tqdm(total=total, desc=desc, leave=False, disable=None)  # None: off when not a terminal

    def stage(self, name: str) -> None:
        if self.callback is not None:
            self.callback(name, self.index, self.total)
        if self.bar is not None:
            if self.index:
                self.bar.update(1)
            self.bar.set_postfix_str(name)
        self.index += 1

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def calibration_checkpoint(cfg: RunConfig, path, *, device: str = "cpu", resume: bool = False, inputs=(),
                           **options) -> _checkpoint.Checkpoint:
    """The :class:`~heliotwin.io.checkpoint.Checkpoint` of a calibration run at ``path``, tagged with the
    run's settings (every field of ``cfg`` but ``progress``, and the device) and inputs (the PAINT folder,
    a ``prior_from`` path and ``inputs``, e.g. the starting scenario). ``options`` go to the checkpoint."""
    settings = {k: v for k, v in cfg.__dict__.items() if k != "progress"}
    settings["paint"] = os.path.abspath(os.fspath(cfg.paint))
    settings["validation"] = cfg.n_validation()
    settings["device"] = resolve_device(device)
    pf = cfg.prior_from
    settings["prior_from"] = pf if pf is None or isinstance(pf, (str, os.PathLike)) else \
        (getattr(pf, "source", "") or type(pf).__name__)
    files = [cfg.paint] + [p for p in [cfg.prior_from, *inputs] if isinstance(p, (str, os.PathLike))]
    tag = _checkpoint.make_tag({"command": "calibrate", "settings": settings}, files)
    return _checkpoint.Checkpoint(path, tag, resume=resume, **options)
