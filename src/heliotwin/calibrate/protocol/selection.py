"""Honest model selection: settings chosen by leave-heliostats-out cross-validation, as code.

A *candidate* is a dict of settings of the ``lm`` calibration (:data:`CANDIDATES`): which prior (the run's
own field prior, or a plant prior learned from other heliostats, :mod:`.archive`), the plant prior's
covariance form, shrinkage and width, and the number of bootstrap bags. Every figure here is computed with
the benchmark protocol (``--split chrono``, test = the latest ``test`` records of a heliostat, ``--train N``)
on heliostats that no choice looked at:

* :func:`cross_validated_errors`: K folds over heliostats; the heliostats of fold k are calibrated with a
  plant prior from every other heliostat of the folder (never fold k's, nor any ``exclude``d heliostat);
  returns each heliostat's mean test error per candidate.
* :func:`select`: the candidate with the lowest median (over heliostats) of those errors — the choice
  procedure, which sees only the heliostats it is given.
* :func:`nested_cv`: the honest estimate of :func:`select` itself: for each outer fold, :func:`select` runs
  on the other heliostats only (inner K-fold, the outer fold excluded from every prior), and the chosen
  candidate is then scored on the outer fold. The median over all heliostats of those held-out errors is
  the leave-heliostats-out CV figure.

Heliostats with fewer than ``min_records`` usable records are never calibrated or tested here, but their
records feed the plant priors (they are the plant's other heliostats).

Every function here that calibrates takes the run itself as ``runner``: a function ``runner(cfg, dataset) ->
(report, model, arrays)`` (:func:`heliotwin.calibrate.protocol.pipeline.run_calibration`). The choice of a
run's settings is a step of that run (``choose_settings``), so the pipeline hands itself down rather than
this module reaching back up for it.
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import replace
from typing import Callable

import numpy as np
import torch
from tqdm.auto import tqdm

from ...errors import HeliotwinError, InputFileError
from ...io.checkpoint import resumable_range
from ...io.paint import load_paint
from ...io.scenario import load_scenario
from ..choice import lowest, worth_its_cost
from ..methods.lm import LM_BAGS
from ..priors import MIN_HELIOSTATS
from ..scenario import KEY
from ..uncertainty import SAMPLES, predictive
from .archive import PriorArchive
from .config import RunConfig

#: ``runner(cfg, dataset) -> (report, model, arrays)``: one calibration run
#: (:func:`heliotwin.calibrate.protocol.pipeline.run_calibration`).
Runner = Callable[[RunConfig, object], tuple]

#: Settings tried, in order (the first is today's ``lm`` default). ``bags``: bootstrap bags of ``lm``;
#: ``half_life_days``: drift tracking by recency weights (:func:`~heliotwin.calibrate.methods.lm.fit_lm`);
#: ``drift_model``/``process_noise``: the random-walk offset (:mod:`heliotwin.calibrate.drift`, q [mrad^2/day]);
#: ``fit_focal_spot``/``loss``: the centroids the fit trains on and its loss (default ``UTIS`` / ``soft_l1``;
#: ``harmonised``: :func:`~heliotwin.calibrate.inputs.source_offsets`).
CANDIDATES = (
    {"prior": "run", "bags": 10},
    {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 1.0, "bags": 10},
    {"prior": "plant", "covariance": "full", "shrink": 0.5, "widen": 1.0, "bags": 10},
    {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 2.0, "bags": 10},
    {"prior": "plant", "covariance": "diag", "widen": 1.0, "bags": 10},
    {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 1.0, "bags": 0},
    {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 2.0, "bags": 10, "half_life_days": 60.0},
    {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 2.0, "bags": 10, "half_life_days": 180.0},
    {"prior": "run", "bags": 10, "half_life_days": 60.0},
    {"prior": "run", "bags": 10, "half_life_days": 20.0},
    {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 2.0, "bags": 10, "half_life_days": 20.0},
    # the rigid body + a random-walk offset of the axis offsets (drift.py): q [mrad^2/day] fixed, or "auto"
    # (chronological validation inside each heliostat's training records)
    {"prior": "run", "bags": 10, "drift_model": "kalman", "process_noise": 0.01},
    {"prior": "run", "bags": 10, "drift_model": "kalman", "process_noise": 0.03},
    {"prior": "run", "bags": 10, "drift_model": "kalman", "process_noise": "auto"},
    {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 2.0, "bags": 10, "drift_model": "kalman",
     "process_noise": 0.03},
    {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 2.0, "bags": 10, "drift_model": "kalman",
     "process_noise": "auto"},
    # the fit's centroid source and loss, which were constants chosen on the shared heliostats' records
    # (inputs.FIT_FOCAL_SPOT, lm.LM_LOSS) and did not carry over to other heliostats: the metric's own
    # centroids and plain least squares, with each kind of prior
    {"prior": "run", "bags": 10, "fit_focal_spot": "HeliOS"},
    {"prior": "run", "bags": 10, "loss": "linear"},
    {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 2.0, "bags": 10, "fit_focal_spot": "HeliOS"},
    {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 2.0, "bags": 10, "loss": "linear"},
    # UTIS moved into the metric's frame by the per-target offset between the two cameras (inputs.source_offsets)
    {"prior": "run", "bags": 10, "fit_focal_spot": "harmonised"},
    {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 2.0, "bags": 10, "fit_focal_spot": "harmonised"},
)


def label(candidate: dict) -> str:
    """Short text of a candidate, e.g. ``plant/full/s0.2/w1/b10``."""
    c = candidate
    hl = f"/hl{c['half_life_days']:g}d" if c.get("half_life_days") else ""
    if c.get("drift_model", "none") == "kalman":
        pn = c.get("process_noise", "auto")
        hl += f"/kq{pn:g}" if isinstance(pn, (int, float)) else f"/kq{pn}"
    if c.get("fit_focal_spot"):
        hl += f"/fit{c['fit_focal_spot']}"
    if c.get("loss"):
        hl += f"/{c['loss']}"
    if c.get("prior", "run") == "run":
        return f"run/b{c.get('bags', 10)}{hl}"
    cov = c.get("covariance", "full")
    shrink = f"/s{c.get('shrink', 0.2):g}" if cov == "full" else ""
    return f"plant/{cov}{shrink}/w{c.get('widen', 1.0):g}/b{c.get('bags', 10)}{hl}"


def config_of(base: RunConfig, candidate: dict, archive=None) -> RunConfig:
    """``base`` with a candidate's settings (``archive``: a :class:`~.archive.PriorArchive` for plant priors)."""
    opts = {k: candidate[k] for k in ("covariance", "shrink", "widen", "min_records") if k in candidate}
    method_options = dict(base.method_options, bags=int(candidate.get("bags", 10)))
    if candidate.get("half_life_days"):
        method_options["half_life_days"] = float(candidate["half_life_days"])
    for key in ("fit_focal_spot", "loss"):  # else the method's defaults (inputs.FIT_FOCAL_SPOT, lm.LM_LOSS)
        if candidate.get(key):
            method_options[key] = str(candidate[key])
    drift = {"drift_model": candidate.get("drift_model", "none"),
             "process_noise": candidate.get("process_noise", "auto")}
    if candidate.get("prior", "run") == "plant":
        return replace(base, prior="plant", prior_from=archive, prior_options=opts, method_options=method_options,
                       **drift)
    return replace(base, prior="run", prior_from=None, prior_options={}, method_options=method_options, **drift)


