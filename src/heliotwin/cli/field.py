"""Whole-field commands: ``scenario from-layout``, ``field`` and ``aimpoints``.

``scenario from-layout LAYOUT.csv --config plant.toml -o plant.h5`` turns a SolarPILOT-style layout and a
small TOML plant description into a scenario file (:mod:`heliotwin.field.layout`); ``field`` reports the
optical efficiency of every heliostat (cosine, shading, blocking, attenuation, intercept, reflectance) and the
receiver's power and flux map for one sun, or over a year (:mod:`heliotwin.workflows.field`); ``aimpoints``
optimises aim points under a peak-flux limit for one or several instants and writes them, per instant, into
``/learned/aimpoints`` with their motor steps (:mod:`heliotwin.workflows.aimpoints`); ``field --aim scenario``
traces the stored instant whose sun is nearest the requested one. The commands parse, call the workflow,
write the outputs and print one line.
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import ctypes
import functools
import os
import sys
import time
import types

from ..errors import HeliotwinError
from ..io.report import atomic_path, output_set, plant_inputs, same_file, write_json
from .common import EXIT_NOT_MET, float_range, int_range, peak_limit, positive_int, run_plant_step, seed_int


# ---------------------------------------------------------------------------------- scenario from-layout
def cmd_scenario_from_layout(args) -> int:
    from ..field.layout import plant_from_layout
    from ..io.scenario import provenance_entry, save_scenario

    with output_set([("LAYOUT", args.layout), ("--config", args.config)]) as out:
        output = out.file(args.output, "-o")
        plant, atmosphere = plant_from_layout(args.layout, args.config)
        meta = {"source": os.path.abspath(args.layout), "config": os.path.abspath(args.config),
                "created_by_command": "heliotwin scenario from-layout"}
        step = provenance_entry("from-layout", layout=os.path.abspath(args.layout),
                                config=os.path.abspath(args.config))
        save_scenario(plant, output, extras=atmosphere.to_extras(), metadata=meta, provenance=[step])
    rec = plant.targets["receiver"]
    if not args.quiet:
        print(f"scenario: {len(plant.field.ids)} heliostats, {rec.kind} receiver, sun {plant.sun.sunshape} -> "
              f"{args.output}")
    return 0


# ---------------------------------------------------------------------------------------------- field
def _resolution(text: str) -> tuple[int, int]:
    """argparse type: ``COLSxROWS`` (e.g. ``48x20``: 48 cells around, 20 up) -> (rows, cols)."""
    try:
        cols, rows = (int(t) for t in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected COLSxROWS such as 48x20, got {text!r}") from None
    if cols <= 0 or rows <= 0:
        raise argparse.ArgumentTypeError(f"expected positive COLSxROWS, got {text!r}")
    return rows, cols


# Ranges of the numeric arguments: a sun, an irradiance or a limit outside them is a typo or a unit mistake.
_AZIMUTH = float_range(-360.0, 360.0, what="an azimuth [deg]")
_ELEVATION = float_range(-90.0, 90.0, what="an elevation [deg]")
_AZIMUTH_STEP = float_range(0.0, 180.0, lo_open=True, what="an azimuth step [deg]")
_DNI = float_range(0.0, 1500.0, what="a direct normal irradiance [W/m2]")  # the solar constant is 1361 W/m2
_PEAK_LIMIT = peak_limit
_YEAR = int_range(1900, 2100, "a year")
_NPROC = int_range(1, 256, "a process count")


def _sun(args, plant):
    """The one sun of ``--time`` or ``--sun-azimuth/--sun-elevation``."""
    if args.time is None:  # PAINT angles: no ephemeris, so pvlib and pandas stay unimported
        from ..workflows.field_one_sun import sun_from_angles

        return sun_from_angles(args.sun_azimuth, args.sun_elevation)
    from ..workflows.field import sun_direction_at

    return sun_direction_at(plant, time_utc=args.time)


def _field_line(report, heliostats: int) -> str:
    e, r = report["field"]["efficiency"], report["receiver"]
    return (f"field: {heliostats} heliostats; efficiency {e['total']:.4f} (cosine {e['cosine']:.4f}, shading "
            f"{e['shading']:.4f}, blocking {e['blocking']:.4f}, attenuation {e['attenuation']:.4f}, intercept "
            f"{e['intercept']:.4f}); receiver {r['power_w'] / 1e6:.3f} MW, peak {r['peak_flux_w_m2'] / 1e3:.1f} "
            f"kW/m2; {report['seconds']:.2f} s")


def _year_line(args, report) -> str:
    if report.get("annual", True):
        energy = (f"annual optical energy {report['annual_optical_energy_mwh']:.1f} MWh of "
                  f"{report['annual_dni_energy_on_mirrors_mwh']:.1f} MWh DNI on the mirrors")
    else:  # a weather file that does not cover the year: the energy of the hours it covers, not annual
        c = report["coverage"]
        energy = (f"optical energy {report['optical_energy_mwh']:.1f} MWh of {report['dni_energy_on_mirrors_mwh']:.1f}"
                  f" MWh DNI on the mirrors over the {c['hours']:.0f} h the weather covers "
                  f"({100 * c['fraction_of_year']:.1f} % of {args.year}; NOT annual)")
    return (f"field {args.year}: {report['instants']} daylight instants every {args.every}; {energy} "
            f"({report['dni_model']}; efficiency {report['mean_efficiency']:.4f}); {report['seconds']:.1f} s")


def _write_field_outputs(args, sc, report, result, paths: dict) -> None:
    """The one-sun outputs into their staged paths: JSON, per-heliostat CSV, the flux figure (axes in metres
    and degrees, kW/m^2) and the numeric map (CSV)."""
    from ..io.export import write_flux_map_csv
    from ..raytrace.field import per_heliostat_rows

    write_json(paths["--json"], report)
    if result is None:  # --year: the report alone
        return
    if paths["--per-heliostat"]:
        _write_csv(paths["--per-heliostat"], per_heliostat_rows(result, sc.plant))
    if paths["--flux"]:
        from ..optimise.aimstate import stored_peak_limit
        from ..plots import plot_receiver_flux  # matplotlib (~0.4 s): only for a figure asked for

        r = report["receiver"]
        limit = stored_peak_limit(sc)  # the stored limit, if any
        plot_receiver_flux({f"{args.aim} aiming": result.flux.cpu()}, sc.plant.targets["receiver"],
                           paths["--flux"], powers_w={f"{args.aim} aiming": r["power_w"]},
                           limit_w_m2=limit,
                           instant={"time_utc": args.time, "sun_enu": report["sun"]["direction_enu"]},
                           title=f"receiver flux: {len(sc.plant.field.ids)} heliostats, DNI "
                                 f"{args.dni or sc.plant.sun.dni:.0f} W/m²")
    if paths["--flux-csv"]:
        write_flux_map_csv(paths["--flux-csv"], result.flux.cpu(), result.extent.cpu().tolist())


def cmd_field(args) -> int:
    _keep_freed_memory()
    from ..io.scenario import load_scenario
    from ..progress import Stages
    from ..workflows.field_one_sun import FieldRunSettings, field

    t0 = time.perf_counter()
    bar = Stages(2, "heliotwin field", enabled=not args.quiet)
    settings = FieldRunSettings(resolution=args.resolution, integrator=args.integrator, occlusion=args.occlusion,
                                seed=args.seed, aim=args.aim, dni=args.dni, nproc=args.nproc,
                                device=getattr(args, "device", None))  # checked here, before any output is staged
    with output_set([("--scenario", args.scenario), ("--weather", getattr(args, "weather", None))]) as out:
        paths = {flag: out.file(path, flag) for flag, path in (("--json", args.json), ("--per-heliostat",
                 args.per_heliostat), ("--flux", args.flux), ("--flux-csv", getattr(args, "flux_csv", None)))}
        if args.year is not None and (paths["--per-heliostat"] or paths["--flux"] or paths["--flux-csv"]):
            raise HeliotwinError("field --year writes the --json report only (no --per-heliostat, --flux, --flux-csv)")
        sc, result = load_scenario(args.scenario), None
        bar.start("efficiency table over the year" if args.year is not None else "field model")
        if args.year is not None:
            from ..io.weather import read_dni_series  # pandas and pvlib: only for a year
            from ..workflows.field_year import field_year

            weather = read_dni_series(args.weather) if getattr(args, "weather", None) else None
            report = field_year(sc, args.year, args.every, azimuth_step_deg=args.table_azimuth_step, weather=weather)
        else:
            report, result = field(sc, _sun(args, sc.plant), settings)
        bar.step("field model")
        report["seconds"] = time.perf_counter() - t0
        line = _year_line(args, report) if args.year is not None else _field_line(report, len(sc.plant.field.ids))
        _write_field_outputs(args, sc, report, result, paths)
        bar.step("outputs")
    for warning in report.get("warnings", []):  # e.g. the weather file's site far from the plant's (also in JSON)
        print(f"heliotwin: warning: {warning}", file=sys.stderr)
    if not args.quiet:
        print(line)
    return 0


def _write_csv(path, rows: list[dict]) -> None:
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


# ------------------------------------------------------------------------------------------- aimpoints
def _print_instant(limit, count: int = 1):
    """Per instant one line; ``limit`` the peak limit [W/m2], or None for an allowable-flux map (the line then gives
    the largest flux / limit and the binding cells)."""
    def show(i, label, rep, best, equator) -> None:
        o = rep["optimised"]
        where = f" {i + 1}/{count}" if count > 1 else ""
        start = (f", warm start: {o['iterations']} steps, exact checks: {o['exact_checks']}" if o.get("warm_start")
                 else "")
        eq = rep["equator"]
        eq_peak = "" if eq.get("estimated") else f", equator {eq['peak_flux_w_m2'] / 1e3:.1f}"
        held = (f"limit {limit / 1e3:.1f}" if limit is not None else
                f"flux/limit {o['max_utilisation']:.4f}, {o['binding_cells']} binding cells")
        print(f"aimpoints{where} {label}: peak {o['peak_flux_w_m2'] / 1e3:.1f} kW/m2 ({held}"
              f"{eq_peak}), power {o['power_vs_equator']:.4f} of equator"
              + (" (estimated)" if eq.get("estimated") else "")
              + "".join(f", {n} {rep[n]['power_vs_equator']:.4f} (peak {rep[n]['peak_flux_w_m2'] / 1e3:.1f})"
                        for n in ("aiming_factor", "image_size_priority") if n in rep)
              + ("" if o.get("note", "").endswith("full power") else f"; {o.get('note')}")
              + (f"; P(peak > limit) {rep['robust']['robust']['exceedance_probability']:.3f} (deterministic "
                 f"{rep['robust']['deterministic']['exceedance_probability']:.3f}, {rep['robust']['draws']} draws), "
                 f"power cost {rep['robust']['power_cost']:.4f}" if "robust" in rep else "")
              + f"; {rep['seconds']:.1f} s{start}", flush=True)
    return show


def _write_aim_maps(folder, i: int, label: str, receiver, equator, optimised, limit) -> None:
    """Per instant: equator vs optimised side by side on one colour scale with the limit contour
    (``iNNN_before_after.png``; no contour for an allowable-flux map), each alone on that same scale
    (``iNNN_equator.png``, ``iNNN_optimised.png``), both numeric maps (``iNNN_equator.csv``, ``iNNN_optimised.csv``
    [W/m2]) and flux / limit of both with the binding cells marked (``iNNN_utilisation.png``). ``limit`` is the
    instant's :class:`~heliotwin.optimise.problem.FluxLimit`."""
    from ..io.export import write_flux_map_csv
    from ..optimise.fluxplots import plot_utilisation
    from ..plots import plot_receiver_flux, receiver_extent
    from ..timefmt import utc_or_label

    maps = {"equator aiming": equator.flux.cpu(), "optimised aim points": optimised.flux.cpu()}
    powers = {"equator aiming": equator.power_w, "optimised aim points": optimised.power_w}
    scale = max(float(m.max()) for m in maps.values())
    stem = os.path.join(folder, f"i{i:03d}")
    plot_utilisation(maps, receiver, limit, f"{stem}_utilisation.png", title=f"aim points at {label}: flux / limit")
    what = (f"peak limit {limit.minimum / 1e3:.0f} kW/m²" if limit.is_uniform else
            f"allowable flux {limit.minimum / 1e3:.0f}..{float(limit.cells.max()) / 1e3:.0f} kW/m² ({limit.source})")
    limit = limit.minimum if limit.is_uniform else None  # a contour of one limit only
    plot_receiver_flux(maps, receiver, f"{stem}_before_after.png", limit_w_m2=limit, powers_w=powers,
                       title=f"aim points at {utc_or_label(label)}: {what}")
    for (name, flux), short in zip(maps.items(), ("equator", "optimised")):
        # alone, but on the pair's scale: the two files compare by eye too
        plot_receiver_flux({name: flux}, receiver, f"{stem}_{short}.png", limit_w_m2=limit, powers_w=powers,
                           vmax_w_m2=scale, title=utc_or_label(label))
        write_flux_map_csv(f"{stem}_{short}.csv", flux, receiver_extent(receiver))


