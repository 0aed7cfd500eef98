"""Kinematic calibration commands: ``calibrate``, ``split`` and ``aim``.

:func:`register` adds them to the main parser. The library (:mod:`heliotwin.calibrate`) is imported inside
the command functions, so ``--help`` stays torch-free.
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import sys
import time
from dataclasses import fields, replace

from ..errors import HeliotwinError
from ..io.report import atomic_path, output_set, write_json
from .common import add_resume_flags, checkpoint_file, checkpointed, float_range, int_range, seed_int, stage

METHOD_CHOICES = ("lm", "gradient", "hybrid", "mlp", "images")
_COUNT, _COUNT0 = int_range(1, 10**6, "a record count"), int_range(0, 10**6, "a record count")
_AZIMUTH = float_range(-360.0, 360.0, what="an azimuth [deg]")


def _ids(text: str | None):
    if not text:
        return None
    ids = [t.strip() for t in text.split(",") if t.strip()]
    if not ids:
        raise HeliotwinError("--heliostats needs a comma-separated list like AK32,BE36")
    return ids


_STUDY_SPLITS = ("chrono", "isolation", "region", "azimuth", "solstice", "balanced", "high_variance")


def _add_common(p, current: bool = False):
    p.add_argument("--paint", required=True, help="PAINT download folder")
    p.add_argument("--heliostats", help="comma-separated heliostat ids (default: every heliostat)")
    p.add_argument("--min-records", type=_COUNT, default=50,
                   help="fewest usable records for the full model (default 50); --split current with lm gives a "
                        "heliostat with fewer the reduced model its records support (the plant prior of the fully "
                        "calibrated ones, the parameter set per record count chosen by validation on them), only "
                        "one without a usable record stays nominal; study splits skip them")
    if current:
        p.add_argument("--split", "--type", dest="split", default=None,
                       choices=("current",) + _STUDY_SPLITS + ("online",),
                       help="current (default; chrono when --train is given): the plant as it is now, fitted on "
                            "every record, its expected error from each heliostat's latest --test records predicted "
                            "from its earlier ones; or a study protocol whose written plant sees only --train "
                            "records (online = each test record predicted from the --train records before it)")
    else:
        p.add_argument("--split", "--type", dest="split", default="chrono", choices=_STUDY_SPLITS + ("online",),
                       help="split type (default chrono)")
    p.add_argument("--train", type=_COUNT, default=None,
                   help="study splits: records a method may see per heliostat, validation included (default 30)")
    p.add_argument("--validation", type=_COUNT0, default=None,
                   help="study splits: validation records carved out of --train (default 20%% of it, 0 below 8)")
    p.add_argument("--test", type=_COUNT, default=None,
                   help="test records per heliostat (study splits, default: every other record; --split current: "
                        "each heliostat's latest records the internal validation predicts, default 10)")
    p.add_argument("--focal-spot", default="HeliOS", help="centroid source: heliOS or utis (falls back to the other)")
    p.add_argument("--seed", type=seed_int, default=0, help="seed of every random choice")


def register(subparsers) -> None:
    """Add ``calibrate``, ``split`` and ``aim`` to an argparse subparsers object."""
    p = subparsers.add_parser("calibrate", help="calibrate heliostat kinematics from PAINT calibration records",
                              description="Calibrate heliostat kinematics from real calibration records. By default "
                                          "the plant written (-o) is fitted on every usable record, and the error "
                                          "it is expected to make is measured inside those records; --split/--train "
                                          "run a study protocol instead.")
    _add_common(p, current=True)
    p.add_argument("--method", default="lm", choices=METHOD_CHOICES, help="calibration method (default lm)")
    p.add_argument("--scenario", help="start from this scenario's plant (default: the PAINT folder's nominal plant)")
    p.add_argument("-o", "--output", help="write the calibrated plant as a scenario file (.h5)")
    p.add_argument("--json", help="write the JSON report (plots are written next to it)")
    p.add_argument("--no-plots", action="store_true", help="do not write plots")
    p.add_argument("--curve", action="store_true",
                   help="also run the error-vs-training-size experiment (lm refits; needs --json)")
    p.add_argument("--no-curve", action="store_true", help=argparse.SUPPRESS)  # the old opt-out: now the default
    p.add_argument("--plane-tolerance", type=float_range(0.0, 100.0, lo_open=True, what="a distance [m]"), default=0.1,
                   help="largest distance of a focal spot from its target plane [m] (default 0.1)")
    p.add_argument("--keep-suspicious", action="store_true",
                   help="report suspicious property values but never replace them")
    p.add_argument("--quiet", action="store_true", help="no progress bars and no summary line")
    p.add_argument("--progress", action="store_true", help=argparse.SUPPRESS)  # old flag: progress is the default
    p.add_argument("--prior", choices=("run", "plant"), default="run",
                   help="lm prior: 'run' = field prior of the run's training records (default), 'plant' = learned "
                        "from the PAINT folder's heliostats that are not calibrated")
    p.add_argument("--prior-from", metavar="ARCHIVE",
                   help="lm plant prior from ARCHIVE: a PAINT folder of the same plant (its heliostats that this run "
                        "calibrates are excluded) or a scenario holding a prior learned from other heliostats")
    p.add_argument("--half-life-days", type=float_range(0.0, 1e5, lo_open=True, what="a half-life [days]"),
                   default=None,
                   help="lm drift tracking: a training record N days older than the latest weighs 0.5**(N/this) "
                        "(default: all records weigh 1; benchmarks/bench_carryover.py chooses it by CV)")
    p.add_argument("--drift-mrad", type=float_range(0.0, 1e3, what="a drift [mrad]"), default=None,
                   help="lm predictive interval: offset drift per component [mrad] added to the Laplace posterior's "
                        "noise (default 0; chosen by cross-validated coverage in benchmarks/bench_carryover.py)")
    p.add_argument("--drift", choices=("auto", "none", "kalman"), default="auto",
                   help="lm drift model: 'kalman' = rigid body + a random-walk offset of the axis offsets, "
                        "smoothed over the training records; the scenario aims with the offset at the latest "
                        "training time; 'none' = static; 'auto' (default): --split current chooses by its "
                        "validation inside the records, a study split is static")
    p.add_argument("--process-noise", default="auto", metavar="auto|Q",
                   help="--drift kalman: process noise of the offset [mrad^2/day] per component, or 'auto' "
                        "(chosen by chronological validation inside the training records; default)")
    p.add_argument("--drift-basis", choices=("axes", "rotation"), default="axes",
                   help="--drift kalman: what drifts: the two axis offsets (default) or a small rotation of the "
                        "whole heliostat")
    p.add_argument("--settings", choices=("auto", "given", "cv", "stored"), default="auto",
                   help="lm settings (prior width, bagging, drift model, interval drift): 'cv' = chosen by "
                        "leave-heliostats-out cross-validation on the --prior-from PAINT folder's heliostats (never "
                        "the calibrated ones); 'stored' = the choice a cv run stored in the --prior-from scenario, "
                        "where it applies (same split and --train, a plant prior, none of this run's heliostats "
                        "scored by it; else the flags, and the report says why); 'given' = the flags; 'auto' "
                        "(default) = cv for a PAINT folder, stored for a scenario, when no lm setting flag is "
                        "given, else given")
    p.add_argument("--learn-settings", action="store_true",
                   help="also choose the lm settings, plant prior and interval calibration once for this plant by "
                        "leave-heliostats-out CV on every eligible heliostat of --paint, and store them in the -o "
                        "scenario; later runs --prior-from that scenario reuse them without recomputing")
    p.add_argument("--nproc", type=_COUNT, default=1,
                   help="shard the heliostats' fits over N local processes (torch.distributed gloo; same result)")
    p.add_argument("--online-step", type=_COUNT, default=5,
                   help="--split online: refit every this many test records (default 5; 1 = before every record)")
    add_resume_flags(p)
    p.set_defaults(func=cmd_calibrate)

    p = subparsers.add_parser("split", help="write a train/validation/test split and its coverage metrics",
                              description="Split every heliostat's records (as calibrate would) and report coverage.")
    _add_common(p)
    p.add_argument("--json", help="write the split and coverage metrics as JSON")
    p.add_argument("--csv", help="write the split in PAINT's benchmark CSV format (Id,HeliostatId,Split)")
    p.set_defaults(func=cmd_split)

    p = subparsers.add_parser("aim", help="motor steps for a sun position and aim point from a calibrated model",
                              description="Inverse kinematics with a calibrated model: motor steps that put the "
                                          "reflection of the sun on an aim point.")
    p.add_argument("--scenario", required=True, help="scenario file (e.g. written by 'calibrate -o')")
    p.add_argument("--heliostat", required=True, help="heliostat id")
    p.add_argument("--sun-azimuth", type=_AZIMUTH, required=True, help="sun azimuth [deg], 0 = south, +90 = east")
    p.add_argument("--sun-elevation", type=float_range(0.0, 90.0, lo_open=True, what="an elevation [deg]"),
                   required=True, help="sun elevation [deg]")
    p.add_argument("--aim", required=True, help="aim point E,N,U [m] in the plant's ENU frame")
    p.add_argument("--time", default=None,
                   help="UTC ISO time of the aim (with a --drift kalman calibration: the offset's uncertainty "
                        "grows with the time since the latest training record)")
    p.add_argument("--json", help="also write the answer as JSON")
    p.set_defaults(func=cmd_aim)


def _settings(args, method: str | None = None):
    """The :class:`~heliotwin.workflows.calibrate.CalibrationSettings` of parsed ``calibrate`` / ``split``
    flags (a flag a command lacks keeps its default; ``method`` replaces ``--method``)."""
    from ..workflows.calibrate import CalibrationSettings

    given = {f.name: getattr(args, f.name) for f in fields(CalibrationSettings) if hasattr(args, f.name)}
    given.update(heliostats=_ids(args.heliostats), curve=False, **({"method": method} if method else {}))
    return CalibrationSettings(**given)


def _config(args, method: str | None = None):
    """The checked run config of the flags (:func:`heliotwin.workflows.calibrate.run_config`; one-line errors)."""
    from ..workflows.calibrate import run_config

    return run_config(_settings(args, method), args.paint)


def _settings_mode(args, method) -> str:
    """``--settings``, with ``auto`` resolved (:func:`heliotwin.workflows.calibrate.resolved_settings_mode`): a
    setting flag given by hand (half-life, interval drift, drift model) keeps the flags."""
    from ..workflows.calibrate import resolved_settings_mode

    return resolved_settings_mode(_settings(args, method))


def cmd_calibrate(args) -> int:
    from ..calibrate.report import write_plots
    from ..io.scenario import write_scenario
    from ..workflows.calibrate import calibrate, run_config

    started = time.perf_counter()
    settings = replace(_settings(args), curve=bool(args.curve and args.json and not args.no_plots))
    if args.learn_settings and not args.output:
        raise HeliotwinError("--learn-settings stores what it learns in the scenario: give -o PLANT.h5")
    run_config(settings, args.paint)  # one-line errors before any output is staged
    device = getattr(args, "device", "cpu")
    # The checkpoint outlives the staged outputs: removed only once they are in place.
    with checkpointed(args, _checkpoint(args, settings, device)), \
            output_set([("--paint", args.paint), ("--scenario", args.scenario)]) as out:
        output, json_path = out.file(args.output, "-o"), out.file(args.json, "--json")
        progress = _progress(args)
        result = calibrate(args.scenario, args.paint, settings, device=device, progress=progress,
                           checkpoint=args.checkpoint, stage=_stages(args, progress))
        report = result.report
        if args.output and result.scenario is None:
            _print_table(report)
            raise HeliotwinError(f"no heliostat could be calibrated (see the table above); {args.output} not written")
        stage(args, "writing outputs")
        report.setdefault("overall", {})["command_seconds"] = time.perf_counter() - started
        if output:
            write_scenario(result.scenario, output)
            report["output"] = os.fspath(args.output)
        if json_path:
            if not args.no_plots:
                report["plots"] = [os.path.basename(p) for p in write_plots(json_path, report, result.arrays,
                                                                            result.curves)]
            if result.curves:
                report["training_size_curve"] = {k: [list(p) for p in v] for k, v in result.curves.items()}
            write_json(json_path, report)
    if not args.quiet:
        _print_table(report)
    return 0


def _progress(args, stream=None):
    """How a run shows progress: nothing with ``--quiet``, tqdm bars when stderr is a terminal, else one line
    per step of the run on stdout, with the run's summary (a log file or a pipe gets ``heliotwin calibrate:
    current plant: step 8/15 fit``, each block of steps named by what it fits; stderr stays for the one-line
    error)."""
    if args.quiet:
        return False
    if sys.stderr.isatty():
        return True
    return _StepLines(sys.stdout if stream is None else stream)


class _StepLines:
    """One line per step of a pipeline run, each named by its block (:meth:`block`: the stage the calibration
    reached, e.g. ``validation candidate 2/3 'static, 10 bags'``): a calibration runs the pipeline once per
    candidate setting and once for the plant it writes, and unnamed ``step 1/15 ... 15/15`` blocks cannot be
    told apart."""

    def __init__(self, stream):
        self.stream, self.name = stream, ""

    def block(self, text: str) -> None:
        """A stage line: printed, and (its part before the first ':') the name of the steps that follow."""
        if text[:1].isspace():  # a detail inside the block (a candidate's result), not a new block
            print(f"heliotwin calibrate: {text.strip()}", file=self.stream, flush=True)
            return
        self.name = text.split(":")[0].strip()
        print(f"heliotwin calibrate: {text}", file=self.stream, flush=True)

    def __call__(self, step: str, index: int, total: int) -> None:
        where = f"{self.name}: " if self.name else ""
        print(f"heliotwin calibrate: {where}step {index + 1}/{total} {step}", file=self.stream, flush=True)


def _stages(args, progress):
    """The calibration's ``stage`` callback: the terminal's stage line (stderr), and the name of the block of step
    lines that follows when progress goes to a log (:class:`_StepLines`)."""
    def named(text: str) -> None:
        stage(args, text)
        if isinstance(progress, _StepLines):
            progress.block(text)

    return named


def _checkpoint(args, settings, device):
    """The run's checkpoint next to its main output (None without one); also ``args.checkpoint``."""
    from ..workflows.calibrate import calibration_checkpoint

    path = checkpoint_file(args)
    args.checkpoint = None if path is None else calibration_checkpoint(
        settings, args.paint, path, scenario=args.scenario, device=device, resume=args.resume,
        min_interval_s=args.checkpoint_interval)
    if args.checkpoint is not None and args.checkpoint.resumed:
        stage(args, f"resuming from {path}")
    return args.checkpoint