def eligible(dataset, min_records: int = 50, focal_spot: str = "HeliOS") -> list:
    """Heliostats with at least ``min_records`` usable records (those a benchmark calibrates and tests)."""
    counts = dataset.records.with_focal_spot(focal_spot).counts()
    ids = dataset.records.heliostat_ids
    return [h for h, c in zip(ids, counts.tolist()) if c >= min_records]


def folds_of(heliostats, k: int, seed: int) -> list:
    """``k`` folds of heliostat ids (seeded shuffle, round-robin; sizes differ by at most one)."""
    order = list(np.random.default_rng(seed).permutation(len(heliostats)))
    return [[heliostats[i] for i in order[j::k]] for j in range(k) if order[j::k]]


def cross_validated_errors(dataset, base: RunConfig, candidates, heliostats, *, runner: Runner, folds: int,
                           seed: int = 0, archive=None, exclude=(), log=None, collect: dict | None = None) -> dict:
    """Per candidate (its :func:`label`), heliostat id -> mean test error [mrad] under K-fold over heliostats.

    Fold k is calibrated in one run of ``runner`` (``base`` settings, ``heliostats=fold k``); the plant prior
    excludes fold k (the run's heliostats) and every id in ``exclude``. ``collect`` (optional) receives, per
    candidate, the list of the runs' predictive-interval inputs (for :func:`choose_drift`).
    """
    out = {}
    for cand in candidates:
        errs = {}
        # The run's own field prior learns only from the run's training records: no fold is needed, and
        # calibrating the heliostats together is how that candidate is used (its prior needs >= 4 of them).
        groups = [list(heliostats)] if cand.get("prior", "run") == "run" else folds_of(list(heliostats), folds, seed)
        for fold in groups:
            cfg = replace(config_of(base, cand, archive), heliostats=fold, prior_exclude=list(exclude))
            rep, _, arrays = runner(cfg, dataset)
            errs.update({h: r["mean_test_mrad"] for h, r in rep["heliostats"].items()
                         if h in fold and r.get("status") == "ok"})
            if collect is not None and arrays.get("interval_inputs"):
                collect.setdefault(label(cand), []).append(arrays["interval_inputs"])
        out[label(cand)] = errs
        if log:
            log(f"  {label(cand):28s} median {median(errs.values()):.3f} mrad over {len(errs)} heliostats")
    return out


