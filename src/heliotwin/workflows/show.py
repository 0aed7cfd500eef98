"""The ``scenario show`` and ``scenario export`` workflows: what a scenario file holds, and the plant in the
formats of other tools.

:func:`describe_scenario` reads nothing but the scenario: plant size, targets, optics, what has been learned
(calibrated kinematics, learned surfaces, aim points) with the ``/learned`` groups, and the provenance steps
with their dates and commands, as a JSON-ready dict (``heliotwin scenario show FILE [--json]``).
:func:`export_plant` writes the plant for SolarPILOT (layout table + TOML) and SolTrace (input file at one
sun, mirror normals from the field model); neither learns anything, so neither returns a new scenario.
"""
from __future__ import annotations

import json
import math
import os

import numpy as np
import torch

from ..atmosphere import Atmosphere
from ..errors import HeliotwinError
from ..io.export import export_solarpilot, export_soltrace
from ..io.scenario import Scenario
from ..optimise.aimstate import KEY as AIM_KEY
from ..optimise.aimstate import stored_aimpoints
from ..raytrace.field import FieldSettings, field_optics

__all__ = ["describe_scenario", "export_plant", "format_description", "kinematics_note", "nominal_heliostats",
           "nominal_summary"]

#: The keys of a step that say how it was run (printed after the step's name).
_STEP_KEYS = ("method", "command", "source", "paint", "heliostats", "instants", "peak_limit_w_m2", "target")


def _groups(tree: dict, prefix: str = "/learned") -> list[str]:
    out = []
    for k, v in tree.items():
        path = f"{prefix}/{k}"
        if isinstance(v, dict):
            out.append(path)
            if len(out) < 200:
                out += [g for g in _groups(v, path) if g.count("/") <= 4]
    return out


#: Longest id lists in :func:`describe_scenario`'s JSON (the counts are always of the full lists).
LISTED_IDS = 1000
LISTED_INSTANTS = 100


def stored_coverage(cal: dict) -> dict:
    """A calibration entry's ``coverage`` (``reduced``, ``nominal``, ``min_records``, ``rule``: what
    :func:`heliotwin.calibrate.scenario.calibration_state` stores) as a dict; empty for a calibration written
    before it was stored, or malformed text. Read here, not from the calibration package: ``score`` and
    ``scenario show`` do not import the calibration methods."""
    try:
        out = json.loads(cal.get("coverage") or "{}")
    except (TypeError, ValueError):
        return {}
    return out if isinstance(out, dict) else {}


def nominal_heliostats(scenario: Scenario) -> dict:
    """The heliostats of ``scenario``'s plant its calibration left nominal, id -> why (in plant order; the
    calibration's stored reason, else "not calibrated"); empty when nothing was calibrated at all."""
    cal = scenario.learned.get("calibration") or {}
    if not cal:
        return {}
    done = set(cal.get("heliostats") or [])
    why = stored_coverage(cal).get("nominal") or {}
    return {h: str(why.get(h) or "not calibrated") for h in scenario.plant.field.ids if h not in done}


def nominal_summary(nominal: dict, limit: int = 12) -> str:
    """``"3 heliostats nominal: no usable record: AA28; fewer than 5 usable records: AB01, AB02"`` (grouped by
    reason, at most ``limit`` ids named); "" when none."""
    if not nominal:
        return ""
    groups: dict = {}
    for h, why in nominal.items():
        groups.setdefault(why.split(" (")[0], []).append(h)
    shown, parts = 0, []
    for why, ids in groups.items():
        take = ids[:max(0, limit - shown)]
        shown += len(take)
        more = f", ... ({len(ids) - len(take)} more)" if len(take) < len(ids) else ""
        parts.append(f"{why}: {', '.join(take)}{more}" if take else f"{why}: {len(ids)} heliostats")
    n = len(nominal)
    return f"{n} heliostat{'s' if n != 1 else ''} nominal: " + "; ".join(parts)


