"""What else could carry the chrono figure (issue 10)? Diagnostics, each an idea that was tried and not kept.

Every fit here uses the calibration's own conventions (properties corrected where the records support it,
:func:`heliotwin.calibrate.protocol.suspicious.check_and_correct`; UTIS centroids for fitting,
:func:`heliotwin.calibrate.inputs.fit_spots`; the robust ``soft_l1`` loss; the nominal Stone/Jülich prior
of :func:`heliotwin.calibrate.methods.lm.fit_lm`); errors are scored on HeliOS centroids as the benchmark does, on
the heliostats with >= 50 records. Figures are medians over heliostats [mrad].

1. **Parameter sets** (``--part params``): the Stone/Jülich 8 against the 8 + the actuator geometry
   (pivot radius, offset of both actuators) and all 26 visible deviations of the chain. Scored by random
   5-fold CV inside each heliostat's whole history (sun-position extrapolation without drift; a static model
   cannot follow drift anyway) and by "every record before the latest 30 -> the latest 30".
2. **Shared sun-position structure** (``--part shared``): the residuals of each heliostat's all-record fit,
   regressed (ridge, polynomial in sun azimuth/elevation) on the *other* heliostats' residuals; does that
   plant-level correction lower a left-out heliostat's residuals on its latest 30 records? An upper bound
   for a plant-level correction model (the heliostat's own fit saw those records).
3. **A plant-wide offset at the same time** (``--part common``): each heliostat's residual on its test
   block (chrono, fit on its earliest N), corrected by the median residual of the *other* heliostats within
   +-W days (from their all-record fits): is the test block's offset common to the plant?
4. **The two cameras** (``--part sources``): HeliOS - UTIS centroid per target, over every record with both
   (no fit): the constant that ``fit_focal_spot = "harmonised"`` removes
   (:func:`heliotwin.calibrate.inputs.source_offsets`; its effect on the protocol is a CV candidate of
   ``bench_carryover.py``).
5. **A trend that extrapolates** (``--part trend``): each heliostat fitted on every record before its latest
   30; the test block's residual after removing the median level of the training residuals of the last W
   days, or their Theil-Sen line extrapolated to each test record's time (a local-linear-trend drift model's
   forecast, in the most favourable case: no gap between training and test).
6. **The heliostat's place in the field** (``--part position``): is a heliostat's kinematic deviation
   predicted better by its neighbours (median of the k nearest) or by a plane in (east, north) than by the
   plant median the plant prior is centred on? Leave-one-heliostat-out over the archive's fits (heliostats
   with >= 15 records): a spatial prior mean would need this.
7. **Which archive heliostats make the plant prior** (``--part archive``): the plant prior built only from
   archive heliostats with >= 9 (the default) / 30 / 50 records, under the benchmark's 4-fold
   leave-heliostats-out CV at N=30 and N=10.
8. **The plant covariance without the archive fits' own noise** (``--part deconvolve``): the deviations'
   covariance minus the mean Laplace posterior covariance of the archive fits (method of moments), same CV.
9. **A plant prior with heavy tails** (``--part tails``): Gaussian near the plant mean, Huber beyond the
   chi-square 99 % Mahalanobis radius (iteratively reweighted), with the archive heliostats of >= 9 / >= 30
   records, same CV: does it keep part 7's gain without pulling the outlier?
10. **The cameras' per-target offset on the prediction** (``--part shift``): the fit trained on UTIS as shipped,
    each test record's prediction moved by the HeliOS - UTIS offset of its target from the run's training
    records (``harmonised`` moves the training centroids instead).
11. **A temperature-dependent offset** (``--part weather``): each heliostat's training residuals of the protocol
    run regressed on the air temperature of ``metadata/calibration-weather.csv``, the line (or its slope
    alone) applied to the test records: thermal expansion of actuators and pylon is of the right size.
12. **Model averaging** (``--part average``): the mean of several candidates' predictions instead of the one
    the CV chooses, on the protocol itself (every pair, and all of them).

Measured on ``../shared/data/paint`` (11 heliostats, 1 thread, 2026-11-22, ~8 min; N=30 in part 3, whose fit
has the nominal prior only, hence its larger test residual than the benchmark's):

* params: random 5-fold CV 0.637 / 0.638 / 0.637 and every earlier record -> latest 30 1.051 / 0.984 / 0.967
  for Stone 8 / + actuators / all 26. The second figure's median moves only because AK32 is the median
  heliostat and the one that gains (1.051 -> 0.967; its axis-2 actuator values are unusual but consistent
  with its records, see :mod:`heliotwin.calibrate.protocol.suspicious`); every other heliostat changes by < 0.05 and
  BG23 gets worse (1.830 -> 1.878). Not kept: more rigid-body parameters do not carry over.
* shared: latest-30 residual 0.724 -> 0.720 (degree 2) and 0.715 (degree 3) after the other heliostats'
  correction, with the heliostat's own fit on those records: at most ~0.01 mrad for a plant-level
  sun-position model. Not kept.
* common: the others' same-time offset moves the median test residual 1.577 -> 1.571 / 1.578 / 1.549 /
  1.557 (W = 5 / 15 / 30 / 60 d) with 6-7 of 11 heliostats better: the test block's offset is the
  heliostat's own, not the plant's. Not kept.
* sources: HeliOS sits 7.8 cm above UTIS on the lower target (429 pairs; per-heliostat medians 1.6..16 cm),
  2.0 cm below on the upper (459) and 4.2 cm above on the multi-focus tower (372); per year 2022/2023/2024
  the "up" medians are 7.8/8.0/6.3, -2.5/-1.8/-1.6 and 2.5/4.2/4.9 cm. Sideways the heliostats differ more
  (-11..+13 cm). A camera offset of a few cm is 0.1-0.4 mrad of normal at 50-280 m: real, stable and the
  plant's, so it is a candidate (``harmonised``) that the CV may choose; see ``bench_carryover.py``.
* trend (~5 s): latest-30 residual static 1.021, level of the last 30 / 90 / 180 d 0.998 / 0.939 / 0.926,
  trend 1.827 / 2.223 / 1.515 mrad; the trend beats the level on 2-3 of 11 heliostats. The offset steps and
  wanders but does not keep going: a trend term (integrated random walk) would extrapolate noise. Not kept;
  the random walk (level) is what ``calibrate.drift`` models.
* position (2026-11-23, ~1 min, 18 heliostats): whitened squared prediction error (median) 7.66 for the plant
  median against 12.74 / 9.45 for the 3 / 5 nearest heliostats and 12.78 for a plane in (east, north); per
  parameter the neighbours win on 2-4 of 8 and lose the rest. Correlations with east or north reach |r| ~0.5
  on 18 heliostats but do not predict a left-out one. Not kept: the plant prior stays centred on the plant.
* archive (2026-11-23, ~4 min; plant/full/s0.2/b10, width x1 / x2): N=30 median 0.997 / 1.108 with >= 9
  records, 0.884 / 1.046 with >= 30, 1.018 / 1.023 with >= 50; N=10 1.232 / 1.261, 1.238 / 1.227, 1.377 /
  1.524. The >= 30 prior wins the N=30 median because BF55 (1.78 -> 0.84) and others gain, but AC33 (the
  outlier whose axis-2 stroke is corrected) goes 2.06 -> 10.22 mrad: a tighter prior from fewer heliostats
  pulls an outlier hard. Not kept as a candidate: a median rule would pick a setting that ruins one
  heliostat. The few-record fits do distort the prior: with all 25 archive heliostats (>= 9 records) the
  prior's sigma of initial_angle_2 is 13.9 mrad, with the 12 of >= 30 records 6.0 (joint_tilt_1_n 9.7 / 6.0,
  joint_tilt_2_n 5.2 / 3.4): the 9-record fits' own noise along the near-degenerate directions widens the
  plant's spread. The remedy is a hierarchical estimate that subtracts (or weights by) each archive fit's
  own posterior covariance, with heavier tails (Student-t) so that an outlier like AC33 is not pulled (not
  built as such; the plain subtraction is part 8 and fails, a heavy tail is part 9 and does not help).
* deconvolve (2026-11-23, ~4 min): subtracting the fits' mean posterior covariance shrinks the prior hard
  (sigma of initial_angle_1 5.45 -> 1.94, concentrator_tilt_e 5.91 -> 1.00 = the floor, initial_angle_2
  13.9 -> 9.8 mrad) and every CV median gets worse: N=30 1.400 / 1.251 (width x1 / x2) against 0.997 /
  1.108, N=10 1.762 / 1.779 against 1.232 / 1.261 (AK46 gains, 3.46 -> 1.81 at N=30; BF41, BH58, AC33
  lose). The Laplace covariance of a loose-prior fit is not the archive fit's real error (its loss is robust,
  its noise is not white over a heliostat's history): not kept.
* tails (2026-11-23, ~2 min, 2 threads; plant/full/s0.2/w1/b10): Gaussian / Huber medians N=30 0.997 / 0.997
  (>= 9 records) and 0.884 / 0.884 (>= 30); N=10 1.232 / 1.232 and 1.238 / 1.238. Only the outliers move: with
  the >= 30 prior AC33 10.22 -> 4.91 at N=30 (still worse than 2.06 under the default prior; the mean over the
  11 heliostats is 1.553 against 1.389) but 10.59 -> 12.77 at N=10, BF41 1.20 -> 1.00. A heavier tail does not
  rescue the prior of long histories: AC33's trouble is where its 30 records leave its parameters free, not
  the prior's tail. Not kept.
* shift (2026-11-23, ~1 min): HeliOS - UTIS "up" from the training records +7.8 / -0.4 / +2.7 cm (lower /
  upper / multi-focus) at N=30. Chosen run-prior candidates: N=30 ``run/b10/hl20d`` median 0.903 -> 0.857,
  mean 1.363 -> 1.338, 6 of 11 better; N=10 ``run/b10`` 1.467 -> 1.512, mean 2.042 -> 2.029, 5 of 11 better
  (at N=10 no training record lies on the multi-focus tower, so its test records keep no offset). Half the
  heliostats gain, half lose, and the medians move in opposite directions at N=10 and N=30: the test block's
  own offset dwarfs the ~0.1-0.4 mrad camera offset. Not kept as a candidate (it would add selection noise
  for no consistent gain).
* weather (2026-11-23, ~1 min): the shared folder has temperatures only for March-July 2022, so only AC33, AK32
  and AK46 have one on every training and test record (the medians cannot move). Their errors before ->
  after the line / the slope alone: N=30 ``run/b10/hl20d`` AC33 3.20 -> 2.61 / 2.66, AK32 0.74 -> 0.74 / 0.62,
  AK46 3.06 -> 3.10 / 3.05; N=10 ``run/b10`` AC33 6.56 -> 10.60 / 9.64, AK32 2.12 -> 4.68 / 4.63, AK46 2.06 ->
  1.79 / 1.80 (plant prior: 1.05 -> 2.49 for AK32). The slopes are 0.3-0.9 mrad per 10 K at N=30 but 0.6-5.1
  at N=10, where 10 records span 4-8 K and the test block is 10-20 K warmer: the slope is fitted to noise and
  extrapolated. Partly real at N=30 (spring to summer), ruinous at N=10, and absent for records without
  weather. Not kept; a plant-level coefficient would need heliostats whose signs agree (the all-record fits'
  "up" slopes run from -0.4 to +0.1 mrad per 10 K).
* average (2026-11-23, ~3 min): N=10 singles 1.298-1.467, the best pair (plant w1 + plant w2/hl20d, picked
  on the test records themselves, so optimistic) 1.262, all five 1.334; N=30 singles 0.903-1.170, best pair
  (run/hl20d + run/hl60d) 0.919, all 1.008. The candidates' errors are the same test-block offset seen
  through slightly different fits, so averaging them removes little; never below the best single by more
  than 0.04 and then only with hindsight. Not kept.
* The random 5-fold CV figure (0.637, no time order) against the chrono protocol's ~0.9 is the cost of time:
  what the benchmark's ``reference`` rows split into "more records" and "the test block's own offset".

Usage::

    python benchmarks/bench_carryover_diagnostics.py [--paint ../shared/data/paint]
        [--part params,shared,common,sources,trend,position,archive,deconvolve,tails,shift,weather,
               average]
"""
from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