def median(values) -> float:
    """Median of the finite values (``None`` and NaN left out); ``inf`` when none is left."""
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.median(v)) if v else float("inf")


def select(scores: dict, candidates) -> dict:
    """The candidate whose per-heliostat errors (``scores[label]``) have the lowest median (ties: earlier)."""
    return candidates[lowest({i: median(scores[label(c)].values()) for i, c in enumerate(candidates)})]


#: Monte-Carlo draws per record when a current run calibrates its predictive interval (:func:`choose_current`).
INTERVAL_CHOICE_SAMPLES = 1000


def held_out_errors(report: dict) -> dict:
    """Heliostat id -> mean held-out error [mrad] of a run's report (heliostats whose fit succeeded)."""
    return {h: r["mean_test_mrad"] for h, r in report["heliostats"].items()
            if r.get("status") == "ok" and r.get("mean_test_mrad") is not None}


def choose_current(cfg: RunConfig, dataset, *, runner: Runner, drift: bool = True, bags: int = LM_BAGS,
                   level: float = 0.05, interval: bool = True, log=None) -> tuple[RunConfig, tuple, dict]:
    """The ``lm`` settings of a current plant chosen by validation inside its records, cheapest first.

    ``cfg`` is a validation protocol (each heliostat's latest records predicted from its earlier ones,
    :func:`~.config.validation_protocol`). The candidates, in order of cost: the static rigid body unbagged;
    bagged over ``bags`` bootstrap resamples (``bags + 1`` fits: it pays where a heliostat has few records, one
    outlier or unlucky sun moving a small fit -- 1.80 -> 1.34 mrad at 10 records in the shared folder's
    chronological study -- and not where it has many, 1.15 -> 1.14 at 30); with ``drift``, the rigid body plus
    a random-walk offset of the axis offsets (``--drift kalman``; its process noise chosen inside each
    training part), which follows steps and drift that a static fit averages over the years. Each is run
    once; a costlier candidate replaces the current choice only when it lowers more heliostats' held-out error
    than chance explains (:func:`heliotwin.calibrate.choice.worth_its_cost`, one-sided sign test at ``level``),
    so the records decide, not a constant. With ``interval`` (and no interval drift given in ``cfg``) the
    predictive interval is then calibrated on the chosen run's held-out records (:func:`choose_interval`): the
    offset drift and walk scale whose 90 % intervals cover them closest to 0.9.

    Returns
    -------
    (settings, run, info): ``cfg``'s method options and drift model as chosen (a random walk's process noise
    fixed at the value its validation run chose), the chosen candidate's ``(report, model, arrays)``, and
    ``info``: each candidate's median held-out error [mrad] and seconds, each sign test, the choice.
    """
    cands = [("static", {"bags": 0}, {}), (f"static, {bags} bags", {"bags": bags}, {})]
    if drift:
        cands.append(("random-walk offset", {"bags": 0}, {"drift_model": "kalman", "process_noise": "auto"}))
    runs = {}
    for k, (name, options, model) in enumerate(cands):
        c = replace(cfg, method_options=dict(cfg.method_options, **options), **model)
        if log:  # names the block of steps that follows (a run of the pipeline per candidate)
            log(f"validation candidate {k + 1}/{len(cands)} '{name}': each heliostat's latest {cfg.test} records "
                "predicted from its earlier ones")
        runs[name] = (c, runner(c, dataset))
    chosen, tests = cands[0][0], []
    for name, _, _ in cands[1:]:
        take, test = worth_its_cost(held_out_errors(runs[chosen][1][0]), held_out_errors(runs[name][1][0]), level)
        tests.append({"candidate": name, "against": chosen, "taken": take, **test})
        chosen = name if take else chosen
    c, run = runs[chosen]
    q = c.process_noise
    if c.drift_model == "kalman":  # the final fit takes the walk the validation chose, not a second choice
        q = float(((run[0].get("overall") or {}).get("method_info") or {}).get("process_noise_mrad2_per_day", q))
    info = {"chosen": chosen, "candidates": [n for n, _, _ in cands], "level": level,
            "median_mrad": {n: median(held_out_errors(r[1][0]).values()) for n, r in runs.items()},
            "seconds": {n: (r[1][0].get("overall") or {}).get("seconds") for n, r in runs.items()}, "tests": tests,
            "rule": "the cheapest candidate unless a costlier one lowers more heliostats' held-out error than "
                    f"chance explains (one-sided sign test, p < {level})"}
    if c.drift_model == "kalman":
        info["process_noise_mrad2_per_day"] = q
    options = dict(c.method_options)
    inputs = (run[2] or {}).get("interval_inputs")
    if interval and inputs and "drift" not in cfg.method_options:
        # the predictive interval calibrated on the same held-out records: its offset drift and walk scale
        t0 = time.perf_counter()
        # 1,000 draws per record (not the interval's 4,000): a coverage averages over thousands of records, and
        # the 28 grid points then cost seconds, not tens of them, at a plant of 2,000 heliostats
        drift, scale, cov = choose_interval([inputs], samples=INTERVAL_CHOICE_SAMPLES)
        options.update(drift=drift, walk_scale=scale)
        info["interval"] = {"drift_mrad": 1e3 * drift, "walk_scale": scale, "coverage": cov[(drift, scale)],
                            "seconds": time.perf_counter() - t0,
                            "uncalibrated_coverage": cov.get((0.0, 1.0)),
                            "rule": "the offset drift and walk scale whose 90 % intervals cover the held-out "
                                    "records closest to 0.9 (DRIFT_GRID x WALK_SCALES)"}
    if log:
        log("  " + ", ".join(f"{n}: {m:.3f} mrad" for n, m in info["median_mrad"].items()) + f" -> {chosen}")
    settings = replace(cfg, method_options=options, drift_model=c.drift_model, process_noise=q)
    return settings, run, info


