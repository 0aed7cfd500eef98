"""Write a simulated plant as a PAINT folder (the layout :mod:`heliotwin.io.paint` reads) and its truth scenario.

The folder is written into a hidden sibling and renamed into place at the end, so a failure never leaves a
half-written plant; an existing non-empty folder is refused. Conventions follow PAINT's Jülich download:
WGS84 ``[latitude, longitude, altitude]`` (latitude first) about the site's ENU origin, sun azimuth from
south (east positive) and elevation in degrees, motor positions in whole steps, the metadata CSV's DateTime
in UTC (a record with a missing timestamp has no metadata row).
"""
from __future__ import annotations

import csv
import json
import math
import os
import shutil
import tempfile
from dataclasses import fields

import pandas as pd
import torch

from ..errors import HeliotwinError, InputFileError
from ..evaluation import TRUTH_KEY
from ..field.plant import Kinematics
from ..field.targets import PlanarTarget
from ..io.images import to_png
from ..io.records import SOURCES
from ..io.scenario import Scenario, next_scenario, provenance_entry
from ..site import enu_to_wgs84
from .plant import DRIFTING, WEATHER, SimulatedPlant


def _lla(site, enu: torch.Tensor) -> torch.Tensor:
    return enu_to_wgs84(enu, torch.tensor([site.latitude_deg, site.longitude_deg, site.altitude_m],
                                          dtype=torch.float64))


def tower_json(plant) -> dict:
    """The tower file's content for ``plant``'s site and targets (corners rebuilt from each target's frame)."""
    site = plant.site
    out = {"power_plant_properties": {"ID": site.name or "SIMULATED",
                                      "coordinates": [site.latitude_deg, site.longitude_deg, site.altitude_m]}}
    for name, t in plant.targets.items():
        c, r, u = t.center.double(), t.right.double(), t.up.double()
        if isinstance(t, PlanarTarget):
            hw, hh = t.width / 2, t.height / 2
            mid = c
            keys = ("upper_left", "upper_right", "lower_left", "lower_right")
        else:
            half = t.opening_angle / 2
            mid = c - t.radius * (1.0 - math.cos(half)) * t.normal.double()
            hw, hh = t.radius * math.sin(half), t.height / 2
            keys = tuple(f"receiver_outer_{k}" for k in ("upper_left", "upper_right", "lower_left", "lower_right"))
        corners = torch.stack([mid - r * hw + u * hh, mid + r * hw + u * hh,
                               mid - r * hw - u * hh, mid + r * hw - u * hh])
        lla = _lla(site, torch.cat([corners, c.unsqueeze(0)])).tolist()
        coords = dict(zip(keys, lla[:4]))
        spec = {"type": "planar" if isinstance(t, PlanarTarget) else "convex_cylinder",
                "normal_vector": t.normal.double().tolist(), "coordinates": coords}
        if isinstance(t, PlanarTarget):
            coords["center"] = lla[4]
        else:
            spec["radius"] = float(t.radius)
            spec["opening_angle"] = math.degrees(t.opening_angle)
        out[name] = spec
    return out


def _properties(kin: dict, facets: dict, width, height, lla, h: int) -> dict:
    """Heliostat ``h``'s properties file; ``kin`` and ``facets``: the field's tensors as nested lists (one
    conversion for the whole field, not a tensor index per value)."""
    acts = []
    for a in range(2):
        acts.append({"type_axis": "linear" if bool(kin["linear"][h][a]) else "ideal",
                     "min_increment": float(kin["min_steps"][h][a]), "max_increment": float(kin["max_steps"][h][a]),
                     "increment": float(kin["increment"][h][a]), "offset_shift": 0,
                     "initial_stroke_length": float(kin["initial_stroke_length"][h][a]),
                     "offset": float(kin["offset"][h][a]), "pivot_radius": float(kin["pivot_radius"][h][a]),
                     "radius_shift": 0, "clockwise_axis_movement": int(bool(kin["clockwise"][h][a])),
                     "initial_angle": float(kin["initial_angle"][h][a]),
                     "min_movement_angle": float(kin["min_angle"][h][a]),
                     "max_movement_angle": float(kin["max_angle"][h][a]),
                     "movement_speed": 0})
    kp = {"actuators": acts}
    for j in range(2):
        for i, ax in enumerate("enu"):
            kp[f"joint_translation_{ax}_{j + 1}"] = float(kin["joint_translation"][h][j][i])
    for i, ax in enumerate("enu"):
        kp[f"concentrator_translation_{ax}"] = float(kin["concentrator_translation"][h][i])
    fac = [{"translation_vector": t, "canting_e": e, "canting_n": n}
           for t, e, n in zip(facets["translation"][h], facets["canting_e"][h], facets["canting_n"][h])]
    return {"heliostat_position": lla, "height": float(height), "width": float(width),
            "initial_orientation": [0.0, -1.0, 0.0], "kinematic_properties": kp,
            "facet_properties": {"canting_type": "receiver canting", "number_of_facets": len(fac), "facets": fac},
            "renovation": ""}


