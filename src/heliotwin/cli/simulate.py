"""``heliotwin simulate`` (an in-silico plant as a PAINT folder with its truth) and ``heliotwin score`` (a
learned scenario against that truth).

The library (:mod:`heliotwin.workflows.simulate`) is imported inside the command functions so that ``--help``
stays torch-free.
"""
from __future__ import annotations

from ..io.report import output_set, write_json
from .common import float_range, int_range, seed_int


def register(subparsers) -> None:
    """Add ``simulate`` and ``score`` to an argparse subparsers object."""
    p = subparsers.add_parser("simulate", help="an in-silico plant: a PAINT folder of simulated calibration records "
                                               "and the truth scenario",
                              description="Draw a plant's true kinematics, their drift and steps, and years of "
                                          "calibration records from one seed; write them as a PAINT folder every "
                                          "command reads, and the truth as a scenario (default OUT/truth.h5).")
    p.add_argument("--heliostats", type=int_range(1, 67600, "a heliostat count"), default=100,
                   help="heliostats of the demo field (default 100; ignored with --layout)")
    p.add_argument("--seed", type=seed_int, default=0, help="seed of every random draw (default 0)")
    p.add_argument("--years", type=float_range(0.01, 50.0, what="years"), default=3.0,
                   help="length of the calibration history (default 3)")
    p.add_argument("--records-per-month", type=float_range(0.01, 1000.0, what="records per month"), default=2.8,
                   help="mean records per heliostat and month (default 2.8)")
    p.add_argument("--start", default="2021-01-01", help="UTC date of the first day (default 2021-01-01)")
    p.add_argument("--noise-mrad", type=float_range(0.0, 100.0, what="a noise [mrad]"), default=0.15,
                   help="centroid noise per coordinate, as the angle at the heliostat (default 0.15 mrad)")
    p.add_argument("--step-rate", type=float_range(0.0, 100.0, what="a rate [1/year]"), default=0.2,
                   help="offset steps per heliostat-year (default 0.2)")
    p.add_argument("--images", type=int_range(0, 1000, "a heliostat count"), default=0,
                   help="heliostats with defective true surfaces whose records get flux-centred images (default 0)")
    p.add_argument("--layout", help="layout CSV (x,y,z[,id] ENU m) with the heliostat positions")
    p.add_argument("--paint-tower", help="PAINT tower file whose site and targets to use")
    p.add_argument("--prior-from", help="draw the true deviations from the plant prior of a PAINT folder (learned "
                                        "from its heliostats' records) or of a scenario that stores one")
    p.add_argument("--out", help="PAINT folder to write (must not exist or be empty)")
    p.add_argument("--until", metavar="DATE", help="write the history up to the end of this UTC day only; "
                   "'--extend OUT --days N' appends the next days later (a folder that grows as a plant's does)")
    p.add_argument("--extend", metavar="FOLDER", help="append the next --days days to a folder written with --until "
                                                      "(same plant, same truth; new record files, metadata rows "
                                                      "appended)")
    p.add_argument("--days", type=int_range(1, 36600, "a day count"), default=1,
                   help="with --extend: days to append (default 1)")
    p.add_argument("--truth", help="truth scenario file (default: OUT/truth.h5)")
    p.add_argument("--json", help="also write the report as JSON")
    p.set_defaults(func=cmd_simulate)

    s = subparsers.add_parser("score", help="how close a learned scenario is to a simulated plant's truth",
                              description="Pointing error at new sun positions, surface normal error and the "
                                          "receiver flux difference of a scenario against a truth scenario "
                                          "(heliotwin simulate).")
    s.add_argument("--truth", required=True, help="truth scenario (heliotwin simulate)")
    s.add_argument("--scenario", required=True, help="scenario to score (calibrate -o, update, reconstruct ...)")
    s.add_argument("--suns", type=int_range(1, 10000, "a sun count"), default=16, help="sun positions (default 16)")
    s.add_argument("--seed", type=seed_int, default=0, help="seed of the sun positions (default 0)")
    s.add_argument("--no-flux", action="store_true", help="skip the receiver flux comparison")
    s.add_argument("--json", help="also write the report as JSON")
    s.set_defaults(func=cmd_score)