#: Offset drift values tried for the predictive interval [rad] (:func:`choose_drift`).
DRIFT_GRID = (0.0, 2.5e-4, 5e-4, 7.5e-4, 1e-3, 1.5e-3, 2e-3)


def coverage(inputs: list, drift: float, seed: int = 0, samples: int | None = None, walk_scale: float = 1.0) -> float:
    """Fraction of the records in ``inputs`` (runs' ``interval_inputs``) whose error lies in the 90 % interval."""
    inside, n = 0, 0
    for x in inputs:
        if len(x["error"]) == 0:
            continue
        cov = x["covariance"] + walk_scale * x["walk"] if x.get("walk") is not None else x["covariance"]
        pred = predictive(x["jacobian"], x["normal"], cov, x["noise"], drift=drift,
                          samples=samples or SAMPLES, generator=torch.Generator().manual_seed(seed))
        inside += int(((x["error"] >= pred["lower"]) & (x["error"] <= pred["upper"])).sum())
        n += len(x["error"])
    return inside / n if n else float("nan")


def choose_drift(inputs: list, grid=DRIFT_GRID, target: float = 0.9, samples: int | None = None) -> tuple[float, dict]:
    """The offset drift [rad] whose 90 % intervals cover a fraction closest to ``target`` of the records of
    ``inputs`` (cross-validation runs on heliostats other than the ones it will be applied to; ties: the
    smaller drift). Returns (drift, {drift: coverage})."""
    cov = {d: coverage(inputs, d, samples=samples) for d in grid}
    best = min(grid, key=lambda d: (abs(cov[d] - target), d))
    return best, cov


#: Scales of the random-walk offset's covariance in the interval (:func:`choose_interval`).
WALK_SCALES = (1.0, 0.3, 0.1, 0.0)


#: Rules of :func:`choose_interval`: the coverage ``closest`` to the target, or the narrowest interval that
#: reaches ``at_least`` the target (what settings learned for a whole plant use: the heliostats they will
#: serve were not among those the coverage was measured on, and a miss below the nominal level is the costly
#: side for an operator).
INTERVAL_RULES = ("closest", "at_least")


