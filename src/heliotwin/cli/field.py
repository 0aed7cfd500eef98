"""Whole-field commands: ``scenario from-layout``, ``field`` and ``aimpoints``.

``scenario from-layout LAYOUT.csv --config plant.toml -o plant.h5`` turns a SolarPILOT-style layout and a
small TOML plant description into a scenario file; ``field`` reports the optical efficiency of every
heliostat (cosine, shading, blocking, attenuation, intercept, reflectance) and the receiver's power and flux
map for one sun. Both are thin shells over :mod:`heliotwin.field.layout` and :mod:`heliotwin.raytrace.field`.
``aimpoints`` optimises aim points under a peak-flux limit for one or several instants
(:mod:`heliotwin.optimise.aimpoints`; ``--nproc`` shards them over local gloo processes,
:mod:`heliotwin.distributed`) and writes them, per instant, into ``/learned/aimpoints`` with their motor steps;
``field --aim scenario`` traces the stored instant whose sun is nearest the requested one.
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
    plant = _on_device(plant, args)
    sun = _sun_direction(args, plant).to(plant.field.kinematics.position.device)
    aim = None
    if args.aim == "scenario":
        aim = _stored_aim(sc, sun)
    settings = FieldSettings(resolution=args.resolution, integrator=args.integrator, seed=args.seed,
                             occlusion_model=args.occlusion)
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
                   "occlusion": args.occlusion,
                   "resolution": {"cols": args.resolution[1], "rows": args.resolution[0]}, "seconds": seconds,
                   "seconds_field_model": seconds_model})
    if args.json:
        write_json(args.json, report)
    if args.per_heliostat:
        _write_csv(args.per_heliostat, per_heliostat_rows(result, plant))
    if args.flux:
        from ..io.images import to_png

        to_png(result.flux.cpu(), args.flux)
    e = report["field"]["efficiency"]
    print(f"field: {len(plant.field.ids)} heliostats; efficiency {e['total']:.4f} (cosine {e['cosine']:.4f}, shading "
          f"{e['shading']:.4f}, blocking {e['blocking']:.4f}, attenuation {e['attenuation']:.4f}, intercept "
          f"{e['intercept']:.4f}); receiver {report['receiver']['power_w'] / 1e6:.3f} MW, peak "
          f"{report['receiver']['peak_flux_w_m2'] / 1e3:.1f} kW/m2; {seconds:.2f} s")
    return 0


def _stored_aim(sc, sun):
    """The scenario's aim points [H, 3] for the instant whose sun is nearest ``sun`` (one instant: those)."""
    import torch

    ap = sc.learned.get("aimpoints") or {}
    if ap.get("aim") is None:
        raise HeliotwinError(f"{sc.path} [/learned/aimpoints/aim]: no aim points in this scenario (use --aim equator)")
    choices = list((ap.get("instants") or {}).values()) or [ap]
    s = sun.detach().cpu().to(torch.float64)
    best = max(choices, key=lambda c: float(torch.as_tensor(c["sun_direction"], dtype=torch.float64) @ s))
    return torch.as_tensor(best["aim"], dtype=torch.float64, device=sun.device)


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
def _instants(args, plant) -> list[tuple[str, object]]:
    """``(label, sun direction [3])`` of every instant: ``--time T1,T2,...``, ``--day DATE --every STEP``
    (daylight instants, sun above 10 deg) or one ``--sun-azimuth/--sun-elevation``."""
    import pandas as pd
    import torch

    from ..sun import direction_from_time

    if args.day is not None:
        try:
            day = pd.Timestamp(args.day)
            step = pd.Timedelta(args.every)
        except ValueError:
            raise HeliotwinError(f"--day/--every: cannot parse {args.day!r} / {args.every!r} (e.g. 2023-06-21, "
                                 "1h)") from None
        day = day.tz_localize("UTC") if day.tzinfo is None else day
        times = pd.date_range(day.normalize(), day.normalize() + pd.Timedelta("1D"), freq=step, inclusive="left")
        s = plant.site
        d = direction_from_time(times, s.latitude_deg, s.longitude_deg, s.altitude_m, check_horizon=False)
        keep = [(t.isoformat(), torch.as_tensor(v, dtype=torch.float64)) for t, v in zip(times, d)
                if math.degrees(math.asin(float(v[2]))) > 10.0]
        if not keep:
            raise HeliotwinError(f"--day: the sun stays below 10 deg elevation on {args.day}")
        return keep
    if args.time is not None:
        out = []
        for text in [t.strip() for t in args.time.split(",") if t.strip()]:
            one = argparse.Namespace(time=text, sun_azimuth=None, sun_elevation=None)
            out.append((text, _sun_direction(one, plant)))
        if not out:
            raise HeliotwinError("--time: no instant given")
        return out
    return [(f"azimuth {args.sun_azimuth} deg, elevation {args.sun_elevation} deg", _sun_direction(args, plant))]


