"""Plant commands: ``demo``, ``scenario from-paint``, ``trace``, ``validate`` and ``bench``.

Each ``cmd_*`` reads its arguments, calls the library (imported inside the function, so ``--help`` stays
torch-free) and prints one summary line; :func:`register` adds the subcommands to the main parser.
"""
from __future__ import annotations

import math
import os
import time

from ..errors import HeliotwinError
from ..io.report import output_set, write_json
from . import field
from .common import csv_list, int_list, int_range, seed_int, stage, utc_time

# Ranges of the numeric arguments: beyond them a run would exhaust memory or mean a typo.
_RESOLUTION = int_range(8, 4096, "a resolution [pixels]")
_SAMPLES = int_range(1, 1000, "a sample count")
_RAYS = int_range(1, 100_000, "a ray count")


def _ray_list(text: str) -> list[int]:
    """argparse type of ``bench --rays-per-point``: comma-separated ray counts, each in 1..100000."""
    return int_list(text, 100_000)


def _fmt(x, spec: str = ".2f", none: str = "n/a") -> str:
    """A number for a summary line; ``None``/NaN (nothing to measure) print as ``n/a``."""
    return none if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


# ------------------------------------------------------------------------------------------------ demo
_CLASSIC_ONLY = (("integrator", "--integrator"), ("rays_per_point", "--rays-per-point"),
                 ("resolution", "--resolution"), ("seed", "--seed"))


def cmd_demo(args) -> int:
    """The whole embedded field (default) or, with ``--classic``, the small traced plant of earlier releases."""
    if args.classic:
        return _cmd_demo_classic(args)
    for attr, flag in _CLASSIC_ONLY:
        if getattr(args, attr) is not None:
            raise HeliotwinError(f"demo: {flag} belongs to the classic demo (add --classic); the field demo uses "
                                 "the Gaussian field model on a 48x20 receiver map")
    from ..workflows.demo import run_field_demo

    with output_set() as out:
        folder = out.folder(args.out, "--out")
        json_path = out.file(args.json, "--json")
        summary = run_field_demo(folder, num_heliostats=args.heliostats or 2000, time_utc=args.time,
                                 iterations=args.iterations, progress=not args.quiet,
                                 device=getattr(args, "device", "cpu"))
        if json_path:
            write_json(json_path, summary)
    if args.quiet:
        return 0
    from ..timefmt import utc_or_label

    a, chain = summary["aim_points"], summary["chain"]
    print(f"demo: {summary['heliostats']} heliostats, {utc_or_label(summary['time_utc'])}, sun elevation "
          f"{summary['sun']['elevation_deg']:.1f} deg; field efficiency {chain['efficiency']:.3f}, "
          f"{chain['power_w'] / 1e6:.2f} MW on the receiver (the tower's shadow included: "
          f"-{100 * (1 - chain['tower_shading_power_weighted']):.1f} %); peak "
          f"{a['equator_peak_w_m2'] / 1e3:.0f} -> {a['optimised_peak_w_m2'] / 1e3:.0f} kW/m2 (limit "
          f"{a['peak_limit_w_m2'] / 1e3:.0f}) at {100 * a['power_vs_equator']:.1f} % of the power; "
          f"{summary['seconds']['total']:.0f} s; outputs in {args.out}")
    return 0


cmd_demo.supports_cuda = True  # both demos run on args.device


