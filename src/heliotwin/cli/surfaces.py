"""Surface learning commands: ``reconstruct`` and ``predict``.

Usage::

    heliotwin reconstruct --paint PAINT_DIR --heliostat AA39 --train-first 3 -o learned.h5 --json report.json
    heliotwin reconstruct ... --deflectometry AA39-deflectometry.h5 [--start-from-deflectometry]
    heliotwin predict --scenario learned.h5 --heliostat AA39 --year 2023 --every 30min --json out.json

:func:`register` adds them to the main parser; the library (:mod:`heliotwin.surfaces`) is imported inside
the command functions, so ``--help`` stays torch-free. Output folders are checked before training, so a
typo costs seconds, not a training run.
"""
from __future__ import annotations

import os

from ..errors import HeliotwinError
from ..io.report import write_json
from .common import check_output_folder

__all__ = ["register"]


def cmd_reconstruct(args) -> int:
    from ..surfaces.reconstruct import reconstruct_paint

    _set_threads(args.threads)
    check_output_folder(args.json, "--json")
    check_output_folder(args.output, "-o")
    train_records = _train_records(args)
    if args.start_from_deflectometry and not args.deflectometry:
        raise HeliotwinError("--start-from-deflectometry needs --deflectometry FILE")
    if args.deflectometry:
        from ..io.deflectometry import read_deflectometry

        read_deflectometry(args.deflectometry)  # fail fast (one-line error naming the file) before training
    slope = None if args.slope_error == "auto" else float(args.slope_error) * 1e-3
    report, model, ds, extras = reconstruct_paint(
        args.paint, args.heliostat, train_records=train_records, train_first=args.train_first,
        settings=_train_settings(args), slope_error=slope, background=args.background, alignment=args.alignment,
        evaluate_mc=not args.no_mc, progress=not args.quiet, deflectometry=args.deflectometry,
        start_from_deflectometry=args.start_from_deflectometry)
    learned = model.surfaces()
    report["plots"] = _plot_reconstruction(args, report, model, learned, extras)
    if args.output:
        _save_learned(args.output, args.heliostat, report, model, learned, ds.plant, extras)
        report["output"] = os.fspath(args.output)
    write_json(args.json, report)
    if not args.quiet:
        _print_reconstruction(args.heliostat, report)
    return 0


def _set_threads(threads: int) -> None:
    if threads:
        import torch

        torch.set_num_threads(threads)


def _train_records(args) -> list[int] | None:
    if args.train_records and args.train_first is not None:
        raise HeliotwinError("use either --train-records or --train-first, not both")
    if not args.train_records:
        return None
    try:
        return [int(x) for x in args.train_records.split(",") if x.strip()]
    except ValueError:
        raise HeliotwinError(f"--train-records: expected comma-separated record ids, "
                             f"got {args.train_records!r}") from None


def _train_settings(args):
    from ..surfaces.learning import parse_grid
    from ..surfaces.reconstruct import TrainSettings

    return TrainSettings(control_points=parse_grid(args.control_points), degree=(args.degree, args.degree),
                         integrator=args.integrator, loss=args.loss, steps=args.steps)


def _plot_reconstruction(args, report, model, learned, extras) -> dict:
    """The normal-deviation map and the test-image comparison, next to the ``--json`` report."""
    from ..surfaces.plots import plot_flux_comparison, plot_normal_deviation

    stem = os.path.splitext(os.fspath(args.json))[0]
    plots = {"normal_deviation": stem + "-normal-deviation.png", "flux": stem + "-flux.png"}
    plot_normal_deviation(extras["facets"], learned.control_points, model.degree, plots["normal_deviation"],
                          title=f"{args.heliostat}: learned normal deviation from ideal [mrad]")
    plot_flux_comparison(extras["test"].images, extras["ideal_images"], extras["learned_images"],
                         extras["test"].ids, plots["flux"], [r["l1_ideal"] for r in report["test"]],
                         [r["l1_learned"] for r in report["test"]])
    return plots


def _save_learned(path, heliostat, report, model, learned, plant, extras) -> None:
    from ..surfaces.store import LearnedHeliostat, save_learned

    save_learned(path, LearnedHeliostat(
        heliostat, learned, model.displacement.detach(), extras["facets"], plant.field.kinematics.index(0),
        plant.targets, (plant.site.latitude_deg, plant.site.longitude_deg, plant.site.altitude_m), extras["optics"],
        {"train": report["train"], "settings": report["settings"], "default_target": extras["test"].targets[0].name}))