def _aim_instant(args, plant, sun, atm, limit, target_spec):
    """Equator, the two heuristics and the optimised aim points at one sun; (report entry, optimised)."""
    from ..optimise.aimpoints import (
        aiming_factor,
        calibrate_images,
        image_size_priority,
        load_target,
        optimise_aimpoints,
        target_mismatch,
        uniform_target,
    )

    t0 = time.perf_counter()
    model, eq_field = calibrate_images(plant, sun, atm, args.resolution)
    from ..optimise.aimpoints import AimResult

    equator = AimResult(eq_field.aim, float(eq_field.power_w.sum()), float(eq_field.flux.max()), eq_field.flux)
    equator.seconds = time.perf_counter() - t0
    target = None
    if target_spec == "uniform":
        target = uniform_target(eq_field.flux)
    elif target_spec is not None:
        target = load_target(target_spec, args.resolution)
    kw = dict(atmosphere=atm, resolution=args.resolution, iterations=args.iterations, target=target,
              field_gradient=args.field_gradient)
    if args.nproc > 1:
        from ..distributed import run_aimpoints_sharded

        best = run_aimpoints_sharded(plant, sun, limit, args.nproc, **kw)
    else:
        best = optimise_aimpoints(plant, sun, limit, equator=eq_field, model=model, **kw)
    baselines = {}
    if not args.no_baselines:
        baselines["aiming_factor"] = aiming_factor(plant, sun, limit, atmosphere=atm, resolution=args.resolution,
                                                   model=model)
        baselines["image_size_priority"] = image_size_priority(plant, sun, limit, atmosphere=atm,
                                                               resolution=args.resolution, model=model)

    def entry(r):
        e = {"power_w": r.power_w, "peak_flux_w_m2": r.peak_flux_w_m2, "violation": r.violation(limit),
             "limit_met": r.peak_flux_w_m2 <= limit, "power_vs_equator": r.power_w / equator.power_w,
             "seconds": r.seconds}
        if target is not None:
            e["target_mismatch"] = target_mismatch(r.flux, target)
        return e

    rep = {"sun_direction_enu": sun.tolist(), "sun_elevation_deg": math.degrees(math.asin(float(sun[2]))),
           "equator": entry(equator)}
    for name, r in baselines.items():
        rep[name] = {**entry(r), "k": r.parameter}
    rep["optimised"] = {**entry(best), "iterations": best.iterations, "rounds": len(best.history),
                        "final_margin": best.parameter, "history": best.history}
    for name, r in baselines.items():
        rep["optimised"][f"power_vs_{name}"] = best.power_w / r.power_w
    rep["seconds"] = time.perf_counter() - t0
    return rep, best, equator


def cmd_aimpoints(args) -> int:
    """Optimise aim points for one or several instants under a peak-flux limit; baselines in the same report."""
    import torch

    from ..atmosphere import Atmosphere
    from ..field.kinematics import inverse
    from ..io.report import output_set
    from ..io.scenario import load_scenario, provenance_entry, save_step

    if args.peak_limit <= 0:
        raise HeliotwinError(f"--peak-limit: expected a positive flux [W/m2], got {args.peak_limit}")
    if args.nproc > 1 and str(getattr(args, "device", "cpu")).startswith("cuda"):
        raise HeliotwinError("--nproc: the local process group is gloo on CPU; use --device cpu with --nproc")
    t_all = time.perf_counter()
    with output_set([("--scenario", args.scenario)]) as out:
        out_h5, out_json = out.file(args.output, "-o"), out.file(args.json, "--json")
        out_png = out.folder(args.flux, "--flux") if args.flux else None
        sc = load_scenario(args.scenario)
        plant = _on_device(sc.plant, args)
        atm = Atmosphere.from_extras(sc.extras)
        instants = _instants(args, plant)
        limit = float(args.peak_limit)
        report = {"scenario": os.path.abspath(args.scenario), "peak_limit_w_m2": limit,
                  "resolution": {"cols": args.resolution[1], "rows": args.resolution[0]},
                  "target": args.target or "max-power", "nproc": args.nproc, "instants": []}
        stored = {}
        for i, (label, sun) in enumerate(instants):
            rep, best, equator = _aim_instant(args, plant, sun, atm, limit, args.target)
            # motor steps through the plant's (possibly calibrated) kinematics; unreachable ones are reported
            steps, reachable = inverse(plant.field.kinematics, best.aim.to(torch.float64),
                                       sun.to(best.aim.device, torch.float64)[None], strict=False)
            rep["optimised"]["motor_steps_reachable"] = int(reachable.sum())
            report["instants"].append({"instant": label, **rep})
            stored[f"i{i:03d}"] = {"instant": label, "aim": best.aim.to(torch.float64).cpu(),
                                   "sun_direction": sun.to(torch.float64).cpu(), "motor_steps": steps.cpu(),
                                   "reachable": reachable.cpu(), "power_w": best.power_w,
                                   "peak_flux_w_m2": best.peak_flux_w_m2}
            if out_png:
                from ..io.images import to_png

                to_png(equator.flux.cpu(), os.path.join(out_png, f"i{i:03d}_equator.png"))
                to_png(best.flux.cpu(), os.path.join(out_png, f"i{i:03d}_optimised.png"))
            if not args.quiet:
                o = rep["optimised"]
                print(f"aimpoints {label}: peak {o['peak_flux_w_m2'] / 1e3:.1f} kW/m2 (limit {limit / 1e3:.1f}, "
                      f"equator {rep['equator']['peak_flux_w_m2'] / 1e3:.1f}), power {o['power_vs_equator']:.4f} "
                      "of equator" + "".join(f", {n} {rep[n]['power_vs_equator']:.4f} (peak "
                                                 f"{rep[n]['peak_flux_w_m2'] / 1e3:.1f})"
                                                 for n in ("aiming_factor", "image_size_priority") if n in rep)
                      + f"; {rep['seconds']:.1f} s")
        report.update({k: v for k, v in report["instants"][0].items() if k != "instant"})  # first instant at top
        report["seconds"] = time.perf_counter() - t_all
        first = stored["i000"]
        learned = dict(sc.learned)
        learned["aimpoints"] = {"aim": first["aim"], "peak_limit_w_m2": limit, "sun_direction": first["sun_direction"],
                                "method": "augmented-lagrangian on the exact-corrected image model",
                                "motor_steps": first["motor_steps"], "reachable": first["reachable"],
                                "target": args.target or "max-power", "instants": stored}
        step = provenance_entry("aimpoints", peak_limit_w_m2=limit, instants=[lbl for lbl, _ in instants],
                                iterations=args.iterations, target=args.target or "max-power",
                                power_w=[s["power_w"] for s in stored.values()],
                                peak_flux_w_m2=[s["peak_flux_w_m2"] for s in stored.values()])
        save_step(out_h5, _on_device(plant, None), sc, learned=learned, step=step)
        write_json(out_json, report)
    return 0