def _year_summary(year) -> dict | None:
    """The stored year's headline (``heliotwin year``: ``/learned/year``), JSON-ready; None without one. Read
    leniently (a show must show a damaged file): what is not a number reads None."""
    if not isinstance(year, dict):
        return None

    def total(v):
        try:
            a = np.asarray(v.detach().cpu() if torch.is_tensor(v) else v, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            return None
        return float(np.nansum(a)) if a.size else None

    per = year.get("heliostats") if isinstance(year.get("heliostats"), dict) else {}
    weather = year.get("weather") if isinstance(year.get("weather"), dict) else {}
    interp = year.get("interpolation") if isinstance(year.get("interpolation"), dict) else None
    return {"year": total(year.get("year")), "aim": year.get("aim"),
            "annual_energy_mwh": total(year.get("annual_energy_mwh")),
            "annual_dni_energy_on_mirrors_mwh": total(year.get("annual_dni_energy_on_mirrors_mwh")),
            "tracking_loss_mwh": total(per.get("tracking_loss_mwh")),
            "surface_loss_mwh": total(per.get("surface_loss_mwh")),
            "weather": os.path.basename(str(weather.get("file") or "")) or None, "weather_kind": weather.get("kind"),
            "interpolation": None if not interp else {k: total(interp.get(k)) for k in
                                                      ("median_error", "p95_error", "field_error", "checked_hours")}}


def _year_line(y: dict) -> str:
    """``year: 2023 (equator aiming): 1234 MWh on the receiver ...`` for ``scenario show``."""
    def mwh(v):
        return "?" if v is None else f"{v:.4g}"

    eff = (f" (mean efficiency {y['annual_energy_mwh'] / y['annual_dni_energy_on_mirrors_mwh']:.3f})"
           if y["annual_energy_mwh"] is not None and y["annual_dni_energy_on_mirrors_mwh"] else "")
    it = y["interpolation"]
    check = "interpolation not checked" if not it or it["median_error"] is None else \
        (f"interpolation checked: median {100 * it['median_error']:.2f} %, p95 {100 * (it['p95_error'] or 0):.2f} %,"
         f" field {100 * (it['field_error'] or 0):.2f} %")
    year = "?" if y["year"] is None else f"{y['year']:.0f}"
    return (f"year: {year} ({y['aim'] or '?'} aiming): {mwh(y['annual_energy_mwh'])} MWh on the receiver{eff}; lost "
            f"to tracking {mwh(y['tracking_loss_mwh'])} MWh, to the mirrors {mwh(y['surface_loss_mwh'])} MWh; "
            f"weather {y['weather'] or '?'} ({y['weather_kind'] or '?'}); {check}")


def _learned_summary(learned: dict, scenario: Scenario | None = None) -> dict:
    cal = learned.get("calibration") or {}
    calibrated = sorted(cal.get("heliostats", [])) if cal else []
    surfaces = sorted(learned.get("surfaces") or {})
    aim = learned.get("aimpoints") or {}
    instants = aim.get("instants") or {}
    coverage = stored_coverage(cal) if cal else {}
    nominal = nominal_heliostats(scenario) if scenario is not None else {}
    return {"kinematics": {"calibrated": bool(cal), "method": cal.get("method"), "count": len(calibrated),
                           "heliostats": calibrated[:LISTED_IDS],
                           "reduced": len(coverage.get("reduced") or {}), "rule": coverage.get("rule"),
                           "min_records": coverage.get("min_records"),
                           "nominal_count": len(nominal), "nominal": dict(list(nominal.items())[:LISTED_IDS]),
                           "nominal_line": nominal_summary(nominal)},
            "surfaces": {"count": len(surfaces), "learned_for": surfaces[:LISTED_IDS]},
            "aimpoints": {"instants": len(instants),
                          "labels": [str(v.get("instant", k)) for k, v in instants.items()][:LISTED_INSTANTS],
                          "peak_limit_w_m2": aim.get("peak_limit_w_m2")},
            "year": _year_summary(learned.get("year")),
            "other": sorted(k for k in learned if k not in ("calibration", "surfaces", "aimpoints", "year"))}


def kinematics_note(scenario: Scenario | None, heliostat: str) -> str:
    """One line: are ``heliostat``'s kinematics calibrated in ``scenario``, or does a step on it run on nominal
    kinematics (and why)? E.g. ``"AA39: no calibration in a.h5 (calibrated: AK32, BH60, ...); nominal
    kinematics"``."""
    cal = ((scenario.learned if scenario is not None else {}) or {}).get("calibration") or {}
    done = list(cal.get("heliostats", []))
    if heliostat in done:
        return f"{heliostat}: calibrated kinematics ({cal.get('method')}) from {scenario.path or 'the scenario'}"
    where = f"in {scenario.path}" if scenario is not None and scenario.path else "(no scenario)"
    listed = f" (calibrated: {', '.join(done[:5])}{', ...' if len(done) > 5 else ''})" if done else ""
    return (f"{heliostat}: no calibration {where}{listed}; this step runs on its nominal kinematics (a "
            "heliostat needs enough records with a time and a focal spot to be calibrated)")


def describe_scenario(scenario: Scenario) -> dict:
    """What a scenario file holds, JSON-ready.

    Returns
    -------
    dict
        ``file``, ``format_version``, ``plant`` (heliostats, ids (first 20), targets with kind and size [m],
        site [deg, m], sun and optics, field extent [m]), ``learned`` (kinematics calibrated or nominal,
        ``count`` of calibrated heliostats and their ids -- the first :data:`LISTED_IDS` --, learned surfaces
        with ``count`` and ids capped the same way, aim-point instants, the stored year's headline (``year``:
        annual energy, losses, weather, interpolation check; None without one), other groups), ``learned_groups``
        (the ``/learned`` HDF5 groups), ``extras`` (names), ``metadata`` and ``provenance`` (per step:
        ``step``, ``utc``, ``heliotwin`` version and the keys that say how it ran).
    """
    plant = scenario.plant
    pos = plant.field.kinematics.position.detach().cpu().to(torch.float64)
    dist = torch.linalg.vector_norm(pos[:, :2], dim=-1) if len(pos) else torch.zeros(1)
    targets = {}
    for name, t in plant.targets.items():
        size = {"width_m": float(t.width), "height_m": float(t.height)}
        if t.kind == "cylinder":
            size.update(radius_m=float(t.radius), opening_angle_deg=math.degrees(float(t.opening_angle)))
        targets[name] = {"kind": t.kind, **size, "center_enu_m": [round(float(v), 3) for v in t.center]}
    s = plant.sun
    steps = []
    for p in scenario.provenance:
        step = {k: p.get(k) for k in ("step", "utc", "heliotwin") if k in p}
        step.update({k: p[k] for k in _STEP_KEYS if k in p and not isinstance(p[k], (dict,))})
        if isinstance(step.get("heliostats"), list) and len(step["heliostats"]) > 20:
            step["heliostats"] = f"{len(step['heliostats'])} heliostats"
        steps.append(step)
    return {"file": os.path.abspath(scenario.path) if scenario.path else None,
            "format_version": scenario.version,
            "plant": {"heliostats": len(plant.field.ids), "ids": list(plant.field.ids[:20]),
                      "site": {"latitude_deg": plant.site.latitude_deg, "longitude_deg": plant.site.longitude_deg,
                               "altitude_m": plant.site.altitude_m},
                      "targets": targets,
                      "field_radius_m": [float(dist.min()), float(dist.max())],
                      "sun": {"sunshape": s.sunshape, "dni_w_m2": s.dni, "reflectivity": s.reflectivity,
                              "slope_error_mrad": s.slope_error * 1e3}},
            "learned": _learned_summary(scenario.learned, scenario),
            "learned_groups": _groups(scenario.learned),
            "extras": sorted(scenario.extras),
            "metadata": {k: v for k, v in scenario.metadata.items() if isinstance(v, (str, int, float, bool))},
            "provenance": steps}


def _reduced_note(k: dict) -> str:
    if not k.get("reduced"):
        return ""
    return f" ({k['reduced']} with a reduced model: fewer than {k.get('min_records')} usable records)"


def _surfaces_line(s: dict) -> str:
    ids, count = s["learned_for"], s.get("count", len(s["learned_for"]))
    if count <= 10:
        return f"learned for {', '.join(ids)}"
    return f"learned for {count} heliostats: {', '.join(ids[:10])} ..."


def format_description(d: dict) -> str:
    """:func:`describe_scenario`'s dict as the lines ``heliotwin scenario show`` prints."""
    p, lr = d["plant"], d["learned"]
    k, sun = lr["kinematics"], p["sun"]
    ids = ", ".join(p["ids"][:5]) + (", ..." if p["heliostats"] > 5 else "")
    targets = ", ".join(f"{n} ({t['kind']} {t['width_m']:.2f} x {t['height_m']:.2f} m)"
                        for n, t in p["targets"].items())
    lines = [f"{d['file']} (format {d['format_version']})",
             f"plant: {p['heliostats']} heliostats ({ids}), {p['field_radius_m'][0]:.0f}-"
             f"{p['field_radius_m'][1]:.0f} m from the tower; targets: {targets}",
             f"sun: {sun['sunshape']}, DNI {sun['dni_w_m2']:.0f} W/m2, reflectivity {sun['reflectivity']}, "
             f"slope error {sun['slope_error_mrad']:.2f} mrad",
             "kinematics: " + (f"calibrated ({k['method']}) for {k.get('count', len(k['heliostats']))} heliostats "
                               f"of {p['heliostats']}{_reduced_note(k)}: "
                               f"{', '.join(k['heliostats'][:10])}"
                               f"{' ...' if k.get('count', len(k['heliostats'])) > 10 else ''}"
                               + (f"; {k['nominal_line']}" if k.get("nominal_line") else "")
                               if k["calibrated"] else "nominal (not calibrated)"),
             "surfaces: " + (_surfaces_line(lr["surfaces"]) if lr["surfaces"]["learned_for"]
                             else "ideal (none learned)"),
             "aim points: " + (f"{lr['aimpoints']['instants']} instants ({', '.join(lr['aimpoints']['labels'][:4])})"
                               if lr["aimpoints"]["instants"] else "none stored (equator aiming)"),
             *([_year_line(lr["year"])] if lr.get("year") else []),
             "/learned groups: " + (", ".join(d["learned_groups"][:12]) or "none")
             + (" ..." if len(d["learned_groups"]) > 12 else ""),
             "created by: " + " ".join(str(d["metadata"].get(k)) for k in ("created_by_command", "created_by",
                                                                          "created_utc") if d["metadata"].get(k)),
             f"provenance ({len(d['provenance'])} steps):"]
    for i, s in enumerate(d["provenance"], 1):
        how = ", ".join(f"{key}={s[key]}" for key in _STEP_KEYS if key in s)
        lines.append(f"  {i}. {s.get('utc', '?')}  {s.get('step', '?')}"
                     f"{f' ({how})' if how else ''}  [heliotwin {s.get('heliotwin', '?')}]")
    return "\n".join(lines)


def export_plant(scenario: Scenario, *, solarpilot: tuple | None = None, soltrace=None, sun=None,
                 aim: str = "auto") -> dict:
    """Write the scenario's plant for SolarPILOT and/or SolTrace (:mod:`heliotwin.io.export`).

    Parameters
    ----------
    scenario : Scenario
    solarpilot : (layout path, TOML path), optional
        SolarPILOT's per-heliostat table (positions and aim points, ``aim``) and the TOML that
        ``scenario from-layout`` reads back.
    soltrace : path, optional
        SolTrace input file at ``sun`` (needed then): mirror normals of the same aim points from the field model.
    sun : torch.Tensor, [3], optional
        Unit vector towards the sun (ENU) [1].
    aim : {"auto", "optimised", "equator"}
        Which aim points [m] (ENU) go out: ``"optimised"`` the ones the plant stores (``aimpoints``; the stored instant
        whose sun is nearest ``sun``), ``"equator"`` equator aiming at ``sun`` (else the receiver centre);
        ``"auto"`` (default): the stored ones when the plant has them, else equator aiming -- what was learned
        goes out unless asked otherwise.

    Returns
    -------
    dict
        What was written (``solarpilot_layout``, ``solarpilot_config``, ``soltrace``), ``heliostats`` and
        ``aim_points`` (``"optimised"`` or ``"equator"``: what the files hold).
    """
    if aim not in ("auto", "optimised", "equator"):
        raise HeliotwinError(f"--aim: expected auto, optimised or equator, got {aim!r}")
    plant, atm = scenario.plant, Atmosphere.from_extras(scenario.extras)
    stored = (scenario.learned.get(AIM_KEY) or {}).get("aim") is not None
    if aim == "optimised" and not stored:
        raise HeliotwinError(f"{scenario.path or 'scenario'} [/learned/aimpoints]: no optimised aim points stored "
                             "(run 'heliotwin aimpoints' first, or export --aim equator)")
    use_stored = aim == "optimised" or (aim == "auto" and stored)
    points = None
    if use_stored:
        near = sun if sun is not None else torch.as_tensor(scenario.learned[AIM_KEY]["sun_direction"],
                                                           dtype=torch.float64)
        points = stored_aimpoints(scenario, near)
    result = None
    if sun is not None:
        with torch.no_grad():
            result = field_optics(plant, sun, atmosphere=atm, aim=points, settings=FieldSettings(resolution=(8, 16)))
    src = os.path.abspath(scenario.path) if scenario.path else ""
    out = {"heliostats": len(plant.field.ids), "aim_points": "optimised" if use_stored else "equator"}
    if solarpilot:
        export_solarpilot(plant, solarpilot[0], solarpilot[1], atmosphere=atm,
                          aim=points if points is not None else (None if result is None else result.aim), source=src)
        out.update(solarpilot_layout=str(solarpilot[0]), solarpilot_config=str(solarpilot[1]))
    if soltrace:
        if result is None:
            raise ValueError("export_plant: SolTrace needs a sun (the mirrors are oriented for one sun)")
        export_soltrace(plant, soltrace, sun, result.normal, source=src)
        out["soltrace"] = str(soltrace)
    return out
