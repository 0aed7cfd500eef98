"""Whole-field commands: ``scenario from-layout``, ``field`` and ``aimpoints``.

``scenario from-layout LAYOUT.csv --config plant.toml -o plant.h5`` turns a SolarPILOT-style layout and a
small TOML plant description into a scenario file; ``field`` reports the optical efficiency of every
heliostat (cosine, shading, blocking, attenuation, intercept, reflectance) and the receiver's power and flux
map for one sun. Both are thin shells over :mod:`heliotwin.field.layout` and :mod:`heliotwin.raytrace.field`.
"""
from __future__ import annotations

import argparse
import math
import os
import time

from ..errors import HeliotwinError
from ..io.report import write_json
from .common import check_output_folder, positive_int


# ---------------------------------------------------------------------------------- scenario from-layout
def cmd_scenario_from_layout(args) -> int:
    from ..field.layout import plant_from_layout
    from ..io.scenario import provenance_entry, save_scenario

    check_output_folder(args.output, "-o")
    plant, atmosphere = plant_from_layout(args.layout, args.config)
    meta = {"source": os.path.abspath(args.layout), "config": os.path.abspath(args.config),
            "created_by_command": "heliotwin scenario from-layout"}
    step = provenance_entry("from-layout", layout=os.path.abspath(args.layout), config=os.path.abspath(args.config))
    save_scenario(plant, args.output, extras=atmosphere.to_extras(), metadata=meta, provenance=[step])
    rec = plant.targets["receiver"]
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


def _sun_direction(args, plant):
    import torch

    from ..sun import direction_from_paint_angles, direction_from_time

    if args.time is not None:
        import pandas as pd

        try:
            stamp = pd.Timestamp(args.time)
        except ValueError:
            raise HeliotwinError(f"--time: cannot parse {args.time!r} (expected ISO UTC, e.g. 2023-06-21T12:00Z)") \
                from None
        if stamp.tzinfo is None:
            stamp = stamp.tz_localize("UTC")
        s = plant.site
        d = direction_from_time(pd.DatetimeIndex([stamp]), s.latitude_deg, s.longitude_deg, s.altitude_m,
                               check_horizon=False)
        d = torch.as_tensor(d, dtype=torch.float64).reshape(3)
        if float(d[2]) <= 0:
            raise HeliotwinError(f"--time: the sun is below the horizon at {args.time} "
                                 f"(elevation {math.degrees(math.asin(float(d[2]))):.1f} deg)")
        return d
    if args.sun_elevation <= 0:
        raise HeliotwinError(f"--sun-elevation: the sun is below the horizon ({args.sun_elevation} deg)")
    return direction_from_paint_angles(torch.tensor(math.radians(args.sun_azimuth), dtype=torch.float64),
                                       torch.tensor(math.radians(args.sun_elevation), dtype=torch.float64))


def cmd_field(args) -> int:
    import torch

    from ..atmosphere import Atmosphere
    from ..io.scenario import load_scenario
    from ..raytrace.field import FieldSettings, field_optics, per_heliostat_rows, summary

    for path, flag in ((args.json, "--json"), (args.per_heliostat, "--per-heliostat"), (args.flux, "--flux")):
        check_output_folder(path, flag)
    t0 = time.perf_counter()
    sc = load_scenario(args.scenario)
    plant = sc.plant
    if args.year is not None:
        return _field_year(args, sc, t0)
    if args.dni is not None:
        if args.dni < 0:
            raise HeliotwinError(f"--dni: expected a non-negative irradiance, got {args.dni}")
        plant.sun.dni = float(args.dni)
    sun = _sun_direction(args, plant)
    aim = None
    if args.aim == "scenario":
        aim = (sc.learned.get("aimpoints") or {}).get("aim")
        if aim is None:
            raise HeliotwinError(f"{sc.path} [/learned/aimpoints/aim]: no aim points in this scenario "
                                 "(use --aim equator)")
        aim = torch.as_tensor(aim, dtype=torch.float64)
    settings = FieldSettings(resolution=args.resolution, integrator=args.integrator, seed=args.seed)
    t1 = time.perf_counter()
    kwargs = dict(atmosphere=Atmosphere.from_extras(sc.extras), aim=aim, settings=settings)
    if args.nproc > 1:
        from ..distributed import run_sharded

        result = run_sharded(plant, sun, args.nproc, **kwargs)
    else:
        with torch.no_grad():
            result = field_optics(plant, sun, **kwargs)
    seconds_model = time.perf_counter() - t1
    seconds = time.perf_counter() - t0
    report = summary(result, plant)
    report.update({"scenario": os.path.abspath(args.scenario), "aim": args.aim, "integrator": args.integrator,
                   "resolution": {"cols": args.resolution[1], "rows": args.resolution[0]}, "seconds": seconds,
                   "seconds_field_model": seconds_model})
    if args.json:
        write_json(args.json, report)
    if args.per_heliostat:
        _write_csv(args.per_heliostat, per_heliostat_rows(result, plant))
    if args.flux:
        from ..raytrace.flux import to_png

        to_png(result.flux, args.flux)
    e = report["field"]["efficiency"]
    print(f"field: {len(plant.field.ids)} heliostats; efficiency {e['total']:.4f} (cosine {e['cosine']:.4f}, shading "
          f"{e['shading']:.4f}, blocking {e['blocking']:.4f}, attenuation {e['attenuation']:.4f}, intercept "
          f"{e['intercept']:.4f}); receiver {report['receiver']['power_w'] / 1e6:.3f} MW, peak "
          f"{report['receiver']['peak_flux_w_m2'] / 1e3:.1f} kW/m2; {seconds:.2f} s")
    return 0