def _cmd_demo_classic(args) -> int:
    """Trace the embedded default plant at a spring-equinox noon and write flux PNGs + a JSON summary."""
    from ..workflows.demo import run_demo

    with output_set() as out:
        folder = out.folder(args.out, "--out")
        json_path = out.file(args.json, "--json")
        summary = run_demo(folder, num_heliostats=args.heliostats or 48, integrator=args.integrator or "mc",
                           rays_per_point=args.rays_per_point or 64, resolution=args.resolution or 256,
                           seed=args.seed or 0, time_utc=args.time, progress=not args.quiet,
                           device=getattr(args, "device", "cpu"))
        if json_path:
            write_json(json_path, summary)
    if args.quiet:
        return 0
    print(f"demo: {summary['heliostats_traced']} heliostats, sun az {summary['sun_azimuth_deg']:.1f} deg "
          f"el {summary['sun_elevation_deg']:.1f} deg; receiver intercepts "
          f"{summary['receiver']['intercepted_power_w'] / 1e3:.1f} kW of {summary['total_power_w'] / 1e3:.1f} kW "
          f"reflected; outputs in {args.out}")
    return 0


# -------------------------------------------------------------------------------------------- scenario
def cmd_scenario_from_paint(args) -> int:
    from ..io.scenario import save_scenario, scenario_from_paint

    if args.paint and args.paint_dir and os.path.abspath(args.paint) != os.path.abspath(args.paint_dir):
        raise HeliotwinError(f"two PAINT folders: {args.paint_dir} and --paint {args.paint}; give one")
    args.paint_dir = args.paint or args.paint_dir
    if not args.paint_dir:
        raise HeliotwinError("scenario from-paint: which PAINT folder? (--paint PAINT_DIR)")

    with output_set([("PAINT_DIR", args.paint_dir)]) as out:
        output = out.file(args.output, "-o")
        plant = scenario_from_paint(args.paint_dir, csv_list(args.heliostats))
        save_scenario(plant, output, metadata={"source": os.path.abspath(args.paint_dir),
                                               "created_by": "heliotwin scenario from-paint"})
    if not args.quiet:
        print(f"scenario: {len(plant.field.ids)} heliostats, {len(plant.targets)} targets -> {args.output}")
    return 0


def cmd_scenario_show(args) -> int:
    """What a scenario file holds: plant, what is learned, /learned groups, provenance (``--json`` as JSON)."""
    from ..io.scenario import load_scenario
    from ..workflows.show import describe_scenario, format_description

    described = describe_scenario(load_scenario(args.file))
    if args.json == "-":
        import json

        print(json.dumps(described, indent=1, default=str))
        return 0
    if args.json:
        with output_set([("FILE", args.file)]) as out:
            write_json(out.file(args.json, "--json"), described)
    if not args.quiet:
        print(format_description(described))
    return 0


def cmd_scenario_export(args) -> int:
    """The scenario's plant for SolarPILOT (layout table + TOML) and/or SolTrace (input file at one sun)."""
    from ..io.scenario import load_scenario
    from ..workflows.field import sun_direction_at
    from ..workflows.show import export_plant

    if not (args.solarpilot or args.soltrace):
        raise HeliotwinError("scenario export: nothing to write (give --solarpilot LAYOUT.csv and/or --soltrace "
                             "FILE.stinput)")
    if args.sun_azimuth is not None and args.sun_elevation is None:
        raise HeliotwinError("--sun-azimuth needs --sun-elevation")
    sc = load_scenario(args.file)
    timed = args.time is not None or args.sun_azimuth is not None
    sun = sun_direction_at(sc.plant, time_utc=args.time, azimuth_deg=args.sun_azimuth,
                           elevation_deg=args.sun_elevation) if timed else None
    if args.soltrace and sun is None:
        raise HeliotwinError("--soltrace: SolTrace's mirrors face one sun; give --time or "
                             "--sun-azimuth/--sun-elevation")
    with output_set([("FILE", args.file)]) as out:
        layout = out.file(args.solarpilot, "--solarpilot")
        config = out.file(args.config_out or (os.path.splitext(args.solarpilot)[0] + ".toml" if args.solarpilot
                                              else None), "--config-out")
        written = export_plant(sc, solarpilot=(layout, config) if layout else None,
                               soltrace=out.file(args.soltrace, "--soltrace"), sun=sun, aim=args.aim)
    if not args.quiet:
        print(f"export: {written['heliostats']} heliostats -> " + ", ".join(
            str(getattr(args, k)) for k in ("solarpilot", "config_out", "soltrace") if getattr(args, k))
            + (f" (+ {os.path.splitext(args.solarpilot)[0]}.toml)" if args.solarpilot and not args.config_out else "")
            + f"; aim points: {written['aim_points']}" + (" (the plant's stored optimised ones)"
                                                          if written["aim_points"] == "optimised" else ""))
    return 0