def choose_interval(inputs: list, grid=DRIFT_GRID, scales=WALK_SCALES, target: float = 0.9,
                    samples: int | None = None, rule: str = "closest") -> tuple[float, float, dict]:
    """:func:`choose_drift` jointly with the scale of the random-walk offset's covariance (runs without a
    drift state: every scale is the same; ties: smaller drift, then larger scale). ``rule``
    (:data:`INTERVAL_RULES`): ``"at_least"`` takes the smallest drift (then the largest scale) whose coverage
    reaches ``target`` (the largest coverage when none does). Returns (drift [rad], walk_scale,
    {(drift, scale): coverage})."""
    if rule not in INTERVAL_RULES:
        raise ValueError(f"rule must be one of {INTERVAL_RULES}, got {rule!r}")
    has_walk = any(x.get("walk") is not None and bool((x["walk"] != 0).any()) for x in inputs)
    scales = scales if has_walk else (1.0,)
    cov = {(d, s): coverage(inputs, d, samples=samples, walk_scale=s) for d in grid for s in scales}
    reaching = [k for k in cov if cov[k] >= target]
    if rule == "at_least" and reaching:
        best = min(reaching, key=lambda k: (k[0], -k[1]))
    elif rule == "at_least":
        best = max(cov, key=lambda k: (cov[k], -k[0], k[1]))
    else:
        best = min(cov, key=lambda k: (abs(cov[k] - target), k[0], -k[1]))
    return best[0], best[1], cov


def nested_cv(dataset, base: RunConfig, candidates=None, *, runner: Runner, folds: int = 4, inner_folds: int = 3,
              min_records: int = 50, seed: int = 0, archive=None, log=None) -> dict:
    """Leave-heliostats-out CV of the whole choice procedure (module docstring): for each outer fold,
    :func:`choose_for_run` (what ``heliotwin calibrate --settings cv`` runs) chooses on the other heliostats
    only, and the chosen settings are scored on the fold.

    Returns
    -------
    dict
        ``heliostats`` (id -> held-out mean test error [mrad]), ``median_of_mean_test_mrad`` (the CV
        figure), ``interval_90_coverage`` (held-out records inside their 90 % interval, drift chosen on the
        inner folds), ``folds`` (per outer fold: held-out ids, chosen candidate and drift, inner medians).
    """
    if archive is None:
        archive = PriorArchive.from_dataset(dataset, focal_spot=base.focal_spot, source=str(base.paint))
    ids = eligible(dataset, min_records, base.focal_spot)
    held_out, report, cov_in = {}, [], []
    for k, fold in enumerate(folds_of(ids, folds, seed)):
        if log:
            log(f"outer fold {k}: held out {','.join(fold)}; choosing on {len(ids) - len(fold)} heliostats")
        cfg, choice = choose_for_run(replace(base, prior_from=base.paint, min_records=min_records), fold, dataset,
                                     runner=runner, folds=inner_folds, candidates=candidates, archive=archive,
                                     seed=seed + 1 + k, run_size=len(ids), log=log)
        chosen = choice["candidate"]
        # a run-prior candidate is used on all heliostats at once (training records only; see above)
        run_on = ids if chosen.get("prior", "run") == "run" else fold
        rep, _, arrays = runner(replace(cfg, heliostats=run_on, settings="given"), dataset)
        errs = {h: rep["heliostats"][h]["mean_test_mrad"] for h in fold if rep["heliostats"][h].get("status") == "ok"}
        held_out.update(errs)
        iv = arrays.get("interval_inputs") or {}
        mine = [i for i, h in enumerate(iv.get("heliostat", [])) if h in fold]
        drift, scale = 1e-3 * choice["drift_mrad"], choice["walk_scale"]
        if mine:
            sub = {key: (iv[key][mine] if key != "heliostat" else None) for key in iv}
            inside = coverage([sub], drift, walk_scale=scale)
            cov_in.append((inside * len(mine), len(mine)))
        report.append({"held_out": fold, "chosen": choice["chosen"], "drift_rad": drift, "walk_scale": scale,
                       "inner_median_mrad": choice["table"], "held_out_mean_test_mrad": errs})
        if log:
            log(f"outer fold {k}: chose {choice['chosen']}, drift {choice['drift_mrad']:.2f} mrad; held-out errors "
                + ", ".join(f"{h} {e:.2f}" for h, e in errs.items()))
    n_cov = sum(n for _, n in cov_in)
    return {"heliostats": held_out, "median_of_mean_test_mrad": median(held_out.values()), "folds": report,
            "interval_90_coverage": sum(c for c, _ in cov_in) / n_cov if n_cov else None}

