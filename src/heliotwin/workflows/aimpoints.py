"""The ``aimpoints`` workflow: aim points under a peak-flux limit at one or several instants, stored in the scenario.

Per instant: equator aiming, the two published heuristics (aiming factor, image-size priority) and the
optimised aim points (:func:`heliotwin.optimise.aimpoints.optimise_aimpoints`, optionally sharded over local
gloo processes), all judged on the exact field model; the optimised ones, with their motor steps through the
plant's kinematics, become the scenario's ``/learned/aimpoints`` (:mod:`heliotwin.optimise.aimstate`).
"""
from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from ..atmosphere import Atmosphere
from ..devices import to_device
from ..errors import HeliotwinError
from ..io.scenario import Scenario, next_scenario, provenance_entry
from ..optimise.aimpoints import (
    AimResult,
    AimSettings,
    aiming_factor,
    calibrate_images,
    image_size_priority,
    load_target,
    optimise_aimpoints,
    run_aimpoints_sharded,
    target_mismatch,
    uniform_target,
)
from ..optimise.aimstate import KEY, aimpoint_state, check_peak_limit, instant_state
from ..optimise.fluxmap import combine, load_flux_limit, resample_min
from ..optimise.problem import FluxLimit
from ..optimise.robust import require_posterior, robust_aimpoints
from ..raytrace.field import reuse_mirror_samples
from .field import check_map_resolution

__all__ = ["AimpointSettings", "aimpoints", "day_summary", "MAX_DRAWS", "check_draws_memory", "limit_of"]


#: Most Monte-Carlo draws of ``--confidence``: 1e5 draws resolve an exceedance probability of 1e-4 to 30 %; more is
#: a typo (1e8 draws of 12 heliostats: about 430 GiB of draws, allocated before any check; ``MemoryError``).
MAX_DRAWS = 100_000
#: Bytes per draw and heliostat of the robust check (:func:`heliotwin.optimise.robust.draw_normal_errors`' [D, H, P]
#: and [D, H, 3] float64 draws, the errors [D, H, 3] and spot shifts [D, H, 2], and their temporaries).
DRAW_BYTES_PER_HELIOSTAT = 8 * 48


