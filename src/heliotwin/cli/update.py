"""``heliotwin update`` (assimilate the records a calibrated plant has not seen yet), ``heliotwin daily`` (the
plant's day as one scheduled command) and ``heliotwin history`` (one heliostat's state across updates).

:func:`register` adds both commands; the library (:mod:`heliotwin.workflows.update`) is imported inside the
command functions so that ``--help`` stays torch-free.
"""
from __future__ import annotations

import os

from ..io.report import output_set, plant_inputs, same_file, write_json
from .common import float_range, frequency, int_range, peak_limit, stage, utc_date


def register(subparsers) -> None:
    """Add ``update``, ``daily`` and ``history`` to an argparse subparsers object."""
    p = subparsers.add_parser("update", help="assimilate new calibration records into a calibrated scenario "
                                             "(posterior update, step alarms)",
                              description="Assimilate the calibration records a calibrated plant has not seen yet "
                                          "as a posterior update of each heliostat's state (not a refit). A record "
                                          "far outside its predictive interval raises a step alarm and re-opens "
                                          "that heliostat's offset.")
    p.add_argument("--scenario", required=True, help="calibrated scenario (calibrate --method lm -o, or an update)")
    p.add_argument("--paint", required=True, help="PAINT folder with the new records (seen ones are skipped by id)")
    p.add_argument("-o", "--output", required=True, help="updated scenario file (.h5)")
    p.add_argument("--in-place", action="store_true", help="allow -o to be the input scenario (replaced atomically)")
    p.add_argument("--json", help="also write the report as JSON")
    p.add_argument("--false-alarm-rate", type=float_range(0.0, 1.0, lo_open=True, what="a rate"), default=None,
                   help="target share of clean records raising a step alarm (default: the threshold calibrate "
                        "stored, whose rate spends 0.05 false alarms per heliostat-year at the plant's record "
                        "rate)")
    p.add_argument("--process-noise", default="stored",
                   help="random-walk process noise of the axis offsets [mrad^2/day], or 'stored' (the "
                        "calibration's drift model's, else the one chosen on the records it saw; default)")
    p.add_argument("--reopen-mrad", type=float_range(0.0, 100.0, what="an angle [mrad]"), default=2.0,
                   help="smallest re-opening of the axis offsets at an alarm [mrad] (default 2)")
    p.add_argument("--iterations", type=int_range(1, 20, "an iteration count"), default=2,
                   help="linearisations per record (iterated extended Kalman filter; default 2)")
    p.add_argument("--window", type=int_range(1, 50, "a record count"), default=3,
                   help="step tests over each heliostat's latest 1..WINDOW records (default 3)")
    p.add_argument("--plane-tolerance", type=float_range(0.0, None, lo_open=True, what="a distance [m]"),
                   default=0.1, help="largest distance [m] of a focal spot from its target plane (default 0.1)")
    p.set_defaults(func=cmd_update)

    h = subparsers.add_parser("history", help="one heliostat's state history across updates",
                              description="Print (and optionally write as JSON) the state history of one "
                                          "heliostat stored by 'heliotwin update'.")
    h.add_argument("--scenario", required=True, help="updated scenario (heliotwin update -o)")
    h.add_argument("--heliostat", required=True, help="heliostat id")
    h.add_argument("--json", help="also write the history as JSON")
    h.set_defaults(func=cmd_history)

    d = subparsers.add_parser("daily", help="the plant's day as one scheduled command: update, alarms, tomorrow's "
                                            "calibration plan, aim points",
                              description="Update the plant with the folder's new records (step alarms), plan the "
                                          "next day's calibration records and optimise its aim points; one "
                                          "provenance step, one report. Exit status: 0 nothing to act on, 3 "
                                          "written but something needs a person (a step alarm, a peak limit not "
                                          "held), 2 refused (nothing written).")
    d.add_argument("--plant", required=True, help="calibrated plant file (.h5), updated in place unless -o")
    d.add_argument("--paint", required=True, help="the plant's PAINT folder (it grows every day)")
    d.add_argument("-o", "--output", help="write the plant here instead of in place")
    d.add_argument("--json", help="also write the day's report as JSON")
    d.add_argument("--day", type=utc_date, help="the planned day, UTC date, years 1950..2200 (default: tomorrow; "
                                                "the day after the plant's latest record when that is more than 3 "
                                                "days behind the wall clock)")
    d.add_argument("--slots", type=int_range(0, 100000, "a record count"), default=20,
                   help="calibration records to plan for the day (default 20)")
    d.add_argument("--every", type=frequency, default="30min",
                   help="spacing of the candidate calibration times, 1min..31d (default 30min)")
    d.add_argument("--peak-limit", type=peak_limit, default=None,
                   help="peak-flux limit of the aim points [W/m2] (default: the one the plant stores from an "
                        "earlier 'aimpoints')")
    d.add_argument("--flux-limit", metavar="FILE", help="allowable flux per receiver cell for the aim points: a HALOS "
                   "allowable_flux.csv-layout CSV or a TOML with [receiver.flux_limit] (see 'aimpoints --flux-limit'; "
                   "default: the map the plant stores from an earlier 'aimpoints', else its peak limit)")
    d.add_argument("--aim-times", help="comma-separated UTC times of the day's aim points (default: the hour "
                                       "with the highest sun)")
    d.add_argument("--no-aim", dest="aim", action="store_false", help="no aim points")
    d.add_argument("--wait", type=float_range(0.0, 86400.0, what="seconds"), default=0.0,
                   help="seconds to wait for another command that holds the plant (default 0: refuse at once)")
    d.set_defaults(func=cmd_daily)