import numpy as np

DEFAULT_PAINT = Path(__file__).resolve().parents[2] / "shared" / "data" / "paint"

#: The parameter sets of part 1.
ACTUATORS = ("pivot_radius_1", "pivot_radius_2", "offset_1", "offset_2")


def _setup(paint):
    from heliotwin.calibrate.protocol import selection as S
    from heliotwin.calibrate.protocol.suspicious import check_and_correct
    from heliotwin.io.paint import load_paint

    ds = load_paint(paint)
    ids = S.eligible(ds)
    all_ids = list(ds.plant.field.ids)
    batch = ds.records.for_heliostats(ids).with_focal_spot("HeliOS")
    nominal_raw = ds.plant.field.kinematics.index([all_ids.index(h) for h in ids])
    nominal, _ = check_and_correct(nominal_raw, ids, ds.plant.field.kinematics, batch)
    return ids, batch, nominal


def _fit(nominal, batch, names):
    from heliotwin.calibrate.inputs import fit_spots
    from heliotwin.calibrate.methods.lm import LM_F_SCALE, LM_LOSS, fit_lm
    from heliotwin.calibrate.params import apply_deviations

    delta, _ = fit_lm(nominal, fit_spots(batch), names=names, loss=LM_LOSS, f_scale=LM_F_SCALE)
    return apply_deviations(nominal, delta, names)