def check_draws_memory(draws: int, heliostats: int, memory_bytes: int | None = None) -> None:
    """Refuse ``--draws`` whose draws would not fit in half the machine's memory (``memory_bytes``: its physical
    memory, read from ``os.sysconf`` when not given), before anything is drawn; one line with the estimate."""
    if memory_bytes is None:
        try:
            memory_bytes = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (AttributeError, OSError, ValueError):
            return
    need = int(draws) * int(heliostats) * DRAW_BYTES_PER_HELIOSTAT
    if need > memory_bytes // 2:
        fit = max(0, (memory_bytes // 2) // max(1, int(heliostats) * DRAW_BYTES_PER_HELIOSTAT))
        raise HeliotwinError(f"--draws {draws}: {draws} draws of {heliostats} heliostats need about {need / 2**30:.1f} "
                             f"GiB, more than half of this machine's {memory_bytes / 2**30:.1f} GiB; use at most "
                             f"{fit} draws")


@dataclass
class AimpointSettings:
    """What :func:`aimpoints` runs (the ``aimpoints`` command's defaults).

    Attributes
    ----------
    peak_limit_w_m2 : float or None
        Limit on every receiver map cell [W/m^2] (None: the ``flux_limit`` map's alone).
    resolution : (int, int)
        Receiver map ``(rows, cols)``.
    iterations : int
        Image-model steps per round.
    target : str, optional
        ``"uniform"`` or a CSV/NPY target map (None: maximise power).
    field_gradient : bool
        Add the smooth field model's power gradient each round.
    baselines : bool
        Also run the aiming-factor and image-size-priority heuristics.
    nproc : int
        Local gloo processes to shard the heliostats over (1: none; CPU only).
    device : str, optional
        Where the models run (None: where the plant is).
    confidence : float, optional
        Hold the limit with this probability under the plant's stored pointing posterior
        (:func:`heliotwin.optimise.robust.robust_aimpoints`; the stored aim points are the robust ones).
    draws : int
        Monte-Carlo draws of the plant's pointing errors behind ``confidence``.
    mc : {"model", "exact"}
        Each draw's map from the image model corrected to the exact map, or from the exact model.
    seed : int
        Seed of the draws.
    warm_start : bool
        Each instant after the first starts from the previous instant's optimised aim points, multipliers and
        margin (``optimise_aimpoints(start_aim=...)``; with ``nproc > 1`` each instant's ranks start from it).
    exact_equator : bool
        With warm starts: make the exact equator check at every instant anyway (its peak and map in the report
        and the flux maps). Without it (and without baselines, a uniform target or a confidence, which need it)
        a warm instant's equator power is the corrected image model's estimate (``equator.estimated``).
    flux_limit : str or FluxLimit, optional
        An allowable-flux map: a ``.csv`` (HALOS layout) or ``.toml`` (``[receiver.flux_limit]``) file
        (:func:`heliotwin.optimise.fluxmap.load_flux_limit`) or a :class:`~heliotwin.optimise.problem.FluxLimit`
        (e.g. the one stored with the plant's aim points). With ``peak_limit_w_m2`` too, every cell is held under
        the lower of the two.
    """

    peak_limit_w_m2: float
    resolution: tuple[int, int] = (20, 48)
    iterations: int = 300
    target: str | None = None
    field_gradient: bool = False
    baselines: bool = True
    nproc: int = 1
    device: str | None = None
    confidence: float | None = None
    draws: int = 200
    mc: str = "model"
    seed: int = 0
    warm_start: bool = True
    exact_equator: bool = False
    flux_limit: object = None

    def __post_init__(self):
        self.check()  # refused when made, before any file is read or output staged

    def check(self) -> None:
        """One-line :class:`HeliotwinError` for settings no run can use (a caller may check before staging
        outputs; :func:`aimpoints` checks again)."""
        if self.peak_limit_w_m2 is None and self.flux_limit is None:
            raise HeliotwinError("no flux limit: give --peak-limit W/m2 or --flux-limit FILE (.csv or .toml)")
        if self.peak_limit_w_m2 is not None:
            check_peak_limit(self.peak_limit_w_m2)
        if self.flux_limit is not None and not isinstance(self.flux_limit, (str, os.PathLike, FluxLimit)):
            raise HeliotwinError(f"--flux-limit: expected a .csv or .toml file, got {self.flux_limit!r}")
        if self.flux_limit is not None and self.confidence is not None:
            raise HeliotwinError("--confidence: holds one peak limit (--peak-limit), not an allowable-flux map "
                                 "(--flux-limit)")
        check_map_resolution(self.resolution)
        for name, v in (("--iterations", self.iterations), ("--nproc", self.nproc)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise HeliotwinError(f"{name}: expected a positive integer, got {v!r}")
        c = self.confidence
        if c is not None and (isinstance(c, bool) or not isinstance(c, (int, float)) or not 0.0 < c < 1.0):
            raise HeliotwinError(f"--confidence: expected a probability strictly between 0 and 1, got {c!r}")
        if isinstance(self.draws, bool) or not isinstance(self.draws, int) or not 20 <= self.draws <= MAX_DRAWS:
            raise HeliotwinError(f"--draws: expected an integer in 20..{MAX_DRAWS}, got {self.draws!r}")
        if self.mc not in ("model", "exact"):
            raise HeliotwinError(f"--mc: expected 'model' or 'exact', got {self.mc!r}")
        if c is not None and (self.nproc > 1 or self.target is not None):
            raise HeliotwinError("--confidence: maximises power in one process (not with --nproc or --target)")
        if self.nproc > 1 and str(self.device or "cpu").startswith("cuda"):
            raise HeliotwinError("--nproc: the local process group is gloo on CPU; use --device cpu with --nproc")


def limit_of(settings: AimpointSettings) -> FluxLimit:
    """The limit per cell of ``settings`` on its resolution: the peak limit, the ``flux_limit`` map (a file is read,
    a stored map on another grid resampled conservatively), or the lower of the two per cell."""
    fl = settings.flux_limit
    if isinstance(fl, (str, os.PathLike)):
        fl = load_flux_limit(fl, settings.resolution)
    elif isinstance(fl, FluxLimit) and tuple(fl.cells.shape) != tuple(settings.resolution):
        fl = FluxLimit(torch.as_tensor(resample_min(fl.cells.numpy(), settings.resolution)), fl.source)
    return combine(settings.peak_limit_w_m2, fl, settings.resolution)


def _limit_entry(limit: FluxLimit, flux) -> dict:
    """How a map sits under the limit: ``peak_vs_limit`` (the largest flux / limit; peak / limit for one peak
    limit), ``max_utilisation`` (the same), ``binding_cells`` (within 1 % of their limit), ``limit_met``."""
    util = limit.summary(flux)
    return {"limit_met": limit.held(flux), "violation": max(0.0, util["max_utilisation"] - 1.0), **util}


@reuse_mirror_samples()  # every exact check below samples the same mirror surfaces
def _instant_time(label) -> float | None:
    """The POSIX time [s] of an instant's label when it is a UTC time (``--time``, ``--day``), else None (an
    instant given by sun angles has no time: the pointing posterior is then the state's own)."""
    try:
        stamp = pd.Timestamp(str(label))
    except (ValueError, TypeError, OverflowError):
        return None
    if pd.isna(stamp):
        return None
    stamp = stamp.tz_localize("UTC") if stamp.tzinfo is None else stamp.tz_convert("UTC")
    return float(stamp.timestamp())


def _instant(plant, sun, atm, settings: AimpointSettings, learned=None, path="", warm: AimResult | None = None,
             label: str | None = None):
    """Equator, the two heuristics and the optimised aim points at one sun: (report entry, optimised, equator,
    deterministic optimised).

    With ``settings.confidence`` the optimised aim points are the robust ones and the entry has ``robust``
    (:func:`heliotwin.optimise.robust.robust_aimpoints`' report). ``warm``: the previous instant's deterministic
    optimised result to start from; without the exact equator check (see :class:`AimpointSettings`) the
    equator entry holds only the image model's estimate of its power."""
    resolution = settings.resolution
    limit = limit_of(settings)
    t0 = time.perf_counter()
    need_equator = (warm is None or settings.exact_equator or settings.baselines or settings.target == "uniform"
                    or settings.confidence is not None)
    model = eq_field = None
    if need_equator:
        model, eq_field = calibrate_images(plant, sun, atm, resolution)
        equator = AimResult(eq_field.aim, float(eq_field.power_w.sum()), float(eq_field.flux.max()), eq_field.flux)
        equator.seconds = time.perf_counter() - t0
    target = None
    if settings.target == "uniform":
        target = uniform_target(eq_field.flux)
    elif settings.target is not None:
        target = load_target(settings.target, resolution)
    knobs = AimSettings(resolution=resolution, iterations=settings.iterations, field_gradient=settings.field_gradient)
    nproc = min(settings.nproc, len(plant.field.ids))  # at most one process per heliostat
    start = {} if warm is None else {"start_aim": warm.aim, "start_multipliers": warm.multipliers,
                                     "start_margin": warm.parameter, "start_field": warm.exact}
    if nproc > 1:  # the ranks calibrate their shards' image models on this equator check (or warm-start)
        best = run_aimpoints_sharded(plant, sun, limit, nproc, knobs, equator=eq_field, atmosphere=atm,
                                     target=target, **start)
    else:
        best = optimise_aimpoints(plant, sun, limit, knobs, atmosphere=atm, target=target, equator=eq_field,
                                  model=model, **start)
    if not need_equator:  # equator aiming's power as the optimiser's corrected image model estimated it
        equator = AimResult(None, float(best.reference_power_w), float("nan"), None)
    deterministic = best
    robust = None
    if settings.confidence is not None:
        peak = float(settings.peak_limit_w_m2)  # --confidence holds one peak limit (checked)
        best, robust = robust_aimpoints(plant, sun, peak, settings.confidence, learned, knobs, atmosphere=atm,
                                        equator=eq_field, model=model, deterministic=best, draws=settings.draws,
                                        seed=settings.seed, mc=settings.mc, path=path, when_s=_instant_time(label))
    baselines = {}
    if settings.baselines:
        baselines["aiming_factor"] = aiming_factor(plant, sun, limit, atmosphere=atm, resolution=resolution,
                                                   model=model)
        baselines["image_size_priority"] = image_size_priority(plant, sun, limit, atmosphere=atm,
                                                               resolution=resolution, model=model)

    def entry(r):
        if r.flux is None:  # the estimated equator: its power only
            return {"power_w": r.power_w, "power_vs_equator": 1.0, "estimated": True}
        e = {"power_w": r.power_w, "peak_flux_w_m2": r.peak_flux_w_m2, **_limit_entry(limit, r.flux),
             "power_vs_equator": r.power_w / equator.power_w, "seconds": r.seconds}
        if target is not None:
            e["target_mismatch"] = target_mismatch(r.flux, target)
        return e

    e, n, u = (float(v) for v in sun)
    rep = {"sun_direction_enu": sun.tolist(), "sun_elevation_deg": math.degrees(math.asin(u)),
           "sun_azimuth_deg": math.degrees(math.atan2(e, -n)),  # PAINT convention: 0 = south, +90 = east
           "equator": entry(equator)}
    for name, r in baselines.items():
        rep[name] = {**entry(r), "k": r.parameter}
    rep["optimised"] = {**entry(best), "iterations": best.iterations, "rounds": len(best.history),
                        "exact_checks": best.exact_checks, "warm_start": warm is not None,
                        "peak_vs_limit": limit.ratio(best.flux),
                        "final_margin": best.parameter, "standby_heliostats": int(best.standby),
                        "note": _note(best, equator, limit), "history": best.history}
    for name, r in baselines.items():
        rep["optimised"][f"power_vs_{name}"] = best.power_w / r.power_w
    if robust is not None:
        rep["robust"] = robust
    rep["seconds"] = time.perf_counter() - t0
    return rep, best, equator, deterministic


def _note(best: AimResult, equator: AimResult, limit: FluxLimit) -> str:
    """One sentence on what the optimised aim points cost, for the report and the summary line."""
    if not limit.held(best.flux):
        return "the limit is not held even with every heliostat on standby"
    if best.standby:
        return (f"the limit cannot be held with every heliostat's light on the receiver: {best.standby} heliostats "
                f"on standby, {best.power_w / equator.power_w:.3f} of equator aiming's power")
    if best.power_w < 0.99 * equator.power_w:
        return (f"the limit is held by spilling light: {best.power_w / equator.power_w:.3f} of equator aiming's "
                "power")
    return "the limit is held at full power"


def day_summary(entries: list[dict], limit: float, seconds: float) -> dict:
    """Summary of the instants' report entries (as :func:`aimpoints` writes them).

    ``instants``, ``warm_starts``, ``limit_met_at_all``, ``worst_peak_vs_limit`` [-], ``exact_checks`` (the
    optimiser's), ``equator_checks`` (exact evaluations of equator aiming) and ``adam_steps`` (all instants),
    ``seconds`` (whole run) and ``seconds_per_instant`` (mean, max) [s]; when the
    instants' labels are UTC times on a regular grid of two or more (``--day``), also ``step_s`` [s] and the
    energy over the day, each instant standing for one step: ``energy_kwh`` of the optimised aim points,
    ``equator_energy_kwh`` (estimated where the instant's equator power is) and their ratio.
    """
    opt = [e["optimised"] for e in entries]
    out = {"instants": len(entries), "warm_starts": sum(bool(o.get("warm_start")) for o in opt),
           "limit_met_at_all": all(o["limit_met"] for o in opt),
           "worst_peak_vs_limit": max(o.get("peak_vs_limit", o["peak_flux_w_m2"] / limit) for o in opt),
           "exact_checks": sum(int(o.get("exact_checks", 0)) for o in opt),
           "equator_checks": sum(not e["equator"].get("estimated", False) for e in entries),
           "adam_steps": sum(int(o.get("iterations", 0)) for o in opt), "seconds": seconds,
           "seconds_per_instant": {"mean": sum(e["seconds"] for e in entries) / len(entries),
                                   "max": max(e["seconds"] for e in entries)}}
    try:
        stamps = pd.DatetimeIndex([pd.Timestamp(e["instant"]) for e in entries])
    except (ValueError, TypeError):
        return out
    gaps = np.diff(np.asarray((stamps - stamps[0]).total_seconds(), dtype=float))  # [s], whatever the unit
    if gaps.size and (gaps > 0).all() and np.allclose(gaps, gaps.min()):
        step = float(gaps.min())
        energy = sum(o["power_w"] for o in opt) * step / 3.6e6
        equator = sum(e["equator"]["power_w"] for e in entries) * step / 3.6e6
        out.update({"step_s": step, "energy_kwh": energy, "equator_energy_kwh": equator,
                    "energy_vs_equator": energy / equator if equator > 0 else float("nan"),
                    "equator_estimated_at": sum(bool(e["equator"].get("estimated")) for e in entries)})
    return out


def aimpoints(scenario: Scenario, instants: list[tuple[str, torch.Tensor]], settings: AimpointSettings, *,
              on_instant: Callable | None = None) -> tuple[Scenario, dict]:
    """Aim points under ``settings.peak_limit_w_m2`` at every instant; the scenario with them learned.

    Parameters
    ----------
    scenario : Scenario
        Plant (its kinematics give the motor steps) and atmosphere (``extras``).
    instants : list of (str, torch.Tensor [3])
        Label and unit sun direction (ENU) of every instant, e.g. from
        :func:`heliotwin.workflows.field.sun_instants`.
    settings : AimpointSettings
    on_instant : callable, optional
        ``on_instant(i, label, entry, optimised, equator)`` after each instant (progress lines, flux maps):
        ``entry`` is the instant's report, ``optimised`` and ``equator`` the :class:`AimResult` s.

    Returns
    -------
    scenario : Scenario
        In memory (:func:`heliotwin.io.scenario.write_scenario` writes it): the plant on the CPU, the
        learned state with ``/learned/aimpoints`` (:func:`heliotwin.optimise.aimstate.aimpoint_state`), one
        more provenance step.
    report : dict
        ``peak_limit_w_m2``, ``resolution``, ``target``, ``nproc``, ``instants`` (per instant: sun elevation
        and azimuth, equator, baselines, optimised with ``peak_vs_limit``, ``exact_checks``, ``warm_start`` and
        ``motor_steps_reachable``, ``seconds``), the first instant's entries at the top, ``seconds`` and
        ``summary`` (:func:`day_summary`).
    """
    settings.check()
    if settings.confidence is not None:
        require_posterior(scenario.learned, scenario.path or "")  # before any optimisation
        check_draws_memory(settings.draws, int(scenario.plant.field.kinematics.position.shape[0]))
    flux_limit = limit_of(settings)  # a file read once, before any optimisation
    settings = dataclasses.replace(settings, flux_limit=None if settings.flux_limit is None else flux_limit)
    # the report's and the stored peak limit: the given one, or no cell's limit above it (a map's highest)
    limit = float(flux_limit.cells.max())
    t_all = time.perf_counter()
    plant = scenario.plant if settings.device is None else to_device(scenario.plant, settings.device)
    atm = Atmosphere.from_extras(scenario.extras)
    target = settings.target or "max-power"
    report = {"scenario": os.path.abspath(scenario.path) if scenario.path else None, "peak_limit_w_m2": limit,
              "resolution": {"cols": settings.resolution[1], "rows": settings.resolution[0]},
              "target": target, "nproc": settings.nproc, "confidence": settings.confidence, "instants": []}
    if settings.flux_limit is not None:
        report["flux_limit"] = {"source": flux_limit.source, "min_w_m2": flux_limit.minimum, "max_w_m2": limit,
                                "uniform": flux_limit.is_uniform, "binding_within": 0.01}
    stored, previous = {}, None
    warm = settings.warm_start
    for i, (label, sun) in enumerate(instants):
        rep, best, equator, previous = _instant(plant, sun, atm, settings, scenario.learned, scenario.path or "",
                                                previous if warm else None, label=label)
        stored[f"i{i:03d}"] = instant_state(plant, label, best.aim, sun, power_w=best.power_w,
                                            peak_flux_w_m2=best.peak_flux_w_m2)
        rep["optimised"]["motor_steps_reachable"] = int(stored[f"i{i:03d}"]["reachable"].sum())
        report["instants"].append({"instant": label, **rep})
        if on_instant is not None:
            on_instant(i, label, rep, best, equator)
    report.update({k: v for k, v in report["instants"][0].items() if k != "instant"})  # first instant at top
    report["seconds"] = time.perf_counter() - t_all
    report["summary"] = day_summary(report["instants"], limit, report["seconds"])
    learned = {**scenario.learned, KEY: aimpoint_state(
        stored, peak_limit_w_m2=limit, target=target,
        flux_limit=None if settings.flux_limit is None else (flux_limit.cells, flux_limit.source))}
    step = provenance_entry("aimpoints", peak_limit_w_m2=limit, instants=[lbl for lbl, _ in instants],
                            iterations=settings.iterations, target=target,
                            power_w=[s["power_w"] for s in stored.values()],
                            peak_flux_w_m2=[s["peak_flux_w_m2"] for s in stored.values()])
    return next_scenario(scenario, to_device(plant, "cpu"), learned=learned, step=step), report