def _on_device(plant, args):
    """The plant on ``args.device`` (None or no ``device``: on the CPU)."""
    from ..devices import to_device

    device = getattr(args, "device", None) if args is not None else "cpu"
    return plant if device is None else to_device(plant, device)


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
    p.add_argument("--integrator", choices=("gaussian", "conv", "mc"), default="gaussian",
                   help="receiver map: Gaussian-equivalent footprints, the exact sunshape per footprint class "
                        "(conv), or Monte Carlo (default: %(default)s)")
    p.add_argument("--resolution", type=_resolution, default=(20, 48), help="COLSxROWS of the receiver map "
                                                                            "(default: 48x20)")
    p.add_argument("--occlusion", choices=("exact", "solarpilot"), default="exact",
                   help="exact: shading and blocking ray-tested on the mirrors (default); solarpilot: SolarPILOT's "
                        "analytic per-pair estimate, to compare with its reports (docs/physics.md)")
    p.add_argument("--seed", type=int, default=0, help="Monte-Carlo seed")
    p.add_argument("--nproc", type=positive_int, default=1, help="shard the heliostats over N local processes "
                                                         "(torch.distributed, gloo)")
    p.add_argument("--json", required=True, help="JSON report")
    p.add_argument("--per-heliostat", help="CSV, one row per heliostat")
    p.add_argument("--flux", help="receiver flux map PNG")
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
    when.add_argument("--sun-azimuth", type=float, help="[deg], PAINT convention (0 = south, +90 = east)")
    when.add_argument("--time", help="UTC time(s), ISO, comma-separated for several instants")
    when.add_argument("--day", help="UTC date: every --every over the day with the sun above 10 deg")
    p.add_argument("--every", default="1h", help="with --day: time step (default: %(default)s)")
    p.add_argument("--sun-elevation", type=float, help="[deg] (with --sun-azimuth)")
    p.add_argument("--peak-limit", type=float, required=True, help="[W/m2] on every map cell")
    p.add_argument("--target", help="'uniform' (flat over the height) or a CSV/NPY map on the receiver grid (rows x "
                                    "cols, row 0 = top; only its shape counts): match it under the limit")
    p.add_argument("--resolution", type=_resolution, default=(20, 48), help="COLSxROWS (default: 48x20)")
    p.add_argument("--iterations", type=positive_int, default=300, help="image-model steps per round")
    p.add_argument("--nproc", type=positive_int, default=1, help="shard the heliostats over N local processes "
                                                                 "(torch.distributed, gloo)")
    p.add_argument("--field-gradient", action="store_true", help="add the smooth field model's power gradient "
                   "(shading, blocking, cosine) to the image model each round (one backward pass per round)")
    p.add_argument("--no-baselines", action="store_true", help="skip the aiming-factor and image-size baselines")
    p.add_argument("-o", "--output", required=True, help="scenario file to write (.h5)")
    p.add_argument("--json", required=True, help="JSON report")
    p.add_argument("--flux", help="folder for the flux maps (PNG) before and after, per instant")
    p.set_defaults(func=_checked(cmd_aimpoints))


def _checked(command):
    def run(args) -> int:
        if getattr(args, "sun_azimuth", None) is not None and args.sun_elevation is None:
            raise HeliotwinError("--sun-azimuth needs --sun-elevation")
        return command(args)
    return run
