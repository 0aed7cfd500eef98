"""Surface learning commands: ``reconstruct`` and ``predict``.

Usage::

    heliotwin reconstruct --paint PAINT_DIR --heliostat AA39 --train-first 3 -o learned.h5 --json report.json
    heliotwin reconstruct ... --deflectometry AA39-deflectometry.h5
    heliotwin reconstruct --paint PAINT_DIR --heliostat AA39 --surface-prior-from S1.h5,S2.h5 -o learned.h5 ...
    heliotwin reconstruct --paint PAINT_DIR --heliostats all --nproc 2 -o plant.h5 --json plant-report.json
    heliotwin reconstruct --paint PAINT_DIR --heliostats AA39,AB40 --resume -o plant.h5 --json plant-report.json
    heliotwin predict --scenario learned.h5 --heliostat AA39 --year 2023 --every 30min --json out.json

:func:`register` adds them to the main parser. Each command parses its flags into the workflow's settings and
calls the workflow (:mod:`heliotwin.workflows.reconstruct`, :mod:`heliotwin.workflows.predict`), imported inside
the command functions so that ``--help`` stays torch-free; it then writes the staged outputs. Output folders are
checked before training, so a typo costs seconds, not a training run.

``--heliostats all|A,B,C`` is the plant form (:mod:`heliotwin.workflows.reconstruct_plant`): every selected heliostat
with enough centred images is learned (``--nproc N`` worker processes), the others are listed as skipped; ``-o``
holds every learned surface, ``--json`` a row per heliostat and a summary (no figures), ``--resume`` continues
from the finished heliostats.

``reconstruct`` has one learner. The flags of the retired second learner (``--method legacy``, ``--loss``,
``--integrator mc``, ``--background``, ``--start-from-deflectometry``) are refused in one line that says what
replaces them; ``--method generalising``, ``--integrator conv`` and ``--no-mc`` are accepted and change nothing.
"""
from __future__ import annotations

import argparse
import os
import sys

from ..errors import HeliotwinError
from ..io.report import output_set, write_json
from .common import (
    EXIT_NOT_MET,
    add_resume_flags,
    checkpoint_file,
    checkpointed,
    float_range,
    frequency,
    int_range,
    positive_int,
    stage,
)

__all__ = ["register"]


def _prior_inputs(args) -> list:
    """``--surface-prior-from``'s scenario files as inputs of the output checks (an output may not replace one)."""
    given = getattr(args, "surface_prior_from", None)
    return [("--surface-prior-from", p.strip()) for p in str(given).split(",") if p.strip()] if given else []


def cmd_reconstruct(args) -> int:
    """``heliotwin reconstruct``: :func:`heliotwin.workflows.reconstruct.reconstruct`, then its figures, the
    scenario (``-o``) and the report (``--json``), all staged."""
    from ..io.scenario import load_scenario, write_scenario
    from ..workflows.reconstruct import reconstruct, reconstruction_checkpoint

    if args.heliostats is not None:
        return _reconstruct_plant(args)
    if args.nproc != 1:
        raise HeliotwinError("--nproc shards heliostats: use it with --heliostats all|A,B,C")
    _set_threads(args.threads)
    settings = _settings(args)
    settings.check()  # before any file is read
    path = checkpoint_file(args)
    args.checkpoint = None if path is None else reconstruction_checkpoint(
        path, args.paint, args.heliostat, settings, scenario_path=args.scenario, resume=args.resume,
        min_interval_s=args.checkpoint_interval)
    if args.checkpoint is not None and args.checkpoint.resumed:
        stage(args, f"resuming from {path}")
    inputs = [("--paint", args.paint), ("--scenario", args.scenario), ("--deflectometry", args.deflectometry),
              *_prior_inputs(args)]
    # The checkpoint outlives the staged outputs: removed only once they are in place.
    with checkpointed(args, args.checkpoint), output_set(inputs) as out:
        json_path = out.file(args.json, "--json")
        output = out.file(args.output, "-o")
        previous = load_scenario(args.scenario) if args.scenario else None
        stage(args, _stage_text(args, settings))
        scenario, report, fit = reconstruct(previous, args.paint, args.heliostat, settings,
                                            checkpoint=args.checkpoint, progress=not args.quiet)
        stage(args, "plotting and writing outputs")
        report["plots"] = _plot_reconstruction(args, json_path, report, fit)
        if output:
            write_scenario(scenario, output)
            report["output"] = os.fspath(args.output)
        write_json(json_path, report)
    if not args.quiet:
        _print_reconstruction(args.heliostat, report)
    return 0