def _residuals_mrad(kin, batch):
    """In-plane miss / (2 distance): the normal's error in the target's (right, up) directions [mrad], [R, 2]."""
    import torch

    from heliotwin.calibrate import metrics

    with torch.no_grad():
        n, c = metrics.model_normals(kin, batch)
        d = metrics.predicted_spot(n, c, batch) - batch.spot
        dist = (batch.spot - c).norm(dim=-1)
        return np.stack([((d * batch.plane_right).sum(-1) / (2 * dist)).numpy(),
                         ((d * batch.plane_up).sum(-1) / (2 * dist)).numpy()], 1) * 1e3


def _chrono_rows(batch, h, n_first=None, n_last=30):
    t = batch.time.numpy()
    rows = np.nonzero((batch.heliostat_index.numpy() == h) & np.isfinite(t))[0]
    rows = rows[np.argsort(t[rows], kind="stable")]
    return (rows[:n_first] if n_first else rows[:-n_last]), rows[-n_last:]


def part_params(ids, batch, nominal, seed=0):
    import torch

    from heliotwin.calibrate import metrics
    from heliotwin.calibrate.params import NAMES, REDUNDANT, STONE8

    sets = {"stone8": STONE8, "stone8+actuators": STONE8 + ACTUATORS,
            "all26": tuple(n for n in NAMES if n not in REDUNDANT)}
    rng = np.random.default_rng(seed)
    out = {k: {"random_cv": [], "every_earlier": []} for k in sets}
    for h, hid in enumerate(ids):
        sub = batch.subset(batch.heliostat_index == h)
        sub.heliostat_index = torch.zeros_like(sub.heliostat_index)
        sub.heliostat_ids = [hid]
        nom = nominal.index([h])
        folds = rng.permutation(len(sub)) % 5
        early, late = _chrono_rows(sub, 0)
        for k, names in sets.items():
            err = np.zeros(len(sub))
            for f in range(5):
                tr, te = np.nonzero(folds != f)[0], np.nonzero(folds == f)[0]
                kin = _fit(nom, sub.subset(torch.as_tensor(tr)), names)
                err[te] = metrics.pointing_error(kin, sub.subset(torch.as_tensor(te))).detach().numpy()
            out[k]["random_cv"].append(1e3 * err.mean())
            kin = _fit(nom, sub.subset(torch.as_tensor(early)), names)
            out[k]["every_earlier"].append(
                1e3 * float(metrics.pointing_error(kin, sub.subset(torch.as_tensor(late))).mean()))
        print(f"  {hid}: " + ", ".join(f"{k} {v['random_cv'][-1]:.3f}/{v['every_earlier'][-1]:.3f}"
                                       for k, v in out.items()), flush=True)
    for k, v in out.items():
        print(f"params {k:18s} random 5-fold CV {np.median(v['random_cv']):.3f}, every earlier record -> latest 30 "
              f"{np.median(v['every_earlier']):.3f} mrad", flush=True)
    return out


def _poly(x, y, degree):
    cols = [np.ones_like(x)]
    for i in range(1, degree + 1):
        cols += [x ** (i - j) * y ** j for j in range(i + 1)]
    return np.stack(cols, 1)


def part_shared(ids, batch, nominal, ridge=0.1):
    from heliotwin.calibrate.params import STONE8

    res = _residuals_mrad(_fit(nominal, batch, STONE8), batch)
    hi = batch.heliostat_index.numpy()
    good = np.isfinite(res).all(1) & (np.abs(res) < 5).all(1)  # gross outliers would steer the ridge fit
    out = {}
    for degree in (2, 3):
        feats = _poly(batch.sun_azimuth.numpy(), batch.sun_elevation.numpy(), degree)
        before, after = [], []
        for h in range(len(ids)):
            tr = good & (hi != h)
            w = np.linalg.solve(feats[tr].T @ feats[tr] + ridge * np.eye(feats.shape[1]), feats[tr].T @ res[tr])
            _, late = _chrono_rows(batch, h)
            late = late[good[late]]
            before.append(np.linalg.norm(res[late], axis=1).mean())
            after.append(np.linalg.norm(res[late] - feats[late] @ w, axis=1).mean())
        out[degree] = (float(np.median(before)), float(np.median(after)))
        print(f"shared degree {degree}: latest-30 residual {out[degree][0]:.3f} -> {out[degree][1]:.3f} mrad "
              f"with the other heliostats' sun-position correction", flush=True)
    return out