#: How many times this process chose settings by CV (:func:`choose_for_run`): a run that reuses stored
#: settings leaves it unchanged (what the tests check; not a timing).
CALLS = {"choose_for_run": 0}

#: Test records per refit in the online CV runs of :func:`choose_for_run` (at least; 3 refits for 30 records).
ONLINE_CV_STEP = 10

#: Fewest eligible archive heliostats for choosing settings by leave-heliostats-out CV (4 folds of >= 1).
MIN_CV_HELIOSTATS = 4

#: Most heliostats the settings CV scores (a seeded sample of the eligible ones; the plant priors of its folds
#: still learn from every other archive heliostat). The median of 200 heliostats' errors is known to a few
#: percent, which is what tells candidates apart; a plant of 2,000 then chooses its settings in minutes, not
#: in the half hour that scoring every heliostat with every candidate took.
CV_HELIOSTATS = 200


def choose_for_run(cfg: RunConfig, calibrated, dataset=None, *, runner: Runner, folds: int = 4, candidates=None,
                   archive=None, seed: int = 0, run_size: int | None = None, log=None,
                   progress: bool = False, interval_rule: str = "closest") -> tuple[RunConfig, dict]:
    """``--settings cv``: the run's settings chosen by leave-heliostats-out CV on its ``--prior-from`` archive.

    The procedure of :func:`nested_cv`'s inner loop, applied to a real run: every candidate of
    :data:`CANDIDATES` is scored by K-fold CV over the archive's heliostats with enough records (the run's
    split, ``--train`` and ``--test``: an ``online`` run chooses on the online protocol, refitting every
    :data:`ONLINE_CV_STEP` test records or the run's ``online_step`` if larger, to bound the cost), the
    lowest median wins (:func:`select`), and the predictive interval's offset drift and walk scale are chosen
    by the CV runs' coverage (:func:`choose_interval`). No record of a ``calibrated`` heliostat enters any of
    it: they are neither scored nor fitted into any prior (the no-leakage rule of :mod:`.archive`). Above
    :data:`CV_HELIOSTATS` eligible heliostats a seeded sample of that many is scored.

    Parameters
    ----------
    cfg : RunConfig
        The run's settings; ``cfg.prior_from`` is a PAINT folder (path) of the same plant.
    calibrated : list of str
        The run's heliostat ids.
    dataset : heliotwin.io.paint.PaintDataset, optional
        The archive folder, already loaded.
    runner : callable
        One calibration run, ``runner(cfg, dataset) -> (report, model, arrays)`` (:data:`Runner`): what scores
        each candidate on each fold.
    candidates : sequence of dict
        The settings tried (default: :data:`CANDIDATES` at call time).
    archive : PriorArchive, optional
        Fits of the archive's heliostats, when already made (the calibrated ones are excluded from every
        prior either way); ``seed`` seeds the folds.
    run_size : int, optional
        Heliostats the chosen settings will be fitted on together (default: the calibrated ones); below
        :data:`~heliotwin.calibrate.priors.MIN_HELIOSTATS` the run-prior candidates are not tried.

    Returns
    -------
    (RunConfig, dict)
        The run's settings with the chosen candidate (its plant prior from a
        :class:`~heliotwin.calibrate.protocol.archive.PriorArchive` of the archive, calibrated heliostats excluded),
        and the JSON-ready record of the choice (``table``: candidate -> CV median [mrad], ``chosen``,
        ``drift_mrad``, ``walk_scale``, ``coverage``, ``heliostats``, ``folds``).

    Raises
    ------
    HeliotwinError
        One line, when the archive has fewer than :data:`MIN_CV_HELIOSTATS` heliostats with enough records
        outside the calibrated ones, or the method is not ``lm``.
    """
    if cfg.method != "lm":
        raise HeliotwinError(f"--settings cv chooses lm settings; --method is {cfg.method}")
    CALLS["choose_for_run"] += 1
    path = os.fspath(cfg.prior_from)
    ds = dataset if dataset is not None else load_paint(path, plane_tolerance=cfg.plane_tolerance)
    calibrated = list(calibrated)
    ids = [h for h in eligible(ds, cfg.min_records, cfg.focal_spot) if h not in set(calibrated)]
    n_eligible = len(ids)
    if n_eligible > CV_HELIOSTATS:  # a seeded sample: every candidate is scored on the same heliostats
        pick = np.random.default_rng(seed).choice(n_eligible, CV_HELIOSTATS, replace=False)
        ids = [ids[i] for i in sorted(pick.tolist())]
    if len(ids) < MIN_CV_HELIOSTATS:
        raise HeliotwinError(f"{path}: --settings cv needs {MIN_CV_HELIOSTATS} heliostats with >= {cfg.min_records} "
                             f"records outside the calibrated ones, found {len(ids)}")
    if archive is None:
        archive = PriorArchive.from_dataset(ds, focal_spot=cfg.focal_spot, source=path, exclude=calibrated)
    base = replace(cfg, paint=path, heliostats=None, prior="run", prior_from=None, prior_options={},
                   prior_exclude=[], method_options={}, drift_model="none", process_noise="auto",
                   online_step=max(cfg.online_step, ONLINE_CV_STEP), progress=False, settings="given")
    collect: dict = {}
    cands = tuple(CANDIDATES if candidates is None else candidates)
    if (len(calibrated) if run_size is None else run_size) < MIN_HELIOSTATS:
        # The run's own field prior needs MIN_HELIOSTATS heliostats; below that it falls back to the nominal
        # prior, which CV (over the whole archive at once) never scored: only plant-prior candidates apply.
        cands = tuple(c for c in cands if c.get("prior", "run") == "plant")
        if not cands:
            raise HeliotwinError(f"--settings cv: the run calibrates {len(calibrated)} heliostat(s); the candidates "
                                 f"with the run's own field prior need {MIN_HELIOSTATS} and none uses a plant prior")
    if progress:
        bar = tqdm(total=len(cands), desc="settings by CV", leave=False, disable=None)
    scores: dict = {}

    def dump():
        return {"scores": dict(scores), "collect": {k: list(v) for k, v in collect.items()}}

    def load(saved):
        scores.update(saved["scores"])
        collect.update(saved["collect"])
        if log:
            log(f"  resumed after {len(scores)} of {len(cands)} candidates")

    # one candidate per step under the run's checkpoint (Ctrl-C keeps the finished ones; --resume goes on)
    for i in resumable_range("settings_cv", len(cands), dump, load):
        scores.update(cross_validated_errors(ds, base, [cands[i]], ids, runner=runner, folds=min(folds, len(ids)),
                                             seed=seed, archive=archive, exclude=calibrated, log=log, collect=collect))
        if progress:
            bar.update(1)
    if progress:
        bar.close()
    chosen = select(scores, cands)
    drift, scale, cov = choose_interval(collect.get(label(chosen), []), rule=interval_rule)
    run_cfg = config_of(cfg, chosen, archive)
    run_cfg = replace(run_cfg, method_options=dict(run_cfg.method_options, drift=drift, walk_scale=scale))
    record = {"procedure": f"leave-heliostats-out {min(folds, len(ids))}-fold CV on {path} "
                           f"({base.split}, train {cfg.train}, test {cfg.test}); lowest median of the heliostats' "
                           "mean test error; interval drift and walk scale by CV coverage "
                           + ("closest to 0.9" if interval_rule == "closest" else "reaching 0.9"),
              "archive": path, "split": cfg.split, "train": cfg.train, "test": cfg.test,
              "heliostats": ids, "eligible_heliostats": n_eligible, "excluded": calibrated,
              "folds": min(folds, len(ids)),
              "table": {k: median(v.values()) for k, v in scores.items()}, "chosen": label(chosen),
              "candidate": dict(chosen), "drift_mrad": 1e3 * drift, "walk_scale": scale,
              "coverage": {f"{1e3 * d:g} mrad, walk x{s:g}": c for (d, s), c in cov.items()}}
    return run_cfg, record