#: Kinematic fields a properties file states (converted to lists once per field).
_PROPERTY_FIELDS = ("linear", "min_steps", "max_steps", "increment", "initial_stroke_length", "offset",
                    "pivot_radius", "clockwise", "initial_angle", "min_angle", "max_angle", "joint_translation",
                    "concentrator_translation")

#: One calibration record's file, exactly as ``json.dumps`` writes its dict (keys in this order, ``", "`` and
#: ``": "`` separators, floats by ``repr``, a missing focal spot ``null``); filled by ``%`` in one pass.
_RECORD_TEMPLATE = ('{"motor_position": {"axis_1_motor_position": %d, "axis_2_motor_position": %d}, '
                    '"target_name": %s, "focal_spot": {' + ", ".join(f'"{src}": %s' for src in SOURCES)
                    + '}, "sun_elevation": %r, "sun_azimuth": %r}')


#: Records whose values are Python numbers at once while their files are written.
_RECORD_BLOCK = 50_000


def _point(p: list, present: bool) -> str:
    return f"[{p[0]!r}, {p[1]!r}, {p[2]!r}]" if present else "null"


def _write_files(folder: str, names: list, contents: list) -> None:
    """Create the files ``names`` (new) in ``folder`` with ``contents`` (str, UTF-8): one openat, write and
    close each, the folder opened once (the format is one small file per record, so the syscalls are the cost;
    Python's buffered text files add a stat, an isatty and a seek per file)."""
    dir_fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        for name, text in zip(names, contents):
            fd = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666, dir_fd=dir_fd)
            try:
                os.write(fd, text.encode("utf-8"))
            finally:
                os.close(fd)
    finally:
        os.close(dir_fd)


