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
:func:`reconstruct_plant` (the mirror surfaces of every heliostat with images),
:func:`to_device` (move plant pieces between CPU and GPU);
the whole field: :func:`field_efficiency` (one sun), :func:`optimise_aimpoints` (aim points under a peak limit),
:func:`plot_receiver_flux` (maps on one scale), :func:`export_plant` (SolarPILOT / SolTrace),
:func:`read_weather` (a DNI time series); in silico: :func:`simulate` (a PAINT folder and its truth),
:func:`score` (a learned plant against the truth).
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
from .io.weather import read_dni_series
from .workflows.aimpoints import AimpointSettings
from .workflows.aimpoints import aimpoints as aimpoints_workflow
from .workflows.calibrate import CalibrationSettings, calibration_checkpoint
from .workflows.calibrate import calibrate as calibrate_kinematics
from .workflows.field import FieldRunSettings, sun_direction_at, sun_instants
from .workflows.field import field as field_workflow
from .workflows.reconstruct import ReconstructionSettings, reconstruction_checkpoint
from .workflows.reconstruct import reconstruct as reconstruct_surface
from .workflows.reconstruct_plant import plant_reconstruction_checkpoint
from .workflows.reconstruct_plant import reconstruct_plant as reconstruct_surfaces
from .workflows.score import score as score_workflow
from .workflows.show import export_plant as export_workflow
from .workflows.simulate import SimulationSettings
from .workflows.simulate import simulate as simulate_workflow
from .workflows.trace import TraceSettings
from .workflows.trace import trace_record as trace_workflow
from .workflows.update import UpdateSettings
from .workflows.update import update as update_workflow
from .workflows.year import YearSettings
from .workflows.year import plant_year as year_workflow