def _keep_freed_memory() -> None:
    """Let glibc's allocator keep freed memory for reuse in this process (no-op elsewhere).

    The field model allocates and frees the same large tensors again and again (mirror samples, footprints,
    occlusion pairs; the aim-point rounds in every exact check). By default glibc returns blocks above its mmap
    threshold to the kernel at once and trims the heap top, so each round faults them back in page by page
    (one 2,000-heliostat ``field`` evaluation: ~0.3 s of system time): measured at 10,000
    heliostats, 15 of a 33 s command were system time; with the thresholds at 1 GiB, 3 s (the process keeps
    ~20 % more resident memory). A process-wide setting, so the command's edge makes it, not the library. The
    same thresholds go into the environment (glibc's ``MALLOC_*_`` variables, read at a process's start) for the
    worker processes a command spawns (``year``'s tables: without them its two workers ran 1.6x slower than one
    process).
    """
    for name, value in (("MALLOC_MMAP_THRESHOLD_", 1 << 30), ("MALLOC_TRIM_THRESHOLD_", 1 << 30),
                        ("MALLOC_TOP_PAD_", 64 << 20)):
        os.environ.setdefault(name, str(value))
    with contextlib.suppress(OSError, AttributeError, TypeError):
        libc = ctypes.CDLL(None)
        for option, value in ((-3, 1 << 30), (-1, 1 << 30), (-2, 64 << 20)):  # M_MMAP_THRESHOLD, TRIM, TOP_PAD
            libc.mallopt(ctypes.c_int(option), ctypes.c_int(value))