cmd_calibrate.supports_cuda = True  # the fit follows args.device (run_calibration moves the plant there)


def _fmt(x, nd=2):
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{nd}f}"


def _print_table(report: dict) -> None:
    headline = (report.get("headline") or {}).get("text")
    if headline:  # what the plant got, first; the per-heliostat table below
        print(headline)
    print(f"{'heliostat':10s} {'status':8s} {'model':8s} {'train':>5s} {'val':>4s} {'test':>4s} {'nominal':>9s} "
          f"{'calib':>8s}  note")
    for hid, r in report["heliostats"].items():
        s = r.get("split", {})
        note = r.get("reason", "")
        if r.get("suspicious", {}).get("note"):
            note = (note + "; " if note else "") + r["suspicious"]["note"]
        model = "reduced" if str(r.get("model", "")).startswith("reduced") else \
            ("full" if r["status"] == "ok" else "nominal")
        print(f"{hid:10s} {r['status']:8s} {model:8s} {s.get('train', 0):5d} {s.get('validation', 0):4d} "
              f"{s.get('test', 0):4d} {_fmt(r.get('nominal_mean_test_mrad')):>9s} {_fmt(r.get('mean_test_mrad')):>8s}"
              f"  {note}")
    red = report.get("reduced")
    if red:
        held = red.get("held_out") or {}
        print(f"reduced models ({len(red.get('calibrated', []))} heliostats, < --min-records {red.get('min_records')}"
              "): "
              f"{red['rule']['rule']}; on their own latest records (held out) {_fmt(held.get('median_mrad'))} mrad "
              f"median against nominal {_fmt(held.get('nominal_median_mrad'))}, better than nominal for "
              f"{held.get('better_than_nominal', 0)} of {held.get('heliostats', 0)}; 'calib' of a reduced heliostat is "
              "its Laplace expected error")
    ov = report["overall"]
    expected = report.get("expected_error")
    if expected:
        print(f"written plant: fitted on every record ({report['written_plant']['records_fitted']} records); "
              f"expected error {_fmt(expected.get('median_of_mean_mrad'))} mrad median, "
              f"{_fmt(expected.get('p95_of_mean_mrad'))} p95 over the {'fully calibrated ' if red else ''}heliostats "
              f"({expected['protocol']})")
    elif report.get("written_plant"):
        print(f"written plant: {report['written_plant']['records']} (a study protocol; --split current fits every "
              "record)")
    took = f"fit run {_fmt(ov.get('seconds'), 1)} s"
    if ov.get("command_seconds") is not None:
        took += f" of the command's {_fmt(ov['command_seconds'], 1)} s (after start-up)"
    full = "fully calibrated " if red else ""
    print(f"overall: median over {full}heliostats of mean test error {_fmt(ov.get('median_of_mean_test_mrad'))} mrad "
          f"(nominal {_fmt(ov.get('nominal_median_of_mean_test_mrad'))}), {ov.get('n_heliostats', 0)} heliostats, "
          f"{took}; skipped records {ov.get('skipped_records', 0)}"
          + ("" if ov.get("interval_90_coverage") is None else
             f"; 90 % interval covers {ov['interval_90_coverage']:.2f} of the test records"))