def _others_offset(residuals, heliostat, day, h, t, window):
    """Median over the other heliostats (>= 2, each with >= 3 records within ``window`` days of ``t``) of their
    median residual there, [2] [mrad]; zero when fewer heliostats have records then."""
    finite = np.isfinite(residuals).all(1)
    per = []
    for g in np.unique(heliostat):
        sel = (heliostat == g) & (np.abs(day - t) <= window) & finite
        if g != h and sel.sum() >= 3:
            per.append(np.median(residuals[sel], 0))
    return np.median(per, 0) if len(per) >= 2 else np.zeros(2)


def part_common(ids, batch, nominal, train=30, windows=(5, 15, 30, 60)):
    import torch

    from heliotwin.calibrate.params import STONE8

    res_all = _residuals_mrad(_fit(nominal, batch, STONE8), batch)
    hi, day = batch.heliostat_index.numpy(), batch.time.numpy() / 86400.0
    first, last = zip(*[_chrono_rows(batch, h, n_first=train) for h in range(len(ids))])
    kin = _fit(nominal, batch.subset(torch.as_tensor(np.concatenate(first))), STONE8)
    test = np.concatenate(last)
    res_test = _residuals_mrad(kin, batch.subset(torch.as_tensor(test)))
    out = {}
    for w in windows:
        before, after = [], []
        for h in range(len(ids)):
            m = hi[test] == h
            corr = np.stack([_others_offset(res_all, hi, day, h, t, w) for t in day[test][m]])
            before.append(np.linalg.norm(res_test[m], axis=1).mean())
            after.append(np.linalg.norm(res_test[m] - corr, axis=1).mean())
        better = int(sum(a < b for a, b in zip(after, before)))
        out[w] = (float(np.median(before)), float(np.median(after)), better)
        print(f"common W={w:3d} d: test residual {out[w][0]:.3f} -> {out[w][1]:.3f} mrad, {better} of {len(ids)} "
              f"heliostats better", flush=True)
    return out


def part_sources(paint, min_pairs=3):
    """The two cameras' disagreement (HeliOS - UTIS centroid, target-plane right/up [cm]) per target.

    :func:`heliotwin.validate.camera_agreement` (the median over every record with both centroids) over the
    whole archive, per heliostat (those with >= ``min_pairs`` pairs on the target) and per year. A constant
    per target is what :func:`heliotwin.calibrate.inputs.source_offsets` removes for ``fit_focal_spot =
    "harmonised"``.
    """
    import datetime

    import torch

    from heliotwin.io.paint import load_paint
    from heliotwin.validate import camera_agreement

    rec = load_paint(paint).records
    hi = rec.heliostat_index.numpy()
    year = np.array([datetime.datetime.fromtimestamp(t, datetime.timezone.utc).year if np.isfinite(t) else 0
                     for t in rec.time.numpy()])

    def cm(c):
        return [round(100 * c["right_m"], 1), round(100 * c["up_m"], 1)]

    def split(key):
        return {int(k): camera_agreement(rec.subset(torch.as_tensor(key == k))) for k in np.unique(key) if k}

    per_heliostat, per_year = split(hi + 1), split(year)  # +1: heliostat 0 is not "no key"
    out = {}
    for name, c in camera_agreement(rec).items():
        per = np.array([cm(v[name]) for v in per_heliostat.values() if v.get(name, {}).get("pairs", 0) >= min_pairs])
        years = {y: cm(v[name]) for y, v in per_year.items() if name in v}
        out[name] = {"pairs": c["pairs"], "median_cm": cm(c), "heliostats": len(per),
                     "per_heliostat_range_cm": [per.min(0).tolist(), per.max(0).tolist()], "per_year_cm": years}
        print(f"sources {name:26s} {c['pairs']:4d} pairs: HeliOS - UTIS (right, up) median {cm(c)} cm; per "
              f"heliostat ({len(per)}) right {per[:, 0].min():.1f}..{per[:, 0].max():.1f}, up "
              f"{per[:, 1].min():.1f}..{per[:, 1].max():.1f} cm; per year {years}", flush=True)
    return out


def _level_and_trend(day, res, t, window, min_records=5):
    """Offset [2] [mrad] at the times ``t`` [T] [days] from the residuals ``res`` [n, 2] at ``day`` [n] within
    ``window`` days of the latest: (median level, robust linear trend extrapolated). Trend = Theil-Sen slope
    (scipy) per component, through the window's median point."""
    from scipy.stats import theilslopes

    sel = day >= day.max() - window
    if sel.sum() < min_records:
        sel = np.argsort(day)[-min_records:]
    d, r = day[sel], res[sel]
    level = np.median(r, 0)
    trend = np.stack([np.median(r[:, k]) + theilslopes(r[:, k], d)[0] * (t - np.median(d)) for k in range(2)], 1)
    return np.broadcast_to(level, (len(t), 2)), trend


