"""Accuracy that carries over: protocol figure next to the leave-heliostats-out CV figure.

For ``--train`` 10 and 30 (split chrono, test = the latest 30 records, heliostats with >= 50 records):

1. every candidate setting of :data:`heliotwin.calibrate.protocol.selection.CANDIDATES` under K-fold
   leave-heliostats-out CV on all heliostats (the table of what was tried; plant priors never contain the
   calibrated fold);
2. the setting :func:`~heliotwin.calibrate.protocol.selection.select` chooses from that table, and its *protocol*
   figure: one ordinary run over all heliostats (``heliotwin calibrate --prior plant`` when a plant prior is
   chosen: the prior then comes from the folder's heliostats with < 50 records only), plus the default
   ``lm`` for comparison;
3. the online protocol (``--split online``) with the chosen setting and with the default ``lm``;
4. the nested leave-heliostats-out CV figure of the whole choice procedure (the honest estimate);
5. ``overall.interval_90_coverage`` of the protocol run (drift term chosen by CV coverage) and of the
   nested CV (drift chosen on the inner folds);
6. what any method trained on earlier records is up against (``reference``): the same two settings
   trained on *every* record before the test block instead of the earliest N, and the protocol run's test
   error once each heliostat's own mean offset over its test block is removed (an oracle: that offset is
   only known after the test records exist), with that offset's share of the test MSE.

Measured on ``../shared/data/paint`` (11 heliostats, 1 thread, 931 s), median over heliostats of the mean
test error [mrad] (``kq``: the random-walk offset of :mod:`heliotwin.calibrate.drift`, q [mrad^2/day] or
``auto``; ``hl``: recency half-life; ``drift``: the interval's offset term; ``walk x``: the scale of the
walk's covariance in the interval, chosen with ``drift`` by CV coverage):

| N | default lm | chosen by LOHO CV | protocol | nested CV | cov90 prot. / nested | online: chosen / lm / walk |
|---|---|---|---|---|---|---|
| 10 | 1.467 | plant/full/s0.2/w2/b10/kq0.03, drift 0.00, walk x0 | 1.336 | 1.178 | .888 / .873 | .626 / .677 / .626 |
| 30 | 0.969 | run/b10/hl20d, drift 1.00, walk x1 | 0.903 | 0.903 | 0.885 / 0.879 | 0.662 / 0.796 / 0.545 |

Since 2026-11-22 (second run that day, ``--online-cv``, 1834 s on one core) the archive checks its own
heliostats' property values before fitting them
(:meth:`heliotwin.calibrate.protocol.archive.PriorArchive.from_dataset`): BF41's wrong initial stroke had
entered every plant prior as a 300-450 mrad outlier (winsorised to 3 robust sigmas). That changed only the
plant-prior rows: N=10 chosen kqauto -> kq0.03 (CV 1.239 -> 1.205), protocol 1.335 -> 1.336, nested
1.417 -> 1.178, coverage .900 / .921 -> .888 / .873; N=30 and the online choices (run prior) are unchanged.

Reference rows (2026-11-22, with the centroid-source and loss candidates; ``--online-cv``, 2044 s on one
core; the table above is unchanged by those candidates except the nested coverage at N=10, .927 -> .921;
re-run with the two ``fitharmonised`` candidates, 23 in all, 1838 s: every figure here unchanged, no
``harmonised`` candidate chosen by the CV, the nested CV or the online CV):

| N | every earlier record: default lm / chosen | test-block offset removed (oracle) | its MSE share |
|---|---|---|---|
| 10 | 0.907 / 0.877 (1.069 with kq0.03, the choice since the archive check) | 0.892 (0.893) | 48 % (50 %) |
| 30 | 0.907 / 0.861 | 0.621 | 54 % |

Online settings chosen on the online protocol (``--online-cv``; what ``calibrate --split online --prior-from
FOLDER`` does by default, ``--settings cv``; CV refits every 10 test records; 1018 s with the table above and
without the nested CV): N=10 ``run/b10/kq0.03``, protocol 0.610 (CV 0.619); N=30 ``run/b10/kq0.03``, protocol
0.545 (CV 0.609) -- the random-walk offset, where the chrono choice (half-life 20 d) gives 0.662.

The random-walk offset is chosen at N=10 (CV 1.205 for kq0.03 against 1.219 for the plant prior without
bagging; before the archive check: kqauto, CV 1.239 against 1.241 for half-life 20 d) and is the better
drift model on the online protocol (N=30:
0.545 with kq0.03, the best walk candidate by CV, against 0.662 with the chosen half-life; N=10: 0.630
against 0.690 before it); on chrono N=30 the half-life still wins (CV 0.942 for kq0.03 against 0.903).
The issue's targets (0.8 at N=30, 1.0 at N=10) are not reached; the coverage target (0.8-0.97) is. The
walk's own growth ``q dt`` over the months between training and a chrono test block overstates the offset
(coverage 1.000 at N=10 with scale 1), hence its scale is chosen by CV coverage.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_carryover.py [--paint ../shared/data/paint] [--json carry.json]
        [--train 10,30] [--folds 4] [--inner-folds 3] [--skip-nested] [--online-cv]
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

DEFAULT_PAINT = Path(__file__).resolve().parents[2] / "shared" / "data" / "paint"


def _fmt(x):
    return "-" if x is None else f"{x:.3f}"


def offset_oracle(model, arrays) -> dict:
    """Test errors of a run with each heliostat's mean residual over its test block removed (an oracle).

    Parameters
    ----------
    model : heliotwin.calibrate.model.Calibrated
        The run's model (its heliostat axis = the run's heliostats).
    arrays : dict
        The run's plot arrays (``test``: the test :class:`~heliotwin.io.records.RecordTable`).

    Returns
    -------
    dict
        ``median_of_mean_test_mrad`` with the offset removed, ``median_offset_share`` (median over heliostats
        of |mean residual|^2 / mean |residual|^2, the part of the test MSE that is one constant offset) and
        both per heliostat. Residuals are model minus measured normal [rad] (their norm is the pointing
        error to second order, :func:`heliotwin.calibrate.metrics.normal_residuals`).
    """
    import numpy as np
    import torch

    from heliotwin.calibrate import metrics

    test = arrays["test"]
    with torch.no_grad():
        r = metrics.normal_residuals(model.kinematics, test).double()
    hi = test.heliostat_index
    per = {}
    for h, hid in enumerate(model.heliostat_ids):
        m = hi == h
        if not bool(model.ok[h]) or int(m.sum()) == 0:
            continue
        rh = r[m]
        mean = rh.mean(0)
        per[hid] = {"mean_test_mrad_without_offset": float(1e3 * (rh - mean).norm(dim=-1).mean()),
                    "offset_mrad": float(1e3 * mean.norm()),
                    "offset_share_of_mse": float(mean.pow(2).sum() / rh.pow(2).sum(-1).mean())}
    return {"median_of_mean_test_mrad": float(np.median([v["mean_test_mrad_without_offset"] for v in per.values()])),
            "median_offset_share": float(np.median([v["offset_share_of_mse"] for v in per.values()])),
            "heliostats": per}


def main(argv=None) -> int:
    import torch

    from heliotwin.calibrate.protocol import selection as S
    from heliotwin.calibrate.protocol.archive import PriorArchive
    from heliotwin.calibrate.protocol.pipeline import RunConfig, run_calibration
    from heliotwin.io.paint import load_paint
    from heliotwin.io.report import write_json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paint", default=str(DEFAULT_PAINT))
    ap.add_argument("--json", default="bench_carryover.json")
    ap.add_argument("--train", default="10,30")
    ap.add_argument("--folds", type=int, default=4)
    ap.add_argument("--inner-folds", type=int, default=3)
    ap.add_argument("--skip-nested", action="store_true")
    ap.add_argument("--online-cv", action="store_true",
                    help="also choose the online run's setting by LOHO CV on the online protocol (--settings cv)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    ds = load_paint(args.paint)
    archive = PriorArchive.from_dataset(ds, source=args.paint)
    ids = S.eligible(ds)
    print(f"{len(ids)} heliostats with >= 50 records: {','.join(ids)}; archive fits of {len(archive.heliostat_ids)} "
          f"heliostats", flush=True)
    out = {"heliostats": ids, "train": {}}
    rows = []
    for n in [int(x) for x in args.train.split(",")]:
        base = RunConfig(paint=args.paint, method="lm", split="chrono", train=n, test=30, min_records=50)
        print(f"\n== N={n}: leave-heliostats-out {args.folds}-fold CV of every candidate", flush=True)
        collect: dict = {}
        scores = S.cross_validated_errors(ds, base, S.CANDIDATES, ids, runner=run_calibration, folds=args.folds,
                                          archive=archive, log=print, collect=collect)
        chosen = S.select(scores, S.CANDIDATES)
        drift, walk_scale, drift_cov = S.choose_interval(collect[S.label(chosen)])
        print("coverage of the 90 % interval vs (offset drift [mrad], walk scale) (CV runs of the chosen setting): "
              + ", ".join(f"({1e3 * d:.2f}, {s:g}): {c:.3f}" for (d, s), c in drift_cov.items()), flush=True)
        rep_default, _, _ = run_calibration(base, ds)
        cfg = S.config_of(base, chosen, None)
        cfg = replace(cfg, method_options=dict(cfg.method_options, drift=drift, walk_scale=walk_scale))
        rep_chosen, model_chosen, arrays_chosen = run_calibration(cfg, ds)
        res = {"cv_table": {k: {"median_of_mean_test_mrad": S.median(v.values()), "heliostats": v}
                            for k, v in scores.items()},
               "chosen": S.label(chosen), "drift_rad": drift,
               "walk_scale": walk_scale, "drift_coverage": {str(k): v for k, v in drift_cov.items()},
               "protocol_chosen": rep_chosen["overall"],
               "protocol_default_lm": rep_default["overall"]}
        print(f"chosen by CV: {S.label(chosen)}; protocol figure "
              f"{_fmt(rep_chosen['overall']['median_of_mean_test_mrad'])} mrad "
              f"(default lm {_fmt(rep_default['overall']['median_of_mean_test_mrad'])})", flush=True)
        # what the chrono protocol is up against: every earlier record instead of the earliest N, and the
        # test block's own mean offset removed
        every = 10 ** 6  # "the earliest N" with N above any history = every record before the test block
        rep_all_default, _, _ = run_calibration(replace(base, train=every), ds)
        rep_all_chosen, _, _ = run_calibration(replace(cfg, train=every), ds)
        oracle = offset_oracle(model_chosen, arrays_chosen)
        res["reference"] = {"every_earlier_record_default_lm": rep_all_default["overall"],
                            "every_earlier_record_chosen": rep_all_chosen["overall"],
                            "chosen_without_test_block_offset": oracle}
        print(f"reference: every record before the test block: default lm "
              f"{_fmt(rep_all_default['overall']['median_of_mean_test_mrad'])}, chosen "
              f"{_fmt(rep_all_chosen['overall']['median_of_mean_test_mrad'])} mrad; chosen with the test block's "
              f"own mean offset removed {_fmt(oracle['median_of_mean_test_mrad'])} mrad (that offset is "
              f"{100 * oracle['median_offset_share']:.0f} % of the test MSE, median)", flush=True)
        cfg_on = replace(cfg, split="online")
        rep_online, _, _ = run_calibration(cfg_on, ds)
        rep_online_default, _, _ = run_calibration(replace(base, split="online"), ds)
        res["online_chosen"] = rep_online["overall"]
        res["online_default_lm"] = rep_online_default["overall"]
        # the drift model on the online protocol: the random-walk candidate that LOHO CV ranks best among
        # the random-walk candidates (chosen on chrono, like every choice here)
        walk = [c for c in S.CANDIDATES if c.get("drift_model") == "kalman"]
        rep_online_walk = None
        if walk:
            best_walk = S.select(scores, walk)
            cfg_w = S.config_of(base, best_walk, None)
            rep_online_walk, _, _ = run_calibration(replace(cfg_w, split="online", prior_from=None), ds)
            res["online_best_walk"] = {"candidate": S.label(best_walk), **rep_online_walk["overall"]}
            print(f"online, best random-walk candidate {S.label(best_walk)}: "
                  f"{_fmt(rep_online_walk['overall']['median_of_mean_test_mrad'])} mrad", flush=True)
        print(f"online (test = latest 30, each block of {base.online_step} predicted from the {n} records before it): "
              f"chosen {_fmt(rep_online['overall']['median_of_mean_test_mrad'])} mrad, default lm "
              f"{_fmt(rep_online_default['overall']['median_of_mean_test_mrad'])}", flush=True)
        if args.online_cv:  # the online run's settings chosen on the online protocol, as --settings cv does
            base_on = replace(base, split="online", online_step=max(base.online_step, S.ONLINE_CV_STEP))
            print(f"== N={n}: leave-heliostats-out CV of every candidate on the online protocol", flush=True)
            scores_on = S.cross_validated_errors(ds, base_on, S.CANDIDATES, ids, runner=run_calibration,
                                                 folds=args.folds, archive=archive, log=print)
            chosen_on = S.select(scores_on, S.CANDIDATES)
            rep_on_cv, _, _ = run_calibration(S.config_of(replace(base, split="online"), chosen_on, archive), ds)
            res["online_cv"] = {"chosen": S.label(chosen_on), "cv_median_mrad": S.median(
                scores_on[S.label(chosen_on)].values()), **rep_on_cv["overall"]}
            print(f"online, chosen on the online protocol by LOHO CV: {S.label(chosen_on)}: protocol "
                  f"{_fmt(rep_on_cv['overall']['median_of_mean_test_mrad'])} mrad (CV "
                  f"{_fmt(res['online_cv']['cv_median_mrad'])})", flush=True)
        nested = None
        if not args.skip_nested:
            print(f"== N={n}: nested leave-heliostats-out CV of the choice procedure", flush=True)
            nested = S.nested_cv(ds, base, runner=run_calibration, folds=args.folds, inner_folds=args.inner_folds,
                                 archive=archive, log=print)
            res["nested_cv"] = nested
        out["train"][str(n)] = res
        rows.append((n, rep_default["overall"], rep_chosen["overall"],
                     f"{S.label(chosen)}, drift {1e3 * drift:.2f}, walk x{walk_scale:g}",
                     nested, S.median(scores[S.label(chosen)].values()), rep_online["overall"],
                     rep_online_default["overall"], rep_online_walk and rep_online_walk["overall"],
                     res["reference"]))
    out["seconds"] = time.perf_counter() - t0
    write_json(args.json, out)  # before the table: the figures are safe whatever the printing does
    print("\n| N | default lm protocol | chosen setting | chosen protocol | CV of chosen (fixed) | nested LOHO CV |"
          " coverage90 protocol | coverage90 nested | online chosen | online default lm | online best walk |"
          " every earlier record: default / chosen | chosen, test-block offset removed (its MSE share) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for n, d, c, lab, nested, cvfix, on, on_d, on_w, ref in rows:
        print(f"| {n} | {_fmt(d['median_of_mean_test_mrad'])} | {lab} | {_fmt(c['median_of_mean_test_mrad'])} | "
              f"{_fmt(cvfix)} | {_fmt(nested['median_of_mean_test_mrad']) if nested else '-'} | "
              f"{_fmt(c.get('interval_90_coverage'))} | "
              f"{_fmt(nested.get('interval_90_coverage')) if nested else '-'} | "
              f"{_fmt(on['median_of_mean_test_mrad'])} | {_fmt(on_d['median_of_mean_test_mrad'])} | "
              f"{_fmt(on_w['median_of_mean_test_mrad']) if on_w else '-'} | "
              f"{_fmt(ref['every_earlier_record_default_lm']['median_of_mean_test_mrad'])} / "
              f"{_fmt(ref['every_earlier_record_chosen']['median_of_mean_test_mrad'])} | "
              f"{_fmt(ref['chosen_without_test_block_offset']['median_of_mean_test_mrad'])} "
              f"({100 * ref['chosen_without_test_block_offset']['median_offset_share']:.0f} %) |")
    print(f"wrote {args.json} ({out['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