def cmd_split(args) -> int:
    if args.split == "online":
        raise HeliotwinError("--type online: the online protocol refits as records arrive, so it exists for "
                             "'heliotwin calibrate --split online' only, not as a fixed split")
    cfg = _config(args)
    with output_set([("--paint", args.paint)]) as out:
        return _split(args, cfg, out.file(args.json, "--json"), out.file(args.csv, "--csv"))


def _split(args, cfg, json_path, csv_path) -> int:
    import torch

    from ..calibrate.protocol.splits import split_records
    from ..workflows.calibrate import load_paint_records

    ds, _ = load_paint_records(args.paint)
    ids = cfg.heliostats or list(ds.plant.field.ids)
    unknown = [h for h in ids if h not in ds.plant.field.ids]
    if unknown:
        raise HeliotwinError(f"heliostat(s) {', '.join(unknown)} not in {args.paint}")
    batch = ds.records.for_heliostats(ids).with_focal_spot(cfg.focal_spot)
    skipped = [s for s in ds.skipped if s["heliostat_id"] in ids]
    counts = batch.counts()
    keep = [h for h in range(len(ids)) if int(counts[h]) >= max(1, cfg.min_records)]
    sub = batch.subset(torch.isin(batch.heliostat_index, torch.tensor(keep, dtype=torch.long)))
    tr, va, te, info = split_records(sub, cfg.split, cfg.train, cfg.n_validation(), cfg.test, seed=cfg.seed)
    label = {}
    for name, idx in (("train", tr), ("validation", va), ("test", te)):
        for i in idx.tolist():
            label[i] = name
    rows = [{"Id": int(sub.record_id[i]), "HeliostatId": ids[int(sub.heliostat_index[i])], "Split": label[i]}
            for i in sorted(label)]
    skipped_h = {ids[h]: f"too few usable records ({int(counts[h])} < --min-records {cfg.min_records})"
                 for h in range(len(ids)) if h not in keep}
    out = {"config": {k: v for k, v in cfg.__dict__.items() if k != "progress"},
           "heliostats": {k: v for k, v in info.items() if k in [ids[h] for h in keep]},
           "skipped_heliostats": skipped_h, "skipped_records": skipped, "split": rows}
    out["config"]["validation"] = cfg.n_validation()
    if json_path:
        write_json(json_path, out)
    if csv_path:
        _write_split_csv(csv_path, rows)
    for hid, s in out["heliostats"].items() if not args.quiet else ():
        d = s.get("mean_train_test_distance_rad")
        print(f"{hid}: train {s['train']} validation {s['validation']} test {s['test']} "
              f"(dropped without time {s['dropped_no_time']}), mean train-test distance {_fmt(d, 3)} rad")
    for hid, why in skipped_h.items() if not args.quiet else ():
        print(f"{hid}: skipped, {why}")
    return 0