def cmd_update(args) -> int:

    from ..errors import HeliotwinError
    from ..workflows.update import UpdateSettings, update_plant_file

    settings = UpdateSettings(false_alarm_rate=args.false_alarm_rate, process_noise=args.process_noise,
                              reopen_mrad=args.reopen_mrad, iterations=args.iterations, window=args.window,
                              plane_tolerance=args.plane_tolerance)
    same = same_file(args.output, args.scenario)
    if same and not args.in_place:
        raise HeliotwinError(f"-o {args.output} is the input scenario; add --in-place to replace it")
    with output_set(plant_inputs(args.scenario, args.output, ("--paint", args.paint), flag="--scenario")) as out:
        out.plant(args.output, "-o")  # before the lock is taken: a refused output leaves nothing beside it
        json_path = out.file(args.json, "--json")
        stage(args, f"assimilating new records of {args.paint}")
        # the plant file is written by the workflow itself: locked, checked unchanged, atomic
        _, report = update_plant_file(args.scenario, args.paint, args.output, settings)
        report["output"] = os.fspath(args.output)
        if json_path:
            write_json(json_path, report)
    if not args.quiet:
        print_update_summary(report)
    return 0


def print_update_summary(report: dict) -> None:
    """The update's report in a few lines (``update`` and ``daily``)."""
    c, o = report["counts"], report["overall"]
    err = o["median_of_mean_predicted_error_mrad"]
    reading = report.get("reading") or {}
    read = (f"; read {reading['parsed']} of {reading['files']} record files (the rest from the record index)"
            if reading else "")
    print(f"{o['records']} new records of {report['heliostats_updated']} heliostats assimilated ({c['seen']} seen "
          f"before, {c['older_than_state']} older than the state, {c['without_time']} without a time){read}; "
          f"predicted error before each: median of the heliostats' means {'-' if err is None else f'{err:.3f}'} "
          f"mrad; {o['alarms']} step alarm(s); offset walk {report['process_noise']['mrad2_per_day']:.3g} "
          f"mrad^2/day ({report['process_noise']['source']})")
    if c.get("dropped"):
        reasons = "; ".join(f"{n} {why}" for why, n in list(c["dropped_by_reason"].items())[:4])
        print(f"  {c['dropped']} record(s) in the folder dropped by the reader: {reasons}")
    if c.get("unknown_heliostats"):
        print(f"  {c['unknown_heliostat_records']} record(s) of {c['unknown_heliostats']} heliostat(s) this plant "
              f"does not know were not used ({', '.join(c['unknown_heliostat_ids'][:5])}"
              f"{', ...' if c['unknown_heliostats'] > 5 else ''})")
    if c.get("nominal_heliostats"):
        print(f"  {c['nominal_heliostat_records']} record(s) of {c['nominal_heliostats']} heliostat(s) on nominal "
              f"kinematics (known, not calibrated) were not used ({', '.join(c['nominal_heliostat_ids'][:5])}"
              f"{', ...' if c['nominal_heliostats'] > 5 else ''}; calibrate again to include them)")
    for a in report["alarms"]:
        print(f"  step alarm: {a['heliostat']} record {a['record_id']} (step statistic {a['statistic']:.1f} over "
              f"{a['window']} record(s) > {report['threshold']['threshold']:.1f})")
    for a in report.get("closed_alarms") or []:
        print(f"  alarm closed: {a['heliostat']} record {a['record_id']} (opened {a['opened_utc']}): {a['outcome']} "
              f"(statistic {a['evidence']:.1f} of the {a['records']} record(s) after it vs "
              f"{report['threshold'].get('confirm_threshold', float('nan')):.1f})")
    for a in report.get("open_alarms") or []:
        age = a.get("age_days")
        print(f"  alarm open: {a['heliostat']} record {a['record_id']} (opened {a['opened_utc']}"
              f"{'' if age is None else f', {age:.1f} day(s) old'}; {a['records']} of {a['records_to_settle']} "
              "records to settle it)")