def learn_for_plant(cfg: RunConfig, *, runner: Runner, run_size: int, progress: bool = False, log=None):
    """``--learn-settings``: the lm settings and interval calibration for later runs on this plant, chosen
    once by :func:`choose_for_run` on every eligible heliostat of the run's own folder (``cfg.paint``; only
    ``cfg.prior_exclude`` left out; the interval by the ``at_least`` rule of :func:`choose_interval`), and the
    plant prior of the chosen candidate learned from all of them. ``run_size`` is the number of heliostats
    the run calibrates [1] (below :data:`~heliotwin.calibrate.priors.MIN_HELIOSTATS` the run-prior candidates
    are not tried).

    Returns
    -------
    (dict, PlantPrior or None)
        The JSON-ready choice record (as :func:`choose_for_run`'s, with ``"learned_for_plant": True``), and the
        chosen plant prior (None when the choice is the run's own field prior).
    """
    path = os.fspath(cfg.paint)
    ds = load_paint(path, plane_tolerance=cfg.plane_tolerance)
    excluded = list(cfg.prior_exclude)
    archive = PriorArchive.from_dataset(ds, focal_spot=cfg.focal_spot, source=path, exclude=excluded)
    base = replace(cfg, prior_from=path, settings="cv", learn_settings=False)
    _, record = choose_for_run(base, excluded, ds, runner=runner, archive=archive, run_size=run_size,
                               progress=progress, log=log, interval_rule="at_least")
    cand = record["candidate"]
    prior = None
    if cand.get("prior", "run") == "plant":
        opts = {k: cand[k] for k in ("covariance", "shrink", "widen", "min_records") if k in cand}
        prior = archive.prior(excluded, **opts)
    return dict(record, learned_for_plant=True), prior