def _write_split_csv(path, rows) -> None:
    """PAINT's benchmark split format: ``Id,HeliostatId,Split``."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=["Id", "HeliostatId", "Split"], lineterminator="\n")
            w.writeheader()
            w.writerows(rows)


def cmd_aim(args) -> int:
    from ..io.scenario import load_scenario
    from ..workflows.plan import AimRequest, aim

    try:
        point = tuple(float(x) for x in args.aim.split(","))
    except ValueError:
        raise HeliotwinError(f"--aim needs E,N,U in metres, got {args.aim!r}") from None
    request = AimRequest(args.sun_azimuth, args.sun_elevation, point, getattr(args, "time", None))
    with output_set([("--scenario", args.scenario)]) as out:
        json_path = out.file(args.json, "--json")
        _, ans = aim(load_scenario(args.scenario), args.heliostat, request)
        if json_path:
            write_json(json_path, ans)
    if not args.quiet:
        note = "" if ans["reachable"] else "  (OUTSIDE the actuator range: not reachable)"
        print(f"{ans['heliostat']}: motor steps axis 1 {ans['motor_steps'][0]:.0f}, axis 2 "
              f"{ans['motor_steps'][1]:.0f}{note} [{ans['method']}]")
        if "expected_error_mrad" in ans:
            lo, hi = ans["error_interval_90_mrad"]
            print(f"expected pointing error {ans['expected_error_mrad']:.2f} mrad, 90 % interval "
                  f"[{lo:.2f}, {hi:.2f}] mrad")
    return 0 if ans["reachable"] else 3