def cmd_aimpoints(args) -> int:
    """Optimise aim points for one or several instants under a peak-flux limit; baselines in the same report."""
    _keep_freed_memory()
    from ..workflows.aimpoints import AimpointSettings

    settings = AimpointSettings(peak_limit_w_m2=args.peak_limit, resolution=args.resolution,
                                iterations=args.iterations, target=args.target, field_gradient=args.field_gradient,
                                baselines=not args.no_baselines, nproc=args.nproc,
                                device=getattr(args, "device", None), confidence=args.confidence,
                                draws=args.draws, mc=args.mc, seed=args.seed, warm_start=not args.cold,
                                exact_equator=bool(args.flux), flux_limit=args.flux_limit)
    settings.check()  # before any output is staged
    target_file = args.target if args.target and os.path.exists(args.target) else None  # a map file, or 'uniform'
    in_place = same_file(args.output, args.scenario)
    if in_place and not args.in_place:
        raise HeliotwinError(f"-o {args.output} is the input scenario; add --in-place to replace it")
    inputs = plant_inputs(args.scenario, args.output, ("--target", target_file), ("--flux-limit", args.flux_limit),
                          flag="--scenario")
    with output_set(inputs) as out:
        # in place: the plant is replaced by its own locked, atomic writer (locked_plant_write), not staged
        out_h5 = out.plant(args.output, "-o") if in_place else out.file(args.output, "-o")
        out_json = out.file(args.json, "--json")
        out_png = out.folder(args.flux, "--flux") if args.flux else None
        run, seen = _aimpoints_run(args, settings, out_png)
        report = run_plant_step(run, out_h5, in_place).report
        write_json(out_json, report)
    if seen["show"] and len(seen["instants"]) > 1:
        _print_summary(report["summary"])
    return _limit_verdict(report)


