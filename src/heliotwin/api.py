"""heliotwin in a few calls: the public surface for notebooks and scripts.

Three lines from a PAINT download to a labelled flux figure::

    from heliotwin import api
    ds = api.load("PAINT_DIR", heliostats=["AA39"])
    flux, report = api.trace_record(ds, 151375)
    api.plot_flux(flux, "flux.png", measured=report)

Conventions at this edge: angles in degrees with ``_deg`` in their names (inside the package: radians),
lengths in metres, powers in watts; every default is the command line's (``heliotwin trace``,
``heliotwin calibrate``, ``heliotwin reconstruct``; a test checks that they agree). Each function calls the
workflow of the same job (:mod:`heliotwin.workflows`) and re-implements none. Importing this module imports
torch and the library, and changes no global state (no backend, no seed, no threads).

Functions
---------
:func:`load` (records on a plant), :func:`field` (the plant alone), :func:`trace_record` (one record's flux
and report), :func:`plot_flux` (a titled, labelled figure with a colour bar), :func:`calibrate` (kinematics),
:func:`update` (assimilate new records into a calibration), :func:`reconstruct` (a mirror surface),
:func:`to_device` (move plant pieces between CPU and GPU).
"""
from __future__ import annotations

import os
from dataclasses import replace

from . import plots
from .devices import resolve_device
from .devices import to_device as _move
from .errors import HeliotwinError
from .field.update import select_heliostats
from .io.scenario import load_records, load_scenario, scenario_from_paint, write_scenario
from .workflows.calibrate import CalibrationSettings, calibration_checkpoint
from .workflows.calibrate import calibrate as calibrate_kinematics
from .workflows.reconstruct import ReconstructionSettings, reconstruction_checkpoint
from .workflows.reconstruct import reconstruct as reconstruct_surface
from .workflows.trace import TraceSettings
from .workflows.trace import trace_record as trace_workflow
from .workflows.update import UpdateSettings
from .workflows.update import update as update_workflow

__all__ = ["load", "field", "trace_record", "plot_flux", "calibrate", "update", "reconstruct",
           "ReconstructionSettings", "to_device"]


def load(paint, heliostats=None, *, scenario=None, plane_tolerance: float = 0.1):
    """The usable calibration records of a PAINT download, on the nominal plant or a scenario's plant.

    Parameters
    ----------
    paint : str or os.PathLike
        PAINT download folder (see ``docs/data.md``).
    heliostats : list of str, optional
        Heliostat ids (default: every heliostat of the folder, or of the scenario).
    scenario : str or os.PathLike, optional
        A scenario file (``heliotwin calibrate -o`` / ``reconstruct -o``): its calibrated kinematics and learned
        surfaces are used instead of the nominal plant.
    plane_tolerance : float
        Largest distance [m] of a measured focal spot from its target plane (CLI ``--plane-tolerance``).

    Returns
    -------
    heliotwin.io.paint.PaintDataset
        ``.plant`` (the plant), ``.records`` (a :class:`~heliotwin.io.records.RecordTable`), ``.skipped`` (records
        that could not be used, with reasons).
    """
    ds, _ = load_records(os.fspath(paint), None if scenario is None else os.fspath(scenario),
                         None if heliostats is None else list(heliostats), plane_tolerance=plane_tolerance)
    return ds


def field(source, heliostats=None):
    """The plant of a PAINT folder (nominal kinematics, ideal surfaces) or of a scenario file (``.h5``).

    Returns
    -------
    heliotwin.field.plant.Plant
    """
    source = os.fspath(source)
    if os.path.isdir(source):
        return scenario_from_paint(source, None if heliostats is None else list(heliostats))
    plant = load_scenario(source).plant
    if heliostats is not None:
        plant = select_heliostats(plant, list(heliostats))
    return plant


def to_device(obj, device):
    """``obj`` with every tensor on ``device`` (:func:`heliotwin.devices.to_device`): plants, targets, record
    tables, flux images, networks and containers of them; dtypes kept."""
    return _move(obj, device)