def _field_year(args, sc, t0) -> int:
    """``field --year``: the efficiency table over sun positions and the clear-sky annual optical energy."""
    import numpy as np

    from ..atmosphere import Atmosphere
    from ..raytrace.yearly import DEFAULT_ELEVATIONS_DEG, annual_energy, efficiency_table

    try:
        import pandas as pd

        pd.Timedelta(args.every)
    except ValueError:
        raise HeliotwinError(f"--every: cannot parse {args.every!r} (e.g. 1h, 30min)") from None
    atm = Atmosphere.from_extras(sc.extras)
    step = float(args.table_azimuth_step)
    if not 0 < step <= 180:
        raise HeliotwinError(f"--table-azimuth-step: expected (0, 180] deg, got {step}")
    table = efficiency_table(sc.plant, atmosphere=atm, azimuths_deg=np.arange(-180.0, 180.0, step),
                             elevations_deg=DEFAULT_ELEVATIONS_DEG)
    report = annual_energy(sc.plant, args.year, args.every, atmosphere=atm, table=table)
    report.update({"scenario": os.path.abspath(args.scenario), "aim": "equator",
                   "dni_model": "pvlib ineichen clear sky", "seconds": time.perf_counter() - t0})
    write_json(args.json, report)
    print(f"field {args.year}: {report['instants']} daylight instants every {args.every}; annual optical energy "
          f"{report['annual_optical_energy_mwh']:.1f} MWh of {report['annual_dni_energy_on_mirrors_mwh']:.1f} MWh "
          f"clear-sky DNI on the mirrors (efficiency {report['mean_efficiency']:.4f}); {report['seconds']:.1f} s")
    return 0


def _write_csv(path, rows: list[dict]) -> None:
    import csv

    from ..io.report import atomic_path

    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


