"""Surface learning commands: ``reconstruct`` and ``predict``.

Usage::

    heliotwin reconstruct --paint PAINT_DIR --heliostat AA39 --train-first 3 -o learned.h5 --json report.json
    heliotwin reconstruct --method legacy ... --deflectometry AA39-deflectometry.h5 [--start-from-deflectometry]
    heliotwin reconstruct --paint PAINT_DIR --heliostat AA39 --surface-prior-from S1.h5,S2.h5 -o learned.h5 ...
    heliotwin predict --scenario learned.h5 --heliostat AA39 --year 2023 --every 30min --json out.json

:func:`register` adds them to the main parser; the library (:mod:`heliotwin.surfaces`) is imported inside
the command functions, so ``--help`` stays torch-free. Output folders are checked before training, so a
typo costs seconds, not a training run.
"""
from __future__ import annotations

import os

from ..errors import HeliotwinError
from ..io.report import output_set, write_json
from .common import (
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


def cmd_reconstruct(args) -> int:
    _set_threads(args.threads)
    _check_method(args)
    if args.method == "generalising":
        return _reconstruct_generalising(args)
    return _reconstruct_legacy(args)


def _reconstruct_legacy(args) -> int:
    from ..io.scenario import load_scenario
    from ..surfaces.study import reconstruct_paint

    inputs = [("--paint", args.paint), ("--scenario", args.scenario), ("--deflectometry", args.deflectometry)]
    train_records = _train_records(args)
    slope = None if args.slope_error == "auto" else args.slope_error * 1e-3
    fit_args = dict(train_records=train_records, train_first=args.train_first, settings=_train_settings(args),
                    slope_error=slope, background=args.background, alignment=args.alignment,
                    deflectometry=args.deflectometry, start_from_deflectometry=args.start_from_deflectometry)
    # The checkpoint outlives the staged outputs: removed only once they are in place.
    with checkpointed(args, _checkpoint(args, fit_args)), output_set(inputs) as out:
        json_path = out.file(args.json, "--json")
        output = out.file(args.output, "-o")
        if args.start_from_deflectometry and not args.deflectometry:
            raise HeliotwinError("--start-from-deflectometry needs --deflectometry FILE")
        if args.deflectometry:
            from ..io.deflectometry import read_deflectometry

            read_deflectometry(args.deflectometry)  # fail fast (one-line error naming the file) before training
        previous = load_scenario(args.scenario) if args.scenario else None
        stage(args, f"learning {args.heliostat}'s surface ({args.integrator}, <= {args.steps} steps) on "
                    f"{getattr(args, 'device', 'cpu')}, then evaluating")
        report, model, ds, extras = reconstruct_paint(
            args.paint, args.heliostat, evaluate_mc=not args.no_mc, progress=not args.quiet,
            plant=previous.plant if previous else None, device=getattr(args, "device", "cpu"),
            checkpoint=args.checkpoint, **fit_args)
        report["method"] = "legacy"
        _write_reconstruction(args, json_path, output, report, model, previous, extras, _plot_reconstruction)
    if not args.quiet:
        _print_reconstruction(args.heliostat, report)
    return 0


def _write_reconstruction(args, json_path, output, report, model, previous, extras, plot) -> None:
    """The end of either method: its figures (``plot``), the learned surface into ``output`` (when given) and
    the JSON report, all into the command's staged output set."""
    learned = model.surfaces()
    stage(args, "plotting and writing outputs")
    report["plots"] = plot(args, json_path, report, model, learned, extras)
    if output:
        _save_learned(args, output, report, model, learned, previous, extras)
        report["output"] = os.fspath(args.output)
    write_json(json_path, report)


def _reconstruct_generalising(args) -> int:
    """``--method generalising`` (:func:`heliotwin.surfaces.generalise.reconstruct_paint_generalising`)."""
    from ..io.scenario import load_scenario
    from ..surfaces.generalise import reconstruct_paint_generalising

    train_records = _train_records(args)
    settings = _generalise_settings(args)
    prior = _surface_prior(args)
    fit_args = dict(method="generalising", train_records=train_records, train_first=args.train_first,
                    settings=settings, alignment=args.alignment)
    if prior is not None:  # a resumed run must use the same prior (the checkpoint's fingerprint holds it)
        fit_args["surface_prior"] = {"heliostats": list(prior.heliostats),
                                     "mean": [float(x) for x in prior.mean.reshape(-1)]}
    # The checkpoint outlives the staged outputs: removed only once they are in place.
    with checkpointed(args, _checkpoint(args, fit_args)), \
            output_set([("--paint", args.paint), ("--scenario", args.scenario)]) as out:
        json_path = out.file(args.json, "--json")
        output = out.file(args.output, "-o")
        previous = load_scenario(args.scenario) if args.scenario else None
        stage(args, f"learning {args.heliostat}'s surface (generalising: optics, leave-one-out over "
                    f"<= {settings.steps} steps, acceptance) on {getattr(args, 'device', 'cpu')}, then evaluating")
        report, model, extras = reconstruct_paint_generalising(
            args.paint, args.heliostat, train_first=args.train_first,
            train_records=train_records, settings=settings, alignment=args.alignment, progress=not args.quiet,
            plant=previous.plant if previous else None, device=getattr(args, "device", "cpu"),
            checkpoint=args.checkpoint, prior=prior)
        report["method"] = "generalising"
        extras["surface_prior"] = prior
        report["choices"] = _generalising_choices(report)
        if output:  # the stored surface records what chose it
            report["settings"] = dict(report["settings"], method="generalising", chosen=report["choices"])
        _write_reconstruction(args, json_path, output, report, model, previous, extras, _plot_generalising)
    if not args.quiet:
        _print_generalising(args.heliostat, report)
    return 0


cmd_reconstruct.supports_cuda = True  # the learner follows args.device


def _checkpoint(args, fit_args: dict):
    """The run's checkpoint next to its main output (None without one); also ``args.checkpoint``."""
    from ..surfaces.study import reconstruction_checkpoint

    path = checkpoint_file(args)
    args.checkpoint = None if path is None else reconstruction_checkpoint(
        path, args.paint, args.heliostat, resume=args.resume, device=getattr(args, "device", "cpu"),
        inputs=[args.scenario, getattr(args, "deflectometry", None)], min_interval_s=args.checkpoint_interval,
        **fit_args)
    if args.checkpoint is not None and args.checkpoint.resumed:
        stage(args, f"resuming from {path}")
    return args.checkpoint


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


#: Flags of the legacy learner that ``--method generalising`` does not take: (flag, is it set?, why).
_LEGACY_ONLY = (
    ("--loss", lambda a: _given(a.loss), "it fits the L1 of unit-sum images after the camera model"),
    ("--integrator", lambda a: a.integrator != "conv", "it renders with the conv integrator"),
    ("--background", lambda a: a.background > 0, "it models each image's background cut instead"),
    ("--deflectometry", lambda a: a.deflectometry is not None, "deflectometry comparison is legacy-only"),
    ("--start-from-deflectometry", lambda a: a.start_from_deflectometry, "it starts from the canting focus"),
)


def _surface_prior(args):
    """``--surface-prior-from S1.h5,S2.h5,...`` (before any PAINT file is read): the plant surface prior, or None.

    One scenario holding a stored prior (``/learned/surface_prior``) is used as it is; otherwise the prior is
    built from the learned surfaces of all the files. Refused (one line) when a file is missing or has no
    learned surface, when the sources' facet counts differ, or when ``--heliostat`` is among the sources.
    """
    if not args.surface_prior_from:
        return None
    from ..surfaces.plantprior import load_surface_prior

    paths = [p.strip() for p in str(args.surface_prior_from).split(",") if p.strip()]
    return load_surface_prior(paths, heliostat_id=args.heliostat)


class _Unset(str):
    """A flag's default that says it was not given (equal to the default it stands for)."""


class _UnsetInt(int):
    """An integer flag's default that says it was not given (equal to the default it stands for)."""


def _given(value) -> bool:
    return not isinstance(value, (_Unset, _UnsetInt))


def _check_method(args) -> None:
    """One line for a flag the chosen method does not take (before any file is read); plain values after."""
    if args.method == "generalising":
        for flag, given, why in _LEGACY_ONLY:
            if given(args):
                raise HeliotwinError(f"{flag} is not supported with --method generalising ({why}); "
                                     f"use --method legacy")
        args.steps = int(args.steps) if _given(args.steps) else None
    else:
        if getattr(args, "surface_prior_from", None):
            raise HeliotwinError("--surface-prior-from is not supported with --method legacy; use --method "
                                 "generalising")
        args.steps = int(args.steps)
    args.loss = str(args.loss)


def _generalise_settings(args):
    """:class:`~heliotwin.surfaces.generalise.GeneraliseSettings` from the flags: ``--control-points``,
    ``--degree``; ``--steps`` is the leave-one-out step budget (held-out L1 every ``min(30, steps // 2)`` steps,
    so even a small budget leaves the step count a choice);
    a numeric ``--slope-error`` fixes the slope-error grid to that value."""
    from ..surfaces.generalise import GeneraliseSettings
    from ..surfaces.learning import parse_grid

    base = GeneraliseSettings()
    steps = args.steps or base.steps
    kw = dict(control_points=parse_grid(args.control_points), degree=(args.degree, args.degree), steps=steps,
              eval_every=min(base.eval_every, max(1, steps // 2)))
    if args.slope_error != "auto":
        kw["slope_grid"] = (args.slope_error * 1e-3,)
    return GeneraliseSettings(**kw)


def _generalising_choices(report: dict) -> dict:
    """What the generalising method chose (JSON): optics, blur mode, penalty weight, steps, drops, acceptance."""
    chosen = report["optics"]["chosen"]
    out = {"focal_length_m": chosen["focal_length_m"], "focus_multiple": chosen["focus_multiple"],
           "slope_error_rad": report["optics_used"]["slope_error_rad"], "blur_mode": report["blur_mode"],
           "slope_weight": report["selection"]["slope_weight"], "steps": report["selection"]["steps"],
           "dropped": [d["record"] for d in report["dropped"]], "acceptance_alpha": report["acceptance"]["alpha"]}
    if "prior" in report:
        out.update(surface_prior_weight=report["prior"]["weight"],
                   surface_prior_heliostats=report["prior"]["heliostats"])
    return out


def _train_settings(args):
    from ..surfaces.learning import parse_grid
    from ..surfaces.training import TrainSettings

    return TrainSettings(control_points=parse_grid(args.control_points), degree=(args.degree, args.degree),
                         integrator=args.integrator, loss=args.loss, steps=args.steps)


def _plot_reconstruction(args, json_path, report, model, learned, extras) -> dict:
    """The normal-deviation map and the test-image comparison, next to the ``--json`` report (written next to
    the staged ``json_path``; the report names them next to the user's ``--json``)."""
    from ..surfaces.plots import plot_flux_comparison, plot_normal_deviation

    names = {"normal_deviation": "-normal-deviation.png", "flux": "-flux.png"}
    staged = {k: os.path.splitext(os.fspath(json_path))[0] + v for k, v in names.items()}
    plot_normal_deviation(extras["facets"], learned.control_points, model.degree, staged["normal_deviation"],
                          title=f"{args.heliostat}: learned normal deviation from ideal [mrad]")
    plot_flux_comparison(extras["test"].images, extras["ideal_images"], extras["learned_images"],
                         extras["test"].ids, staged["flux"], [r["l1_ideal"] for r in report["test"]],
                         [r["l1_learned"] for r in report["test"]])
    return {k: os.path.splitext(os.fspath(args.json))[0] + v for k, v in names.items()}


def _plot_generalising(args, json_path, report, model, learned, extras) -> dict:
    """Measured vs predicted test images (through the camera model), the normal-deviation map and the residual
    map beyond each facet's tilt + quadratic shape (where edge ridges show), next to the ``--json`` report."""
    from ..surfaces.plots import plot_flux_comparison, plot_normal_deviation, plot_residual_deviation

    names = {"normal_deviation": "-normal-deviation.png", "residual_deviation": "-residual-deviation.png",
             "flux": "-flux.png"}
    staged = {k: os.path.splitext(os.fspath(json_path))[0] + v for k, v in names.items()}
    plot_normal_deviation(extras["facets"], learned.control_points.detach(), model.degree,
                          staged["normal_deviation"],
                          title=f"{args.heliostat}: learned normal deviation from the flat canted ideal [mrad]")
    plot_residual_deviation(learned, extras["ideal"], extras["facets"], staged["residual_deviation"],
                            title=f"{args.heliostat}: residual normal deviation [mrad]")
    images = extras["info"]["test_images"]
    plot_flux_comparison(extras["test"].images, images["ideal"], images["learned"], extras["test"].ids,
                         staged["flux"], [r["l1_ideal"] for r in report["test"]],
                         [r["l1_learned"] for r in report["test"]],
                         title="centred flux: measured vs ideal vs learned (camera model)")
    return {k: os.path.splitext(os.fspath(args.json))[0] + v for k, v in names.items()}


def _save_learned(args, output, report, model, learned, previous, extras) -> None:
    """plant″: the scenario's plant (or the PAINT folder's) with this heliostat's learned surface."""
    from ..io.scenario import scenario_from_paint
    from ..surfaces.state import save_learned_surface

    plant = previous.plant if previous is not None else scenario_from_paint(args.paint)
    prior = extras.get("surface_prior")
    save_learned_surface(output, plant, args.heliostat, learned, model.displacement.detach(), extras["optics"],
                         previous=previous, train_records=[int(r["record"]) for r in report["train"]],
                         target=extras["test"].targets[0].name, settings=report["settings"],
                         source=os.path.abspath(args.paint), surface_prior=None if prior is None else prior.state())


def _print_reconstruction(heliostat: str, report: dict) -> None:
    print(f"{heliostat}: median test L1 ideal {report['median_l1_ideal']:.3f} -> learned "
          f"{report['median_l1_learned']:.3f} (median IMP {100 * report['median_imp']:+.0f} %), "
          f"{report['seconds']:.1f} s")
    if "deflectometry" in report:
        c = report["deflectometry"]["learned_vs_deflectometry"]
        print(f"learned vs deflectometry: {c['normal_deviation_mrad']:.3f} mrad mean normal deviation, "
              f"{c['height_rms_mm']:.3f} mm height RMS; median test L1 deflectometry "
              f"{report['deflectometry']['median_l1_deflectometry']:.3f}")


def _print_generalising(heliostat: str, report: dict) -> None:
    lo, hi = report["test_improved_wilson95"]
    print(f"{heliostat} (generalising): median test L1 ideal {report['median_l1_ideal']:.3f} -> learned "
          f"{report['median_l1_learned']:.3f}; test improved {report['test_improved']}/{report['test_images']} "
          f"(Wilson 95 % [{lo:.2f}, {hi:.2f}]); training images worse than ideal "
          f"{report['train_worse_than_ideal']}; edge ridge {report['edge_ridge']['edge_max_mrad']:.2f} mrad; "
          + (f"surface prior from {len(report['prior']['heliostats'])} heliostats, weight {report['prior']['weight']:g}"
             f"{', start = its mean' if report['prior']['start_is_prior_mean'] else ''}; " if "prior" in report else "")
          + f"{report['seconds']:.1f} s")


def cmd_predict(args) -> int:
    from ..io.scenario import load_scenario

    _set_threads(args.threads)
    with output_set([("--scenario", args.scenario)]) as outputs:
        json_path = outputs.file(args.json, "--json")
        out = _predict(args, load_scenario(args.scenario))
        write_json(json_path, out)
    if not args.quiet:
        st = out["statistics"]["l1_ideal_vs_learned"]
        print(f"{args.heliostat}: {out['instants']} instants; L1(ideal, learned) median "
              f"{'n/a' if st.get('median') is None else format(st['median'], '.3f')}")
    return 0


def _predict(args, sc) -> dict:
    """The yearly prediction of ``args.heliostat`` (default: the only learned surface) in scenario ``sc``."""
    from ..surfaces.predict import summarize, yearly_flux
    from ..surfaces.state import learned_surface

    learned = sorted(sc.learned.get("surfaces") or {})
    if args.heliostat is None:
        if len(learned) != 1:
            raise HeliotwinError(f"{args.scenario}: {len(learned)} learned surfaces ({', '.join(learned) or 'none'}); "
                                 f"choose one with --heliostat")
        args.heliostat = learned[0]
    item = learned_surface(sc, args.heliostat)
    plant = sc.plant
    name = args.target or item["target"]
    target = plant.target(name)
    site = (plant.site.latitude_deg, plant.site.longitude_deg, plant.site.altitude_m)
    kin = plant.field.kinematics.index([plant.field.index_of(args.heliostat)])
    surfaces, ideal = item["surfaces"], item["ideal"]
    device = getattr(args, "device", "cpu")
    if device != "cpu":
        from ..api import to_device

        kin, target, surfaces, ideal = to_device((kin, target, surfaces, ideal), device)
    series = yearly_flux(kin, target, site, surfaces, ideal, item["optics"],
                         year=args.year, every=args.every, progress=not args.quiet)
    optics = item["optics"]
    return {"heliostat": args.heliostat, "target": name, "year": args.year, "every": args.every,
            "instants": len(series["time"]), "statistics": summarize(series), "series": series,
            "optics": {"sunshape": optics.sunshape, "slope_error_rad": optics.slope_error}, "device": device}


cmd_predict.supports_cuda = True  # yearly_flux follows the device of the plant pieces moved to args.device


def _slope_error(text: str):
    """argparse type of ``--slope-error``: ``auto`` or a slope error in [0, 100] mrad."""
    return "auto" if str(text).strip().lower() == "auto" else _SLOPE(text)


_SLOPE = float_range(0.0, 100.0, what="a slope error [mrad] or 'auto'")


def register(subparsers) -> None:
    """Add ``reconstruct`` and ``predict`` to an argparse subparsers object."""
    p = subparsers.add_parser("reconstruct", help="learn a heliostat's mirror surface from PAINT flux images")
    p.add_argument("--paint", required=True, help="PAINT download folder")
    p.add_argument("--heliostat", required=True, help="heliostat id, e.g. AA39")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--train-records", help="comma-separated record ids to train on (rest with images: test)")
    g.add_argument("--train-first", type=positive_int,
                   help="train on the K earliest records with centred images (default 3)")
    p.add_argument("--control-points", default="7x7", help="control points per facet, e.g. 7x7")
    p.add_argument("--degree", type=int_range(1, 5, "a NURBS degree"), default=3, help="NURBS degree (both directions)")
    p.add_argument("--integrator", choices=("conv", "mc"), default="conv",
                   help="renderer of the training images: exact-sunshape convolution or Monte Carlo (default conv)")
    p.add_argument("--method", choices=("generalising", "legacy"), default="generalising",
                   help="legacy: KL loss with early stopping on the latest training image; generalising: "
                        "camera model, optics chosen on the training images, settings "
                        "and step count by leave-one-training-image-out, outlier drop, acceptance rule (no "
                        "training image worse than the ideal) (default %(default)s)")
    p.add_argument("--loss", choices=("kl", "l1", "l2"), default=_Unset("kl"), help="legacy: image loss (default kl)")
    p.add_argument("--steps", type=positive_int, default=_UnsetInt(200),
                   help="maximum optimiser steps (legacy, default 200); generalising: the leave-one-out step "
                        "budget (default 300)")
    p.add_argument("--slope-error", type=_slope_error, default="auto",
                   help="mirror slope error [mrad] or 'auto' (chosen on the training images)")
    p.add_argument("--background", type=float_range(0.0, 1.0, what="a fraction"), default=0.0,
                   help="background to subtract, fraction of image max")
    p.add_argument("--alignment", choices=("focal-spot", "motor"), default="focal-spot")
    p.add_argument("--no-mc", action="store_true",
                   help="skip the Monte-Carlo evaluation (legacy; generalising has none)")
    p.add_argument("--deflectometry", help="PAINT deflectometry HDF5: trace its NURBS fit on the test images and "
                                          "compare the learned surface with it (mm, mrad)")
    p.add_argument("--start-from-deflectometry", action="store_true",
                   help="start the learning from the deflectometry surface instead of flat")
    p.add_argument("--scenario", help="start from this scenario's plant, e.g. a calibrated one (default: the PAINT "
                                      "folder's nominal plant)")
    p.add_argument("-o", "--output", help="write the plant with the learned surface as a scenario file (.h5)")
    p.add_argument("--surface-prior-from", metavar="S1.h5,S2.h5,...",
                   help="generalising: a plant prior on the facets' canting and low-order shape, learned from the "
                        "learned surfaces in these scenarios (>= 2 other heliostats of the same design), or one "
                        "scenario holding a stored prior; its weight is chosen by leave-one-training-image-out "
                        "(0 included); -o stores it under /learned/surface_prior")
    p.add_argument("--json", required=True, help="report JSON to write")
    p.add_argument("--threads", type=int_range(0, 1024, "a thread count"), default=0,
                   help="torch threads (0: leave as is)")
    p.add_argument("--quiet", action="store_true", help="no progress bars and no summary line")
    add_resume_flags(p)
    p.set_defaults(func=cmd_reconstruct)

    q = subparsers.add_parser("predict", help="yearly flux prediction of a learned heliostat")
    q.add_argument("--scenario", required=True, help="scenario with a learned surface (from reconstruct -o)")
    q.add_argument("--heliostat", help="heliostat id (default: the scenario's only learned surface)")
    q.add_argument("--year", type=int_range(1900, 2100, "a year"), default=2023)
    q.add_argument("--every", type=frequency, default="30min",
                   help="time step between 1min and 31d, e.g. 30min, 1h (default: %(default)s)")
    q.add_argument("--target", help="target name (default: the training images' target)")
    q.add_argument("--json", required=True)
    q.add_argument("--threads", type=int_range(0, 1024, "a thread count"), default=0)
    q.add_argument("--quiet", action="store_true", help="no progress bars and no summary line")
    q.set_defaults(func=cmd_predict)