def _aimpoints_run(args, settings, out_png):
    """``aimpoints``' read-optimise step as a function of nothing (what :func:`locked_plant_write` calls under the
    lock when the plant is replaced in place) and the dict it fills (``sc``, ``instants``, ``show``)."""
    from ..io.scenario import load_scenario
    from ..workflows.aimpoints import aimpoints, limit_of
    from ..workflows.field import sun_instants

    seen = {"sc": None, "instants": [], "show": None}
    limit = limit_of(settings)  # a map file read (and refused) before the plant is
    peak = None if args.flux_limit else float(args.peak_limit)

    def on_instant(i, label, rep, best, equator) -> None:
        if out_png:
            _write_aim_maps(out_png, i, label, seen["sc"].plant.targets["receiver"], equator, best, limit)
        if seen["show"]:
            seen["show"](i, label, rep, best, equator)

    def run():
        sc = seen["sc"] = load_scenario(args.scenario)
        instants = seen["instants"] = sun_instants(sc.plant, times=args.time, day=args.day, every=args.every,
                                                   azimuth_deg=args.sun_azimuth, elevation_deg=args.sun_elevation)
        show = seen["show"] = None if args.quiet else _print_instant(peak, len(instants))
        if show:  # a line before the long part; one more per instant as each finishes
            what = (f"limit {peak / 1e3:.1f} kW/m2" if peak is not None else
                    f"allowable flux {limit.minimum / 1e3:.1f}..{float(limit.cells.max()) / 1e3:.1f} kW/m2 "
                    f"({limit.source})")
            print(f"aimpoints: {len(sc.plant.field.ids)} heliostats, {len(instants)} instant(s), {what} ...",
                  flush=True)
        aimed, report = aimpoints(sc, instants, settings, on_instant=on_instant)
        return types.SimpleNamespace(scenario=aimed, report=report)

    return run, seen