def cmd_simulate(args) -> int:
    import os

    from ..io.scenario import write_scenario
    from ..workflows.simulate import SimulationSettings, prior_from, simulate

    if args.extend:
        return _extend(args)
    _check_new_plant(args)
    inputs = [("--layout", args.layout), ("--paint-tower", args.paint_tower), ("--prior-from", args.prior_from)]
    with output_set(inputs) as out:
        folder = out.folder(args.out, "--out")
        truth_path = out.file(args.truth, "--truth") if args.truth else os.path.join(folder, "truth.h5")
        json_path = out.file(args.json, "--json")
        settings = SimulationSettings(heliostats=args.heliostats, seed=args.seed, years=args.years,
                                      start=args.start, records_per_month=args.records_per_month,
                                      centroid_noise_mrad=args.noise_mrad, step_rate_per_year=args.step_rate,
                                      images=args.images, layout=args.layout, paint_tower=args.paint_tower)
        prior = prior_from(args.prior_from) if args.prior_from else None
        truth, report = simulate(settings, folder, prior=prior, until=args.until)
        write_scenario(truth, truth_path)
        report.update(folder=os.path.abspath(args.out), truth=os.path.abspath(args.truth or
                                                                             os.path.join(args.out, "truth.h5")))
        if json_path:
            write_json(json_path, report)
    if not args.quiet:
        if args.until:
            print(f"until {args.until}: {report['written']} of the history's {report['records']} records written "
                  f"(extend with 'heliotwin simulate --extend {args.out} --days N')")
        print(f"{report['heliostats']} heliostats, {report['records']} records ({report['steps']} offset steps) "
              f"-> {args.out}; truth {report['truth']} ({report['seconds_simulate']:.1f} s simulate, "
              f"{report['seconds_write']:.1f} s write)")
    return 0


def _check_new_plant(args) -> None:
    """A new simulated plant goes to a new folder and, with --truth, a new truth file (refused before any work)."""
    import os

    from ..errors import InputFileError

    if not args.out:
        raise InputFileError("simulate", "give --out FOLDER (a new plant) or --extend FOLDER (a grown one)",
                             field="--out")
    if args.truth and os.path.lexists(args.truth):
        raise InputFileError(args.truth, "exists; the truth of a new simulated plant is written to a new file",
                             field="--truth")
    if os.path.exists(args.out) and (not os.path.isdir(args.out) or os.listdir(args.out)):
        raise InputFileError(args.out, "exists and is not an empty folder; write a simulated plant to a new one",
                             field="--out")


def _extend(args) -> int:
    from ..errors import HeliotwinError
    from ..workflows.simulate import extend

    if args.out or args.until or args.truth:
        raise HeliotwinError("--extend FOLDER takes --days only (the folder's simulation.json holds the rest)")
    added = extend(args.extend, args.days)
    if args.json:
        write_json(args.json, added)
    if not args.quiet:
        print(f"{args.extend}: {added['records']} record(s) appended, the history now until {added['until']}")
    return 0


def cmd_score(args) -> int:
    from ..io.scenario import load_scenario
    from ..workflows.score import score, summary_lines

    with output_set([("--truth", args.truth), ("--scenario", args.scenario)]) as out:
        json_path = out.file(args.json, "--json")
        _, report = score(load_scenario(args.truth), load_scenario(args.scenario), suns=args.suns, seed=args.seed,
                          flux=not args.no_flux)
        if json_path:
            write_json(json_path, report)
    if not args.quiet:
        p, hp = report["pointing_mrad"], report["pointing_per_heliostat_mrad"]
        print(f"{report['heliostats']} heliostats x {report['suns']} suns: pointing error median {p['median']:.3f} "
              f"mrad, p95 {p['p95']:.3f} mrad (per heliostat median {hp['median']:.3f}, p95 {hp['p95']:.3f})")
        for line in summary_lines(report):
            print(line)
        if report["surface_mrad"]:
            print(f"surface normal error median {report['surface_mrad']['median']:.3f} mrad")
        if report["flux"]:
            print(f"receiver flux: relative L1 difference {report['flux']['relative_l1']:.4f}, "
                  f"predicted/delivered power {report['flux']['power_ratio']:.4f}")
    return 0