cmd_reconstruct.supports_cuda = True  # the learner follows args.device


def _reconstruct_plant(args) -> int:
    """``heliotwin reconstruct --heliostats``: :func:`heliotwin.workflows.reconstruct_plant.reconstruct_plant`, then
    the scenario (``-o``) and the report (``--json``), staged; the per-heliostat checkpoint folder
    (``<output>.ckpt``) is kept whenever the run does not finish (``--resume`` continues it)."""
    from ..io.scenario import load_scenario, write_scenario
    from ..workflows.reconstruct_plant import check_plant_settings, plant_reconstruction_checkpoint, reconstruct_plant

    _set_threads(args.threads)
    settings = _settings(args)
    check_plant_settings(settings, args.nproc)  # before any file is read
    path = checkpoint_file(args)
    ck = None if path is None else plant_reconstruction_checkpoint(path, args.paint, settings,
                                                                   scenario_path=args.scenario, resume=args.resume)
    if ck is not None and ck.resumed:
        stage(args, f"resuming from {path} ({len(ck.done)} heliostats finished)")
    args.checkpoint_kept = None if ck is None else ck.path
    with output_set([("--paint", args.paint), ("--scenario", args.scenario), *_prior_inputs(args)]) as out:
        json_path, output = out.file(args.json, "--json"), out.file(args.output, "-o")
        previous = load_scenario(args.scenario) if args.scenario else None
        stage(args, f"learning the surfaces of {args.heliostats} ({args.nproc} process(es)) on {settings.device}")
        scenario, report = reconstruct_plant(previous, args.paint, _selection(args.heliostats), settings,
                                             nproc=args.nproc, checkpoint=ck, progress=not args.quiet)
        if output:
            write_scenario(scenario, output)
            report["output"] = os.fspath(args.output)
        write_json(json_path, report)
    if ck is not None:
        ck.remove()
    if not args.quiet:
        s = report["summary"]
        fmt = lambda v: "n/a" if v is None else f"{v:.3f}"  # noqa: E731
        print(f"{s['learned']} learned ({s['accepted']} accepted, {s['resumed']} resumed), {s['skipped']} skipped, "
              f"{s['failed']} failed of {s['heliostats']} heliostats; median test L1 ideal "
              f"{fmt(s['median_test_l1_ideal'])} -> learned {fmt(s['median_test_l1_learned'])}; "
              + ("" if s["seconds_per_heliostat"] is None else f"{s['seconds_per_heliostat']:.1f} s per heliostat; ")
              + f"{s['seconds']:.1f} s")
    failed = report["summary"]["failed"]
    if failed:  # the outputs hold the others; a script must still see that the plant is not complete
        print(f"heliotwin reconstruct: {failed} heliostat(s) failed (their reasons are in {args.json}); "
              f"exit status {EXIT_NOT_MET}", file=sys.stderr)
    return EXIT_NOT_MET if failed else 0


def _selection(text: str):
    """``--heliostats``: ``"all"`` or the list of ids."""
    return "all" if text.strip().lower() == "all" else [h.strip() for h in text.split(",") if h.strip()]


#: Flags of the retired second learner: (flag, was it given?, what replaces it).
_RETIRED = (
    ("--method legacy", lambda a: a.method == "legacy", "reconstruct has one learner (the former default); "
     "the in-silico study's L-BFGS settings are heliotwin.surfaces.insilico.insilico_settings"),
    ("--loss", lambda a: a.loss is not None, "the learner fits the L1 of unit-sum images after the camera model"),
    ("--integrator mc", lambda a: a.integrator == "mc", "the learner renders with the conv integrator"),
    ("--background", lambda a: bool(a.background), "the learner models each image's background cut"),
    ("--start-from-deflectometry", lambda a: a.start_from_deflectometry,
     "the learner starts from the canting focus or a plant prior's mean; --deflectometry FILE compares with it"),
)


