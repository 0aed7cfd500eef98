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
:func:`reconstruct` (a mirror surface), :func:`to_device` (move plant pieces between CPU and GPU).
"""
from __future__ import annotations

import os

from . import plots
from .devices import resolve_device
from .devices import to_device as _move
from .field.update import select_heliostats
from .io.scenario import load_records, load_scenario, scenario_from_paint
from .workflows.reconstruct import ReconstructionSettings, reconstruction_checkpoint
from .workflows.reconstruct import reconstruct as reconstruct_surface
from .workflows.trace import TraceSettings
from .workflows.trace import trace_record as trace_workflow

__all__ = ["load", "field", "trace_record", "plot_flux", "calibrate", "reconstruct", "ReconstructionSettings",
           "to_device"]


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


def plot_flux(flux, path=None, *, title: str | None = None, measured: dict | None = None, ax=None):
    """A flux image as a figure people read: title, axes in metres on the target, colour bar in kW/m².

    Parameters
    ----------
    flux : FluxImage
        The first image of the batch is drawn.
    path : str or os.PathLike, optional
        Write the figure here (atomically; format from the extension).
    title : str, optional
        Default: the target's name.
    measured : dict, optional
        A :func:`trace_record` report: its measured focal spots (HeliOS, UTIS) and the predicted centroid are
        marked, so the figure reads "measured vs predicted"; when the record has PAINT's whole-target camera
        image (``measured_flux_png``) it is drawn on the left, on the same target extent (relative scale).
    ax : matplotlib.axes.Axes, optional
        Draw the prediction into this axes (e.g. a notebook's) instead of a new figure (no camera panel).

    Returns
    -------
    matplotlib.figure.Figure
        Made without pyplot (no backend is selected, nothing global changes); in a notebook, display it.
    """
    return plots.plot_flux(flux, path, title=title, measured=measured, ax=ax)


def calibrate(paint, *, method: str = "lm", heliostats=None, split: str = "chrono", train: int = 30,
              validation: int | None = None, test: int | None = None, min_records: int = 50,
              focal_spot: str = "HeliOS", seed: int = 0, plane_tolerance: float = 0.1,
              keep_suspicious: bool = False, progress: bool = True, scenario=None, output=None, device: str = "auto",
              checkpoint=None, resume: bool = False, prior_from=None, settings: str = "auto"):
    """Calibrate heliostat kinematics from PAINT calibration records (``heliotwin calibrate``'s defaults).

    ``prior_from``: a PAINT folder of the same plant or a scenario holding a prior (lm's plant prior from
    other heliostats); ``settings``: ``"auto"`` (as the CLI: with a PAINT folder, lm settings chosen by
    leave-heliostats-out CV on its heliostats), ``"cv"`` or ``"given"``.

    ``progress``: tqdm bars (the run's steps, titled ``calibrate <method>``, and the fit loops), or a callable
    ``progress(step_name, index, total)`` called before each step of the run (no bars then).
    ``device``: ``"auto"`` (CUDA when present, as the CLI), ``"cpu"`` or ``"cuda"``; the model comes back on
    the CPU. ``checkpoint``: a file where the fit saves its state as it goes (e.g. ``"run.ckpt"``); after an
    interruption, the same call with ``resume=True`` continues from it and reaches the same result (refused,
    one line, when the settings or inputs differ). The file is removed when the call succeeds.

    Returns
    -------
    report : dict
        Per-heliostat and overall pointing errors [mrad] on held-out test records (see ``docs/glossary.md``).
    model : heliotwin.calibrate.methods.Calibrated or None
        None when no heliostat could be calibrated.
    output : str or None
        The scenario file written (``output``), when asked and something was calibrated.
    """
    from .calibrate.pipeline import RunConfig, run_calibration, settings_mode, validate_config
    from .calibrate.scenario import save_calibration
    from .errors import HeliotwinError

    cfg = RunConfig(paint=os.fspath(paint), method=method, split=split, train=train, validation=validation,
                    test=test, heliostats=None if heliostats is None else list(heliostats), min_records=min_records,
                    focal_spot=focal_spot, seed=seed, plane_tolerance=plane_tolerance,
                    correct_suspicious=not keep_suspicious, progress=progress is True,
                    prior_from=None if prior_from is None else os.fspath(prior_from),
                    settings=settings_mode(settings, method=method, prior_from=prior_from))
    validate_config(cfg)
    ck = None
    if checkpoint is not None:
        from .calibrate.pipeline import calibration_checkpoint

        ck = calibration_checkpoint(cfg, checkpoint, device=_device(device), resume=resume,
                                    inputs=[scenario] if scenario is not None else [])
    ds = load(paint, scenario=scenario, plane_tolerance=plane_tolerance)
    report, model, arrays = run_calibration(cfg, ds, device=_device(device), checkpoint=ck,
                                            progress=progress if callable(progress) else None)
    if output is None:
        if ck is not None:
            ck.remove()
        return report, model, None
    if model is None or not bool(model.ok.any()):
        raise HeliotwinError(f"no heliostat could be calibrated; {os.fspath(output)} not written")
    from .io.scenario import load_scenario

    seen: dict = {}
    for name in ("train", "validation"):
        t = arrays.get(name)
        for h, rid in zip(t.heliostat_index.tolist(), t.record_id.tolist()) if t is not None else ():
            seen.setdefault(t.heliostat_ids[h], []).append(int(rid))
    settings = {k: v for k, v in report["config"].items() if k != "method_options"}
    save_calibration(output, ds.plant, model, previous=load_scenario(scenario) if scenario else None,
                     focal_spot=cfg.focal_spot, records=seen, settings=settings, source=os.path.abspath(paint),
                     settings_choice=report.get("settings_choice"))
    if ck is not None:
        ck.remove()
    return report, model, os.fspath(output)


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