def _print_summary(d: dict) -> None:
    """The line after several instants: worst peak, the day's energy (``--day``), work and time."""
    energy = (f", energy {d['energy_kwh']:.4g} kWh ({d['energy_vs_equator']:.4f} of equator aiming's)"
              if "energy_kwh" in d else "")
    print(f"aimpoints: {d['instants']} instants, worst peak {d['worst_peak_vs_limit']:.4f} of the limit{energy}; "
          f"{d['exact_checks']} exact checks, {d['adam_steps']} steps, {d['seconds']:.1f} s "
          f"({d['seconds_per_instant']['mean']:.1f} s per instant)", flush=True)


def _limit_verdict(report: dict) -> int:
    """Exit status 3 with one line on stderr when the optimised aim points exceed the limit at some instant."""
    unmet = [(e["instant"], e["optimised"]["peak_flux_w_m2"], e["optimised"]["peak_vs_limit"])
             for e in report["instants"] if not e["optimised"]["limit_met"]]
    if not unmet:
        return 0
    label, peak, ratio = max(unmet, key=lambda u: u[2])
    fl = report.get("flux_limit")
    what = (f"the peak-flux limit {report['peak_limit_w_m2'] / 1e3:.1f} kW/m2" if fl is None else
            f"the allowable-flux map ({fl['source']})")
    worst = f"{peak / 1e3:.1f} kW/m2" if fl is None else f"flux/limit {ratio:.4f}"
    print(f"heliotwin: aimpoints: {what} is not met at {len(unmet)} of {len(report['instants'])} instants (worst: "
          f"{worst} at {label}); the outputs hold the best aim points found (exit status {EXIT_NOT_MET})",
          file=sys.stderr)
    return EXIT_NOT_MET


cmd_field.supports_cuda = True  # the field model runs on args.device
cmd_aimpoints.supports_cuda = True


# -------------------------------------------------------------------------------------------- register
def register_scenario_action(ssub) -> None:
    """Add ``from-layout`` to the ``scenario`` command's ACTION subparsers (called by :mod:`.plant`)."""
    q = ssub.add_parser(
        "from-layout", help="build a scenario file from a layout CSV and a TOML plant description",
        description="Read a heliostat layout (x,y,z = east,north,up [m] about the tower base, '#' comments, optional "
                    "id column; as SolarPILOT writes it) and a TOML plant description (site, heliostat, receiver, "
                    "sun, atmosphere; see heliotwin.field.layout) into a versioned HDF5 scenario.")
    q.add_argument("layout", help="layout CSV")
    q.add_argument("--config", required=True, help="TOML plant description")
    q.add_argument("-o", "--output", required=True, help="scenario file to write (.h5)")
    q.set_defaults(func=cmd_scenario_from_layout)