def _settings(args):
    """:class:`~heliotwin.workflows.reconstruct.ReconstructionSettings` from the flags (one line for a retired
    flag)."""
    from ..workflows.reconstruct import ReconstructionSettings

    for flag, given, instead in _RETIRED:
        if given(args):
            raise HeliotwinError(f"{flag} was an option of the retired legacy learner: {instead}")
    prior = None
    if args.surface_prior_from:
        prior = tuple(p.strip() for p in str(args.surface_prior_from).split(","))
    return ReconstructionSettings(
        train_records=_train_records(args), train_first=args.train_first,
        train_latest=args.train_latest, control_points=args.control_points,
        degree=args.degree, steps=args.steps, slope_error_mrad=None if args.slope_error == "auto" else args.slope_error,
        alignment=args.alignment, deflectometry=args.deflectometry, surface_prior_from=prior,
        device=getattr(args, "device", "cpu"))


def _stage_text(args, settings) -> str:
    learner, device = settings.learner(), getattr(args, "device", "cpu")
    cv = "leave-one-out" if learner.folds is None else f"{learner.folds}-fold cross-validation"
    return (f"learning {args.heliostat}'s surface (optics, {cv} over <= {learner.steps} steps, "
            f"acceptance) on {device}, then evaluating")


def _set_threads(threads: int) -> None:
    if threads:
        import torch

        torch.set_num_threads(threads)


def _train_records(args) -> tuple[int, ...] | None:
    if not args.train_records:
        return None
    try:
        return tuple(int(x) for x in args.train_records.split(",") if x.strip())
    except ValueError:
        raise HeliotwinError(f"--train-records: expected comma-separated record ids, "
                             f"got {args.train_records!r}") from None


def _plot_reconstruction(args, json_path, report, fit) -> dict:
    """Measured vs predicted test images (through the camera model), the normal-deviation map and the residual
    map beyond each facet's tilt + quadratic shape (where edge ridges show), next to the ``--json`` report."""
    from ..surfaces.plots import plot_flux_comparison, plot_normal_deviation, plot_residual_deviation

    model = fit["model"]
    learned = model.surfaces()
    names = {"normal_deviation": "-normal-deviation.png", "residual_deviation": "-residual-deviation.png",
             "flux": "-flux.png"}
    staged = {k: os.path.splitext(os.fspath(json_path))[0] + v for k, v in names.items()}
    plot_normal_deviation(fit["facets"], learned.control_points.detach(), model.degree,
                          staged["normal_deviation"],
                          title=f"{args.heliostat}: learned normal deviation from the flat canted ideal [mrad]")
    plot_residual_deviation(learned, fit["ideal"], fit["facets"], staged["residual_deviation"],
                            title=f"{args.heliostat}: residual normal deviation [mrad]")
    images = fit["info"]["test_images"]
    plot_flux_comparison(fit["test"].images, images["ideal"], images["learned"], fit["test"].ids,
                         staged["flux"], [r["l1_ideal"] for r in report["test"]],
                         [r["l1_learned"] for r in report["test"]],
                         title="centred flux: measured vs ideal vs learned (camera model)"
                         + ("; learned = cross-validated, each image by fits that did not see it"
                            if report.get("test_is") == "cross-validation" else ""))
    return {k: os.path.splitext(os.fspath(args.json))[0] + v for k, v in names.items()}