def cmd_examples(args) -> int:
    """List the shipped example inputs, or copy them into a folder."""
    from ..examples import EXAMPLES, copy_examples, example_path

    if args.copy:
        if not os.path.isdir(args.copy):
            raise HeliotwinError(f"--copy {args.copy}: not a folder (create it first)")
        for path in copy_examples(args.copy):
            print(path)
        return 0
    for name, what in EXAMPLES.items():
        print(f"{example_path(name)}  # {what}")
    return 0


# ----------------------------------------------------------------------------------------------- trace
def cmd_trace(args) -> int:
    """Trace one real record with the scenario's plant (default: nominal kinematics, ideal surface)."""
    from ..io.images import to_png
    from ..io.scenario import load_records
    from ..plots import plot_flux
    from ..workflows.trace import TraceSettings, describe_plant, trace_record

    with output_set([("--paint", args.paint), ("--scenario", args.scenario)]) as out:
        png = out.file(args.out, "--out")
        json_path = out.file(args.json, "--json")
        plot_path = out.file(args.plot, "--plot")
        ds, sc = load_records(args.paint, args.scenario, [args.heliostat])
        settings = TraceSettings(integrator=args.integrator, rays_per_point=args.rays_per_point,
                                 resolution=args.resolution, samples=args.samples, seed=args.seed, device=args.device)
        flux, report = trace_record(ds, args.record, settings, progress=not args.quiet)
        report.update(describe_plant(sc))
        to_png(flux.bitmap[0], png)
        if plot_path:
            plot_flux(flux, plot_path, measured=report,
                      title=f"{args.heliostat} record {args.record} on {report['target']} ({report['kinematics']} "
                            f"kinematics, {report['surface']} surface)")
        if json_path:
            write_json(json_path, report)
    if args.quiet:
        return 0
    where = ("no light on the target: no centroid" if report["centroid_enu_m"] is None else
             f"centroid ENU {', '.join(f'{v:.3f}' for v in report['centroid_enu_m'])} m")
    print(f"trace {args.heliostat}/{args.record}: {where}; {report['intercepted_power_w'] / 1e3:.2f} "
          f"of {report['total_power_w'] / 1e3:.2f} kW on {report['target']} -> {args.out}")
    return 0


cmd_trace.supports_cuda = True  # the tracing happens here, on args.device


# -------------------------------------------------------------------------------------------- validate
def cmd_validate(args) -> int:
    from ..io.scenario import load_records
    from ..plots import plot_validation
    from ..workflows.validate import ValidateSettings, validate

    t0 = time.perf_counter()
    with output_set([("--paint", args.paint), ("--scenario", args.scenario)]) as out:
        json_path = out.file(args.json, "--json")
        plot_path = out.file(args.plot, "--plot")
        stage(args, f"reading {args.paint}")
        # without metadata/calibration-metadata.csv (the records' times) the folder is not a whole PAINT folder:
        # one line naming it, as report --paint, not a report that cannot say when any record was taken
        ds, sc = load_records(args.paint, args.scenario, csv_list(args.heliostats), require_times=True)
        stage(args, f"tracing {len(ds.records.record_id)} records")
        settings = ValidateSettings(resolution=args.resolution, samples=args.samples, with_images=not args.no_images,
                                    progress=not args.quiet, device=getattr(args, "device", "cpu"))
        report = validate(ds, sc, settings, paint_dir=args.paint)
        report["overall"]["seconds"] = time.perf_counter() - t0  # reading the folder included
        write_json(json_path, report)
        if plot_path and report["heliostats"]:
            plot_validation(report, plot_path)
    if not args.quiet:
        _print_validate_summary(args, report)
    return 0


