"""``heliotwin year``: the plant's year heliostat by heliostat (:mod:`heliotwin.workflows.year`).

``heliotwin year --scenario plant.h5 [--weather FILE] [--year Y] [--aim equator|scenario|optimised] -o year.h5
--csv heliostats.csv --json year.json``: per heliostat its annual energy on the receiver, DNI-weighted efficiency
and factors, the energy lost to its own tracking error and to its own mirror (with intervals); the field's annual
and monthly energy. ``-o`` writes a copy of the plant with the year stored (``/learned/year``); never over the
input unless ``--in-place`` (then atomically under the plant's lock, as ``update --in-place``).
"""
from __future__ import annotations

import csv
import math
import sys

from ..errors import HeliotwinError
from ..io.report import atomic_path, output_set, plant_inputs, same_file, write_json
from .common import float_range, int_range, peak_limit, run_plant_step, seed_int

_AZIMUTH_STEP = float_range(1.0, 90.0, what="an azimuth step [deg]")


def register(subparsers) -> None:
    """Add ``year`` to the main parser's subparsers."""
    p = subparsers.add_parser(
        "year", help="the plant's year heliostat by heliostat: energy, factors, tracking and mirror losses",
        description="For every heliostat: annual energy on the receiver [MWh], DNI-weighted efficiency and "
                    "factors (cosine, shading, blocking, attenuation, intercept, reflectance), the energy lost to "
                    "its own tracking error (a perfectly calibrated heliostat against one that moves as the "
                    "calibration's posterior says while the controller aims with the learned kinematics: the "
                    "expected loss and its 5-95 % interval) and to its own mirror (learned surface against ideal "
                    "facets). Per-heliostat tables over sun positions, interpolated bilinearly over the weather's "
                    "daylight hours with each hour's exact cosine.")
    p.add_argument("--scenario", required=True, help="plant file (.h5)")
    p.add_argument("--weather", metavar="FILE", help="DNI time series (SAM/TMY weather file, PAINT's "
                   "calibration-weather.csv, or a CSV with time and dni columns); default: pvlib clear sky at the "
                   "plant's site")
    p.add_argument("--year", type=int_range(1900, 2100, "a year"), default=None,
                   help="calendar year (default: the weather file's, 2023 under clear sky)")
    p.add_argument("--every", default="1h", help="clear sky only: time step, 1min..12h (default: %(default)s)")
    p.add_argument("--aim", choices=("equator", "scenario", "optimised"), default="equator",
                   help="equator: the receiver point facing each heliostat at mid-height (default); scenario: the "
                        "plant's stored aim points; optimised: optimised under the plant's peak-flux limit at each "
                        "table node (warm-started node to node)")
    p.add_argument("--peak-limit", type=peak_limit, default=None,
                   help="with --aim optimised: the limit [W/m2] (default: the plant's stored one)")
    p.add_argument("--draws", type=int_range(0, 1000, "a draw count"), default=16,
                   help="posterior draws of the tracking loss's 5-95 %% interval (default: %(default)s)")
    p.add_argument("--seed", type=seed_int, default=0, help="seed of the draws and the checked hours")
    p.add_argument("--check-hours", type=int_range(0, 100_000, "an hour count"), default=0,
                   help="also evaluate the field model directly at N drawn daylight hours and report the "
                        "interpolation's per-heliostat error (median, p95) and the field total's")
    p.add_argument("--table-azimuth-step", type=_AZIMUTH_STEP, default=None,
                   help="azimuth step [deg] of the tables (default: the grid chosen on generated fields, 30)")
    p.add_argument("--nproc", type=int_range(1, 256, "a process count"), default=None,
                   help="worker processes the tables' sun positions are dealt over (default: the cores this "
                        "command may use, when the plant is large enough to pay for starting them)")
    p.add_argument("-o", "--output", help="plant file to write with the year stored (/learned/year)")
    p.add_argument("--in-place", action="store_true", help="allow -o to be --scenario (replaced atomically under "
                   "the plant's lock)")
    p.add_argument("--csv", help="one row per heliostat: id, energy_mwh, efficiency, factors, tracking_loss_mwh, "
                                 "surface_loss_mwh and the interval columns")
    p.add_argument("--json", help="the report: annual and monthly energy, DNI on the mirrors, DNI share below the "
                                  "horizon, site, time convention, interpolation check")
    p.set_defaults(func=cmd_year)