def part_trend(ids, batch, nominal, windows=(30, 90, 180)):
    """Does the offset move with a trend that extrapolates? Each heliostat's fit on every record before its
    latest 30, its residuals [mrad] there, and the test block's residual after removing (a) nothing, (b) the
    median level of the last W days of training residuals, (c) their Theil-Sen line extrapolated to each test
    record's time. The favourable case for a trend (no gap between training and test)."""
    import torch

    from heliotwin.calibrate.params import STONE8

    day = batch.time.numpy() / 86400.0
    static, out = [], {w: {"level": [], "trend": []} for w in windows}
    for h, hid in enumerate(ids):
        early, late = _chrono_rows(batch, h)
        sub = batch.subset(torch.as_tensor(np.concatenate([early, late])))
        kin = _fit(nominal, batch.subset(torch.as_tensor(early)), STONE8)
        res = _residuals_mrad(kin, sub)
        r_tr, r_te = res[: len(early)], res[len(early):]
        ok = np.isfinite(r_tr).all(1) & (np.abs(r_tr) < 5).all(1)
        static.append(np.linalg.norm(r_te, axis=1).mean())
        for w in windows:
            level, trend = _level_and_trend(day[early][ok], r_tr[ok], day[late], w)
            out[w]["level"].append(np.linalg.norm(r_te - level, axis=1).mean())
            out[w]["trend"].append(np.linalg.norm(r_te - trend, axis=1).mean())
        print(f"  {hid}: static {static[-1]:.3f}, " + ", ".join(
            f"W={w} {v['level'][-1]:.3f}/{v['trend'][-1]:.3f}" for w, v in out.items()), flush=True)
    for w, v in out.items():
        better = int(sum(a < b for a, b in zip(v["trend"], v["level"])))
        print(f"trend W={w:3d} d: latest-30 residual static {np.median(static):.3f}, level "
              f"{np.median(v['level']):.3f}, trend {np.median(v['trend']):.3f} mrad; trend beats level on {better} "
              f"of {len(ids)} heliostats", flush=True)
    return {"static": static, **out}


@functools.lru_cache(maxsize=None)
def _dataset(paint):
    """The loaded PAINT folder (read once for the parts that need it)."""
    from heliotwin.io.paint import load_paint

    return load_paint(paint)


def _protocol_run(paint, n, candidate):
    """The benchmark protocol's run (chrono, train ``n``, test the latest 30, heliostats with >= 50 records)
    of one candidate: its ``model``, ``train`` and ``test`` records and ``run_ids`` (the model's heliostats)."""
    from types import SimpleNamespace

    from heliotwin.calibrate.protocol import selection as S
    from heliotwin.calibrate.protocol.pipeline import RunConfig, run_calibration

    ds = _dataset(paint)
    cfg = S.config_of(RunConfig(paint=str(paint), method="lm", split="chrono", train=n, test=30, min_records=50,
                                heliostats=S.eligible(ds)), candidate)
    _, model, arrays = run_calibration(cfg, ds)
    return SimpleNamespace(model=model, train=arrays["train"], test=arrays["test"], run_ids=arrays["heliostat_ids"])


@functools.lru_cache(maxsize=None)
def _plant_archive(paint):
    """The loaded PAINT folder and its :class:`~heliotwin.calibrate.protocol.archive.PriorArchive` (fitted once for the
    parts that need it)."""
    from heliotwin.calibrate.protocol.archive import PriorArchive

    ds = _dataset(paint)
    return ds, PriorArchive.from_dataset(ds, source=str(paint))


def _print_sigma(tag, prior):
    """One line: a plant prior's marginal sigma per parameter [mrad, or 1e-3 for increments]."""
    sd = 1e3 * prior.covariance.diagonal().sqrt()
    print(f"{tag}: sigma " + ", ".join(f"{n} {v:.2f}" for n, v in zip(prior.names, sd.tolist())), flush=True)


def _plant_prior_cv(tag, paint, n, candidate):
    """The benchmark's 4-fold leave-heliostats-out CV (chrono, train ``n``, test 30) of one plant-prior
    candidate; prints the median and each heliostat, returns {id: mean test error [mrad]}."""
    from heliotwin.calibrate.protocol import selection as S
    from heliotwin.calibrate.protocol.pipeline import RunConfig, run_calibration

    ds, archive = _plant_archive(paint)
    base = RunConfig(paint=str(paint), method="lm", split="chrono", train=n, test=30, min_records=50)
    errs = next(iter(S.cross_validated_errors(ds, base, [candidate], S.eligible(ds), runner=run_calibration,
                                              folds=4, archive=archive).values()))
    each = ", ".join(f"{h} {e:.2f}" for h, e in sorted(errs.items()))
    print(f"{tag}: median {S.median(errs.values()):.3f} mrad; {each}", flush=True)
    return errs


def part_position(paint, min_records=15, neighbours=(3, 5)):
    """Does a heliostat's place in the field predict its deviations? Leave-one-heliostat-out over the archive.

    Each archive heliostat's fitted Stone/Jülich deviations (:class:`heliotwin.calibrate.protocol.archive.PriorArchive`,
    properties checked) are predicted from the *other* heliostats by the plant median (what the plant prior's
    mean does), by the median of its k nearest heliostats in the field, and by a plane in (east, north). Score:
    median over heliostats of |prediction error| per parameter [mrad or 1e-3 of the parameter] and of the
    error's squared norm whitened by the plant's robust spread (the prior's view; lower = a better prior mean).
    """
    ds, archive = _plant_archive(paint)
    keep = (archive.counts >= min_records).numpy()
    ids = [h for h, k in zip(archive.heliostat_ids, keep) if k]
    dev = 1e3 * archive.deviations.double().numpy()[keep]
    field_ids = list(ds.plant.field.ids)
    en = ds.plant.field.kinematics.position.double().numpy()[[field_ids.index(h) for h in ids], :2]
    scale = 1.4826 * np.median(np.abs(dev - np.median(dev, 0)), 0)
    preds = {"plant median": [], **{f"{k} nearest": [] for k in neighbours}, "plane (E, N)": []}
    design = np.c_[np.ones(len(ids)), en / 100.0]
    for i in range(len(ids)):
        others = np.array([j for j in range(len(ids)) if j != i])
        preds["plant median"].append(np.median(dev[others], 0))
        near = others[np.argsort(np.linalg.norm(en[others] - en[i], axis=1))]
        for k in neighbours:
            preds[f"{k} nearest"].append(np.median(dev[near[:k]], 0))
        coef, *_ = np.linalg.lstsq(design[others], dev[others], rcond=None)
        preds["plane (E, N)"].append(design[i] @ coef)
    out = {}
    for name, p in preds.items():
        err = dev - np.array(p)
        out[name] = {"median_abs": np.median(np.abs(err), 0).tolist(),
                     "median_whitened_sq": float(np.median(((err / scale) ** 2).sum(1)))}
        print(f"position: {name:13s} median |error| " + " ".join(f"{v:6.2f}" for v in out[name]["median_abs"])
              + f"; whitened squared norm {out[name]['median_whitened_sq']:.2f}", flush=True)
    print(f"position: {len(ids)} heliostats with >= {min_records} records; parameters {', '.join(archive.names)}",
          flush=True)
    return out