def _device(name) -> str:
    """``"auto"`` -> ``"cuda"`` when torch sees a CUDA device, else ``"cpu"``; anything else as given."""
    return resolve_device(name)


def trace_record(dataset, record_id: int, *, integrator: str = "mc", rays_per_point: int = 100,
                 resolution: int = 256, samples: int = 50, seed: int = 0, device: str = "auto"):
    """Trace one calibration record (its sun, motor steps and target) with the dataset's plant
    (:func:`heliotwin.workflows.trace.trace_record`; the defaults are ``heliotwin trace``'s).

    Parameters
    ----------
    dataset : PaintDataset
        From :func:`load`.
    record_id : int
        PAINT record id (one of ``dataset.records.record_id``).
    integrator : {"mc", "gaussian"}
    rays_per_point : int
        Monte-Carlo rays per mirror sample (``mc`` only).
    resolution : int
        Bitmap rows = columns over the whole target.
    samples : int
        Mirror samples per facet and direction.
    seed : int
        Seed of the ray generator.
    device : {"auto", "cpu", "cuda"} or torch.device
        Where to trace (``auto``: CUDA when present); the returned flux image is on the CPU.

    Returns
    -------
    flux : heliotwin.raytrace.flux.FluxImage
        Batch of one, on the CPU.
    report : dict
        Powers [W], centroid (ENU [m], WGS84 [deg], target-local [m]; ``None`` when no light reaches the
        target), sun angles [deg] (PAINT: azimuth 0 = south, +90 = east), the measured spots, optics.
    """
    settings = TraceSettings(integrator=integrator, rays_per_point=rays_per_point, resolution=resolution,
                             samples=samples, seed=seed, device=device)
    return trace_workflow(dataset, record_id, settings)


#: A flux image as a figure people read (:func:`heliotwin.plots.plot_flux`: title, axes in metres on the target,
#: colour bar in kW/m², the measured spots of a :func:`trace_record` report marked).
plot_flux = plots.plot_flux


def calibrate(paint, config=None, *, scenario=None, output=None, device: str = "auto", progress=True,
              checkpoint=None, resume: bool = False, **options):
    """Calibrate heliostat kinematics from PAINT calibration records (``heliotwin calibrate``'s defaults).

    Parameters
    ----------
    paint : str or os.PathLike
        PAINT download folder.
    config : heliotwin.workflows.calibrate.CalibrationSettings, optional
        The calibration's settings, one per ``heliotwin calibrate`` flag with the same name and default
        (method, heliostats, split, train, validation, test, min_records, focal_spot, seed, plane_tolerance,
        keep_suspicious, prior, prior_from, half_life_days, drift_mrad, drift, process_noise, drift_basis,
        settings, online_step, curve); default: the command line's.
    **options
        Any of those settings by keyword, replacing ``config``'s (e.g. ``heliostats=["BH60"], train=10``).
        ``prior_from``: a PAINT folder of the same plant or a scenario holding a prior (lm's plant prior from
        other heliostats); ``settings``: ``"auto"`` (as the CLI: with a PAINT folder, lm settings chosen by
        leave-heliostats-out CV on its heliostats), ``"cv"``, ``"stored"`` or ``"given"``.
    scenario : str or os.PathLike, optional
        Start from this scenario's plant (default: the PAINT folder's nominal plant).
    output : str or os.PathLike, optional
        Write the calibrated scenario there (when something was calibrated; else a one-line error).
    device : {"auto", "cpu", "cuda"}
        ``"auto"``: CUDA when present, as the CLI; the model comes back on the CPU.
    progress : bool or callable
        tqdm bars (the run's steps, titled ``calibrate <method>``, and the fit loops), or a callable
        ``progress(step_name, index, total)`` called before each step of the run (no bars then).
    checkpoint : str or os.PathLike, optional
        A file where the fit saves its state as it goes (e.g. ``"run.ckpt"``); after an interruption, the same
        call with ``resume=True`` continues from it and reaches the same result (refused, one line, when the
        settings or inputs differ). The file is removed when the call succeeds.

    Returns
    -------
    report : dict
        Per-heliostat and overall pointing errors [mrad] on held-out test records (see ``docs/glossary.md``).
    model : heliotwin.calibrate.model.Calibrated or None
        None when no heliostat could be calibrated.
    output : str or None
        The scenario file written (``output``), when asked and something was calibrated.
    """
    settings = replace(config or CalibrationSettings(), **options)
    ck = None
    if checkpoint is not None:
        ck = calibration_checkpoint(settings, paint, checkpoint, scenario=scenario, device=_device(device),
                                    resume=resume)
    result = calibrate_kinematics(scenario, paint, settings, device=_device(device), progress=progress, checkpoint=ck)
    if output is not None:
        if result.scenario is None:
            raise HeliotwinError(f"no heliostat could be calibrated; {os.fspath(output)} not written")
        write_scenario(result.scenario, output)
    if ck is not None:
        ck.remove()
    return result.report, result.model, None if output is None else os.fspath(output)