def _print_reconstruction(heliostat: str, report: dict) -> None:
    lo, hi = report["test_improved_wilson95"]
    test = "cross-validated" if report.get("test_is") == "cross-validation" else "test"
    print(f"{heliostat}: median {test} L1 ideal {report['median_l1_ideal']:.3f} -> learned "
          f"{report['median_l1_learned']:.3f}; {test} images improved {report['test_improved']}/"
          f"{report['test_images']} "
          f"(Wilson 95 % [{lo:.2f}, {hi:.2f}]); training images worse than ideal "
          f"{report['train_worse_than_ideal']}; edge ridge {report['edge_ridge']['edge_max_mrad']:.2f} mrad; "
          + (f"surface prior from {len(report['prior']['heliostats'])} heliostats, weight {report['prior']['weight']:g}"
             f"{', start = its mean' if report['prior']['start_is_prior_mean'] else ''}; " if "prior" in report else "")
          + f"{report['seconds']:.1f} s")
    if "deflectometry" in report:
        c = report["deflectometry"]["learned_vs_deflectometry"]
        print(f"learned vs deflectometry: {c['normal_deviation_mrad']:.3f} mrad mean normal deviation, "
              f"{c['height_rms_mm']:.3f} mm height RMS; median test L1 deflectometry "
              f"{report['deflectometry']['median_l1_deflectometry']:.3f}")


def cmd_predict(args) -> int:
    """``heliotwin predict``: :func:`heliotwin.workflows.predict.predict` into the ``--json`` report."""
    from ..io.scenario import load_scenario
    from ..workflows.predict import PredictionSettings, predict

    _set_threads(args.threads)
    from ..plots import plot_prediction

    settings = PredictionSettings(year=args.year, every=args.every, target=args.target,
                                  device=getattr(args, "device", "cpu"), weather=getattr(args, "weather", None))
    with output_set([("--scenario", args.scenario), ("--weather", getattr(args, "weather", None))]) as outputs:
        json_path = outputs.file(args.json, "--json")
        plot_path = outputs.file(getattr(args, "plot", None), "--plot")
        _, out = predict(load_scenario(args.scenario), args.heliostat, settings, progress=not args.quiet)
        write_json(json_path, out)
        if plot_path:
            plot_prediction(out, plot_path)
    for warning in out["energy"].get("warnings", []):  # the weather file's site far from the plant's
        print(f"heliotwin: warning: {warning}", file=sys.stderr)
    if not args.quiet:
        st = out["statistics"]["l1_ideal_vs_learned"]
        print(f"{out['heliostat']}: {out['instants']} instants; L1(ideal, learned) median "
              f"{'n/a' if st.get('median') is None else format(st['median'], '.3f')}; "
              f"{out['energy']['energy_kwh']:.0f} kWh on the target under {out['energy']['dni_source']}"
              + ("" if out["energy"].get("annual", True) else
                 f" (NOT annual: {out['energy']['coverage']['instants_with_dni']} of "
                 f"{out['energy']['coverage']['instants']} instants have weather)"))
    return 0


cmd_predict.supports_cuda = True  # yearly_flux follows the device of the plant pieces moved to args.device


def _slope_error(text: str):
    """argparse type of ``--slope-error``: ``auto`` or a slope error in [0, 100] mrad."""
    return "auto" if str(text).strip().lower() == "auto" else _SLOPE(text)


_SLOPE = float_range(0.0, 100.0, what="a slope error [mrad] or 'auto'")


