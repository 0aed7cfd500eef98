"""heliotwin in a few calls: the public surface for notebooks and scripts.

Three lines from a PAINT download to a labelled flux figure::

    from heliotwin import api
    ds = api.load("PAINT_DIR", heliostats=["AA39"])
    flux, report = api.trace_record(ds, 151375)
    api.plot_flux(flux, "flux.png", measured=report)

Conventions at this edge: angles in degrees with ``_deg`` in their names (inside the package: radians),
lengths in metres, powers in watts; every default is the command line's (``heliotwin trace``,
``heliotwin calibrate``, ``heliotwin reconstruct``; a test checks that they agree). Importing this module
imports neither torch nor matplotlib and changes no global state (no backend, no seed, no threads): each
function imports what it needs when called.

Functions
---------
:func:`load` (records on a plant), :func:`field` (the plant alone), :func:`trace_record` (one record's flux
and report), :func:`plot_flux` (a titled, labelled figure with a colour bar), :func:`calibrate` (kinematics),
:func:`reconstruct` (a mirror surface), :func:`to_device` (move plant pieces between CPU and GPU).
"""
from __future__ import annotations

import math
import os
import time

__all__ = ["load", "field", "trace_record", "plot_flux", "calibrate", "reconstruct", "to_device"]


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
    from .io.scenario import load_records

    ds, _ = load_records(os.fspath(paint), None if scenario is None else os.fspath(scenario),
                         None if heliostats is None else list(heliostats), plane_tolerance=plane_tolerance)
    return ds


def field(source, heliostats=None):
    """The plant of a PAINT folder (nominal kinematics, ideal surfaces) or of a scenario file (``.h5``).

    Returns
    -------
    heliotwin.field.plant.Plant
    """
    from .io.scenario import load_scenario, scenario_from_paint

    source = os.fspath(source)
    if os.path.isdir(source):
        return scenario_from_paint(source, None if heliostats is None else list(heliostats))
    plant = load_scenario(source).plant
    if heliostats is not None:
        from .field.update import select_heliostats

        plant = select_heliostats(plant, list(heliostats))
    return plant


def to_device(obj, device):
    """``obj`` with every tensor on ``device`` (:func:`heliotwin.devices.to_device`): plants, targets, record
    tables, flux images, networks and containers of them; dtypes kept."""
    from .devices import to_device as move

    return move(obj, device)


def _device(name) -> str:
    """``"auto"`` -> ``"cuda"`` when torch sees a CUDA device, else ``"cpu"``; anything else as given."""
    from .devices import resolve_device

    return resolve_device(name)