# ------------------------------------------------------------------------------------------- aimpoints
def cmd_aimpoints(args) -> int:
    """Optimise aim points for one sun under a peak-flux limit; baselines in the same report."""
    import torch

    from ..atmosphere import Atmosphere
    from ..io.scenario import load_scenario, provenance_entry, save_step
    from ..optimise.aimpoints import aiming_factor, evaluate, optimise_aimpoints
    from ..raytrace.field import equator_aim_points

    for path, flag in ((args.json, "--json"), (args.output, "-o")):
        check_output_folder(path, flag)
    if args.peak_limit <= 0:
        raise HeliotwinError(f"--peak-limit: expected a positive flux [W/m2], got {args.peak_limit}")
    sc = load_scenario(args.scenario)
    plant = sc.plant
    sun = _sun_direction(args, plant)
    atm = Atmosphere.from_extras(sc.extras)
    rec = plant.target("receiver")
    limit = float(args.peak_limit)
    equator = evaluate(plant, sun, equator_aim_points(rec, plant.field.kinematics.position.to(torch.float64)), atm,
                       args.resolution)
    factor = aiming_factor(plant, sun, limit, atmosphere=atm, resolution=args.resolution)
    best = optimise_aimpoints(plant, sun, limit, atmosphere=atm, resolution=args.resolution,
                              iterations=args.iterations)

    def entry(r):
        return {"power_w": r.power_w, "peak_flux_w_m2": r.peak_flux_w_m2, "violation": r.violation(limit),
                "power_vs_equator": r.power_w / equator.power_w, "seconds": r.seconds}

    report = {"scenario": os.path.abspath(args.scenario), "peak_limit_w_m2": limit, "sun_direction_enu": sun.tolist(),
              "resolution": {"cols": args.resolution[1], "rows": args.resolution[0]},
              "equator": entry(equator), "aiming_factor": {**entry(factor), "k": factor.parameter},
              "optimised": {**entry(best), "iterations": best.iterations}}
    from ..field.kinematics import inverse

    # motor steps through the plant's (possibly calibrated) kinematics; unreachable ones are reported, not hidden
    steps, reachable = inverse(plant.field.kinematics, best.aim.to(torch.float64), sun.to(torch.float64)[None],
                               strict=False)
    report["optimised"]["motor_steps_reachable"] = int(reachable.sum())
    learned = dict(sc.learned)
    learned["aimpoints"] = {"aim": best.aim.to(torch.float64), "peak_limit_w_m2": limit,
                            "sun_direction": sun.to(torch.float64), "method": "augmented-lagrangian",
                            "motor_steps": steps, "reachable": reachable}
    step = provenance_entry("aimpoints", peak_limit_w_m2=limit, sun_direction=sun.tolist(), iterations=args.iterations,
                            power_w=best.power_w, peak_flux_w_m2=best.peak_flux_w_m2)
    save_step(args.output, plant, sc, learned=learned, step=step)
    write_json(args.json, report)
    print(f"aimpoints: peak {best.peak_flux_w_m2 / 1e3:.1f} kW/m2 (limit {limit / 1e3:.1f}, equator "
          f"{equator.peak_flux_w_m2 / 1e3:.1f}), power {best.power_w / equator.power_w:.4f} of equator aiming "
          f"(aiming factor: {factor.power_w / equator.power_w:.4f}, peak {factor.peak_flux_w_m2 / 1e3:.1f}); "
          f"{best.seconds:.1f} s -> {args.output}")
    return 0


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
    when.add_argument("--sun-azimuth", type=float, help="[deg], PAINT convention: 0 = south, +90 = east "
                                                        "(SolarPILOT azimuth = 180 - this)")
    when.add_argument("--time", help="UTC time (ISO), sun position from pvlib at the scenario's site")
    when.add_argument("--year", type=int, help="efficiency table over sun positions and the annual optical energy "
                                               "under pvlib's clear-sky DNI (equator aiming)")
    p.add_argument("--sun-elevation", type=float, help="[deg] (with --sun-azimuth)")
    p.add_argument("--every", default="1h", help="with --year: time step (default: %(default)s)")
    p.add_argument("--table-azimuth-step", type=float, default=15.0, help="with --year: azimuth step [deg] of the "
                                                                          "efficiency table (default: %(default)s)")
    p.add_argument("--dni", type=float, help="direct normal irradiance [W/m2] (default: the scenario's)")
    p.add_argument("--aim", choices=("equator", "scenario"), default="equator",
                   help="equator: each heliostat aims at the receiver point facing it at mid-height (SolarPILOT "
                        "'simple'); scenario: the scenario's /learned/aimpoints")
    p.add_argument("--integrator", choices=("gaussian", "mc"), default="gaussian")
    p.add_argument("--resolution", type=_resolution, default=(20, 48), help="COLSxROWS of the receiver map "
                                                                            "(default: 48x20)")
    p.add_argument("--seed", type=int, default=0, help="Monte-Carlo seed")
    p.add_argument("--nproc", type=positive_int, default=1, help="shard the heliostats over N local processes "
                                                         "(torch.distributed, gloo)")
    p.add_argument("--json", required=True, help="JSON report")
    p.add_argument("--per-heliostat", help="CSV, one row per heliostat")
    p.add_argument("--flux", help="receiver flux map PNG")
    p.set_defaults(func=_checked(cmd_field))

    p = sub.add_parser("aimpoints", help="aim points under a peak-flux limit, one sun",
                       description="Per heliostat an aim point on the receiver (2 degrees of freedom) by gradient "
                                   "descent through the differentiable field model (smooth shading and blocking) that "
                                   "maximises intercepted power with every map cell at or below the limit "
                                   "(augmented Lagrangian); baselines: equator aiming and the aiming-factor heuristic. "
                                   "Writes the scenario with /learned/aimpoints (use with field --aim scenario).")
    p.add_argument("--scenario", required=True)
    when = p.add_mutually_exclusive_group(required=True)
    when.add_argument("--sun-azimuth", type=float, help="[deg], PAINT convention (0 = south, +90 = east)")
    when.add_argument("--time", help="UTC time (ISO)")
    p.add_argument("--sun-elevation", type=float, help="[deg] (with --sun-azimuth)")
    p.add_argument("--peak-limit", type=float, required=True, help="[W/m2] on every map cell")
    p.add_argument("--resolution", type=_resolution, default=(20, 48), help="COLSxROWS (default: 48x20)")
    p.add_argument("--iterations", type=positive_int, default=150)
    p.add_argument("-o", "--output", required=True, help="scenario file to write (.h5)")
    p.add_argument("--json", required=True, help="JSON report")
    p.set_defaults(func=_checked(cmd_aimpoints))


def _checked(command):
    def run(args) -> int:
        if args.sun_azimuth is not None and args.sun_elevation is None:
            raise HeliotwinError("--sun-azimuth needs --sun-elevation")
        return command(args)
    return run
