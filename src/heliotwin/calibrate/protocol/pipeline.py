"""One calibration run as a pipeline of named steps (:data:`STEPS`), each a function from what the steps
before it made to one small frozen record of its own.

:func:`run_calibration` is what ``heliotwin calibrate`` does (through :mod:`heliotwin.workflows.calibrate`);
benchmarks and tests call it directly. The steps, in order, and what each makes:

====================  ==========================================================================  ===============
step                  does                                                                        makes
====================  ==========================================================================  ===============
``select``            the PAINT folder on the run's device, the heliostats asked for              :class:`Loaded`
``prepare``           their validated records; heliostats with too few are skipped                :class:`Prepared`
``rebatch``           records and nominal kinematics over the heliostats that run                 :class:`Batch`
``split``             train/validation/test records per heliostat                                 :class:`Split`
``choose_settings``   ``--settings cv|stored``: lm settings chosen by CV or stored (runs the run);  :class:`Choice`
                      ``--learn-settings``: chosen once for the plant, stored in its scenario
``learn_prior``       a plant prior from other heliostats, when asked for                         ``PlantPrior``
``check_properties``  suspicious property values, corrected where the training records support it  :class:`Checked`
``fit``               the method                                                                  :class:`Fit`
``evaluate``          pointing error and miss distance of the calibrated and the nominal model     :class:`Evaluation`
``online_refit``      ``--split online``: test errors of refits as records arrive                 :class:`Evaluation`
``predict_intervals`` predictive error and its 90 % interval per test record (lm's posterior)      :class:`Evaluation`
``report_heliostats`` one report entry per heliostat that ran                                     dict
``report_overall``    statistics over heliostats                                                  dict
``report_records``    per test record: calibrated and nominal error                               list
``plot_arrays``       per-record arrays for the plots                                             dict
====================  ==========================================================================  ===============

Every heliostat or record that cannot be used is reported with a reason, never dropped silently.

Devices: ``run_calibration(..., device="cuda")`` moves the plant and the record table there (the methods follow
the device of their inputs) and hands the model and the plot arrays back on the CPU. Progress: a tqdm bar
over the steps, titled ``calibrate <method>`` with the step's name, plus the methods' own loop bars
(``cfg.progress``; or a callable ``progress(step, index, total)``). Checkpoints: under a
:class:`~heliotwin.io.checkpoint.Checkpoint` (:func:`calibration_checkpoint`) every fit loop of the run
saves its state and a resumed run restores it (:mod:`heliotwin.calibrate.fitloop`).

Report keys mean one thing each: per heliostat, ``mean_test_mrad``/``median_test_mrad`` are the mean and
median over its test records; over the run, ``median_of_mean_test_mrad`` is the median over heliostats of
those per-heliostat means (the headline figure), ``median_of_median_test_mrad`` the median of the medians.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from tqdm.auto import tqdm

from ...devices import resolve_device, to_device
from ...errors import HeliotwinError
from ...field.plant import Kinematics, Surfaces
from ...io import checkpoint as _checkpoint
from ...io.paint import PaintDataset, load_paint
from ...io.records import RecordTable
from .. import metrics
from ..drift import predicted_covariance
from ..inputs import MIN_TRAIN
from ..methods import get_method
from ..metrics import record_jacobian
from ..model import Calibrated, nominal_model
from ..priors import PlantPrior
from ..uncertainty import predictive
from .archive import PriorArchive, load_prior_source, reference_kinematics, resolve_prior
from .config import RunConfig, validate_config, validation_protocol
from .online import online_errors, online_split
from .selection import choose_for_run, learn_for_plant, stored_choice
from .splits import split_records
from .suspicious import check_and_correct

__all__ = ["RunConfig", "validate_config", "STEPS", "run_calibration", "calibration_checkpoint", "Loaded",
           "Prepared", "Batch", "Split", "Choice", "Checked", "Fit", "Evaluation", "record_intervals"]


# ============================================================================ what the steps make
@dataclass(frozen=True)
class Loaded:
    """``select``: the PAINT folder (on the run's device) and the heliostats asked for, in order."""

    dataset: PaintDataset
    wanted: list


@dataclass(frozen=True)
class Prepared:
    """``prepare``: the usable records of the wanted heliostats and which of those heliostats run.

    Attributes
    ----------
    records : RecordTable
        Heliostat axis = ``Loaded.wanted``; the run's ``--focal-spot`` source chosen per record.
    run_ids : list of str
        The heliostats with at least ``--min-records`` records (the run's heliostat axis from here on).
    skipped_records : list of dict
        Records of the wanted heliostats that could not be used (``record_id``, ``heliostat_id``, ``reason``).
    skipped_heliostats : dict
        Heliostat id -> why it does not run.
    """

    records: RecordTable
    run_ids: list
    skipped_records: list
    skipped_heliostats: dict


@dataclass(frozen=True)
class Batch:
    """``rebatch``: the records and nominal kinematics of the H heliostats that run (heliostat index =
    position in ``run_ids``). ``nominal`` is uncorrected: what the plant would do without this calibration."""

    records: RecordTable
    nominal: Kinematics


@dataclass(frozen=True)
class Split:
    """``split``: train/validation/test records (heliostat axis = the run's), ``test_rows`` [R_test] their
    rows in :attr:`Batch.records` (the online protocol refits on the records before them) and ``info`` per
    heliostat id (sizes, ``dropped_no_time``, coverage)."""

    train: RecordTable
    validation: RecordTable
    test: RecordTable
    test_rows: torch.Tensor | None = None
    info: dict = field(default_factory=dict)

    @property
    def parts(self) -> dict:
        """``{"train", "validation", "test"}`` -> that part of the split."""
        return {"train": self.train, "validation": self.validation, "test": self.test}


@dataclass(frozen=True)
class Choice:
    """``choose_settings``: the settings that run and, for ``--settings cv|stored``, the JSON-ready record of
    the choice (report ``settings_choice``); ``record`` is None when the flags were taken as given."""

    cfg: RunConfig
    record: dict | None = None
    #: ``--learn-settings``: the plant prior of the chosen candidate (stored in the run's scenario).
    learned_prior: PlantPrior | None = None


@dataclass(frozen=True)
class Checked:
    """``check_properties``: the nominal kinematics the method starts from (suspicious property values
    corrected) and the findings per heliostat id."""

    nominal: Kinematics
    findings: dict


@dataclass(frozen=True)
class Fit:
    """``fit``: the calibrated model (run's heliostat axis) and the method's wall time [s]."""

    model: Calibrated
    seconds: float


@dataclass(frozen=True)
class Evaluation:
    """``evaluate`` (then ``online_refit``, ``predict_intervals``): per part of :attr:`Split.parts` and
    ``nominal_test``, ``(pointing error [R] [rad], miss distance [R] [m])``; ``intervals`` =
    {"expected", "median", "lower", "upper"} [R_test] [rad] (interval ``[0, q_0.9]``), "inside" [R_test] bool,
    and ``interval_inputs`` (:func:`record_intervals`), both empty without a posterior."""

    errors: dict
    intervals: dict = field(default_factory=dict)
    interval_inputs: dict = field(default_factory=dict)


# ============================================================================ the steps
def select(cfg: RunConfig, dataset: PaintDataset | None, device: str) -> Loaded:
    """The PAINT folder (``dataset``, or read from ``cfg.paint``) on ``device``, and the heliostats asked for
    (``--heliostats``, default all); an unknown id is a one-line error."""
    if dataset is None:
        dataset = load_paint(cfg.paint, plane_tolerance=cfg.plane_tolerance)
    if device != "cpu":
        dataset = to_device(dataset, device)
    all_ids = list(dataset.plant.field.ids)
    if not cfg.heliostats:
        return Loaded(dataset, all_ids)
    unknown = [h for h in cfg.heliostats if h not in all_ids]
    if unknown:
        raise HeliotwinError(f"heliostat(s) {', '.join(unknown)} not in {cfg.paint}; available: {', '.join(all_ids)}")
    return Loaded(dataset, list(dict.fromkeys(cfg.heliostats)))


def prepare(cfg: RunConfig, loaded: Loaded) -> Prepared:
    """Validated records of the wanted heliostats; heliostats with fewer than ``--min-records`` are skipped."""
    # The dataset's record table already judged every record (with the tolerance it was loaded with).
    records = loaded.dataset.records.for_heliostats(loaded.wanted).with_focal_spot(cfg.focal_spot)
    skipped_records = [s for s in loaded.dataset.skipped if s["heliostat_id"] in loaded.wanted]
    counts = records.counts()
    need = max(cfg.min_records, 1)
    run_ids, skipped = [], {}
    for h, hid in enumerate(loaded.wanted):
        if int(counts[h]) < need:
            skipped[hid] = f"too few usable records ({int(counts[h])} < --min-records {need})"
        else:
            run_ids.append(hid)
    return Prepared(records, run_ids, skipped_records, skipped)


def rebatch(loaded: Loaded, prepared: Prepared) -> Batch:
    """Records and nominal kinematics over the heliostats that run (heliostat index = position in run_ids)."""
    run_ids, wanted, every = prepared.run_ids, loaded.wanted, prepared.records
    dev = every.heliostat_index.device
    keep = torch.tensor([wanted.index(h) for h in run_ids], device=dev)
    batch = every.subset(torch.isin(every.heliostat_index, keep))
    remap = torch.full((len(wanted),), -1, dtype=torch.long, device=dev)
    remap[keep] = torch.arange(len(run_ids), device=dev)
    batch.heliostat_index = remap[batch.heliostat_index]
    batch.heliostat_ids = list(run_ids)
    all_ids = list(loaded.dataset.plant.field.ids)
    return Batch(batch, loaded.dataset.plant.field.kinematics.index([all_ids.index(h) for h in run_ids]))


def split(cfg: RunConfig, batch: Batch) -> Split:
    """Train/validation/test records per heliostat (validation carved out of ``--train``)."""
    records = batch.records
    if cfg.split == "current":
        return _every_record(cfg, records)
    if cfg.split == "online":
        tr, va, te, info = online_split(records, cfg.train, cfg.test)
    else:
        tr, va, te, info = split_records(records, cfg.split, cfg.train, cfg.n_validation(), cfg.test, seed=cfg.seed)
    return Split(records.subset(tr), records.subset(va), records.subset(te), te, info)


def _every_record(cfg: RunConfig, records: RecordTable) -> Split:
    """``current``: every usable record is training (a drift model needs times: records without one are then
    dropped and counted); nothing is held out."""
    keep = torch.ones(len(records), dtype=torch.bool, device=records.heliostat_index.device)
    if cfg.drift_model != "none":
        keep = torch.isfinite(records.time)
    rows = keep.nonzero().flatten()
    none = rows[:0]
    n = torch.bincount(records.heliostat_index, minlength=len(records.heliostat_ids)).tolist()
    used = torch.bincount(records.heliostat_index[rows], minlength=len(records.heliostat_ids)).tolist()
    info = {hid: {"n_records": n[h], "train": used[h], "validation": 0, "test": 0, "dropped_no_time": n[h] - used[h]}
            for h, hid in enumerate(records.heliostat_ids)}
    return Split(records.subset(rows), records.subset(none), records.subset(none), none, info)


def choose_settings(cfg: RunConfig, run_ids: list, runner, log=None) -> Choice:
    """``--settings cv``: the run's lm settings replaced by those leave-heliostats-out CV chooses on the
    ``--prior-from`` folder (:func:`~heliotwin.calibrate.protocol.selection.choose_for_run`, scoring every
    candidate with ``runner``, i.e. :func:`run_calibration`); ``--settings stored``: by the choice stored in
    the ``--prior-from`` scenario where it applies (:func:`~heliotwin.calibrate.protocol.selection.stored_choice`).
    Otherwise the flags as given."""
    # a current run (nothing held out) is scored on its validation protocol, then fits every record
    study = validation_protocol(cfg)

    def back(chosen: RunConfig) -> RunConfig:
        return replace(chosen, split=cfg.split, train=cfg.train, validation=cfg.validation, test=cfg.test)

    def cv_run(c: RunConfig, dataset):
        # A CV run is not the run's fit: its own loops stay out of the run's checkpoint, which keeps the CV's
        # finished candidates instead (selection.choose_for_run: a resumed run goes on after the last one).
        with _checkpoint.active(None):
            return runner(c, dataset)

    if cfg.learn_settings:
        record, prior = learn_for_plant(study, runner=cv_run, run_size=len(run_ids), progress=bool(cfg.progress),
                                        log=log)
        return Choice(cfg, record, prior)
    if cfg.settings == "stored":
        chosen, record = stored_choice(study, _held_out(cfg, run_ids))
        return Choice(back(chosen), record)
    if cfg.settings == "cv":
        chosen, record = choose_for_run(study, _held_out(cfg, run_ids), runner=cv_run,
                                        progress=bool(cfg.progress), run_size=len(run_ids), log=log)
        return Choice(back(chosen), record)
    return Choice(cfg)


def _held_out(cfg: RunConfig, run_ids: list) -> list:
    """Heliostats no prior and no settings choice of the run may learn from: its own and ``prior_exclude``."""
    return list(run_ids) + list(cfg.prior_exclude)


def learn_prior(cfg: RunConfig, dataset: PaintDataset, run_ids: list) -> PlantPrior | None:
    """The plant prior of a run that asks for one, from heliostats that are neither calibrated nor tested
    (None otherwise).

    Leakage rule (:mod:`.archive`): the run's heliostats (and ``prior_exclude``) never enter the prior.
    """
    if not cfg.uses_plant_prior():
        return None
    source, excluded = cfg.prior_from, _held_out(cfg, run_ids)
    if source is None:
        source = PriorArchive.from_dataset(dataset, focal_spot=cfg.focal_spot, source=os.fspath(cfg.paint),
                                           exclude=excluded)
    elif isinstance(source, (str, os.PathLike)):
        source = load_prior_source(os.fspath(source), cfg.plane_tolerance, exclude=excluded)
    return resolve_prior(source, excluded, settings=cfg.prior_options)


def check_properties(cfg: RunConfig, dataset: PaintDataset, batch: Batch, parts: Split, prior: PlantPrior | None,
                     prior_source=None) -> Checked:
    """Suspicious property values, corrected where the training + validation records support it.

    The field medians the values are judged against come from every heliostat of the run's plant and, with
    ``prior_source`` (the run's ``--prior-from`` as given: the chosen settings may not use it, but its plant
    still has heliostats to compare with), of the prior's plant too
    (:func:`~heliotwin.calibrate.protocol.archive.reference_kinematics`): a run on a folder of a few
    heliostats would otherwise have no field to compare with. For the same reason the run's plant ``prior``
    judges a correction when the run's own heliostats are too few for a field prior.
    """
    if not cfg.correct_suspicious:
        return Checked(batch.nominal, {})
    seen = RecordTable.concatenate([parts.train, parts.validation])
    field_kin = dataset.plant.field.kinematics
    _, extra = reference_kinematics(prior_source, skip=dataset.plant.field.ids)
    if extra is not None:
        field_kin = Kinematics.concatenate([field_kin, extra.to(device=field_kin.initial_angle.device)])
    fallback = None if prior is None else (prior.mean, prior.sigma)
    return Checked(*check_and_correct(batch.nominal, batch.records.heliostat_ids, field_kin, seen,
                                      fallback_prior=fallback))


def _image_context(ds: PaintDataset, run_ids: list) -> dict:
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


def _fit_options(cfg: RunConfig, prior: PlantPrior | None) -> dict:
    """The method's keyword options: the config's (:meth:`RunConfig.fit_options`) and the plant prior."""
    options = cfg.fit_options()
    if prior is not None:
        options["plant_prior"] = prior
    return options


def fit(cfg: RunConfig, dataset: PaintDataset, checked: Checked, parts: Split, prior: PlantPrior | None) -> Fit:
    """The method on the training (and validation) records; ``Fit.seconds`` is its wall time alone."""
    options = _fit_options(cfg, prior)
    if cfg.method == "images":
        options.update(_image_context(dataset, parts.train.heliostat_ids))
    t_fit = time.perf_counter()
    model = get_method(cfg.method)(checked.nominal, parts.train, parts.validation, seed=cfg.seed,
                                   progress=cfg.progress, **options)
    seconds = time.perf_counter() - t_fit
    model.corrections = {h: f for h, f in checked.findings.items() if f.get("corrected")}
    return Fit(model, seconds)


def evaluate(model: Calibrated, nominal: Kinematics, parts: Split) -> Evaluation:
    """Per-record pointing error [rad] and miss distance [m]: ``model`` on every part, the uncalibrated
    ``nominal`` kinematics (:attr:`Batch.nominal`: what the plant would do without this calibration) on test.
    """
    def of(m, b):
        empty = b.spot.new_zeros(0)
        return (m.pointing_error(b), m.miss_distance(b)) if len(b) else (empty, empty)

    with torch.no_grad():
        errors = {name: of(model, b) for name, b in parts.parts.items()}
        errors["nominal_test"] = of(nominal_model(model.heliostat_ids, nominal), parts.test)
    return Evaluation(errors)


def online_refit(cfg: RunConfig, nominal: Kinematics, records: RecordTable, parts: Split,
                 prior: PlantPrior | None, evaluation: Evaluation) -> Evaluation:
    """``--split online``: the test errors replaced by those of refits of the method (from ``nominal``, the
    checked kinematics) on the records before each test block (``records``: :attr:`Batch.records`), and each
    test record's interval by the one of the refit that predicted it. Other splits: ``evaluation`` as is."""
    if cfg.split != "online" or parts.test is None or len(parts.test) == 0:
        return evaluation
    options = _fit_options(cfg, prior)
    method = get_method(cfg.method)

    def fit_one(train):
        return method(nominal, train, None, seed=cfg.seed, progress=False, **options)

    blocks = []

    def interval_of_block(model, block, where, err):
        pred, inputs = record_intervals(model, block, err, cfg.seed)
        if pred is not None:
            blocks.append((where, pred, inputs))

    test_errors = online_errors(fit_one, records, parts.test_rows, cfg.train, cfg.online_step,
                                on_block=interval_of_block)
    out = replace(evaluation, errors={**evaluation.errors, "test": test_errors})
    if blocks:
        intervals, inputs = _assemble_blocks(blocks, len(parts.test_rows))
        out = replace(out, intervals=intervals, interval_inputs=inputs)
    return out


def _assemble_blocks(blocks, n: int) -> tuple[dict, dict]:
    """The online protocol's intervals in test order from its blocks ``(positions, intervals, inputs)``;
    records of no block stay NaN / outside."""
    out = {k: torch.full((n,), float("nan"), dtype=torch.float64) for k in ("expected", "median", "lower", "upper")}
    out["inside"] = torch.zeros(n, dtype=torch.bool)
    for where, pred, _ in blocks:
        at = torch.as_tensor(where, dtype=torch.long)
        for k, v in pred.items():
            out[k][at] = v.to(device=out[k].device, dtype=out[k].dtype)  # blocks may sit on the GPU
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
        What :func:`heliotwin.calibrate.protocol.selection.coverage` needs to re-draw the interval with another offset
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
    # [R, P, P] per record: copies only where needed (the walk is zero without a drift state, every record is
    # usually kept), since R x P x P doubles are the largest arrays of a plant-sized run
    walk = None
    if state is not None:  # the offset's uncertainty at the latest training time, grown by q dt (drift.py)
        rows = state["columns"].to(cov.device)
        walk = torch.zeros_like(cov)
        walk[:, rows[:, None], rows[None, :]] = predicted_covariance(state, hidx, records.time).to(cov)
    every = bool(keep.all())
    kept = (lambda t: t) if every else (lambda t: t[keep])
    n_kept, p = int(keep.sum()), cov.shape[-1]
    inputs = {"jacobian": kept(jac), "normal": kept(normal.detach()), "covariance": kept(cov),
              "walk": kept(walk) if walk is not None else cov.new_zeros(()).expand(n_kept, p, p),
              "noise": post["noise_rad"][hidx][keep], "error": err[keep],
              "heliostat": [model.heliostat_ids[h] for h in hidx[keep].tolist()]}
    # The posterior predictive samples on the CPU (its draws take a CPU generator): a few thousand numbers.
    jac, normal, err, hidx = jac.cpu(), normal.detach().cpu(), err.cpu(), hidx.cpu()
    full = (cov + float(post.get("walk_scale", 1.0)) * walk).cpu() if walk is not None else cov.cpu()
    pred = predictive(jac, normal, full, post["noise_rad"].cpu()[hidx],
                      drift=post.get("drift_rad", 0.0), generator=torch.Generator().manual_seed(seed))
    pred["inside"] = (err >= pred["lower"]) & (err <= pred["upper"])
    return pred, inputs


def predict_intervals(cfg: RunConfig, model: Calibrated, parts: Split, evaluation: Evaluation) -> Evaluation:
    """Predictive pointing error of every test record from ``model``'s Laplace posterior (when it has one):
    :attr:`Evaluation.intervals` and :attr:`Evaluation.interval_inputs` (:func:`record_intervals`).
    ``--split online`` has them from :func:`online_refit` already: each block of test records is predicted
    by the refit before it."""
    test = parts.test
    if test is None or len(test) == 0 or cfg.split == "online":
        return evaluation
    pred, inputs = record_intervals(model, test, evaluation.errors["test"][0], cfg.seed)
    if pred is None:
        return evaluation
    return replace(evaluation, intervals=pred, interval_inputs=inputs)


def _median(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.median(xs)) if xs else None


def _mean(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.mean(xs)) if xs else None


def _heliostat_report(cfg: RunConfig, parts: Split, checked: Checked, fitted: Fit, evaluation: Evaluation, h: int,
                      hid: str, per_h_seconds: float, rows: dict) -> dict:
    """``rows``: each part's (and ``nominal_test``'s) :meth:`~heliotwin.io.records.RecordTable.rows_by_heliostat`."""
    model, info = fitted.model, parts.info[hid]
    ok = bool(model.ok[h])
    rep = {"status": "ok" if ok else "skipped", "split": info}
    if not ok:
        why = f"too few training records ({info['train']} < {MIN_TRAIN})"
        if info.get("dropped_no_time"):
            # a time-ordered split cannot place a record without a time (metadata/calibration-metadata.csv)
            why += (f"; {info['dropped_no_time']} record(s) have no DateTime in metadata/calibration-metadata.csv, "
                    f"which the {cfg.split} split needs")
        rep["reason"] = model.reasons.get(hid, why)
    for name, by_heliostat in rows.items():
        e, m = evaluation.errors[name]
        mine = by_heliostat[h].to(e.device)
        rep[name] = metrics.summarize(e[mine], m[mine])
    if not ok:
        # An uncalibrated heliostat has no calibrated error; do not let nominal numbers pass as one.
        rep["test"] = {k: None for k in rep["test"]}
    rep["mean_test_mrad"] = rep["test"]["mean_mrad"]
    rep["median_test_mrad"] = rep["test"]["median_mrad"]
    rep["nominal_mean_test_mrad"] = rep["nominal_test"]["mean_mrad"]
    rep["fit_seconds_share"] = per_h_seconds
    if evaluation.intervals and ok:
        mine = rows["nominal_test"][h].cpu()  # the test records (nominal_test is the test part)
        iv = evaluation.intervals
        rep["interval_90_coverage"] = float(iv["inside"][mine].double().mean()) if len(mine) else None
        rep["expected_test_mrad"] = float(1e3 * iv["expected"][mine].mean()) if len(mine) else None
        rep["interval_90_mrad"] = ([float(1e3 * iv["lower"][mine].median()), float(1e3 * iv["upper"][mine].median())]
                                   if len(mine) else None)
    if model.names and ok:
        rep["parameters"] = {n: float(model.delta[h, j]) for j, n in enumerate(model.names)}
    if hid in checked.findings:
        rep["suspicious"] = checked.findings[hid]
    if model.extras.get("per_heliostat", {}).get(hid):
        rep["method_info"] = model.extras["per_heliostat"][hid]
    return rep


def report_heliostats(cfg: RunConfig, parts: Split, checked: Checked, fitted: Fit, evaluation: Evaluation) -> dict:
    """One entry per heliostat that ran (heliostat id -> dict, the model's order); ``fit_seconds_share`` = the
    run's fit seconds / H (the fit is batched, a heliostat has no time of its own; ``overall.seconds`` is the
    whole run's wall time)."""
    ids = fitted.model.heliostat_ids
    per_h_seconds = fitted.seconds / max(1, len(ids))
    rows = {name: b.rows_by_heliostat() for name, b in list(parts.parts.items()) + [("nominal_test", parts.test)]}
    return {hid: _heliostat_report(cfg, parts, checked, fitted, evaluation, h, hid, per_h_seconds, rows)
            for h, hid in enumerate(ids)}


def report_overall(cfg: RunConfig, prepared: Prepared, parts: Split, fitted: Fit, evaluation: Evaluation,
                   heliostats: dict, t_start: float) -> dict:
    """Statistics over the calibrated heliostats (each key: which statistic over heliostats of which one);
    ``heliostats`` is the report's per-heliostat part, ``t_start`` when the run started
    (:func:`time.perf_counter`)."""
    run_ids = prepared.run_ids
    ran = [heliostats[h] for h in run_ids if heliostats[h]["status"] == "ok"]
    overall = {
        "method": cfg.method, "split": cfg.split, "n_heliostats": len(ran),
        "median_of_mean_test_mrad": _median([r["mean_test_mrad"] for r in ran]),
        "mean_of_mean_test_mrad": _mean([r["mean_test_mrad"] for r in ran]),
        "median_of_median_test_mrad": _median([r["median_test_mrad"] for r in ran]),
        "nominal_median_of_mean_test_mrad": _median([r["nominal_mean_test_mrad"] for r in ran]),
        "nominal_mean_of_mean_test_mrad": _mean([r["nominal_mean_test_mrad"] for r in ran]),
        "median_of_mean_train_mrad": _median([r["train"]["mean_mrad"] for r in ran]),
        "median_of_median_test_miss_m": _median([r["test"].get("median_miss_m") for r in ran]),
        "mean_of_mean_train_test_distance_rad": _mean([r["split"].get("mean_train_test_distance_rad") for r in ran]),
        "fit_seconds": fitted.seconds,
        "seconds": time.perf_counter() - t_start,
        "skipped_heliostats": len(prepared.skipped_heliostats) + sum(1 for h in run_ids
                                                                     if heliostats[h]["status"] != "ok"),
        "skipped_records": len(prepared.skipped_records),
        "dropped_no_time": int(sum(parts.info[h]["dropped_no_time"] for h in run_ids)),
    }
    if evaluation.intervals:
        mine = fitted.model.ok[parts.test.heliostat_index].cpu()
        inside = evaluation.intervals["inside"][mine]
        overall["interval_90_coverage"] = float(inside.double().mean()) if len(inside) else None
        overall["median_of_expected_test_mrad"] = _median([r.get("expected_test_mrad") for r in ran])
    if fitted.model.extras.get("summary"):
        overall["method_info"] = fitted.model.extras["summary"]
    return overall


def report_records(parts: Split, model: Calibrated, evaluation: Evaluation) -> list:
    """Per test record: heliostat, id, calibrated and nominal pointing error [mrad] (report ``test_records``),
    the numbers ``heliotwin validate --scenario`` reproduces record by record."""
    test, ok, ids = parts.test, model.ok, model.heliostat_ids
    cal, nom = evaluation.errors["test"][0].tolist(), evaluation.errors["nominal_test"][0].tolist()
    return [{"record": int(rid), "heliostat": ids[h], "pointing_error_mrad": 1e3 * cal[i] if bool(ok[h]) else None,
             "nominal_pointing_error_mrad": 1e3 * nom[i]}
            for i, (rid, h) in enumerate(zip(test.record_id.tolist(), test.heliostat_index.tolist()))]


def plot_arrays(parts: Split, checked: Checked, evaluation: Evaluation) -> dict:
    """Per-record arrays of the test records for the plots (errors in mrad), and the parts themselves."""
    test = parts.test
    return {"heliostat_ids": list(test.heliostat_ids),
            "test_heliostat": test.heliostat_index.cpu().numpy(), "test_azimuth": test.sun_azimuth.cpu().numpy(),
            "test_elevation": test.sun_elevation.cpu().numpy(),
            "test_error_mrad": evaluation.errors["test"][0].cpu().numpy() * 1e3,
            "test_nominal_mrad": evaluation.errors["nominal_test"][0].cpu().numpy() * 1e3,
            "train": parts.train, "validation": parts.validation, "test": test, "nominal": checked.nominal,
            "interval_inputs": evaluation.interval_inputs}


#: The steps of :func:`run_calibration`, in order (name, function): :func:`_run` calls them in this order.
STEPS = (("select", select), ("prepare", prepare), ("rebatch", rebatch), ("split", split),
         ("choose_settings", choose_settings), ("learn_prior", learn_prior),
         ("check_properties", check_properties), ("fit", fit), ("evaluate", evaluate),
         ("online_refit", online_refit), ("predict_intervals", predict_intervals),
         ("report_heliostats", report_heliostats), ("report_overall", report_overall),
         ("report_records", report_records), ("plot_arrays", plot_arrays))


# ============================================================================ the run
def _config_report(cfg: RunConfig, device) -> dict:
    config = {k: v for k, v in cfg.__dict__.items() if k not in ("progress",)}
    config["paint"] = os.fspath(cfg.paint)
    pf = cfg.prior_from
    config["prior_from"] = pf if pf is None or isinstance(pf, str) else (getattr(pf, "source", "") or type(pf).__name__)
    config["validation"] = cfg.n_validation()
    config["device"] = device
    return config


def _run(cfg: RunConfig, dataset, device: str, step, log=None) -> tuple[dict, Calibrated | None, dict]:
    """The steps, wired: each gets what it reads from the steps before it. ``step(fn, *args)`` announces the
    step (progress) and calls it; ``log(text)`` reports progress inside a long step."""
    t_start = time.perf_counter()
    loaded = step(select, cfg, dataset, device)
    prepared = step(prepare, cfg, loaded)
    report = {"config": _config_report(cfg, device), "skipped_records": prepared.skipped_records,
              "heliostats": {hid: {"status": "skipped", "reason": r} for hid, r in prepared.skipped_heliostats.items()}}
    if not prepared.run_ids:
        report["overall"] = {"n_heliostats": 0, "median_of_mean_test_mrad": None, "mean_of_mean_test_mrad": None,
                             "nominal_median_of_mean_test_mrad": None, "note": "no heliostat with enough records",
                             "seconds": time.perf_counter() - t_start}
        return report, None, {}
    batch = step(rebatch, loaded, prepared)
    parts = step(split, cfg, batch)
    choice = step(choose_settings, cfg, prepared.run_ids, run_calibration, log)
    if choice.record is not None:
        report["config"] = _config_report(choice.cfg, device)  # the settings that ran
        report["settings_choice"] = choice.record
    prior_source, cfg = cfg.prior_from, choice.cfg
    prior = step(learn_prior, cfg, loaded.dataset, prepared.run_ids)
    checked = step(check_properties, cfg, loaded.dataset, batch, parts, prior, prior_source)
    fitted = step(fit, cfg, loaded.dataset, checked, parts, prior)
    if choice.learned_prior is not None:  # what later runs of this plant start from (the scenario stores it)
        fitted.model.extras["learned_plant_prior"] = choice.learned_prior
    evaluation = step(evaluate, fitted.model, batch.nominal, parts)
    evaluation = step(online_refit, cfg, checked.nominal, batch.records, parts, prior, evaluation)
    evaluation = step(predict_intervals, cfg, fitted.model, parts, evaluation)
    report["heliostats"].update(step(report_heliostats, cfg, parts, checked, fitted, evaluation))
    report["overall"] = step(report_overall, cfg, prepared, parts, fitted, evaluation, report["heliostats"], t_start)
    report["test_records"] = step(report_records, parts, fitted.model, evaluation)
    return report, fitted.model, step(plot_arrays, parts, checked, evaluation)


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
        error [mrad]) and the train/validation/test records, on the CPU.
    """
    validate_config(cfg)
    device = resolve_device(device)
    bar = _StageBar(f"calibrate {cfg.method}", len(STEPS), cfg.progress if progress is None else progress)
    try:
        with _checkpoint.active(checkpoint):
            report, model, arrays = _run(cfg, dataset, device, bar.step, bar.log)
    finally:
        bar.close()
    if device == "cpu":
        return report, model, arrays
    return report, to_device(model, "cpu"), to_device(arrays, "cpu")


class _StageBar:
    """Progress over the steps of a run: a tqdm bar titled ``desc`` showing the step's name, a callable
    ``progress(step, index, total)``, or nothing. :meth:`step` announces and calls each step of :data:`STEPS`."""

    def __init__(self, desc: str, total: int, progress):
        self.callback = progress if callable(progress) else None
        self.total, self.index, self.bar = total, 0, None
        if progress is True:
            self.bar = tqdm(total=total, desc=desc, leave=False, disable=None)  # None: off when not a terminal

    def step(self, fn, *args):
        """``fn(*args)``, announced under its name in :data:`STEPS` (the steps must come in that order)."""
        name, expected = STEPS[self.index]
        assert fn is expected, f"step {self.index} is {name}, not {fn.__name__}"
        if self.callback is not None:
            self.callback(name, self.index, self.total)
        if self.bar is not None:
            if self.index:
                self.bar.update(1)
            self.bar.set_postfix_str(name)
        self.index += 1
        return fn(*args)

    def log(self, text: str) -> None:
        """A line of progress inside the current step (e.g. each settings candidate scored by CV)."""
        if self.callback is not None and self.index:
            self.callback(f"{STEPS[self.index - 1][0]}: {' '.join(text.split())}", self.index - 1, self.total)
        elif self.bar is not None:
            self.bar.set_postfix_str(" ".join(text.split())[:60])

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