def stored_choice(cfg: RunConfig, calibrated) -> tuple[RunConfig, dict]:
    """``--settings stored``: the settings a ``--settings cv`` run chose and stored in the ``--prior-from``
    scenario (``/learned/calibration/settings_choice``), applied to this run where that is honest.

    The stored choice is used only when (a) the scenario holds one, (b) it was chosen for this run's protocol
    (same ``--split`` family: online or not, and the same ``--train``), (c) it used a plant prior (the
    scenario's stored prior is then exactly the prior that was chosen; a choice of the run's *own* field
    prior says nothing about a prior learned elsewhere), and (d) none of this run's heliostats was scored by
    that choice (its CV saw their records: the no-leakage rule of :mod:`.archive`). Otherwise the run keeps
    its flags and the returned record says why.

    Returns
    -------
    (RunConfig, dict)
        The run's settings and the JSON-ready record (``used``: bool, ``reason`` when not, the stored
        ``chosen``/``candidate``/``drift_mrad``/``walk_scale`` and where it came from).
    """
    path = os.fspath(cfg.prior_from)
    text = (load_scenario(path).learned.get(KEY) or {}).get("settings_choice")
    given = replace(cfg, settings="given")
    if not text:
        return given, {"used": False, "source": path, "reason": "the scenario holds no settings choice (it was "
                                                                  "not written by a --settings cv run)"}
    try:
        stored = json.loads(text)
        cand, drift, scale = dict(stored["candidate"]), float(stored["drift_mrad"]), float(stored["walk_scale"])
    except (TypeError, ValueError, KeyError):
        raise InputFileError(path, "malformed settings choice", field=f"/learned/{KEY}/settings_choice") from None
    record = {"used": False, "source": path, **{k: stored.get(k) for k in ("chosen", "candidate", "drift_mrad",
                                                                           "walk_scale", "split", "train",
                                                                           "archive", "procedure")}}
    scored = sorted(set(stored.get("heliostats") or []) & set(calibrated))
    online = (stored.get("split") == "online", cfg.split == "online")
    if online[0] != online[1] or stored.get("train") != cfg.train:
        record["reason"] = (f"chosen for split {stored.get('split')}, train {stored.get('train')}; this run is "
                            f"split {cfg.split}, train {cfg.train}")
    elif cand.get("prior", "run") != "plant" and not stored.get("learned_for_plant"):
        record["reason"] = "the stored choice is the run's own field prior, not a prior to carry to other heliostats"
    elif scored:
        record["reason"] = f"the stored choice was scored on heliostat(s) {', '.join(scored)} that this run calibrates"
    else:
        # the scenario's stored prior is the chosen plant prior; a run-prior choice learned for the plant
        # (settings of the run's own field prior, and the interval calibration) applies as it is
        run_cfg = config_of(given, cand, path if cand.get("prior", "run") == "plant" else None)
        run_cfg = replace(run_cfg, method_options=dict(run_cfg.method_options, drift=1e-3 * drift, walk_scale=scale))
        record.update(used=True, original=stored)  # kept whole: a scenario written by this run stores it again
        return run_cfg, record
    return given, record
