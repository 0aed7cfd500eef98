"""``heliotwin report``: the plant at a glance, one self-contained HTML page (:mod:`heliotwin.workflows.report`).

:func:`register` adds the command; the library is imported inside the command function so that ``--help`` stays
torch-free.
"""
from __future__ import annotations

from ..io.report import output_set
from .common import int_range, stage, utc_time

#: The field map's colour choices (the keys of heliotwin.workflows.report.QUANTITIES; listed here so that
#: building the parser imports no torch; a test checks that the two agree).
COLOURS = ("predicted_error_mrad", "interval_mrad", "days_since_record", "alarms", "alarms_latest",
           "statistic_latest", "surface_learned", "calibrated")


def register(subparsers) -> None:
    """Add ``report`` to an argparse subparsers object."""
    p = subparsers.add_parser("report", help="the plant at a glance: one self-contained HTML page (field map, "
                                             "alarms, calibration plan, receiver, provenance)",
                              description="Write one self-contained HTML page (Plotly, no network needed) from "
                                          "what a scenario holds: the field map coloured by a chosen quantity, "
                                          "the latest update's step alarms, per-heliostat histories, the "
                                          "calibration plan, the receiver maps with the stored limit, and the "
                                          "provenance.")
    p.add_argument("--scenario", required=True, help="scenario file (.h5): calibrated, updated, with aim points ...")
    p.add_argument("--paint", help="PAINT folder whose record times count for 'days since the last record'")
    p.add_argument("-o", "--output", required=True, help="HTML file to write")
    p.add_argument("--colour", choices=COLOURS, default="predicted_error_mrad",
                   help="the field map's initial colour (the page switches between all; default %(default)s)")
    p.add_argument("--detail", type=int_range(0, 10000, "a heliostat count"), default=40,
                   help="most heliostats with a section of their own (default %(default)s)")
    p.add_argument("--plan", type=int_range(0, 1000, "a heliostat count"), default=10,
                   help="heliostats with a sun-position coverage map (heliotwin plan; default %(default)s)")
    p.add_argument("--slots", type=int_range(0, 10000, "a record count"), default=20,
                   help="records in tomorrow's calibration plan for the plant (default %(default)s)")
    p.add_argument("--time", type=utc_time, help="instant of the receiver map (default: the stored aim points')")
    p.add_argument("--no-flux", action="store_true", help="no receiver map (skips the field model)")
    p.set_defaults(func=cmd_report)


def cmd_report(args) -> int:
    import os

    from ..io.scenario import load_records, load_scenario
    from ..workflows.report import ReportSettings, plant_report

    settings = ReportSettings(colour=args.colour, detail=args.detail, plan_heliostats=args.plan,
                              plan_slots=args.slots, time_utc=args.time, flux=not args.no_flux)
    with output_set([("--scenario", args.scenario), ("--paint", args.paint)]) as out:
        path = out.file(args.output, "-o")
        scenario = load_scenario(args.scenario)
        records = None
        if args.paint:
            stage(args, f"reading the records of {args.paint}")
            # tomorrow's plan starts after the latest record: without the records' times it would silently be empty
            records = load_records(args.paint, scenario, require_times=True)[0].records
        stage(args, "gathering the plant's state, plan and receiver")
        _, report = plant_report(scenario, records, settings)
        with open(path, "w", encoding="utf-8") as fh:  # staged: moved into place when every output is written
            fh.write(report["html"])
    if not args.quiet:
        size = os.path.getsize(args.output) / 1e6
        print(f"report: {report['heliostats']} heliostats, {len(report['alarms'])} alarm(s), {len(report['detail'])} "
              f"heliostat sections, {len(report['tomorrow']['heliostats'])} records planned for "
              f"{report['tomorrow']['day'] or '-'}, receiver {'yes' if report['receiver'] else 'no'} "
              f"-> {args.output} ({size:.1f} MB)")
    return 0
