"""The calibrated-model file (``-o calibrated.h5``) and the aim command built on it.

Format ``heliotwin-calibration``, version 1 (HDF5, h5py)::

    /                       attrs: format="heliotwin-calibration", version=1, method, split, created (UTC ISO)
    /heliostats/<HID>/      one group per calibrated heliostat
        kinematics/<field>  the calibrated static Kinematics, every field of
                            heliotwin.field.plant.Kinematics without the heliostat axis
                            (e.g. joint_tilt (2, 3), increment (2,), clockwise (2,) as uint8)
        deviations          (P,) learned deviations from the nominal file (rad, m, relative increments)
                            attrs: names (JSON list)
        network/            optional (hybrid, mlp): attrs config (JSON); one dataset per state-dict entry

This is the calibration module's own small format (the plant scenario format lives elsewhere); readers
check ``format`` and ``version`` and raise :class:`~heliotwin.errors.ScenarioVersionError` otherwise.
"""
from __future__ import annotations

import json
import os
import tempfile
from dataclasses import fields
from datetime import datetime, timezone

import torch

from ..errors import InputFileError, ScenarioVersionError
from ..io.hdf5 import open_for_reading
from ..field.plant import Kinematics

FORMAT = "heliotwin-calibration"
VERSION = 1


def save_calibration(path, model, *, split: str = "") -> None:
    """Write a :class:`~heliotwin.calibrate.model.Calibrated` model (calibrated heliostats only), atomically."""
    import h5py

    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".h5", dir=folder)
    os.close(fd)
    kin = model.kinematics
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT
            f.attrs["version"] = VERSION
            f.attrs["method"] = model.method
            f.attrs["split"] = split
            f.attrs["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
            root = f.create_group("heliostats")
            for h, hid in enumerate(model.heliostat_ids):
                if not bool(model.ok[h]):
                    continue
                g = root.create_group(hid)
                kg = g.create_group("kinematics")
                for fl in fields(Kinematics):
                    v = getattr(kin, fl.name)[h].detach()
                    kg.create_dataset(fl.name, data=(v.to(torch.uint8) if v.dtype == torch.bool else v).numpy())
                d = g.create_dataset("deviations", data=model.delta[h].detach().double().numpy())
                d.attrs["names"] = json.dumps(list(model.names))
                net = model.extras.get("networks", {}).get(hid)
                if net is not None:
                    ng = g.create_group("network")
                    ng.attrs["config"] = json.dumps(net["config"])
                    for k, t in net["state"].items():
                        ng.create_dataset(k, data=t.detach().cpu().numpy())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def load_calibration(path) -> dict:
    """Read a calibration file.

    Returns
    -------
    dict
        ``method``, ``heliostats``: dict of HID -> {"kinematics": Kinematics (1 heliostat),
        "deviations": dict name -> value, "network": {"config": dict, "state": dict} or None}.
    """
    path = os.fspath(path)
    with open_for_reading(path) as f:
        fmt = f.attrs.get("format")
        fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
        if fmt != FORMAT:
            raise ScenarioVersionError(path, f"format {fmt!r} is not {FORMAT!r}", field="format")
        ver = int(f.attrs.get("version", -1))
        if ver != VERSION:
            raise ScenarioVersionError(path, f"version {ver} not supported (this heliotwin reads version {VERSION})",
                                       field="version")
        if "heliostats" not in f:
            raise InputFileError(path, "missing group", field="heliostats")
        out = {"method": str(f.attrs.get("method", "")), "heliostats": {}}
        for hid, g in f["heliostats"].items():
            vals = {}
            for fl in fields(Kinematics):
                key = f"kinematics/{fl.name}"
                if key not in g:
                    raise InputFileError(path, "missing dataset", field=f"heliostats/{hid}/{key}")
                t = torch.as_tensor(g[key][()])
                vals[fl.name] = (t.bool() if fl.name in ("clockwise", "linear") else t.double()).unsqueeze(0)
            names = json.loads(g["deviations"].attrs["names"]) if "deviations" in g else []
            dev = dict(zip(names, g["deviations"][()].tolist())) if names else {}
            net = None
            if "network" in g:
                net = {"config": json.loads(g["network"].attrs["config"]),
                       "state": {k: torch.as_tensor(v[()]) for k, v in g["network"].items()}}
            out["heliostats"][hid] = {"kinematics": Kinematics(**vals), "deviations": dev, "network": net}
    return out


def aim(calibration: dict, heliostat_id: str, sun_azimuth: float, sun_elevation: float, aim_point) -> dict:
    """Motor steps that put the sun's reflection on ``aim_point`` with the calibrated model.

    Parameters
    ----------
    calibration : dict
        From :func:`load_calibration`.
    sun_azimuth, sun_elevation : float
        [rad], PAINT convention.
    aim_point : sequence of 3 float
        ENU [m].

    Returns
    -------
    dict
        ``motor_steps`` [2] (real-valued), ``reachable`` (bool), ``method``.
    """
    from ..errors import HeliotwinError
    from ..field import kinematics as K
    from ..sun import direction_from_paint_angles

    hs = calibration["heliostats"]
    if heliostat_id not in hs:
        raise HeliotwinError(f"heliostat {heliostat_id!r} not in the calibration file; it has {', '.join(sorted(hs)) or 'none'}")
    entry = hs[heliostat_id]
    kin = entry["kinematics"]
    sun = direction_from_paint_angles(torch.tensor([sun_azimuth]), torch.tensor([sun_elevation]))
    target = torch.as_tensor(aim_point, dtype=torch.float64).reshape(1, 3)
    net = entry.get("network")
    if net is not None and net["config"].get("kind") == "mlp":
        from .mlp import aim_mlp

        steps = aim_mlp(net, kin, sun, target)
    elif net is not None and net["config"].get("kind") == "hybrid":
        from .hybrid import aim_hybrid

        steps = aim_hybrid(net, kin, sun, target)
    else:
        steps, _ = K.inverse(kin, target, sun, strict=False)
    steps = steps.reshape(-1, 2)[0]
    reachable = bool(((steps >= kin.min_steps[0]) & (steps <= kin.max_steps[0])).all())
    return {"heliostat": heliostat_id, "motor_steps": [float(s) for s in steps], "reachable": reachable,
            "method": calibration["method"]}