def update(scenario, paint, config: UpdateSettings | None = None, *, output=None, **options):
    """Assimilate the calibration records a calibrated scenario has not seen yet (``heliotwin update``'s defaults).

    Parameters
    ----------
    scenario : str, os.PathLike or heliotwin.io.scenario.Scenario
        A scenario calibrated with ``lm`` (``api.calibrate(..., output=...)``) or updated before.
    paint : str or os.PathLike
        PAINT folder with the new records (records the scenario has seen are recognised by id and skipped).
    config : heliotwin.workflows.update.UpdateSettings, optional
        One setting per ``heliotwin update`` flag with the same name and default (false_alarm_rate,
        process_noise, reopen_mrad, iterations, plane_tolerance, ...).
    output : str or os.PathLike, optional
        Write the updated scenario there.
    **options
        Any of those settings by keyword (e.g. ``false_alarm_rate=1e-4``).

    Returns
    -------
    report : dict
        Records assimilated, each heliostat's mean predicted error [mrad] before each record, step alarms.
    scenario : heliotwin.io.scenario.Scenario
        The updated scenario (its per-heliostat history: :func:`heliotwin.workflows.update.state_history`).
    output : str or None
        The scenario file written, when asked.
    """
    result = update_workflow(scenario, paint, replace(config or UpdateSettings(), **options))
    if output is not None:
        write_scenario(result.scenario, output)
    return result.report, result.scenario, None if output is None else os.fspath(output)


def reconstruct(paint, heliostat: str, settings: ReconstructionSettings | None = None, *, scenario=None,
                checkpoint=None, resume: bool = False, progress: bool = True):
    """Learn one heliostat's mirror surface from its centred flux images (``heliotwin reconstruct``).

    Parameters
    ----------
    paint : str or os.PathLike
        PAINT download folder.
    heliostat : str
    settings : heliotwin.workflows.reconstruct.ReconstructionSettings, optional
        The learner (``method``: ``generalising`` or ``legacy``) and its options; the defaults are the command
        line's (a test checks that they agree).
    scenario : str or os.PathLike, optional
        Start from this scenario's plant (e.g. a calibrated one).
    checkpoint, resume
        As in :func:`calibrate` (the model comes back on the CPU).
    progress : bool
        tqdm bars.

    Returns
    -------
    report : dict
        Per-record normalised L1 of ideal and learned surfaces on test images and IMP (see the glossary).
    model : heliotwin.surfaces.learning.LearnableSurface
        ``model.surfaces()`` is the learned NURBS surface, ``control_points`` [1, F, nu, nv, 3] [m].
    """
    s = settings or ReconstructionSettings()
    ck = None if checkpoint is None else reconstruction_checkpoint(checkpoint, paint, heliostat, s,
                                                                   scenario_path=scenario, resume=resume)
    previous = load_scenario(scenario) if scenario is not None else None
    _, report, fit = reconstruct_surface(previous, paint, heliostat, s, checkpoint=ck, progress=progress)
    if ck is not None:
        ck.remove()
    return report, fit["model"]