def _print_reconstruction(heliostat: str, report: dict) -> None:
    print(f"{heliostat}: median test L1 ideal {report['median_l1_ideal']:.3f} -> learned "
          f"{report['median_l1_learned']:.3f} (median IMP {100 * report['median_imp']:+.0f} %), "
          f"{report['seconds']:.1f} s")
    if "deflectometry" in report:
        c = report["deflectometry"]["learned_vs_deflectometry"]
        print(f"learned vs deflectometry: {c['normal_deviation_mrad']:.3f} mrad mean normal deviation, "
              f"{c['height_rms_mm']:.3f} mm height RMS; median test L1 deflectometry "
              f"{report['deflectometry']['median_l1_deflectometry']:.3f}")


def cmd_predict(args) -> int:
    from ..field.facets import ideal_surfaces
    from ..surfaces.predict import summarize, yearly_flux
    from ..surfaces.store import load_learned

    _set_threads(args.threads)
    check_output_folder(args.json, "--json")
    item = load_learned(args.scenario)
    if args.heliostat and args.heliostat != item.heliostat_id:
        raise HeliotwinError(f"{args.scenario}: holds heliostat {item.heliostat_id}, not {args.heliostat}")
    name = args.target or item.settings.get("default_target") or sorted(item.targets)[0]
    if name not in item.targets:
        raise HeliotwinError(f"unknown target {name!r}; stored: {', '.join(sorted(item.targets))}")
    cp = item.surfaces.control_points
    ideal = ideal_surfaces(item.facets, (cp.shape[2], cp.shape[3]), (item.surfaces.degree_u, item.surfaces.degree_v))
    series = yearly_flux(item.kinematics, item.targets[name], item.site, item.surfaces, ideal, item.sun,
                         year=args.year, every=args.every, progress=not args.quiet)
    out = {"heliostat": item.heliostat_id, "target": name, "year": args.year, "every": args.every,
           "instants": len(series["time"]), "statistics": summarize(series), "series": series,
           "optics": {"sunshape": item.sun.sunshape, "slope_error_rad": item.sun.slope_error}}
    write_json(args.json, out)
    if not args.quiet:
        st = out["statistics"]["l1_ideal_vs_learned"]
        print(f"{item.heliostat_id}: {out['instants']} instants; L1(ideal, learned) median {st['median']:.3f}")
    return 0


def register(subparsers) -> None:
    """Add ``reconstruct`` and ``predict`` to an argparse subparsers object."""
    p = subparsers.add_parser("reconstruct", help="learn a heliostat's mirror surface from PAINT flux images")
    p.add_argument("--paint", required=True, help="PAINT download folder")
    p.add_argument("--heliostat", required=True, help="heliostat id, e.g. AA39")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--train-records", help="comma-separated record ids to train on (rest with images: test)")
    g.add_argument("--train-first", type=int, help="train on the K earliest records with centred images (default 3)")
    p.add_argument("--control-points", default="7x7", help="control points per facet, e.g. 7x7")
    p.add_argument("--degree", type=int, default=3, help="NURBS degree (both directions)")
    p.add_argument("--integrator", choices=("analytic", "mc"), default="analytic")
    p.add_argument("--loss", choices=("kl", "l1", "l2"), default="kl")
    p.add_argument("--steps", type=int, default=200, help="maximum optimiser steps")
    p.add_argument("--slope-error", default="auto", help="mirror slope error [mrad] or 'auto' (fit on training images)")
    p.add_argument("--background", type=float, default=0.0, help="background to subtract, fraction of image max")
    p.add_argument("--alignment", choices=("focal-spot", "motor"), default="focal-spot")
    p.add_argument("--no-mc", action="store_true", help="skip the Monte-Carlo evaluation")
    p.add_argument("--deflectometry", help="PAINT deflectometry HDF5: trace its NURBS fit on the test images and "
                                          "compare the learned surface with it (mm, mrad)")
    p.add_argument("--start-from-deflectometry", action="store_true",
                   help="start the learning from the deflectometry surface instead of flat")
    p.add_argument("-o", "--output", help="learned surface HDF5 to write")
    p.add_argument("--json", required=True, help="report JSON to write")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: leave as is)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_reconstruct)

    q = subparsers.add_parser("predict", help="yearly flux prediction of a learned heliostat")
    q.add_argument("--scenario", required=True, help="learned surface HDF5 (from reconstruct -o)")
    q.add_argument("--heliostat", help="heliostat id (checked against the file)")
    q.add_argument("--year", type=int, default=2023)
    q.add_argument("--every", default="30min", help="pandas frequency, e.g. 30min")
    q.add_argument("--target", help="target name (default: the training images' target)")
    q.add_argument("--json", required=True)
    q.add_argument("--threads", type=int, default=0)
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=cmd_predict)