def trace_record(dataset, record_id: int, *, integrator: str = "mc", rays_per_point: int = 100,
                 resolution: int = 256, samples: int = 50, seed: int = 0, device: str = "auto"):
    """Trace one calibration record (its sun, motor steps and target) with the dataset's plant.

    The defaults are ``heliotwin trace``'s.

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
    import torch

    from .field import kinematics as kin_ops
    from .io.records import SOURCES
    from .scene import trace, world_surface

    device = _device(device)
    plant = dataset.plant
    row = dataset.record(int(record_id))
    kin, surfaces, target, row_on = to_device((plant.field.kinematics, plant.field.surfaces,
                                               plant.target(row.target[0]), row), device)
    t0 = time.perf_counter()
    with torch.no_grad():
        pts, nrm, area, R, c = world_surface(kin, surfaces, row_on.heliostat_index, row_on.motor_steps,
                                             (samples, samples))
        flux = trace(pts, nrm, area, row_on.sun.to(pts), target, integrator=integrator,
                     resolution=(resolution, resolution), sun=plant.sun, rays_per_point=rays_per_point,
                     generator=torch.Generator(device=device).manual_seed(seed))
    seconds = time.perf_counter() - t0
    # Reporting happens on the CPU, where the plant's site and targets live.
    flux, nrm, area, R, c = to_device((flux, nrm, area, R, c), "cpu")
    s = row.sun
    # No light on the target: there is no centroid (a zero image's "centroid" would be the target centre).
    lit = bool(flux.bitmap[0].sum() > 0) and float(flux.intercepted_power_w[0]) > 0
    centroid = flux.centroid_enu()[0] if lit else None
    lla = plant.site.to_wgs84(centroid) if lit else None
    cosines = (nrm[0].to(torch.float64) @ s[0]).clamp_min(0)
    spots = {src: row.focal_spots[0, k].tolist() for k, src in enumerate(SOURCES)
             if bool(torch.isfinite(row.focal_spots[0, k]).all())}
    report = {
        "heliostat": row.heliostat_ids[int(row.heliostat_index[0])], "record": int(row.record_id[0]),
        "target": row.target[0], "integrator": integrator, "device": str(device),
        "rays_per_point": rays_per_point if integrator == "mc" else None, "resolution": resolution,
        "sun_azimuth_deg": math.degrees(float(row.sun_azimuth[0])),
        "sun_elevation_deg": math.degrees(float(row.sun_elevation[0])),
        "motor_steps": row.motor_steps[0].tolist(),
        "centroid_enu_m": centroid.tolist() if lit else None,
        "centroid_wgs84": {"latitude_deg": float(lla[0]), "longitude_deg": float(lla[1]),
                           "altitude_m": float(lla[2])} if lit else None,
        "centroid_local_m": flux.centroid_local()[0].tolist() if lit else None,
        "measured_spot_enu_m": spots,
        "measured_flux_png": row.flux_png[0],
        "total_power_w": float(flux.total_power_w[0]), "intercepted_power_w": float(flux.intercepted_power_w[0]),
        "mirror_area_m2": float(area[0].sum()),
        "mean_incidence_cosine": float((cosines * area[0]).sum() / area[0].sum()),
        "dni_w_m2": plant.sun.dni, "reflectivity": plant.sun.reflectivity, "sunshape": plant.sun.sunshape,
        "slope_error_mrad": plant.sun.slope_error * 1e3, "seconds": seconds,
        "concentrator_enu_m": c[0].tolist(), "mirror_normal_enu": kin_ops.mirror_normal(R)[0].tolist(),
    }
    return flux, report


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
    from matplotlib.figure import Figure

    from .io.report import save_figure
    from .plots import draw_flux, draw_measured_image

    camera = (measured or {}).get("measured_flux_png") if ax is None else None
    if ax is None:
        fig = Figure(figsize=(12.4, 5.2) if camera else (6.4, 5.2))
        axes = fig.subplots(1, 2 if camera else 1)
        ax = axes[-1] if camera else axes
        if camera:
            draw_measured_image(axes[0], flux, camera, measured=measured)
    fig = ax.figure
    title = title or f"flux on {flux.target.name}"
    if camera:
        fig.suptitle(title)
    draw_flux(ax, flux, "predicted" if camera else title, measured=measured)
    if path is not None:
        save_figure(fig, path)
    return fig


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
    from dataclasses import replace

    from .errors import HeliotwinError
    from .io.scenario import write_scenario
    from .workflows.calibrate import CalibrationSettings, calibration_checkpoint
    from .workflows.calibrate import calibrate as run

    settings = replace(config or CalibrationSettings(), **options)
    ck = None
    if checkpoint is not None:
        ck = calibration_checkpoint(settings, paint, checkpoint, scenario=scenario, device=_device(device),
                                    resume=resume)
    result = run(scenario, paint, settings, device=_device(device), progress=progress, checkpoint=ck)
    if output is not None:
        if result.scenario is None:
            raise HeliotwinError(f"no heliostat could be calibrated; {os.fspath(output)} not written")
        write_scenario(result.scenario, output)
    if ck is not None:
        ck.remove()
    return result.report, result.model, None if output is None else os.fspath(output)


def reconstruct(paint, heliostat: str, *, method: str = "generalising", train_records=None,
                train_first: int | None = None, control_points: str = "7x7", degree: int = 3,
                integrator: str = "conv", loss: str = "kl", steps: int | None = None,
                slope_error_mrad: float | None = None, background: float = 0.0, alignment: str = "focal-spot",
                evaluate_mc: bool = True, progress: bool = True, deflectometry=None, scenario=None,
                device: str = "auto", checkpoint=None, resume: bool = False):
    """Learn one heliostat's mirror surface from its centred flux images (``heliotwin reconstruct``'s defaults).

    ``method``: ``generalising`` (camera model, leave-one-out choices, acceptance; see
    :mod:`heliotwin.surfaces.generalise`) or ``legacy`` (KL loss, early stopping; the only one that takes
    ``loss``, ``integrator="mc"``, ``background``, ``deflectometry`` and ``evaluate_mc``). ``steps=None``: the
    method's default (legacy 200 optimiser steps, generalising a 300-step leave-one-out budget).
    ``slope_error_mrad=None`` fits the slope error on the training images (the CLI's ``auto``). ``device``,
    ``checkpoint`` and ``resume`` as in :func:`calibrate` (the model comes back on the CPU).

    Returns
    -------
    report : dict
        Per-record normalised L1 of ideal and learned surfaces on test images and IMP (see the glossary).
    model : heliotwin.surfaces.learning.LearnableSurface
        ``model.surfaces()`` is the learned NURBS surface.
    """
    from .errors import HeliotwinError
    from .io.scenario import load_scenario
    from .surfaces.learning import parse_grid

    if method not in ("generalising", "legacy"):
        raise HeliotwinError(f"reconstruct: method must be 'generalising' or 'legacy', got {method!r}")
    if method == "generalising":
        legacy_only = {"loss": loss != "kl", "integrator": integrator != "conv", "background": background > 0,
                       "deflectometry": deflectometry is not None}
        given = [k for k, v in legacy_only.items() if v]
        if given:
            raise HeliotwinError(f"reconstruct: {', '.join(given)} only apply to method='legacy'")
        from .surfaces.generalise import GeneraliseSettings, reconstruct_paint_generalising

        base = GeneraliseSettings()
        n = int(steps or base.steps)
        kw = dict(control_points=parse_grid(control_points), degree=(degree, degree), steps=n,
                  eval_every=min(base.eval_every, max(1, n // 2)))
        if slope_error_mrad is not None:
            kw["slope_grid"] = (slope_error_mrad * 1e-3,)
        settings = GeneraliseSettings(**kw)
        fit_args = dict(method="generalising", train_records=train_records, train_first=train_first,
                        settings=settings, alignment=alignment)
    else:
        from .surfaces.training import TrainSettings

        settings = TrainSettings(control_points=parse_grid(control_points), degree=(degree, degree),
                                 integrator=integrator, loss=loss, steps=int(steps or 200))
        fit_args = dict(train_records=train_records, train_first=train_first, settings=settings,
                        slope_error=None if slope_error_mrad is None else slope_error_mrad * 1e-3,
                        background=background, alignment=alignment, deflectometry=deflectometry,
                        start_from_deflectometry=False)
    ck = None
    if checkpoint is not None:
        from .surfaces.study import reconstruction_checkpoint

        ck = reconstruction_checkpoint(checkpoint, paint, heliostat, resume=resume, device=_device(device),
                                       inputs=[scenario, deflectometry], **fit_args)
    plant = load_scenario(scenario).plant if scenario is not None else None
    if method == "generalising":
        fit_args.pop("method")
        report, model, _ = reconstruct_paint_generalising(os.fspath(paint), heliostat, progress=progress,
                                                          plant=plant, device=_device(device), checkpoint=ck,
                                                          **fit_args)
        report["method"] = "generalising"
    else:
        from .surfaces.study import reconstruct_paint

        report, model, _, _ = reconstruct_paint(os.fspath(paint), heliostat, evaluate_mc=evaluate_mc,
                                                progress=progress, plant=plant, device=_device(device),
                                                checkpoint=ck, **fit_args)
    if ck is not None:
        ck.remove()
    return report, model