__all__ = ["load", "field", "trace_record", "plot_flux", "calibrate", "reconstruct", "reconstruct_plant",
           "ReconstructionSettings",
           "to_device", "field_efficiency", "FieldRunSettings", "optimise_aimpoints", "AimpointSettings",
           "plot_receiver_flux", "export_plant", "read_weather", "update",
           "simulate", "score", "SimulationSettings", "year", "YearSettings"]


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
        Kinematics ``position`` [H, 3] ENU [m], facets, surfaces, targets, site and sun.

    Examples
    --------
    A scenario file written from the demo plant, read back whole or for one heliostat:

    >>> import os, tempfile
    >>> from heliotwin.field.demo import demo_plant
    >>> from heliotwin.io.scenario import save_scenario
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = save_scenario(demo_plant(3), os.path.join(folder.name, "plant.h5"))
    >>> field(path).field.ids
    ['AK29', 'AM42', 'AQ49']
    >>> tuple(field(path, heliostats=["AM42"]).field.kinematics.position.shape)
    (1, 3)
    >>> folder.cleanup()
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
    tables, flux images, networks and containers of them; shapes and dtypes kept.

    >>> import torch
    >>> moved = to_device({"flux": torch.zeros(2, 3), "ids": ["AM43"]}, "cpu")
    >>> moved["flux"].device.type, tuple(moved["flux"].shape), moved["flux"].dtype, moved["ids"]
    ('cpu', (2, 3), torch.float32, ['AM43'])
    """
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
        Batch of one, bitmap [1, resolution, resolution] [W/m^2], on the CPU.
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


def year(scenario, weather=None, settings: YearSettings | None = None, *, output=None, **options):
    """The plant's year heliostat by heliostat (``heliotwin year``'s defaults).

    Parameters
    ----------
    scenario : str, os.PathLike or heliotwin.io.scenario.Scenario
    weather : str, os.PathLike or heliotwin.io.weather.DniSeries, optional
        A weather file (TMY3, TMY2, EPW, PSM3, SAM CSV, PAINT's weather CSV, ``time,dni`` CSV) or a series read by
        :func:`read_weather`; default: pvlib's clear sky at the plant's site.
    settings : heliotwin.workflows.year.YearSettings, optional
        One setting per ``heliotwin year`` flag (year, aim, draws, seed, check_hours, nproc, ...).
    output : str or os.PathLike, optional
        Write the plant with the year stored (``/learned/year``) there.
    **options
        Any of those settings by keyword (e.g. ``aim="scenario"``).

    Returns
    -------
    heliotwin.workflows.year.YearResult
        ``report`` (the JSON), ``rows`` (one dict per heliostat: the CSV), ``scenario`` (the plant with the
        year), ``tables`` (the per-heliostat tables over the sun positions).
    """
    series = read_dni_series(os.fspath(weather)) if isinstance(weather, (str, os.PathLike)) else weather
    result = year_workflow(_scenario(scenario), series, replace(settings or YearSettings(), **options))
    if output is not None:
        write_scenario(result.scenario, output)
    return result


def reconstruct(paint, heliostat: str, settings: ReconstructionSettings | None = None, *, scenario=None,
                checkpoint=None, resume: bool = False, progress: bool = True):
    """Learn one heliostat's mirror surface from its centred flux images (``heliotwin reconstruct``).

    Parameters
    ----------
    paint : str or os.PathLike
        PAINT download folder.
    heliostat : str
    settings : heliotwin.workflows.reconstruct.ReconstructionSettings, optional
        The learner's options; the defaults are the command line's (a test checks that they agree).
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


def reconstruct_plant(paint, heliostats="all", settings: ReconstructionSettings | None = None, *, scenario=None,
                      nproc: int = 1, output=None, checkpoint=None, resume: bool = False, progress: bool = True):
    """Learn the mirror surface of every selected heliostat with enough centred flux images (``heliotwin
    reconstruct --heliostats``).

    Parameters
    ----------
    paint : str or os.PathLike
        PAINT download folder.
    heliostats : "all" or list of str
        The selection; heliostats without enough images are skipped (listed in the report with the reason).
    settings : heliotwin.workflows.reconstruct.ReconstructionSettings, optional
        Per heliostat, as for :func:`reconstruct`.
    scenario : str or os.PathLike, optional
        Start from this scenario's plant (e.g. a calibrated one).
    nproc : int
        Worker processes (CPU).
    output : str or os.PathLike, optional
        Write the scenario with every learned surface there.
    checkpoint, resume
        A checkpoint *folder* (one file per finished heliostat); ``resume=True`` skips the heliostats it holds.
        Removed after a finished run.
    progress : bool
        Progress per heliostat.

    Returns
    -------
    report : dict
        ``heliostats`` (a row per heliostat: status, train/test median L1 ideal vs learned, accepted, seconds)
        and ``summary`` (:func:`heliotwin.workflows.reconstruct_plant.reconstruct_plant`).
    scenario : heliotwin.io.scenario.Scenario
        The plant with every learned surface.
    """
    s = settings or ReconstructionSettings()
    ck = None if checkpoint is None else plant_reconstruction_checkpoint(checkpoint, paint, s, scenario_path=scenario,
                                                                         resume=resume)
    previous = load_scenario(scenario) if scenario is not None else None
    new, report = reconstruct_surfaces(previous, paint, heliostats, s, nproc=nproc, checkpoint=ck, progress=progress)
    if output is not None:
        write_scenario(new, output)
    if ck is not None:
        ck.remove()
    return report, new


# ------------------------------------------------------------------------------------ the whole field
def _scenario(source):
    """A :class:`~heliotwin.io.scenario.Scenario` from a path (``.h5``) or as given."""
    return load_scenario(os.fspath(source)) if isinstance(source, (str, os.PathLike)) else source


def field_efficiency(scenario, *, time_utc: str | None = None, sun_azimuth_deg: float | None = None,
                     sun_elevation_deg: float | None = None, settings: FieldRunSettings | None = None):
    """The whole field at one sun (:func:`heliotwin.workflows.field.field`, ``heliotwin field``'s defaults).

    Parameters
    ----------
    scenario : Scenario or path
        E.g. ``heliotwin scenario from-layout``'s or ``heliotwin demo``'s ``plant.h5``.
    time_utc : str, optional
        ISO UTC time [UTC] (sun from pvlib at the plant's site); else ``sun_azimuth_deg`` [deg] and
        ``sun_elevation_deg`` [deg] (PAINT convention: 0 = south, +90 = east).
    settings : FieldRunSettings, optional
        Resolution, integrator, occlusion model, aiming (``"equator"``/``"scenario"``), DNI.

    Returns
    -------
    report : dict
        Field averages, losses per factor, receiver power [W], peak [W/m^2] and the map
        (``receiver.flux_map_w_m2``, ``receiver.flux_map_extent_m``).
    result : heliotwin.raytrace.field.FieldResult
        Per-heliostat factors [H] and the map ``flux`` [rows, cols] [W/m^2];
        ``api.plot_receiver_flux({"equator": result.flux}, plant.targets["receiver"])`` draws it.
    """
    sc = _scenario(scenario)
    sun = sun_direction_at(sc.plant, time_utc=time_utc, azimuth_deg=sun_azimuth_deg, elevation_deg=sun_elevation_deg)
    return field_workflow(sc, sun, settings)


def optimise_aimpoints(scenario, peak_limit_w_m2: float, *, time_utc: str | None = None,
                       sun_azimuth_deg: float | None = None, sun_elevation_deg: float | None = None,
                       settings: AimpointSettings | None = None, output=None):
    """Aim points under a peak-flux limit at one or several instants (:func:`heliotwin.workflows.aimpoints.
    aimpoints`, ``heliotwin aimpoints``'s defaults).

    Parameters
    ----------
    scenario : Scenario or path
    peak_limit_w_m2 : float
        Limit on every receiver map cell [W/m^2].
    time_utc : str, optional
        One or several comma-separated ISO UTC times; else the sun angles [deg] (PAINT convention).
    settings : AimpointSettings, optional
        Everything but the limit (its ``peak_limit_w_m2`` is replaced by the argument).
    output : path, optional
        Write the new scenario here (with ``/learned/aimpoints``).

    Returns
    -------
    scenario : Scenario
        The plant with the aim points learned (``field_efficiency(..., settings=FieldRunSettings(aim="scenario"))``
        traces them).
    report : dict
        Per instant: equator aiming, the baselines and the optimised aim points (power [W], peak [W/m^2]).
    maps : list of dict
        Per instant ``{"equator aiming": flux, "optimised aim points": flux}`` [rows, cols] [W/m^2], ready for
        :func:`plot_receiver_flux` with the limit.
    """
    sc = _scenario(scenario)
    s = replace(settings, peak_limit_w_m2=float(peak_limit_w_m2)) if settings else AimpointSettings(
        peak_limit_w_m2=float(peak_limit_w_m2))
    instants = sun_instants(sc.plant, times=time_utc, azimuth_deg=sun_azimuth_deg, elevation_deg=sun_elevation_deg)
    maps = []
    aimed, report = aimpoints_workflow(sc, instants, s, on_instant=lambda i, label, rep, best, eq: maps.append(
        {"equator aiming": eq.flux.cpu(), "optimised aim points": best.flux.cpu()}))
    if output is not None:
        write_scenario(aimed, output)
    return aimed, report, maps


def plot_receiver_flux(maps: dict, receiver, path=None, *, limit_w_m2: float | None = None, title: str | None = None):
    """Receiver flux maps side by side on one colour scale [kW/m^2], axes in metres (and degrees around a
    cylinder), the limit as a dashed contour (:func:`heliotwin.plots.plot_receiver_flux`); returns the Figure."""
    return plots.plot_receiver_flux(maps, receiver, path, limit_w_m2=limit_w_m2, title=title)


def export_plant(scenario, *, solarpilot=None, solarpilot_config=None, soltrace=None, time_utc: str | None = None,
                 sun_azimuth_deg: float | None = None, sun_elevation_deg: float | None = None,
                 aim: str = "auto") -> dict:
    """The plant for SolarPILOT (layout table + the TOML ``heliotwin scenario from-layout`` reads back) and/or
    SolTrace (``.stinput``, mirrors facing the sun given by ``time_utc`` or the angles), as ``heliotwin scenario
    export`` (:func:`heliotwin.workflows.show.export_plant`). ``time_utc`` is an ISO time [UTC];
    ``sun_azimuth_deg`` [deg] (0 = south, +90 = east) and ``sun_elevation_deg`` [deg] give the sun instead.
    ``aim``: ``"auto"`` (the stored optimised aim points when the plant has them, else equator aiming),
    ``"optimised"`` or ``"equator"``. Returns what was written (``aim_points`` says which)."""
    sc = _scenario(scenario)
    timed = time_utc is not None or sun_azimuth_deg is not None
    sun = sun_direction_at(sc.plant, time_utc=time_utc, azimuth_deg=sun_azimuth_deg,
                           elevation_deg=sun_elevation_deg) if timed else None
    pair = None
    if solarpilot is not None:
        pair = (solarpilot, solarpilot_config or os.path.splitext(os.fspath(solarpilot))[0] + ".toml")
    return export_workflow(sc, solarpilot=pair, soltrace=soltrace, sun=sun, aim=aim)


def read_weather(path):
    """A DNI time series (SAM/typical-year file, PAINT's calibration weather, or a time + dni CSV;
    :func:`heliotwin.io.weather.read_dni_series`): ``.times`` (UTC), ``.dni`` [W/m^2], ``.step_hours``."""
    return read_dni_series(os.fspath(path))


def simulate(out, settings: SimulationSettings | None = None, *, truth=None, **options):
    """An in-silico plant (``heliotwin simulate``'s defaults): a PAINT folder at ``out`` that every command reads,
    and its truth (:func:`heliotwin.workflows.simulate.simulate`).

    Parameters
    ----------
    out : str or os.PathLike
        The PAINT folder to write (absent or empty).
    settings : heliotwin.workflows.simulate.SimulationSettings, optional
        Heliostats, seed, years, noise [mrad], step rate [1/year], ... (``**options`` override its fields).
    truth : str or os.PathLike, optional
        Also write the truth scenario there.

    Returns
    -------
    report : dict
        Counts (heliostats, records, steps) and times [s].
    truth : heliotwin.io.scenario.Scenario
        The true plant (its kinematics as ``/learned/calibration``).
    """
    sc, report = simulate_workflow(replace(settings or SimulationSettings(), **options), os.fspath(out))
    if truth is not None:
        write_scenario(sc, truth)
    return report, sc


def score(truth, scenario, *, suns: int = 16, seed: int = 0, flux: bool = True) -> dict:
    """A learned plant against the truth (``heliotwin score``): pointing error [mrad] at ``suns`` new sun
    positions (median, p95, per heliostat), surface normal error [mrad] and the receiver map difference."""
    return score_workflow(_scenario(truth), _scenario(scenario), suns=suns, seed=seed, flux=flux)[1]