def part_archive(paint, trains=(30, 10), min_records=(9, 30, 50), widths=(1.0, 2.0)):
    """Which archive heliostats should make the plant prior? 4-fold leave-heliostats-out CV (as
    ``bench_carryover.py``) of the plant prior ``full/s0.2/b10`` built only from archive heliostats with at least
    ``min_records`` records (the default, :data:`heliotwin.calibrate.priors.MIN_PRIOR_RECORDS` = 9, lets
    9-record fits in), for each width; per heliostat and median [mrad]."""
    _, archive = _plant_archive(paint)
    for mr in min_records:  # what the threshold does to the prior itself (every archive heliostat, width x1)
        pp = archive.prior(covariance="full", shrink=0.2, widen=1.0, min_records=mr)
        _print_sigma(f"archive: prior from {len(pp.heliostats)} heliostats with >= {mr} records", pp)
    out = {}
    for n in trains:
        for mr in min_records:
            for w in widths:
                cand = {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": w, "bags": 10,
                        "min_records": mr}
                out[f"N{n}/min{mr}/w{w:g}"] = _plant_prior_cv(
                    f"archive: N={n} prior from heliostats with >= {mr} records, width x{w:g}", paint, n, cand)
    return out


def part_deconvolve(paint, trains=(30, 10), widths=(1.0, 2.0)):
    """The plant prior's covariance without the archive fits' own noise (method of moments), under the
    benchmark's 4-fold leave-heliostats-out CV.

    An archive heliostat's fitted deviation is its true deviation plus the fit's error, whose covariance is
    that fit's Laplace posterior (on the same records, kinematics and loose prior as the archive's fit). The
    plant's covariance is then the deviations' covariance minus the mean posterior covariance of the
    heliostats that make the prior (eigenvalues clipped at 0; the prior's floor still applies); mean,
    winsorising, shrinkage and width as :func:`heliotwin.calibrate.priors.plant_prior`.
    """
    import torch

    from heliotwin.calibrate import priors
    from heliotwin.calibrate.inputs import fit_spots
    from heliotwin.calibrate.methods.lm import laplace
    from heliotwin.calibrate.params import STONE8
    from heliotwin.calibrate.protocol.suspicious import check_and_correct

    ds, archive = _plant_archive(paint)
    table = ds.records.for_heliostats(archive.heliostat_ids).with_focal_spot("HeliOS")
    plant_ids = list(ds.plant.field.ids)
    kin = ds.plant.field.kinematics.index([plant_ids.index(h) for h in table.heliostat_ids])
    kin, _ = check_and_correct(kin, table.heliostat_ids, ds.plant.field.kinematics, table)
    delta = archive.deviations[[archive.heliostat_ids.index(h) for h in table.heliostat_ids]]
    loose = torch.diag(1.0 / priors.sigma_vector(STONE8, priors.LOOSE_SIGMA).double() ** 2)
    fit_cov = dict(zip(table.heliostat_ids, laplace(kin, fit_spots(table), delta, loose)["covariance"]))
    original = priors.plant_prior

    def deconvolved(deviations, names, heliostats, *, covariance="full", shrink=0.2, widen=1.0, floor=None):
        pp = original(deviations, names, heliostats, covariance=covariance, shrink=shrink, widen=widen, floor=floor)
        _, clipped = priors.winsorised(deviations.detach().double())
        centred = clipped - clipped.mean(0)
        noise = torch.stack([fit_cov[h] for h in heliostats]).mean(0)
        w, v = torch.linalg.eigh(centred.T @ centred / (len(centred) - 1) - noise)
        # P pseudo-samples whose covariance is the clipped spectrum: shrinkage, floor and width exactly as the
        # original prior
        pseudo = (len(w) - 1) ** 0.5 * (v * w.clamp_min(0.0).sqrt()).T
        cov = priors.shrunk_covariance(pseudo, priors.sigma_vector(names, floor or priors.FLOOR_SIGMA),
                                       covariance=covariance, shrink=shrink, widen=widen)
        return priors.PlantPrior(pp.names, pp.mean, cov, pp.heliostats, pp.settings)

    out = {}
    try:
        priors.plant_prior = deconvolved
        for name, fn in (("as shipped", original), ("deconvolved", deconvolved)):
            _print_sigma(f"deconvolve: prior {name} (all {len(archive.heliostat_ids)} archive heliostats)",
                         fn(archive.deviations, archive.names, archive.heliostat_ids))
        for n in trains:
            for w in widths:
                cand = {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": w, "bags": 10}
                out[f"N{n}/w{w:g}"] = _plant_prior_cv(f"deconvolve: N={n} deconvolved prior, width x{w:g}",
                                                      paint, n, cand)
    finally:
        priors.plant_prior = original
    return out


def part_tails(paint, trains=(30, 10), min_records=(9, 30), quantile=0.99, rounds=4):
    """A plant prior with heavy tails: Gaussian inside the Mahalanobis radius that holds ``quantile`` of a
    chi-square with P degrees of freedom, Huber (linear) beyond it, under the benchmark's 4-fold
    leave-heliostats-out CV (plant ``full/s0.2/w1/b10``; archive heliostats with >= ``min_records``).

    Iteratively reweighted: fit, then scale each heliostat's prior whitening by ``sqrt(min(1, k / m))`` (``m``
    its Mahalanobis distance from the plant mean, ``k`` the radius), ``rounds`` fits in all. An outlier whose
    records contradict the plant (AC33 under the prior of long histories, part 7) is then pulled with a
    constant force instead of one that grows with its distance; every other heliostat keeps the Gaussian prior.
    """
    from scipy.stats import chi2

    from heliotwin.calibrate.methods import lm
    from heliotwin.calibrate.params import STONE8

    original = lm.stone8_plant_fit
    radius2 = float(chi2.ppf(quantile, len(STONE8)))

    def huber(nominal, batch, prior, **kw):  # stands in for lm.stone8_plant_fit (always called with keywords)
        mean = prior.mean.double().expand(nominal.num_heliostats, len(STONE8)).clone()
        w = prior.whitening()
        scaled = w.expand(nominal.num_heliostats, *w.shape).clone()
        for _ in range(rounds):
            delta, _ = lm.fit_lm(nominal, batch, names=STONE8, prior_mean=mean, prior_whitening=scaled, **kw)
            m2 = ((delta.double() - mean) @ w.T).pow(2).sum(-1)
            scaled = (radius2 / m2.clamp_min(1e-30)).pow(0.25).clamp(max=1.0)[:, None, None] * w
        return delta

    out = {}
    for n in trains:
        for mr in min_records:
            cand = {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 1.0, "bags": 10, "min_records": mr}
            out[f"N{n}/min{mr}/gauss"] = _plant_prior_cv(f"tails: N={n} >= {mr} records, Gaussian", paint, n, cand)
            try:
                lm.stone8_plant_fit = huber
                out[f"N{n}/min{mr}/huber"] = _plant_prior_cv(
                    f"tails: N={n} >= {mr} records, Huber beyond chi2 {quantile:g}", paint, n, cand)
            finally:
                lm.stone8_plant_fit = original
    return out


def part_shift(paint, cases=((30, {"prior": "run", "bags": 10, "half_life_days": 20.0}),
                             (10, {"prior": "run", "bags": 10}))):
    """The two cameras' per-target offset added to the *prediction* instead of the training centroids.

    ``harmonised`` (a CV candidate, not chosen) moves the UTIS training centroids into the HeliOS frame and so
    moves weakly determined parameters. Here the fit is left alone (trained on UTIS as shipped) and each
    test record's HeliOS centroid is compared with the model's spot plus the HeliOS - UTIS offset of its
    target, pooled over every run heliostat's *training* records
    (:meth:`heliotwin.io.records.RecordTable.camera_offsets`): at N=10 most heliostats train on one target
    and are tested on three. Cases: the protocol's chosen run-prior candidates; per heliostat and median.
    """
    import torch

    from heliotwin.calibrate.protocol import selection as S

    out = {}
    for n, cand in cases:
        run = _protocol_run(paint, n, cand)
        offsets = {t: v["offset"] for t, v in run.train.camera_offsets().items()}
        moved = run.test.subset(torch.arange(len(run.test)))
        moved.spot = run.test.spot - torch.stack([offsets.get(t, torch.zeros(3, dtype=run.test.spot.dtype))
                                                 for t in run.test.target]).to(run.test.spot)
        hi = run.test.heliostat_index.numpy()
        before, after = (1e3 * run.model.pointing_error(b).numpy() for b in (run.test, moved))
        rows = np.array([[before[hi == h].mean(), after[hi == h].mean()] for h in range(len(run.run_ids))])
        up = ", ".join(f"{t} {100 * float(v @ run.test.plane_up[run.test.target.index(t)]):+.1f}"
                       for t, v in offsets.items() if t in run.test.target)
        print(f"shift: N={n} {S.label(cand)}: HeliOS - UTIS up [cm] {up}", flush=True)
        print(f"shift: N={n} median {np.median(rows[:, 0]):.3f} -> {np.median(rows[:, 1]):.3f}, mean "
              f"{rows[:, 0].mean():.3f} -> {rows[:, 1].mean():.3f} mrad, {int((rows[:, 1] < rows[:, 0]).sum())} of "
              f"{len(rows)} better; " + ", ".join(f"{h} {a:.2f}->{b:.2f}" for h, (a, b) in zip(run.run_ids, rows)),
              flush=True)
        out[n] = rows
    return out


def part_weather(paint, cases=((30, {"prior": "run", "bags": 10, "half_life_days": 20.0}),
                               (30, {"prior": "run", "bags": 10}),
                               (10, {"prior": "run", "bags": 10}),
                               (10, {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 2.0,
                                     "bags": 10}))):
    """A temperature-dependent offset: does the air temperature of ``calibration-weather.csv`` predict the
    test block's offset?

    Thermal expansion of the actuators and the pylon is of the right size (steel, 0.3 m of stroke, 20 K:
    ~70 um, ~0.2 mrad). Per heliostat, the protocol run's training residuals (model minus measured normal,
    [mrad]) are regressed on the records' temperature [degC] (least squares with an intercept), and each test
    record's residual is corrected by that line ("OLS") or by its slope alone, relative to the mean
    temperature of the latest 5 training records ("slope"; the fit's own level is already the recent one).
    Only heliostats whose training and test records all carry a temperature are corrected; the others keep
    their error. Cases: run-prior and plant-prior candidates without the random-walk offset (whose
    prediction is not the static kinematics').
    """
    import torch

    from heliotwin.calibrate import metrics
    from heliotwin.calibrate.protocol import selection as S

    out = {}
    for n, cand in cases:
        run = _protocol_run(paint, n, cand)
        with torch.no_grad():
            res = {k: 1e3 * metrics.normal_residuals(run.model.kinematics, b).double().numpy()
                   for k, b in (("train", run.train), ("test", run.test))}
        temp = {k: b.weather[:, 3].numpy() for k, b in (("train", run.train), ("test", run.test))}
        hix = {k: b.heliostat_index.numpy() for k, b in (("train", run.train), ("test", run.test))}
        base = 1e3 * run.model.pointing_error(run.test).numpy()
        rows, lines = [], []
        for h, hid in enumerate(run.run_ids):
            tr, te = hix["train"] == h, hix["test"] == h
            before = base[te].mean()
            if not (np.isfinite(temp["train"][tr]).all() and np.isfinite(temp["test"][te]).all()):
                rows.append((before, before, before))
                continue
            x, y = temp["train"][tr], res["train"][tr]
            slope = ((x - x.mean()) @ (y - y.mean(0))) / ((x - x.mean()) @ (x - x.mean()))  # [2 or 3] per degC
            latest = np.argsort(run.train.time.numpy()[tr], kind="stable")[-5:]
            ols = y.mean(0) + np.outer(temp["test"][te] - x.mean(), slope)
            level = np.outer(temp["test"][te] - x[latest].mean(), slope)
            rows.append((before, np.linalg.norm(res["test"][te] - ols, axis=1).mean(),
                         np.linalg.norm(res["test"][te] - level, axis=1).mean()))
            lines.append(f"{hid} {rows[-1][0]:.2f}->{rows[-1][1]:.2f}/{rows[-1][2]:.2f} "
                         f"(T train {x.min():.0f}..{x.max():.0f}, test {temp['test'][te].min():.0f}.."
                         f"{temp['test'][te].max():.0f} degC, {10 * np.linalg.norm(slope):.2f} mrad/10 K)")
        rows = np.array(rows)
        print(f"weather: N={n} {S.label(cand)} median {np.median(rows[:, 0]):.3f} -> OLS {np.median(rows[:, 1]):.3f} "
              f"/ slope {np.median(rows[:, 2]):.3f} mrad; " + "; ".join(lines), flush=True)
        out[(n, S.label(cand))] = rows
    return out


def _plant_candidate(**settings):
    """A plant-prior candidate: full covariance, shrinkage 0.2, width x2, 10 bags, updated by ``settings``."""
    return {"prior": "plant", "covariance": "full", "shrink": 0.2, "widen": 2.0, "bags": 10, **settings}


def part_average(paint, cases=((10, ({"prior": "run", "bags": 10}, _plant_candidate(), _plant_candidate(widen=1.0),
                                     {"prior": "plant", "covariance": "diag", "widen": 1.0, "bags": 10},
                                     _plant_candidate(half_life_days=20.0))),
                               (30, ({"prior": "run", "bags": 10, "half_life_days": 20.0}, {"prior": "run", "bags": 10},
                                     _plant_candidate(half_life_days=20.0), _plant_candidate(),
                                     {"prior": "run", "bags": 10, "half_life_days": 60.0})))):
    """Model averaging instead of choosing: the mean of several candidates' predicted normals.

    Each candidate's protocol run gives its test residuals (model minus measured normal [mrad]); the average
    of two candidates' (or of all) residual vectors is the residual of their averaged prediction. Cases: the
    candidates near the top of the CV table at N=10 and N=30 (static kinematics only: no random-walk
    offset). Prints each candidate's median, the best pair's and all's.
    """
    import itertools

    import torch

    from heliotwin.calibrate import metrics
    from heliotwin.calibrate.protocol import selection as S

    out = {}
    for n, cands in cases:
        res = {}
        for cand in cands:
            run = _protocol_run(paint, n, cand)
            with torch.no_grad():
                res[S.label(cand)] = 1e3 * metrics.normal_residuals(run.model.kinematics, run.test).double().numpy()
        hi = run.test.heliostat_index.numpy()

        def median(r):
            return float(np.median([np.linalg.norm(r[hi == h], axis=1).mean() for h in np.unique(hi)]))

        single = {k: median(r) for k, r in res.items()}
        pairs = {(a, b): median((res[a] + res[b]) / 2) for a, b in itertools.combinations(res, 2)}
        best = min(pairs, key=pairs.get)
        out[n] = {"single": single, "pairs": pairs, "all": median(sum(res.values()) / len(res))}
        print(f"average: N={n} single " + ", ".join(f"{k} {v:.3f}" for k, v in single.items())
              + f"; best pair {best[0]} + {best[1]} {pairs[best]:.3f}; all {out[n]['all']:.3f} mrad", flush=True)
    return out


def main(argv=None) -> int:
    import torch

    # parts on the all-record fits' inputs (ids, HeliOS batch, checked nominal) and parts on the folder
    on_fits = {"params": part_params, "shared": part_shared, "common": part_common, "trend": part_trend}
    on_folder = {"sources": part_sources, "position": part_position, "archive": part_archive,
                 "deconvolve": part_deconvolve, "tails": part_tails, "shift": part_shift, "weather": part_weather,
                 "average": part_average}
    order = ("params", "shared", "common", "sources", "trend", "position", "archive", "deconvolve", "tails", "shift",
             "weather", "average")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paint", default=str(DEFAULT_PAINT))
    ap.add_argument("--part", default=",".join(order))
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    parts = args.part.split(",")
    unknown = sorted(set(parts) - set(order))
    if unknown:
        ap.error(f"unknown part(s) {', '.join(unknown)}; known: {', '.join(order)}")
    fits = _setup(args.paint) if on_fits.keys() & set(parts) else None
    for name in (n for n in order if n in parts):
        if name in on_fits:
            on_fits[name](*fits)
        else:
            on_folder[name](args.paint)
    return 0

if __name__ == "__main__":
    sys.exit(main())