def _print_validate_summary(args, report: dict) -> None:
    o = report["overall"]
    print(f"validate: {o.get('records', 0)} records, {o.get('heliostats', 0)} heliostats; median pointing error "
          f"{_fmt(o.get('median_pointing_error_mrad'))} mrad (median over heliostats), median distance "
          f"{_fmt(o.get('median_distance_m'), '.3f')} m; {o.get('images', 0)} images, median centred L1 "
          f"{_fmt(o.get('median_centered_l1'), '.3f')} -> {args.json}")
    for name, g in (report.get("by_state") or {}).items():
        if g["heliostats"] and report["by_state"]["calibrated"]["heliostats"]:  # only worth a line when mixed
            print(f"  {name} kinematics: {len(g['heliostats'])} heliostats, median pointing error "
                  f"{_fmt(g['median_pointing_error_mrad'])} mrad, median centred L1 "
                  f"{_fmt(g['median_centered_l1'], '.3f')}")
    cams = report.get("camera_agreement") or {}
    if cams:  # a per-target camera offset is a survey matter, not a heliostat's: worth a line of its own
        print("cameras, HeliOS - UTIS (right, up) [cm], median per target: " + "; ".join(
            f"{name} ({100 * c['right_m']:+.1f}, {100 * c['up_m']:+.1f}) over {c['pairs']} records"
            for name, c in cams.items()))


cmd_validate.supports_cuda = True  # validate_dataset traces on args.device


# ----------------------------------------------------------------------------------------------- bench
def cmd_bench(args) -> int:
    import torch

    from ..workflows.bench import run_benchmark

    rpp = args.rays_per_point
    with output_set() as out:
        json_path = out.file(args.json, "--json")
        result = run_benchmark(surface_points=args.surface_points, rays_per_point=tuple(rpp),
                               resolution=args.resolution, seed=args.seed, device=getattr(args, "device", "cpu"),
                               progress=not args.quiet)
        if json_path:
            write_json(json_path, result)
    mc = result["mc"]
    if args.quiet:
        return 0
    where = "cuda" if result["device"].startswith("cuda") else f"{torch.get_num_threads()} threads"
    print(f"bench ({where}, {args.surface_points} points, {args.resolution}^2, "
          f"{max(rpp)} rays/point): forward {mc['forward_rays_per_s'] / 1e6:.1f} M rays/s, "
          f"forward+backward {mc['forward_backward_rays_per_s'] / 1e6:.1f} M rays/s")
    return 0


cmd_bench.supports_cuda = True  # run_benchmark traces and times on args.device