def register(subparsers) -> None:
    """Add ``reconstruct`` and ``predict`` to an argparse subparsers object."""
    p = subparsers.add_parser("reconstruct", help="learn a heliostat's mirror surface from PAINT flux images")
    p.add_argument("--paint", required=True, help="PAINT download folder")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--heliostat", help="heliostat id, e.g. AA39")
    which.add_argument("--heliostats", metavar="all|A,B,C",
                       help="the plant form: learn every listed heliostat (all: the whole folder) that has enough "
                            "centred images; the others are reported as skipped")
    p.add_argument("--nproc", type=int_range(1, 1024, "a process count"), default=1,
                   help="with --heliostats: learn the heliostats in N worker processes (threads split over them)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--train-records", help="comma-separated record ids to train on (rest with images: test)")
    g.add_argument("--train-latest", type=positive_int,
                   help="a study's split: train on the K latest records with centred images, test on the earlier "
                        "ones (default: every centred image trains, and cross-validation over them is the test)")
    g.add_argument("--train-first", type=positive_int,
                   help="a study's split: train on the K earliest records with centred images (the written surface "
                        "is then the oldest one)")
    p.add_argument("--control-points", default="7x7", help="control points per facet, e.g. 7x7")
    p.add_argument("--degree", type=int_range(1, 5, "a NURBS degree"), default=3, help="NURBS degree (both directions)")
    p.add_argument("--steps", type=positive_int, default=None,
                   help="the cross-validation's step budget (default 300)")
    p.add_argument("--slope-error", type=_slope_error, default="auto",
                   help="mirror slope error [mrad] or 'auto' (chosen on the training images)")
    p.add_argument("--alignment", choices=("focal-spot", "motor"), default="focal-spot")
    p.add_argument("--deflectometry", help="PAINT deflectometry HDF5: evaluate its NURBS fit on the test images and "
                                          "compare the learned surface with it (mm, mrad)")
    # Accepted for old scripts: these change nothing, or are refused in one line (_RETIRED).
    p.add_argument("--method", choices=("generalising", "legacy"), default="generalising", help=argparse.SUPPRESS)
    p.add_argument("--integrator", choices=("conv", "mc"), default="conv", help=argparse.SUPPRESS)
    p.add_argument("--loss", default=None, help=argparse.SUPPRESS)
    p.add_argument("--background", type=float, default=0.0, help=argparse.SUPPRESS)
    p.add_argument("--start-from-deflectometry", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--no-mc", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--scenario", help="start from this scenario's plant, e.g. a calibrated one (default: the PAINT "
                                      "folder's nominal plant)")
    p.add_argument("-o", "--output", help="write the plant with the learned surface as a scenario file (.h5)")
    p.add_argument("--surface-prior-from", metavar="S1.h5,S2.h5,...",
                   help="a plant prior on the facets' canting and low-order shape, learned from the "
                        "learned surfaces in these scenarios (>= 2 other heliostats of the same design), or one "
                        "scenario holding a stored prior; its weight is chosen by leave-one-training-image-out "
                        "(0 included); -o stores it under /learned/surface_prior")
    p.add_argument("--json", required=True, help="report JSON to write")
    p.add_argument("--threads", type=int_range(0, 1024, "a thread count"), default=0,
                   help="torch threads (0: leave as is)")
    p.add_argument("--quiet", action="store_true", help="no progress bars and no summary line")
    add_resume_flags(p)
    p.set_defaults(func=cmd_reconstruct)

    q = subparsers.add_parser(
        "predict", help="yearly flux prediction of a learned heliostat",
        description="For every daylight instant of a year (every --every, sun above 5 deg), aim the heliostat at its "
                    "target's centre through the scenario's kinematics and predict its flux image with the learned "
                    "and with the ideal surface: power on the target [W], peak flux [W/m2] of both, and how far "
                    "the two images differ (L1 of unit-sum images). The report keeps the series and their "
                    "statistics, and the year's energy on the target [kWh] under clear-sky DNI or --weather; "
                    "--plot draws the series over the year.")
    q.add_argument("--scenario", required=True, help="scenario with a learned surface (from reconstruct -o)")
    q.add_argument("--heliostat", help="heliostat id (default: the scenario's only learned surface)")
    q.add_argument("--year", type=int_range(1900, 2100, "a year"), default=2023)
    q.add_argument("--every", type=frequency, default="30min",
                   help="time step between 1min and 31d, e.g. 30min, 1h (default: %(default)s)")
    q.add_argument("--target", help="target name (default: the training images' target)")
    q.add_argument("--json", required=True, help="JSON report (series per instant, statistics, energy)")
    q.add_argument("--plot", help="figure (PNG/PDF/SVG): power, peak flux and L1 over the year")
    q.add_argument("--weather", metavar="CSV", help="DNI time series for the energy (SAM/TMY weather file, PAINT's "
                                                    "calibration-weather.csv, or a time + dni CSV); default: clear sky")
    q.add_argument("--threads", type=int_range(0, 1024, "a thread count"), default=0,
                   help="torch threads (0: torch's default)")
    q.add_argument("--quiet", action="store_true", help="no progress bars and no summary line")
    q.set_defaults(func=cmd_predict)