def _write_csv(path, rows: list[dict]) -> None:
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        for r in rows:
            writer.writerow({k: ("nan" if isinstance(v, float) and math.isnan(v) else v) for k, v in r.items()})


def cmd_year(args) -> int:
    from .field import _keep_freed_memory

    _keep_freed_memory()  # the tables re-allocate the field model's large tensors at every node
    if not (args.output or args.csv or args.json):
        raise HeliotwinError("year: nothing to write; give -o, --csv and/or --json")
    settings = _settings(args)
    settings.check()  # before any output is staged
    in_place = bool(args.output) and same_file(args.output, args.scenario)
    if in_place and not args.in_place:
        raise HeliotwinError(f"-o {args.output} is the input scenario; add --in-place to replace it")
    inputs = plant_inputs(args.scenario, args.output, ("--weather", args.weather), flag="--scenario") \
        if args.output else [("--scenario", args.scenario), ("--weather", args.weather)]
    with output_set(inputs) as out:
        out_h5 = None
        if args.output:
            out_h5 = out.plant(args.output, "-o") if in_place else out.file(args.output, "-o")
        out_csv, out_json = out.file(args.csv, "--csv"), out.file(args.json, "--json")

        res = run_plant_step(lambda: _year_run(args, settings), out_h5, in_place).result
        report = res.report
        report["output"] = args.output
        if out_csv:
            _write_csv(out_csv, res.rows)
        if out_json:
            write_json(out_json, report)
    for warning in report.get("warnings", []):  # the weather file's site or times (also in the JSON)
        print(f"heliotwin: warning: {warning}", file=sys.stderr)
    if not args.quiet:
        _print_year(report)
    return 0


def _settings(args):
    """The command's :class:`~heliotwin.workflows.year.YearSettings`."""
    import dataclasses

    from ..raytrace.annual import DEFAULT_GRID
    from ..workflows.year import YearSettings

    grid = DEFAULT_GRID if args.table_azimuth_step is None else \
        dataclasses.replace(DEFAULT_GRID, azimuth_step_deg=float(args.table_azimuth_step))
    return YearSettings(year=args.year, aim=args.aim, every=args.every, grid=grid, draws=args.draws,
                        seed=args.seed, check_hours=args.check_hours, peak_limit_w_m2=args.peak_limit, nproc=args.nproc,
                        device=getattr(args, "device", None), progress=not args.quiet)


def _year_run(args, settings):
    """The read-compute step (what :func:`~heliotwin.cli.common.run_plant_step` runs, under the plant's lock when it
    is replaced in place): the year's result with its plant as ``.scenario``."""
    import types

    from ..io.scenario import load_scenario
    from ..io.weather import read_dni_series
    from ..workflows.year import plant_year

    sc = load_scenario(args.scenario)
    weather = read_dni_series(args.weather) if args.weather else None
    res = plant_year(sc, weather, settings)
    return types.SimpleNamespace(scenario=res.scenario, result=res)


def _print_year(r: dict) -> None:
    """The year's one-line headline."""
    track = (f"tracking loss {r['tracking_loss_mwh']:.1f} MWh"
             + (f" ({r['tracking_loss_unknown_heliostats']} heliostat(s) unknown: nominal only)"
                if r["tracking_loss_unknown_heliostats"] else ""))
    check = r.get("interpolation")
    checked = (f"; interpolation vs direct on {check['checked_hours']} h: per heliostat median "
               f"{100 * check['median_error']:.2f} %, p95 {100 * check['p95_error']:.2f} %, field "
               f"{100 * check['field_error']:.3f} %" if check else "")
    print(f"year {r['year']}: {r['heliostats']} heliostats, {r['aim']} aiming, {r['weather']['kind']}; "
          f"{'annual' if r['annual'] else 'NOT annual (partial coverage):'} energy {r['annual_energy_mwh']:.1f} "
          f"MWh of {r['annual_dni_energy_on_mirrors_mwh']:.1f} MWh DNI on the mirrors (efficiency "
          f"{r['field_efficiency']:.4f}); {track}, mirror loss {r['surface_loss_mwh']:.2f} MWh; DNI below the "
          f"horizon {100 * r['dni_share_below_horizon']:.2f} %; {r['table']['nodes']} table nodes{checked}; "
          f"{r['seconds']:.1f} s")


cmd_year.supports_cuda = True