def cmd_daily(args) -> int:
    from ..workflows.daily import DailySettings, daily_plant_file

    settings = DailySettings(day=args.day, slots=args.slots, every=args.every, aim=args.aim,
                             peak_limit_w_m2=args.peak_limit, aim_times=args.aim_times, flux_limit=args.flux_limit)
    output = args.output or args.plant
    with output_set(plant_inputs(args.plant, output, ("--paint", args.paint), ("--flux-limit", args.flux_limit),
                                 flag="--plant")) as out:
        out.plant(output, "-o" if args.output else "--plant")  # before the lock: nothing left beside a refused one
        json_path = out.file(args.json, "--json")
        stage(args, f"the plant's day: {args.plant} with the new records of {args.paint}")
        result = daily_plant_file(args.plant, args.paint, args.output, settings, timeout=args.wait or None)
        report = result.report
        report["output"] = os.fspath(args.output or args.plant)
        if json_path:
            write_json(json_path, report)
    if not args.quiet:
        from ..timefmt import utc_or_label

        print_update_summary(report["update"])
        plan = report["plan"]
        print(f"planned {report['day']}: {report.get('day_reason', '')}")
        print_plan(plan)
        aim = report["aimpoints"]
        if "skipped" in aim:
            print(f"aim points: skipped, {aim['skipped']}")
        else:
            for e in aim["instants"]:
                standby = e.get("standby_heliostats", 0)
                held = (f"limit {aim['peak_limit_w_m2'] / 1e3:.1f}" if "flux_limit" not in aim else
                        f"flux/limit {e['max_utilisation']:.4f} of {aim['flux_limit']['source']}, "
                        f"{e['binding_cells']} binding cells")
                print(f"aim points {utc_or_label(e['instant'])}: peak {e['peak_flux_w_m2'] / 1e3:.1f} kW/m2 ({held}"
                      f"{'' if e['limit_met'] else ', NOT held'})"
                      + (f"; {standby} heliostat(s) on standby, {e['power_w'] / 1e3:.3g} of "
                         f"{e['equator_power_w'] / 1e3:.3g} kW" if standby and e.get("equator_power_w") else ""))
        print(f"status {report['status']}: {'; '.join(report['attention']) or 'nothing to act on'}")
    return result.status


#: Most plan rows a daily run prints (the JSON holds every one).
PLAN_ROWS = 50


def print_plan(plan: dict) -> None:
    """The day's calibration plan: how many of the slots are planned (and why fewer), the spread's definition, the
    ranking, and one line per planned record with the number it is ranked by."""
    from ..timefmt import AZIMUTH_CONVENTION, utc_text

    props = plan.get("proposals") or []
    print(f"calibration plan for {plan['day']}: {len(props)} of {plan.get('slots', len(props))} slot(s) planned"
          f"{_fewer(plan)} on {plan['target']}; ranked by {plan.get('ranked_by', 'spread')}; predicted pointing "
          f"spread over the plant's {plan.get('heliostats', '?')} calibrated heliostat(s): median "
          f"{_mrad(plan['median_spread_mrad'])}, p95 {_mrad(plan['p95_spread_mrad'])} mrad")
    if plan.get("spread_definition"):
        print(f"  ({plan['spread_definition']})")
    for k, p in enumerate(props[:PLAN_ROWS], 1):
        print(f"  {k:2d}. {utc_text(p['time'])}  {p['heliostat']}  sun azimuth {p['sun_azimuth_deg']:.1f}, elevation "
              f"{p['sun_elevation_deg']:.1f} deg  ({p['reason']}: predicted pointing spread "
              f"{p['spread_now_mrad']:.3f} -> {p['spread_after_mrad']:.3f} mrad after this record)")
    if len(props) > PLAN_ROWS:
        print(f"  ... and {len(props) - PLAN_ROWS} more planned record(s) (--json lists every one)")
    if props:
        print(f"  (sun azimuth: {AZIMUTH_CONVENTION})")


def _mrad(x) -> str:
    return "-" if x is None else f"{x:.3f}"


def cmd_history(args) -> int:
    from ..timefmt import utc_text
    from ..workflows.update import state_history

    with output_set([("--scenario", args.scenario)]) as out:
        json_path = out.file(args.json, "--json")
        hist = state_history(args.scenario, args.heliostat)
        if json_path:
            write_json(json_path, {k: (v.tolist() if hasattr(v, "tolist") else v) for k, v in hist.items()})
    if args.quiet:
        return 0
    names = hist["parameter_names"]
    cols = [names.index(n) for n in ("initial_angle_1", "initial_angle_2") if n in names]
    print(f"{hist['heliostat']}: {len(hist['time'])} assimilated record(s)")
    for i in range(len(hist["time"])):
        when = utc_text(float(hist["time"][i]))
        offs = ", ".join(f"{1e3 * hist['mean'][i][c]:+.3f}+-{1e3 * hist['variance'][i][c] ** 0.5:.3f}" for c in cols)
        print(f"  {when} record {int(hist['record_id'][i])}: predicted error {1e3 * hist['predicted_error'][i]:.3f} "
              f"mrad, d2 {hist['d2'][i]:.1f}{'  STEP ALARM' if hist['alarm'][i] else ''}; axis offsets [mrad] {offs}")
    return 0


def _fewer(plan: dict) -> str:
    """Why fewer records were planned than slots asked for, in parentheses ('' when all were)."""
    return f" ({plan['why_fewer']})" if plan.get("why_fewer") else ""