# -------------------------------------------------------------------------------------------- register
def register(sub) -> None:
    """Add ``demo``, ``scenario``, ``trace``, ``validate`` and ``bench`` to the main parser's subparsers."""
    p = sub.add_parser("demo", help="the whole embedded ~2000-heliostat field, before and after aim points",
                       description="The main job on an embedded Jülich-like field of about 2000 heliostats "
                                   "(generated in code, no data needed): per-heliostat optical efficiency with "
                                   "shading, blocking and attenuation, the loss breakdown, and the receiver flux "
                                   "before and after aim-point optimisation under a peak limit; writes PNGs, "
                                   "heliostats.csv and summary.json. --classic runs the earlier small demo "
                                   "(a few dozen PAINT-style heliostats traced one by one, no shading).")
    p.add_argument("-o", "--output", "--out", dest="out", default="heliotwin-demo",
                   help="output folder, created when missing (default: %(default)s)")
    p.add_argument("--heliostats", type=int_range(1, 10_000, "a heliostat count"), default=None,
                   help="number of heliostats (default: 2000; 48 with --classic)")
    p.add_argument("--time", type=utc_time, default="2023-03-20T11:30:00Z",
                   help="UTC time of the sun position, ISO 8601 (default: %(default)s)")
    p.add_argument("--iterations", type=int_range(1, 10_000, "an iteration count"),
                   help="image-model steps per round of the aim-point optimiser (default: the optimiser's)")
    p.add_argument("--json", help="also write the summary here")
    p.add_argument("--quiet", action="store_true", help="no progress bars and no summary line")
    p.add_argument("--classic", action="store_true",
                   help="the earlier demo: trace a few PAINT-style heliostats one by one (no shading or blocking)")
    g = p.add_argument_group("classic demo (--classic)")
    g.add_argument("--integrator", choices=("mc", "gaussian"), default=None, help="(default: mc)")
    g.add_argument("--rays-per-point", type=_RAYS, default=None, help="(default: 64)")
    g.add_argument("--resolution", type=_RESOLUTION, default=None, help="(default: 256)")
    g.add_argument("--seed", type=seed_int, default=None, help="(default: 0)")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("scenario", help="scenario files", description="Build and inspect scenario files.")
    ssub = p.add_subparsers(dest="scenario_command", metavar="ACTION")
    ssub.required = True
    q = ssub.add_parser("from-paint", help="build a scenario file from a PAINT folder",
                        description="Read a PAINT download (tower, heliostat properties) into a versioned HDF5 "
                                    "scenario.")
    q.add_argument("paint_dir", nargs="?", metavar="PAINT_DIR", help="PAINT folder (or --paint)")
    q.add_argument("--paint", help="PAINT folder")
    q.add_argument("--heliostats", help="comma-separated heliostat ids (default: all)")
    q.add_argument("-o", "--output", required=True, help="scenario file to write (.h5)")
    q.set_defaults(func=cmd_scenario_from_paint)
    field.register_scenario_action(ssub)
    q = ssub.add_parser("show", help="what a scenario file holds: plant, what is learned, provenance",
                        description="Print the plant's size and targets, what has been learned (calibrated "
                                    "kinematics and for which heliostats, learned surfaces, stored aim points), the "
                                    "/learned groups and every provenance step with its date and how it ran.")
    q.add_argument("file", metavar="FILE", help="scenario file (.h5)")
    q.add_argument("--json", help="also write this as JSON here ('-': JSON on stdout instead of the text)")
    q.add_argument("--quiet", action="store_true", help="no text (with --json)")
    q.set_defaults(func=cmd_scenario_show)
    q = ssub.add_parser("export", help="the plant for SolarPILOT (layout + TOML) and SolTrace (input file)",
                        description="Write the scenario's plant as SolarPILOT's per-heliostat layout table (id, "
                                    "x/y/z_location, x/y/z_aimpoint [m]) with the TOML plant description that "
                                    "'heliotwin scenario from-layout' reads back, and/or as a SolTrace input file "
                                    "(.stinput) with every mirror oriented for one sun. The aim points are the "
                                    "plant's stored optimised ones when it has them (--aim equator for equator "
                                    "aiming). Learned "
                                    "kinematics and surfaces stay in the scenario: the formats hold pivots and ideal "
                                    "mirrors.")
    q.add_argument("file", metavar="FILE", help="scenario file (.h5)")
    q.add_argument("--solarpilot", metavar="LAYOUT.csv", help="SolarPILOT layout table to write")
    q.add_argument("--config-out", metavar="PLANT.toml", help="plant description to write (default: next to "
                                                              "--solarpilot, .toml)")
    q.add_argument("--soltrace", metavar="FILE.stinput", help="SolTrace input file to write (needs a sun)")
    q.add_argument("--aim", choices=("auto", "optimised", "equator"), default="auto",
                   help="aim points written: the stored optimised ones (default when the plant has them: 'auto'), "
                        "or equator aiming at the sun (else the receiver centre)")
    q.add_argument("--time", help="UTC time (ISO) of the sun the mirrors face")
    q.add_argument("--sun-azimuth", type=float, help="[deg], PAINT convention (0 = south, +90 = east)")
    q.add_argument("--sun-elevation", type=float, help="[deg] (with --sun-azimuth)")
    q.set_defaults(func=cmd_scenario_export)

    p = sub.add_parser("examples", help="the example layout and plant description shipped with heliotwin",
                       description="List the example inputs shipped in the package (a 300-heliostat layout CSV and "
                                   "its TOML plant description), or copy them into a folder to start from.")
    p.add_argument("--copy", metavar="DIR", help="copy the examples into this (existing) folder")
    p.set_defaults(func=cmd_examples)

    p = sub.add_parser("trace", help="trace one real calibration record",
                       description="Trace a PAINT record (its sun, motor steps and target) with nominal kinematics "
                                   "and the ideal surface, or a scenario's calibrated/learned plant; writes the "
                                   "whole-target flux PNG (PAINT orientation).")
    p.add_argument("--paint", required=True, help="PAINT folder")
    p.add_argument("--scenario", help="trace this scenario's plant (default: the PAINT folder's nominal plant)")
    p.add_argument("--heliostat", required=True)
    p.add_argument("--record", required=True, type=int_range(0, 2**63 - 1, "a record id"))
    p.add_argument("--integrator", choices=("mc", "gaussian"), default="mc")
    p.add_argument("--rays-per-point", type=_RAYS, default=100)
    p.add_argument("--resolution", type=_RESOLUTION, default=256)
    p.add_argument("--samples", type=_SAMPLES, default=50, help="surface samples per facet and direction")
    p.add_argument("--seed", type=seed_int, default=0)
    p.add_argument("-o", "--output", "--out", dest="out", required=True, help="flux PNG to write")
    p.add_argument("--json", help="JSON report")
    p.add_argument("--plot", help="figure (PNG/PDF/SVG): the predicted flux in kW/m² with the measured spots and the "
                                  "predicted centroid marked")
    p.set_defaults(func=cmd_trace)

    p = sub.add_parser("validate", help="predicted vs measured focal spots on real records",
                       description="For every record: pointing error (mrad), spot distance on the target (m) and, with "
                                   "flux-centered images, normalised L1 and cross-correlation; nominal kinematics or a "
                                   "scenario's calibrated/learned plant.")
    p.add_argument("--paint", required=True)
    p.add_argument("--scenario", help="validate this scenario's plant (default: the PAINT folder's nominal plant)")
    p.add_argument("--heliostats", help="comma-separated heliostat ids (default: all)")
    p.add_argument("--json", required=True)
    p.add_argument("--resolution", type=_RESOLUTION, default=128, help="whole-target bitmap for centroids")
    p.add_argument("--samples", type=_SAMPLES, default=16, help="surface samples per facet and direction")
    p.add_argument("--no-images", action="store_true", help="skip the image comparison")
    p.add_argument("--plot", help="PNG with per-heliostat errors")
    p.add_argument("--quiet", action="store_true", help="no progress bars and no summary line")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("bench", help="ray-tracer speed and accuracy",
                       description="Forward and forward+backward rays/s, peak memory and time-to-accuracy of both "
                                   "integrators.")
    p.add_argument("--surface-points", type=int_range(1, 10_000_000, "a point count"), default=10000)
    # argparse applies type= to a string default too, so args.rays_per_point is always a list.
    p.add_argument("--rays-per-point", type=_ray_list, default="10,100", help="comma-separated (default: %(default)s)")
    p.add_argument("--resolution", type=_RESOLUTION, default=256)
    p.add_argument("--seed", type=seed_int, default=0)
    p.add_argument("--json")
    p.set_defaults(func=cmd_bench)
