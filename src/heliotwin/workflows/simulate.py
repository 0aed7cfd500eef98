"""The ``simulate`` and ``score`` workflows: an in-silico plant written as a PAINT folder with its truth, and
how close a learned scenario comes to that truth.

:func:`simulate` draws the plant and its calibration history (:func:`heliotwin.simulate.simulate_plant`),
writes the PAINT folder (atomically; every reader reads it unchanged) and returns the truth scenario in
memory (the true kinematics at the end of the history as ``/learned/calibration``, method ``truth``, and the
static deviations, drift and steps under ``/learned/simulation``) with a report; the caller writes the
scenario. :func:`score` (:mod:`heliotwin.workflows.score`, re-exported here) compares a scenario with a truth
scenario.
"""
from __future__ import annotations

import os
import time

from ..calibrate.priors import PlantPrior
from ..calibrate.protocol.archive import PriorArchive, load_prior_source
from ..errors import InputFileError
from ..io.scenario import Scenario
from ..simulate import SimulationSettings, simulate_plant, truth_scenario, write_paint_folder
from ..simulate.growth import day_end, extend_paint_folder, read_growth_state, records_until, write_growth_state
from .score import score

__all__ = ["SimulationSettings", "simulate", "extend", "score", "prior_from"]


def prior_from(path) -> PlantPrior:
    """A plant prior as ``calibrate --prior-from`` takes it: learned from every heliostat of a PAINT folder with
    enough records (:class:`~heliotwin.calibrate.protocol.archive.PriorArchive`), or stored in a scenario
    (``/learned/calibration/prior``)."""
    if not os.path.exists(path):
        raise InputFileError(path, "not found; --prior-from needs a PAINT folder or a scenario file",
                             field="--prior-from")
    source = load_prior_source(path)
    return source.prior() if isinstance(source, PriorArchive) else source


def simulate(settings: SimulationSettings, out, *, prior: PlantPrior | None = None,
             until: str | None = None) -> tuple[Scenario, dict]:
    """Simulate a plant and write its PAINT folder at ``out`` (absent or empty).

    Parameters
    ----------
    settings : SimulationSettings
    out : path
        The PAINT folder to write.
    prior : PlantPrior, optional
        Distribution of the true static deviations (default: the one learned from PAINT's Jülich records).
    until : str, optional
        Write the records up to the end of this UTC day only (ISO date); :func:`extend` appends the next days
        later (the folder keeps its settings in ``simulation.json``). The truth is the whole history's.

    Returns
    -------
    truth : Scenario
        In memory (one ``simulate`` provenance step); write it with :func:`heliotwin.io.scenario.write_scenario`.
    report : dict
        Counts (heliostats, records, dropped, steps), ``seconds_simulate`` and ``seconds_write`` [s].
    """
    if until is not None and prior is not None:
        raise InputFileError(str(out), "--until needs the default prior (a folder that grows is simulated again "
                                       "from its settings)", field="--prior-from")
    t0 = time.perf_counter()
    sim = simulate_plant(settings, prior=prior, out=out)
    t1 = time.perf_counter()
    written = sim if until is None else records_until(sim, -float("inf"), day_end(until))
    folder = write_paint_folder(written, out)
    if until is not None:
        write_growth_state(folder, settings, until)
    t2 = time.perf_counter()
    report = dict(sim.report, folder=os.path.abspath(folder), seed=settings.seed, written=len(written.records),
                  until=until,
                  prior="given" if prior is not None else "default", seconds_simulate=t1 - t0, seconds_write=t2 - t1)
    return truth_scenario(sim, source=os.path.abspath(folder)), report


def extend(folder, days: int) -> dict:
    """Append the next ``days`` days of a grown folder's history (``simulate --until``, then ``--extend``): the
    same plant and truth, new record files only, metadata rows appended. Returns ``records`` and ``until``."""
    if isinstance(days, bool) or not isinstance(days, int) or not 1 <= days <= 36600:
        raise InputFileError(str(folder), f"--days: expected 1..36600 days, got {days!r}", field="--days")
    settings, _ = read_growth_state(folder)
    return extend_paint_folder(folder, days, simulate_plant(settings))