def write_paint_folder(sim: SimulatedPlant, folder) -> str:
    """Write ``sim`` as a PAINT folder at ``folder`` (absent or empty), atomically; returns the folder."""
    folder = os.path.abspath(os.fspath(folder))
    if os.path.exists(folder) and (not os.path.isdir(folder) or os.listdir(folder)):
        raise InputFileError(folder, "exists and is not an empty folder; a simulated plant is written to a new one",
                             field="--out")
    parent = os.path.dirname(folder)
    if not os.path.isdir(parent):
        raise InputFileError(folder, f"output folder {parent} does not exist (create it first)", field="--out")
    tmp = tempfile.mkdtemp(prefix=".heliotwin-simulate-", dir=parent)
    try:
        _write(sim, tmp)
        os.chmod(tmp, 0o755)
        os.replace(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder


def _write(sim: SimulatedPlant, root: str) -> None:
    plant, rec = sim.plant, sim.records
    site = plant.site
    name = site.name or "SIMULATED"
    with open(os.path.join(root, f"{name}-tower-measurements.json"), "w", encoding="utf-8") as fh:
        json.dump(tower_json(plant), fh, indent=2)
    fl = plant.field
    kin = fl.kinematics
    pos_lla = _lla(site, kin.position.double()).tolist()
    kin_lists = {f: getattr(kin, f).tolist() for f in _PROPERTY_FIELDS}
    facet_lists = {f: getattr(fl.facets, f).tolist() for f in ("translation", "canting_e", "canting_n")}
    widths, heights = torch.as_tensor(fl.width).tolist(), torch.as_tensor(fl.height).tolist()
    for h, hid in enumerate(fl.ids):
        os.makedirs(os.path.join(root, hid, "Properties"))
        os.makedirs(os.path.join(root, hid, "Calibration"))
        doc = _properties(kin_lists, facet_lists, widths[h], heights[h], pos_lla[h], h)
        _write_files(os.path.join(root, hid, "Properties"), [f"{hid}-heliostat-properties.json"],
                     [json.dumps(doc, indent=2)])
    r = len(rec)
    spots = _lla(site, torch.nan_to_num(rec.focal_spots.reshape(-1, 3))).reshape(r, 2, 3)
    present = torch.isfinite(rec.focal_spots).all(-1)
    steps = rec.motor_steps.to(torch.int64)
    az, el = torch.rad2deg(rec.sun_azimuth), torch.rad2deg(rec.sun_elevation)
    # one file per record is the format; the values were computed batched above, the text is one template
    # fill per record, and the files are written heliostat by heliostat (records grouped by a stable sort), the
    # values turned into Python numbers a block of records at a time (memory bounded at any plant size)
    target_json = {t: json.dumps(t) for t in set(rec.target)}
    order = torch.argsort(rec.heliostat_index, stable=True)
    bounds = torch.searchsorted(rec.heliostat_index[order], torch.arange(len(fl.ids) + 1)).tolist()
    h0 = 0
    while h0 < len(fl.ids):
        h1 = h0 + 1
        while h1 < len(fl.ids) and bounds[h1 + 1] - bounds[h0] <= _RECORD_BLOCK:
            h1 += 1
        rows = order[bounds[h0]:bounds[h1]]
        b_rid, b_steps, b_el, b_az = (rec.record_id[rows].tolist(), steps[rows].tolist(), el[rows].tolist(),
                                      az[rows].tolist())
        b_spots, b_present, b_rows = spots[rows].tolist(), present[rows].tolist(), rows.tolist()
        for h in range(h0, h1):
            mine = range(bounds[h] - bounds[h0], bounds[h + 1] - bounds[h0])
            names = [f"{b_rid[j]}-calibration-properties.json" for j in mine]
            texts = [_RECORD_TEMPLATE % (b_steps[j][0], b_steps[j][1], target_json[rec.target[b_rows[j]]],
                                         *(_point(b_spots[j][k], b_present[j][k]) for k in range(len(SOURCES))),
                                         b_el[j], b_az[j]) for j in mine]
            _write_files(os.path.join(root, fl.ids[h], "Calibration"), names, texts)
        h0 = h1
    ids, hidx = rec.record_id.tolist(), rec.heliostat_index.tolist()
    az, el = az.tolist(), el.tolist()
    for rid, img in sim.images.items():
        hid = fl.ids[hidx[ids.index(rid)]]
        to_png(img, os.path.join(root, hid, "Calibration", f"{rid}-flux-centered.png"))
    os.makedirs(os.path.join(root, "metadata"))
    when = pd.to_datetime(rec.time.numpy(), unit="s", utc=True).strftime("%Y-%m-%d %H:%M:%S+00:00")
    keep = rec.has_time.tolist()
    with open(os.path.join(root, "metadata", "calibration-metadata.csv"), "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["Id", "HeliostatId", "Azimuth", "Elevation", "DateTime"])
        w.writerows([ids[i], fl.ids[hidx[i]], az[i], el[i], when[i]] for i in range(r) if keep[i])
    if rec.weather is not None:
        wx = rec.weather.tolist()
        stamp = pd.to_datetime(rec.time.numpy(), unit="s", utc=True).strftime("%Y-%m-%dT%H:%M:%SZ")
        with open(os.path.join(root, "metadata", "calibration-weather.csv"), "w", newline="",
                  encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["Id", "HeliostatId", "DateTime", *WEATHER])
            w.writerows([ids[i], fl.ids[hidx[i]], stamp[i], *(f"{v:.4f}" for v in wx[i])] for i in range(r)
                        if not math.isnan(wx[i][0]))


def truth_learned(sim: SimulatedPlant) -> tuple[dict, Kinematics]:
    """The truth as ``/learned`` state: ``calibration`` (deviations from nominal at the end time, as a
    calibration writes them, method ``"truth"``) and ``simulation`` (static deviations, steps, settings)."""
    names = tuple(sim.names) + tuple(n for n in DRIFTING if n not in sim.names)
    dev = torch.cat([sim.static, torch.zeros(sim.static.shape[0], len(names) - len(sim.names),
                                             dtype=torch.float64)], 1)
    for k, n in enumerate(DRIFTING):
        dev[:, names.index(n)] += sim.end_drift[:, k]
    kin = sim.true_kinematics()
    nominal = sim.plant.field.kinematics
    calibration = {"method": "truth", "focal_spot": "HeliOS", "heliostats": list(sim.plant.field.ids),
                   "parameter_names": list(names), "deviations": dev,
                   "nominal": {f.name: getattr(nominal, f.name) for f in fields(Kinematics)}}
    steps = sim.steps
    simulation = {"settings": json.dumps(sim.settings.__dict__), "static_names": list(sim.names),
                  "static_deviations": sim.static, "drifting_names": list(DRIFTING), "end_drift": sim.end_drift,
                  "end_time": torch.tensor([sim.end_time], dtype=torch.float64),
                  "step_heliostat": steps["heliostat"].long(), "step_time": steps["time"].double(),
                  "step_size": steps["size"].double(), "report": json.dumps(sim.report)}
    return {"calibration": calibration, TRUTH_KEY: simulation}, kin


def truth_scenario(sim: SimulatedPlant, source: str = "") -> Scenario:
    """The true plant (kinematics at the end of the history) as an in-memory scenario."""
    learned, kin = truth_learned(sim)
    plant = sim.plant
    surfaces = sim.surfaces if sim.surfaces is not None else plant.field.surfaces
    true_plant = type(plant)(plant.site, plant.targets, type(plant.field)(
        plant.field.ids, kin, plant.field.facets, surfaces, plant.field.width, plant.field.height,
        plant.field.renovation), plant.sun)
    if kin.num_heliostats != len(plant.field.ids):
        raise HeliotwinError("simulate: truth and plant disagree on the heliostats")
    return next_scenario(None, true_plant, learned=learned,
                         step=provenance_entry("simulate", source=source, settings=sim.settings.__dict__),
                         metadata={"simulated": True})
