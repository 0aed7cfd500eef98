"""A simulated plant's folder that grows a day at a time, as a real plant's does (``simulate --until`` /
``simulate --extend``).

The whole history is deterministic in its :class:`~heliotwin.simulate.plant.SimulationSettings` (every draw from
the seed), so a folder written up to a date and extended later holds exactly the files of the one-shot history:
:func:`records_until` cuts the simulated records at the end of a UTC day, :func:`write_growth_state` stores the
settings and the day written so far beside the records (``simulation.json``), and :func:`extend_paint_folder`
re-simulates, writes the next days' record files (never touching an existing one) and appends their rows to the
metadata CSVs. A folder without ``simulation.json`` was not grown by ``simulate --until`` and is refused.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile

import pandas as pd
import torch

from ..errors import InputFileError
from ..io.report import write_json
from .plant import SimulatedPlant, SimulationSettings
from .writer import write_paint_folder

__all__ = ["GROWTH_FILE", "day_end", "records_until", "write_growth_state", "read_growth_state",
           "extend_paint_folder"]

#: The file beside the records that says how the folder was simulated and up to which day.
GROWTH_FILE = "simulation.json"
_META = ("calibration-metadata.csv", "calibration-weather.csv")


def day_end(day: str) -> float:
    """POSIX time [s] of the end of UTC day ``day`` (ISO date): records before it belong to the day or earlier."""
    try:
        start = pd.Timestamp(day)
    except (ValueError, TypeError):
        raise InputFileError(str(day), "not a UTC date (expected e.g. 2021-09-01)", field="--until") from None
    start = (start.tz_localize("UTC") if start.tzinfo is None else start.tz_convert("UTC")).normalize()
    return float((start + pd.Timedelta("1D")).timestamp())


def records_until(sim: SimulatedPlant, start_s: float, end_s: float) -> SimulatedPlant:
    """``sim`` with only the records timed in ``[start_s, end_s)`` [s] (and their images)."""
    rec = sim.records
    keep = ((rec.time >= start_s) & (rec.time < end_s)).nonzero().flatten()
    fields = {}
    for f in dataclasses.fields(rec):
        v = getattr(rec, f.name)
        if isinstance(v, torch.Tensor):
            fields[f.name] = v[keep]
        elif isinstance(v, list):
            fields[f.name] = [v[i] for i in keep.tolist()]
        else:
            fields[f.name] = v
    ids = set(fields["record_id"].tolist())
    images = {rid: img for rid, img in (sim.images or {}).items() if rid in ids}
    return dataclasses.replace(sim, records=dataclasses.replace(rec, **fields), images=images)


def write_growth_state(folder, settings: SimulationSettings, until: str) -> None:
    """Store ``settings`` and the last day written (``until``, ISO date) in ``folder/simulation.json``."""
    doc = {"settings": dataclasses.asdict(settings), "until": pd.Timestamp(until).date().isoformat()}
    write_json(os.path.join(folder, GROWTH_FILE), doc, make_folder=False)  # atomic: the old state or the new


def read_growth_state(folder) -> tuple[SimulationSettings, str]:
    """The settings and last day of a grown folder (:func:`write_growth_state`); a one-line error otherwise."""
    path = os.path.join(folder, GROWTH_FILE)
    if not os.path.isfile(path):
        raise InputFileError(folder, f"has no {GROWTH_FILE}: only a folder written by 'heliotwin simulate "
                                     "--until' can be extended", field="--extend")
    try:
        with open(path, encoding="utf-8") as fh:
            doc = json.load(fh)
        settings = SimulationSettings(**doc["settings"])
        until = str(doc["until"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputFileError(path, f"not a growth state ({exc})", field="--extend") from None
    return settings, until


def extend_paint_folder(folder, days: int, sim: SimulatedPlant) -> dict:
    """Append the ``days`` days after the folder's last day to ``folder``: new record files (and images) in each
    heliostat's ``Calibration`` folder and their rows at the end of the metadata CSVs; ``sim`` is the folder's
    simulation (:func:`read_growth_state`'s settings, simulated again). Existing files are never rewritten
    except the appended CSVs and ``simulation.json``. Returns ``records`` added and the new ``until``."""
    settings, until = read_growth_state(folder)
    start = day_end(until)
    new_until = (pd.Timestamp(until) + pd.Timedelta(days=int(days))).date().isoformat()
    part = records_until(sim, start, day_end(new_until))
    parent = os.path.dirname(os.path.abspath(folder))
    stage = tempfile.mkdtemp(prefix=".heliotwin-extend-", dir=parent)
    try:
        written = write_paint_folder(part, os.path.join(stage, "part"))
        moves = []
        for hid in sim.plant.field.ids:
            src = os.path.join(written, hid, "Calibration")
            for name in sorted(os.listdir(src)):
                dest = os.path.join(folder, hid, "Calibration", name)
                if os.path.exists(dest):
                    raise InputFileError(dest, "exists already: the folder does not match its simulation.json",
                                         field="--extend")
                moves.append((os.path.join(src, name), dest))
        rows = {}
        for name in _META:
            src = os.path.join(written, "metadata", name)
            if os.path.isfile(src):
                with open(src, encoding="utf-8", newline="") as fh:  # the CSV's own line ends (\r\n)
                    rows[name] = fh.readlines()[1:]  # the header is the folder's already
        for src, dest in moves:  # the rows last: a reader meanwhile sees a new file as a record without a time
            os.replace(src, dest)
        for name, lines in rows.items():
            dest = os.path.join(folder, "metadata", name)
            if lines and os.path.isfile(dest):
                with open(dest, "a", encoding="utf-8", newline="") as fh:
                    fh.writelines(lines)
            elif lines:
                shutil.copy(os.path.join(written, "metadata", name), dest)
        write_growth_state(folder, settings, new_until)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return {"records": len(part.records), "until": new_until}