def register(sub) -> None:
    """Add ``field`` and ``aimpoints`` to the main parser's subparsers (``scenario from-layout`` is added by
    :mod:`.plant` with the other scenario actions, through :func:`register_scenario_action`)."""
    p = sub.add_parser("field", help="optical efficiency of every heliostat and the receiver flux, one sun",
                       description="Per heliostat: cosine, shading (by other heliostats), blocking, atmospheric "
                                   "attenuation, intercept, reflectance and their product; the field averages "
                                   "(unweighted, as SolarPILOT reports them, and power-weighted); receiver power and "
                                   "flux map [W/m2].")
    p.add_argument("--scenario", required=True, help="scenario file (from-layout, from-paint, or a learned plant)")
    when = p.add_mutually_exclusive_group(required=True)
    when.add_argument("--sun-azimuth", type=_AZIMUTH, help="[deg], PAINT convention: 0 = south, +90 = east "
                                                        "(SolarPILOT azimuth = 180 - this)")
    when.add_argument("--time", help="UTC time (ISO), sun position from pvlib at the scenario's site")
    when.add_argument("--year", type=_YEAR, help="efficiency table over sun positions and the annual optical energy "
                                               "under pvlib's clear-sky DNI (equator aiming)")
    p.add_argument("--sun-elevation", type=_ELEVATION, help="[deg] (with --sun-azimuth)")
    p.add_argument("--every", default="1h", help="with --year: time step, 1min..366d, not a whole "
                   "number of days (every instant would fall at the same time of day; default: %(default)s)")
    p.add_argument("--table-azimuth-step", type=_AZIMUTH_STEP, default=15.0,
                   help="with --year: azimuth step [deg] of the efficiency table (default: %(default)s)")
    p.add_argument("--dni", type=_DNI, help="direct normal irradiance [W/m2], 0..1500 (default: the scenario's)")
    p.add_argument("--weather", metavar="CSV", help="with --year: measured or typical-year DNI instead of clear sky "
                                                    "(SAM/TMY weather file, PAINT's calibration-weather.csv, or any "
                                                    "CSV with a time and a dni [W/m2] column)")
    p.add_argument("--aim", choices=("equator", "scenario"), default="equator",
                   help="equator: each heliostat aims at the receiver point facing it at mid-height (SolarPILOT "
                        "'simple'); scenario: the scenario's /learned/aimpoints")
    p.add_argument("--integrator", choices=("gaussian", "conv", "mc"), default="gaussian",
                   help="receiver map: Gaussian-equivalent footprints, the exact sunshape per footprint class "
                        "(conv), or Monte Carlo (default: %(default)s)")
    p.add_argument("--resolution", type=_resolution, default=(20, 48), help="COLSxROWS of the receiver map "
                                                                            "(default: 48x20)")
    p.add_argument("--occlusion", choices=("exact", "solarpilot"), default="exact",
                   help="exact: shading and blocking ray-tested on the mirrors (default); solarpilot: SolarPILOT's "
                        "analytic per-pair estimate, to compare with its reports (docs/physics.md)")
    p.add_argument("--seed", type=seed_int, default=0, help="Monte-Carlo seed")
    p.add_argument("--nproc", type=_NPROC, default=1, help="shard the heliostats over N local processes, at "
                   "most one per heliostat "
                                                         "(torch.distributed, gloo)")
    p.add_argument("--json", required=True, help="JSON report")
    p.add_argument("--per-heliostat", help="CSV, one row per heliostat")
    p.add_argument("--flux", help="receiver flux figure (PNG/PDF/SVG): axes in metres along the unrolled receiver "
                                  "and degrees around it, colour bar in kW/m2, the peak marked")
    p.add_argument("--flux-csv", help="the numeric receiver map [W/m2] as a CSV matrix (first row: arc of each "
                                      "column's cell centre [m]; first column: height of each row [m], top first)")
    p.set_defaults(func=_checked(cmd_field))

    p = sub.add_parser("aimpoints", help="aim points under a peak-flux limit, one or several instants",
                       description="Per heliostat an aim point on the receiver (2 degrees of freedom) that maximises "
                                   "intercepted power (or matches --target) with every map cell at or below the "
                                   "limit: an augmented Lagrangian on an image model corrected, round by round, by "
                                   "the exact field model (hard shading and blocking), until the exact check passes. "
                                   "Baselines in the same report: equator aiming, the aiming-factor heuristic "
                                   "(Sanchez-Gonzalez et al. 2017), SolarPILOT-style image-size priority. Writes the "
                                   "scenario with /learned/aimpoints (use with field --aim scenario).")
    p.add_argument("--scenario", required=True)
    when = p.add_mutually_exclusive_group(required=True)
    when.add_argument("--sun-azimuth", type=_AZIMUTH, help="[deg], PAINT convention (0 = south, +90 = east)")
    when.add_argument("--time", help="UTC time(s), ISO, comma-separated for several instants")
    when.add_argument("--day", help="UTC date: every --every over the day with the sun above 10 deg (each instant "
                      "warm-started from the previous one's aim points unless --cold; the report's summary has the "
                      "day's energy)")
    p.add_argument("--every", default="1h", help="with --day: time step, 1min..1d (default: "
                                                                   "%(default)s)")
    p.add_argument("--sun-elevation", type=_ELEVATION, help="[deg] (with --sun-azimuth)")
    p.add_argument("--peak-limit", type=_PEAK_LIMIT, help="[W/m2] on every map cell; exit status 3 "
                   "when the aim points found cannot hold it at some instant (outputs still written)")
    p.add_argument("--flux-limit", metavar="FILE", help="allowable flux per receiver cell: a CSV in NREL HALOS' "
                   "allowable_flux.csv layout (no header; rows top to bottom, columns around/across the receiver; "
                   "W/m2, or a '# unit: kW/m2' line), resampled onto the map taking each cell's lowest limit; or a "
                   "TOML with [receiver.flux_limit] (panels_w_m2, flow_path, derating, top_bottom_w_m2). With "
                   "--peak-limit too, every cell's lower limit. Stored with the aim points (daily keeps it)")
    p.add_argument("--target", help="'uniform' (flat over the height) or a CSV/NPY map on the receiver grid (rows x "
                                    "cols, row 0 = top; only its shape counts): match it under the limit")
    p.add_argument("--resolution", type=_resolution, default=(20, 48), help="COLSxROWS (default: 48x20)")
    p.add_argument("--iterations", type=positive_int, default=300, help="image-model steps per round")
    p.add_argument("--nproc", type=_NPROC, default=1, help="shard the heliostats over N local processes, at "
                   "most one per heliostat "
                                                                 "(torch.distributed, gloo)")
    p.add_argument("--field-gradient", action="store_true", help="add the smooth field model's power gradient "
                   "(shading, blocking, cosine) to the image model each round (one backward pass per round)")
    p.add_argument("--no-baselines", action="store_true", help="skip the aiming-factor and image-size baselines")
    p.add_argument("--cold", action="store_true", help="several instants: start every one from equator aiming "
                   "(default: from the previous instant's optimised aim points; without baselines, --flux, a "
                   "uniform target or --confidence, a warm instant's equator power is the image model's estimate)")
    p.add_argument("--confidence", type=float, help="hold the limit with this probability (e.g. 0.95) under the "
                   "plant's stored pointing posterior (calibrate --method lm); the report gives the probability of "
                   "exceeding the limit for these and for the deterministic aim points, and the power it costs")
    p.add_argument("--draws", type=int_range(20, 100_000, "a draw count"), default=200,
                   help="with --confidence: Monte-Carlo draws of the pointing errors, 20..100000 (default: "
                        "%(default)s)")
    p.add_argument("--mc", choices=("model", "exact"), default="model", help="with --confidence: each draw's map from "
                   "the image model corrected to the exact map (fast) or from the exact model (one field evaluation "
                   "per draw; default: %(default)s)")
    p.add_argument("--seed", type=seed_int, default=0, help="with --confidence: seed of the draws")
    p.add_argument("-o", "--output", required=True, help="scenario file to write (.h5)")
    p.add_argument("--in-place", action="store_true", help="allow -o to be --scenario (replaced atomically under "
                   "the plant's lock, as 'update --in-place')")
    p.add_argument("--json", required=True, help="JSON report")
    p.add_argument("--flux", help="folder for the receiver flux maps per instant: equator vs optimised side by side on "
                                  "one scale with the limit contour (iNNN_before_after.png), each alone on that "
                                  "scale (iNNN_equator.png, iNNN_optimised.png) and the numeric maps [W/m2] "
                                  "(iNNN_equator.csv, iNNN_optimised.csv)")
    p.set_defaults(func=_checked(cmd_aimpoints))


def _checked(command):
    @functools.wraps(command)  # keeps the command's attributes (supports_cuda) for run_command's --device
    def run(args) -> int:
        if getattr(args, "sun_azimuth", None) is not None and args.sun_elevation is None:
            raise HeliotwinError("--sun-azimuth needs --sun-elevation")
        return command(args)
    return run
