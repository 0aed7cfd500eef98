"""``heliotwin plan``: which calibration records to take next for one heliostat.

:func:`register` adds the command; the library (:mod:`heliotwin.calibrate.protocol.plan`) is imported inside the
command function so that ``--help`` stays torch-free.
"""
from __future__ import annotations

from ..io.report import output_set, write_json
from .common import float_range, frequency, int_range, utc_date


def register(subparsers) -> None:
    """Add ``plan`` to an argparse subparsers object."""
    p = subparsers.add_parser("plan", help="sun positions whose calibration records would shrink a heliostat's "
                                           "predictive uncertainty most",
                              description="Propose the times (sun positions) at which a calibration record of one "
                                          "heliostat would shrink its predictive pointing uncertainty most, from "
                                          "the posterior stored by 'calibrate -o' (method lm).")
    p.add_argument("--scenario", required=True, help="calibrated scenario file (calibrate --method lm -o)")
    p.add_argument("--heliostat", required=True, help="heliostat id")
    p.add_argument("--year", type=int_range(1900, 2100, "a year"), default=None,
                   help="year of the candidate times (default: the year from the plant's next day on: tomorrow, or "
                        "the day after the plant's latest record when that is more than 3 days behind the clock)")
    p.add_argument("--day", type=utc_date, default=None,
                   help="the planned day (UTC date): candidates over the year from it on, the spread of that day "
                        "(default: the plant's next day); not with --year")
    p.add_argument("--every", type=frequency, default="1h", help="spacing of candidate times (default 1h)")
    p.add_argument("--count", type=int_range(1, 1000, "a record count"), default=5,
                   help="records to propose (default 5)")
    p.add_argument("--target", help="planar calibration target to aim at (default: the first by name)")
    p.add_argument("--min-elevation", type=float_range(0.0, 89.0, what="an elevation [deg]"), default=15.0,
                   help="lowest sun elevation [deg] (default 15)")
    p.add_argument("--json", help="also write the proposals as JSON (and the sky map <stem>-plan.png next to it)")
    p.add_argument("--no-plots", action="store_true", help="do not write the sky map")
    p.set_defaults(func=cmd_plan)


def cmd_plan(args) -> int:
    import os

    from ..calibrate.report import plot_plan
    from ..io.scenario import load_scenario
    from ..progress import Stages
    from ..workflows.plan import PlanSettings, plan

    bar = Stages(2, "heliotwin plan", enabled=not args.quiet)
    with output_set([("--scenario", args.scenario)]) as out:
        json_path = out.file(args.json, "--json")
        plot_path = None if not args.json or args.no_plots else out.file(
            f"{os.path.splitext(args.json)[0]}-plan.png", "--json")
        settings = PlanSettings(year=args.year, day=args.day, every=args.every, count=args.count, target=args.target,
                                min_elevation=args.min_elevation, sky=plot_path is not None)
        bar.start("candidate sun positions and proposals")
        _, ans = plan(load_scenario(args.scenario), args.heliostat, settings)
        bar.step("proposals")
        if plot_path:
            plot_plan(plot_path, ans)
            ans["plots"] = [os.path.basename(plot_path)]
        ans.pop("sky", None)
        if json_path:
            write_json(json_path, ans)
        bar.step("outputs")
    bar.close()
    if not args.quiet:
        _print_plan(ans)
    return 0


def _print_plan(ans: dict) -> None:
    """The heliostat's spread and its proposed records, one line each."""
    from ..calibrate.spread import DEFINITION
    from ..timefmt import AZIMUTH_CONVENTION, utc_text

    print(f"{ans['heliostat']}: predicted pointing spread on {ans['spread_day']} {ans['spread_now_mrad']:.3f} mrad "
          f"({ans['candidates']} candidate times in {ans['year']}, target {ans['target']})")
    print(f"  ({DEFINITION})")
    if ans.get("candidates_from"):
        print(f"  candidates from {ans['candidates_from']['day']} on: {ans['candidates_from']['why']}")
    for p in ans["proposals"]:
        print(f"  {utc_text(p['time'])}  sun azimuth {p['sun_azimuth_deg']:7.2f} deg, elevation "
              f"{p['sun_elevation_deg']:5.2f} deg  -> spread {p['spread_after_mrad']:.3f} mrad after this record")
    print(f"  (sun azimuth: {AZIMUTH_CONVENTION})")
