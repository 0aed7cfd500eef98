"""The ``year`` workflow: the plant's year heliostat by heliostat (``heliotwin year``, :func:`heliotwin.api.year`).

For every heliostat: its annual energy on the receiver [MWh], its DNI-weighted efficiency and factors, and the
energy it loses to its own tracking error and to its own mirror, with intervals (method:
:mod:`heliotwin.raytrace.annual`); the field's annual energy (the rows' sum), monthly totals, the DNI on the
mirrors while the sun is up and the share of the file's DNI energy that falls while the sun is below the
horizon (a time-convention check: <= 0.5 % for a correct reading). The result is stored in the plant as
``learned["year"]`` (the layout is in :func:`year_state`) and reported as JSON and one CSV row per heliostat.

Instants: the weather file's rows placed in the year (:func:`heliotwin.io.weather.weather_for_year`), or
without a file pvlib's Ineichen clear sky at the site every ``every`` (default 1 h). Aiming: ``equator``
(SolarPILOT's simple aiming), ``scenario`` (the plant's stored ``/learned/aimpoints``) or ``optimised`` (aim
points optimised under the plant's peak-flux limit at each *table node*, warm-started node to node along the
grid; the tables then interpolate the optimised field between nodes, and the limit is held at the plant's
design DNI at each node, not at each hour's DNI).

``check_hours`` N > 0: the field model is also evaluated directly at N daylight hours drawn (seeded) from the
year, and each heliostat's energy over those hours by interpolation is compared with the direct one: median
and p95 of the per-heliostat relative error and the field total's, stored under ``interpolation``.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import torch
import torch.distributed as dist

from ..atmosphere import Atmosphere
from ..calibrate.twinstate import nominal_kinematics
from ..calibrate.uncertainty import posterior_draws
from ..devices import resolve_device, to_device
from ..distributed import run_spawned
from ..errors import HeliotwinError, InputFileError
from ..io import weather as _weather
from ..io.scenario import next_scenario, provenance_entry
from ..optimise.aimpoints import optimise_aimpoints
from ..optimise.aimstate import stored_peak_limit
from ..progress import Progress
from ..raytrace import annual as A
from ..raytrace.field import FACTORS, equator_aim_points, field_optics, reuse_mirror_samples
from ..raytrace.yearly import clear_sky_dni
from ..sun import direction_from_paint_angles, solar_position

__all__ = ["YearSettings", "YearResult", "plant_year", "year_state", "csv_rows", "AIMS", "KEY"]

#: The ``Scenario.learned`` key of the stored year.
KEY = "year"
AIMS = ("equator", "scenario", "optimised")
#: The interval of the tracking loss: 5 and 95 % quantiles over the posterior draws.
LEVELS = (0.05, 0.95)
VERSION = 1


@dataclass
class YearSettings:
    """What :func:`plant_year` computes.

    Attributes
    ----------
    year : int or None
        Calendar year (default: the weather file's middle year; 2023 without a file).
    aim : {"equator", "scenario", "optimised"}
    every : str
        Step of the clear-sky instants (no weather file).
    grid : heliotwin.raytrace.annual.TableGrid
        The tables' sun positions.
    draws : int
        Posterior draws of the tracking loss's interval (0: the point value twice).
    seed : int
        Seed of the draws and of the checked hours.
    check_hours : int
        Hours for the direct check of the interpolation (0: none).
    peak_limit_w_m2 : float or None
        ``aim="optimised"``: the limit (default: the plant's stored one).
    device : str or None
        Where the field model runs (``"auto"``: CUDA when present).
    nproc : int or None
        Worker processes the table nodes are dealt over (None: the threads this command may use, when the
        work pays for their start; :func:`_processes`).
    progress : bool
        Progress bars / lines (:mod:`heliotwin.progress`).
    """

    year: int | None = None
    aim: str = "equator"
    every: str = "1h"
    grid: A.TableGrid = field(default_factory=lambda: A.DEFAULT_GRID)
    draws: int = 16
    seed: int = 0
    check_hours: int = 0
    peak_limit_w_m2: float | None = None
    device: str | None = None
    nproc: int | None = None
    progress: bool = False

    def check(self) -> None:
        """One-line errors for settings out of range (before any work)."""
        if self.year is not None and (isinstance(self.year, bool) or not isinstance(self.year, int)
                                      or not 1900 <= self.year <= 2100):
            raise HeliotwinError(f"--year: expected a year in 1900..2100, got {self.year!r}")
        if self.aim not in AIMS:
            raise HeliotwinError(f"--aim: expected one of {', '.join(AIMS)}, got {self.aim!r}")
        if not 0 <= int(self.draws) <= 1000:
            raise HeliotwinError(f"--draws: expected 0..1000, got {self.draws}")
        if self.nproc is not None and not 1 <= int(self.nproc) <= 256:
            raise HeliotwinError(f"--nproc: expected 1..256, got {self.nproc}")
        if not 0 <= int(self.check_hours) <= 100_000:
            raise HeliotwinError(f"--check-hours: expected 0..100000, got {self.check_hours}")
        step = pd.Timedelta(self.every)
        if not pd.Timedelta("1min") <= step <= pd.Timedelta("12h"):
            raise HeliotwinError(f"--every {self.every}: expected 1min..12h")


@dataclass
class YearResult:
    """``scenario``: the plant with ``learned["year"]`` (not written); ``report``: the JSON report; ``rows``: one
    dict per heliostat (the CSV); ``tables``: the per-heliostat tables (tensors, for scripts)."""

    scenario: object
    report: dict
    rows: list
    tables: dict


# ------------------------------------------------------------------------------------------------- instants
def _instants(scenario, weather, settings: YearSettings) -> dict:
    """UTC instants with their DNI [W/m^2] and interval [h] and what the weather says about itself."""
    s = scenario.plant.site
    if weather is not None:
        year = settings.year if settings.year is not None else int(weather.times.year[len(weather.times) // 2])
        wy = _weather.weather_for_year(weather, int(year))
        # a series built in code may state no convention (DniSeries.convention defaults to "")
        convention = wy.convention or f"{weather.kind}: times as the reader converts them to UTC instants"
        info = {"file": os.path.abspath(weather.path), "kind": str(weather.kind), "annual": bool(wy.annual),
                "step_hours": float(wy.step_hours), "coverage_fraction": float(wy.coverage.get("fraction_of_year",
                                                                                              float("nan"))),
                "assumptions": "; ".join(wy.assumptions)}
        km = _weather.site_offset_km(weather, s)  # None when the file names no site
        if km is not None:
            info["site_offset_km"] = float(km)
        return {"year": int(year), "times": wy.times, "dni": np.asarray(wy.dni, dtype=np.float64),
                "hours": np.asarray(wy.hours, dtype=np.float64), "annual": bool(wy.annual), "weather": info,
                "convention": str(convention), "coverage": wy.coverage, "assumptions": list(wy.assumptions)}
    year = 2023 if settings.year is None else int(settings.year)
    step = pd.Timedelta(settings.every)
    times = pd.date_range(pd.Timestamp(year, 1, 1, tz="UTC"), pd.Timestamp(year + 1, 1, 1, tz="UTC"),
                          freq=step, inclusive="left")
    dni = np.nan_to_num(np.asarray(clear_sky_dni(times, scenario.plant), dtype=np.float64))
    hours = np.full(len(times), step.total_seconds() / 3600.0)
    info = {"file": "", "kind": "pvlib ineichen clear sky", "annual": True, "step_hours": float(hours[0]),
            "coverage_fraction": 1.0, "assumptions": "clear sky at the plant's site (pvlib Ineichen, Linke "
                                                     "turbidity climatology)"}
    return {"year": year, "times": times, "dni": dni, "hours": hours, "annual": True, "weather": info,
            "convention": f"UTC instants every {settings.every} from 00:00 (each stands for the {settings.every} "
                          "that follows it)", "coverage": {"fraction_of_year": 1.0}, "assumptions": []}


# ------------------------------------------------------------------------------------------------- aiming
def _aims(scenario, plant, settings: YearSettings, atmosphere):
    """Aim points [H, 3] or a per-node callable ``(s, sun) -> [H, 3]``."""
    target = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    if settings.aim == "equator":
        return equator_aim_points(target, pos)
    if settings.aim == "scenario":
        state = scenario.learned.get("aimpoints")
        if not isinstance(state, dict) or state.get("aim") is None:
            raise InputFileError(scenario.path, "--aim scenario: the plant stores no aim points (run heliotwin "
                                                "aimpoints -o first)", field="/learned/aimpoints/aim")
        return torch.as_tensor(state["aim"], dtype=torch.float64).to(pos.device)
    limit = settings.peak_limit_w_m2 or stored_peak_limit(scenario)
    if not limit:
        raise InputFileError(scenario.path, "--aim optimised: the plant stores no peak-flux limit (run heliotwin "
                                            "aimpoints -o once, or give --peak-limit)",
                             field="/learned/aimpoints@peak_limit_w_m2")
    state = {"aim": None}

    def aim_at(s, sun):
        with torch.enable_grad():  # the tables run without gradients; the aim-point optimiser needs them
            res = optimise_aimpoints(plant, sun, float(limit), atmosphere=atmosphere, start_aim=state["aim"])
        state["aim"] = res.aim.detach()
        return state["aim"].to(torch.float64)

    return aim_at


# ---------------------------------------------------------------------------------------------- tracking
def _calibrated(scenario, plant):
    """Rows [h] of the heliostats with learned kinematics, their nominal (controller's) kinematics, the learned
    ones (the plant's), the posterior covariance [h, P, P] (or None) and parameter names; None without any."""
    cal = scenario.learned.get("calibration")
    if not isinstance(cal, dict) or not cal.get("heliostats") or not isinstance(cal.get("nominal"), dict):
        return None
    ids = list(cal["heliostats"])
    index = {h: i for i, h in enumerate(plant.field.ids)}
    keep = [j for j, h in enumerate(ids) if h in index]
    if not keep:
        return None
    nominal = nominal_kinematics(cal, scenario.path, len(ids)).index(torch.tensor(keep))
    rows = torch.tensor([index[ids[j]] for j in keep], dtype=torch.long)
    learned = plant.field.kinematics.index(rows)
    names = list(cal.get("parameter_names") or [])
    post = cal.get("posterior")
    cov = None
    if isinstance(post, dict) and post.get("covariance") is not None and names and not cal.get("networks"):
        cov = torch.as_tensor(post["covariance"], dtype=torch.float64)[torch.tensor(keep)]
    nominal = nominal.to(dtype=torch.float64)
    return {"rows": rows, "nominal": nominal, "learned": learned.to(dtype=torch.float64), "covariance": cov,
            "names": names, "method": str(cal.get("method", ""))}


# ---------------------------------------------------------------------------------------------- the year
def _on_device(plant, device):
    return plant if device is None else to_device(plant, resolve_device(device))


def plant_year(scenario, weather=None, settings: YearSettings | None = None) -> YearResult:
    """The plant's year heliostat by heliostat (module docstring).

    Parameters
    ----------
    scenario : heliotwin.io.scenario.Scenario
    weather : heliotwin.io.weather.DniSeries, optional
        From :func:`heliotwin.io.weather.read_dni_series`; default: pvlib's clear sky.
    settings : YearSettings, optional

    Returns
    -------
    YearResult
    """
    t0 = time.perf_counter()
    settings = settings or YearSettings()
    settings.check()
    plant = _on_device(scenario.plant, settings.device)
    if "receiver" not in plant.targets:
        raise InputFileError(scenario.path, "the plant has no 'receiver' target", field="/targets/receiver")
    atm = Atmosphere.from_extras(scenario.extras)
    inst = _instants(scenario, weather, settings)
    s = plant.site
    az, el = solar_position(inst["times"], s.latitude_deg, s.longitude_deg, s.altitude_m)
    dni = torch.as_tensor(inst["dni"].copy())
    hours = torch.as_tensor(inst["hours"].copy())
    q = dni * hours  # [Wh/m^2] per instant
    up = el > 0
    total_q = float(q.sum())
    if total_q <= 0:
        raise HeliotwinError(f"{inst['weather']['file'] or 'clear sky'}: no direct sun in {inst['year']} (every DNI "
                             "is 0): no energy to report")
    below = float(q[~up].sum()) / total_q
    up = up & (q > 0)  # the daylight instants with direct sun: the others add nothing (and need no table node)
    az_u, el_u, q_u = az[up], el[up], q[up]
    if float(q_u.sum()) <= 0:
        raise HeliotwinError(f"{inst['weather']['file'] or 'clear sky'}: no direct sun in {inst['year']} while the "
                             "sun is up: no energy to report")
    months = torch.as_tensor(np.asarray(inst["times"].month)[up.numpy()] - 1)
    grid = settings.grid
    idx, w = A.bilinear_weights(grid, az_u, el_u)
    nodes = A.needed_nodes(idx, w, q_u)
    col = A.node_columns(nodes, idx, w)  # [T, 4]
    dev = plant.field.kinematics.position.device
    suns = grid.suns(nodes).to(dev)
    aims = _aims(scenario, plant, settings, atm)
    cal = _calibrated(scenario, plant)
    index = {h: i for i, h in enumerate(plant.field.ids)}
    surf_ids = [h for h in (scenario.learned.get("surfaces") or {}) if h in index]
    surf_rows = torch.tensor([index[h] for h in surf_ids], dtype=torch.long)
    h_n = len(plant.field.ids)
    draws = int(settings.draws) if cal is not None and cal["covariance"] is not None else 0
    track_job = None
    if draws:
        kins = posterior_draws(cal["learned"], cal["names"], cal["covariance"], draws, settings.seed)
        track_job = (cal["rows"].to(dev), cal["learned"].to(device=dev), [k.to(device=dev) for k in kins])
    job = {"plant": plant, "suns": suns, "aims": aims, "atmosphere": atm, "tracking": track_job,
           "surface_rows": surf_rows.to(dev) if surf_ids else None}
    nproc = _processes(settings, plant, nodes.numel(), callable(aims))
    per_node = 1 + (1 if draws else 0) + (1 if surf_ids else 0)
    label = "heliotwin year: tables over sun positions"
    if nproc > 1:  # the nodes dealt over worker processes; rank 0 reports the progress of its share
        tables = run_spawned(_tables_rank, {**job, "progress": settings.progress, "per_node": per_node,
                                            "label": f"{label} ({nproc} processes)"}, nproc)
    serial = nodes.numel() * per_node if nproc == 1 else 0
    with Progress(serial + int(settings.check_hours), label if serial else "heliotwin year: direct check",
                  unit="node" if serial else "hour", enabled=settings.progress and serial + settings.check_hours > 0,
                  every=5.0) as bar:
        tick = bar.update
        if nproc == 1:
            tables = _node_tables(job, torch.arange(nodes.numel()), tick)
        eff = tables["efficiency"].cpu()
        area = tables["mirror_area"].cpu()
        track = tables.get("tracking_ratio")
        track = None if track is None else track.cpu()
        surf_eff = tables.get("surface_efficiency")
        surf_eff = None if surf_eff is None else surf_eff.cpu()
        year = _Hours(plant, tables, col, w, q_u, direction_from_paint_angles(az_u, el_u).reshape(-1, 3), months)
        check = _check(plant, atm, tables, grid, nodes, az_u, el_u, q_u, settings, tick) \
            if settings.check_hours else None
    # ---- sums over the year's instants: the exact cosine of each hour times the interpolated rest
    over_cos = eff / tables["cosine"].cpu().clamp_min(1e-12)  # [H, S]
    all_rows = torch.arange(h_n)
    by_month = year.sums(all_rows, over_cos, monthly=True)  # [H, 12] Wh/m^2
    energy = area * by_month.sum(-1) / 1e6  # [H] MWh
    monthly = (area.unsqueeze(-1) * by_month).sum(0) / 1e6  # [12]
    sum_q = float(q_u.sum())
    efficiency = energy * 1e6 / (area * sum_q).clamp_min(1e-30)
    node_q = year.weights[False].sum(0)  # [S] the year's DNI x hours on each node [Wh/m^2]
    factors = {name: (tables[name].cpu() @ node_q) / sum_q for name in FACTORS if name != "cosine"}
    factors["cosine"] = year.cosine_means(all_rows) / sum_q
    factors = {name: factors[name] for name in FACTORS}
    nan = torch.full((h_n,), float("nan"), dtype=torch.float64)
    t_point, t_low, t_high = nan.clone(), nan.clone(), nan.clone()
    notes = []
    if track is not None:
        rows = cal["rows"]
        lost = over_cos[rows].unsqueeze(0) * (1.0 - track)  # [V, h, S]
        loss = area[rows] * year.sums(rows, lost) / 1e6  # [V, h] MWh
        t_point[rows] = loss.mean(0)
        q_lo, q_hi = torch.quantile(loss, torch.tensor(LEVELS, dtype=torch.float64), dim=0)
        t_low[rows], t_high[rows] = q_lo, q_hi
    elif cal is not None:
        notes.append("tracking loss unknown (NaN): " + ("--draws 0" if cal["covariance"] is not None else
                     f"the {cal['method'] or 'stored'} calibration has no posterior") + " (the loss is the "
                     "expected loss over the posterior of the learned kinematics)")
    uncal = int(torch.isnan(t_point).sum())
    if uncal and (cal is None or track is not None):
        notes.append(f"tracking loss unknown (NaN) for {uncal} heliostat(s) with nominal kinematics only (no "
                     "calibration: the twin knows nothing of their errors)")
    s_point = torch.zeros(h_n, dtype=torch.float64)
    learned_surface = torch.zeros(h_n, dtype=torch.bool)
    if surf_eff is not None:
        gain = (surf_eff - eff[surf_rows]) / tables["cosine"].cpu()[surf_rows].clamp_min(1e-12)
        s_point[surf_rows] = area[surf_rows] * year.sums(surf_rows, gain) / 1e6
        learned_surface[surf_rows] = True
        notes.append("surface-loss interval: the learned surfaces carry no uncertainty: the point value twice")
    e_mirror = float(area.sum()) * sum_q / 1e6
    state = year_state(inst, settings, below, energy, efficiency, factors, monthly, e_mirror,
                       (t_point, t_low, t_high), s_point, learned_surface, check)
    learned = dict(scenario.learned)
    learned[KEY] = state
    step = provenance_entry("year", year=inst["year"], aim=settings.aim, weather=inst["weather"]["file"],
                            draws=int(settings.draws), seed=int(settings.seed), nodes=int(nodes.numel()))
    out = next_scenario(scenario, scenario.plant, learned=learned, step=step)
    report = _report(scenario, inst, state, grid, nodes, below, notes, uncal, surf_ids, time.perf_counter() - t0)
    report["tables_processes"] = nproc
    report["warnings"] = _warnings(weather, plant.site, below)
    tables_out = {"nodes": nodes, "efficiency": eff, "cosine": tables["cosine"].cpu(), "tracking_ratio": track,
                  "surface_efficiency": surf_eff, "aim": tables["aim"].cpu(), "suns": suns.cpu(), "hours": year,
                  "mirror_area": area, "calibrated_rows": None if cal is None else cal["rows"]}
    return YearResult(out, report, csv_rows(plant.field.ids, state), tables_out)


def _processes(settings: YearSettings, plant, nodes: int, chained: bool) -> int:
    """Worker processes for the tables: ``settings.nproc``, or by default the threads this command may use
    (:func:`heliotwin.cli.common.default_threads`: the cores others leave idle) when the work is large enough
    to pay for starting them (:data:`SPAWN_WORK`). One for optimised aiming (each node warm-starts from the
    previous one) and off the CPU."""
    if chained or plant.field.kinematics.position.device.type != "cpu" or nodes < 2:
        return 1
    if settings.nproc is not None:
        return max(1, min(int(settings.nproc), nodes))
    if len(plant.field.ids) * nodes < SPAWN_WORK:
        return 1
    return max(1, min(torch.get_num_threads(), nodes))


#: Heliostat-nodes below which the tables stay in this process: a worker's start (importing torch and the
#: package, loading the job) costs 2-4 s, about 40,000 heliostat-nodes of the field model on one core.
SPAWN_WORK = 100_000


def _node_tables(job: dict, nodes: torch.Tensor, progress) -> dict:
    """The tables of nodes ``nodes`` (indices into ``job["suns"]``): the field model's efficiency and factors
    [H, s], the mirror area [H], the aim points [s, H, 3], and where asked the tracking ratio [V, h, s]
    (:func:`~heliotwin.raytrace.annual.tracking_tables`) and the ideal-mirror efficiency [h, s]."""
    plant, suns, aims = job["plant"], job["suns"][nodes], job["aims"]
    tables = A.heliostat_tables(plant, suns, aims, atmosphere=job["atmosphere"], progress=progress)
    if job["tracking"] is not None:
        rows, controller, variants = job["tracking"]
        tables["tracking_ratio"] = A.tracking_tables(plant, suns, tables["aim"], rows, controller, variants,
                                                     progress=progress)
    if job["surface_rows"] is not None:
        per_node = (lambda k, _sun: tables["aim"][k]) if callable(aims) else aims
        tables["surface_efficiency"] = A.surface_tables(plant, suns, per_node, job["surface_rows"],
                                                        atmosphere=job["atmosphere"], progress=progress)
    return tables


def _tables_rank(job: dict, group):
    """One worker of the tables: nodes ``rank, rank + world, ...`` (neighbouring nodes on different workers, so
    the shares cost alike), gathered on rank 0 into the one-process layout."""
    rank, world = dist.get_rank(group), dist.get_world_size(group)
    s_n = job["suns"].shape[0]
    mine = torch.arange(rank, s_n, world)
    with Progress(s_n * job["per_node"], job["label"], unit="node", enabled=bool(job["progress"]) and rank == 0,
                  every=5.0) as bar:
        part = _node_tables(job, mine, lambda: bar.update(world))
    parts = [None] * world if rank == 0 else None
    dist.gather_object(part, parts, dst=0, group=group)
    if rank:
        return None
    out = {}
    for name, first in parts[0].items():
        if name == "mirror_area":
            out[name] = first
            continue
        axis = 0 if name == "aim" else first.dim() - 1  # the node axis
        shape = list(first.shape)
        shape[axis] = s_n
        full = first.new_zeros(shape)
        for r, p in enumerate(parts):
            full.index_copy_(axis, torch.arange(r, s_n, world), p[name])
        out[name] = full
    return out


def _warnings(weather, site, below: float) -> list[str]:
    """One-line warnings for the report (the CLI prints them): the weather file's site beyond 50 km of the
    plant's, and DNI energy while the sun is below the horizon beyond :data:`BELOW_HORIZON_LIMIT`."""
    out = []
    far = _weather.site_warning(weather, site.latitude_deg, site.longitude_deg) if weather is not None else None
    if far:
        out.append(far)
    if below > BELOW_HORIZON_LIMIT:
        name = getattr(weather, "path", None) or "the weather"
        out.append(f"{name}: {100 * below:.1f} % of its DNI energy falls while the sun is below the horizon at the "
                   f"plant (more than {100 * BELOW_HORIZON_LIMIT:.1f} %): its times are likely read in the wrong "
                   "convention or zone, or the file is another place's")
    return out


#: Share of the DNI energy below the horizon beyond which the report warns (a correct reading: <= 0.5 %).
BELOW_HORIZON_LIMIT = 0.005


class _Hours:
    """The year's daylight instants for the sums (:func:`heliotwin.raytrace.annual.hourly_sums`), in chunks of
    heliostats: columns ``col`` and weights ``w`` [T, 4], energies ``q`` (T,) [Wh/m^2], suns [T, 3], months (T,)
    0..11; each instant's aim is the tables' (one a year, or with optimised aiming the node of its largest
    weight)."""

    def __init__(self, plant, tables, col, w, q, suns, months):
        self.pos = plant.field.kinematics.position.detach().cpu().to(torch.float64)
        aim = tables["aim"].detach().cpu().to(torch.float64)  # [S, H, 3]
        self.fixed = aim[0] if bool((aim == aim[:1]).all()) else None
        self.aim, self.node = aim, col.gather(1, w.argmax(1, keepdim=True)).squeeze(1)  # (T,)
        self.col, self.w, self.q, self.suns, self.months = col, w, q.to(torch.float64), suns.to(torch.float64), months
        s_n = aim.shape[0]
        self.weights = {False: A.hour_weights(col, w, self.q, s_n),
                        True: A.hour_weights(col, w, self.q, s_n, months, 12)}

    def cosine(self, rows: torch.Tensor) -> torch.Tensor:
        """[h, T] exact cosine of heliostats ``rows`` at every instant."""
        aim = self.fixed[rows] if self.fixed is not None else self.aim[self.node][:, rows].transpose(0, 1)
        return A.hourly_cosine(self.pos[rows], aim, self.suns)

    def _chunks(self, rows: torch.Tensor):
        step = max(1, HOURLY_BUDGET // max(1, self.q.numel()))
        for k in range(0, rows.numel(), step):
            yield slice(k, k + step), rows[k:k + step]

    def sums(self, rows: torch.Tensor, over_cos: torch.Tensor, monthly: bool = False) -> torch.Tensor:
        """:func:`~heliotwin.raytrace.annual.hourly_sums` of tables ``over_cos`` [..., h, S] (rows ``rows``) ->
        [..., h] or [..., h, 12] [Wh/m^2]."""
        parts = [A.hourly_sums(over_cos[..., sl, :], self.cosine(r), self.col, self.w, self.q,
                               self.months if monthly else None, 12, weights=self.weights[monthly])
                 for sl, r in self._chunks(rows)]
        return torch.cat(parts, dim=over_cos.dim() - 2) if parts else over_cos.new_zeros(
            *over_cos.shape[:-1], *((12,) if monthly else ()))

    def cosine_means(self, rows: torch.Tensor) -> torch.Tensor:
        """(h,) ``sum_t q_t cos_ht`` [Wh/m^2]."""
        return torch.cat([self.cosine(r) @ self.q for _, r in self._chunks(rows)])


#: Elements of one chunk's [h, T] hourly cosines (float64, with a few temporaries of the same size: ~100 MB):
#: a memory bound, not a tuning knob.
HOURLY_BUDGET = 1 << 22


def _check(plant, atm, tables, grid, nodes, az, el, q, settings: YearSettings, tick) -> dict:
    """The interpolation against the field model evaluated directly at ``check_hours`` drawn daylight hours."""
    have = torch.nonzero(q > 0).flatten()
    n = min(int(settings.check_hours), have.numel())
    gen = torch.Generator().manual_seed(int(settings.seed) + 1)
    pick = have[torch.randperm(have.numel(), generator=gen)[:n]].sort().values
    idx, w = A.bilinear_weights(grid, az[pick], el[pick])
    col = A.node_columns(nodes, idx, w)
    eff = tables["efficiency"].cpu()
    hours = _Hours(plant, tables, col, w, q[pick], direction_from_paint_angles(az[pick], el[pick]).reshape(-1, 3),
                   torch.zeros(n, dtype=torch.long))
    all_rows = torch.arange(eff.shape[0])
    interp = A.interpolate(eff / tables["cosine"].cpu().clamp_min(1e-12), col, w) * hours.cosine(all_rows)  # [H, n]
    suns = hours.suns
    settings_f = A.TABLE_SETTINGS
    direct = []
    fixed = tables["aim"][0] if settings.aim != "optimised" else None
    with torch.no_grad(), reuse_mirror_samples():
        for k in range(n):
            aim = fixed if fixed is not None else tables["aim"][int(col[k, int(w[k].argmax())])]
            r = field_optics(plant, suns[k].to(plant.field.kinematics.position.device), atmosphere=atm, aim=aim,
                             settings=settings_f)
            direct.append(r.efficiency.detach().cpu().to(torch.float64))
            tick()
    direct = torch.stack(direct, -1)
    e_d, e_i = direct @ q[pick], interp @ q[pick]
    ok = e_d > 0
    rel = (e_i[ok] - e_d[ok]).abs() / e_d[ok]
    return {"median_error": float(rel.median()) if rel.numel() else float("nan"),
            "p95_error": float(torch.quantile(rel, 0.95)) if rel.numel() else float("nan"),
            "field_error": float(abs(e_i.sum() - e_d.sum()) / e_d.sum().clamp_min(1e-30)), "checked_hours": int(n)}


# ------------------------------------------------------------------------------------------------ storage
def year_state(inst: dict, settings: YearSettings, below: float, energy, efficiency, factors: dict, monthly,
               e_mirror: float, tracking: tuple, surface, surface_learned, check: dict | None) -> dict:
    """``learned["year"]`` (the agreed layout; every array one entry per heliostat in the plant's order)::

        {"version": 1, "year", "aim", "weather": {"file", "kind", "annual", "dni_share_below_horizon", ...},
         "time_convention", "annual_energy_mwh", "annual_dni_energy_on_mirrors_mwh", "monthly_energy_mwh" [12],
         "heliostats": {"energy_mwh", "efficiency", <factors>, "tracking_loss_mwh", "tracking_loss_low_mwh",
                        "tracking_loss_high_mwh", "surface_loss_mwh", "surface_loss_low_mwh",
                        "surface_loss_high_mwh", "surface_learned" (bool)},
         "interpolation": {"median_error", "p95_error", "field_error", "checked_hours"}}   # only when checked

    Inputs: ``energy`` [H] [MWh] and ``efficiency`` [H] [-] per heliostat, ``factors`` name -> [H] [-],
    ``monthly`` [12] [MWh], ``e_mirror`` the DNI on the mirrors [MWh], ``below`` the DNI share below the horizon
    [-], ``tracking`` (point, low, high) [H] each [MWh], ``surface`` [H] [MWh], ``surface_learned`` [H] bool.
    Arrays are float64 NumPy (the scenario writer's types); NaN marks an unknown tracking loss."""
    t_point, t_low, t_high = tracking
    np64 = lambda t: np.asarray(t.detach().cpu().numpy(), dtype=np.float64)  # noqa: E731
    hel = {"energy_mwh": np64(energy), "efficiency": np64(efficiency)}
    hel.update({name: np64(factors[name]) for name in FACTORS})
    hel.update({"tracking_loss_mwh": np64(t_point), "tracking_loss_low_mwh": np64(t_low),
                "tracking_loss_high_mwh": np64(t_high), "surface_loss_mwh": np64(surface),
                "surface_loss_low_mwh": np64(surface), "surface_loss_high_mwh": np64(surface),
                "surface_learned": np.asarray(surface_learned.numpy(), dtype=bool)})
    weather = {k: v for k, v in inst["weather"].items() if v is not None}
    weather["dni_share_below_horizon"] = float(below)
    state = {"version": VERSION, "year": int(inst["year"]), "aim": settings.aim, "weather": weather,
             "time_convention": inst["convention"], "annual_energy_mwh": float(energy.sum()),
             "annual_dni_energy_on_mirrors_mwh": float(e_mirror), "monthly_energy_mwh": np64(monthly),
             "heliostats": hel}
    if check is not None:
        state["interpolation"] = {k: (int(v) if k == "checked_hours" else float(v)) for k, v in check.items()}
    return state


CSV_COLUMNS = ("id", "energy_mwh", "efficiency") + FACTORS + (
    "tracking_loss_mwh", "surface_loss_mwh", "tracking_loss_low_mwh", "tracking_loss_high_mwh",
    "surface_loss_low_mwh", "surface_loss_high_mwh", "surface_learned")


def csv_rows(ids, state: dict) -> list[dict]:
    """One dict per heliostat with :data:`CSV_COLUMNS` (NaN: unknown)."""
    hel = state["heliostats"]
    cols = {k: np.asarray(hel[k]).tolist() for k in CSV_COLUMNS[1:]}
    return [{"id": hid, **{k: v[i] for k, v in cols.items()}} for i, hid in enumerate(ids)]


def _report(scenario, inst, state, grid, nodes, below, notes, uncal, surf_ids, seconds) -> dict:
    """The JSON report: the stored year plus where it came from (site, convention, the grid, notes)."""
    s = scenario.plant.site
    hel = state["heliostats"]
    track = np.asarray(hel["tracking_loss_mwh"])
    rep = {"scenario": os.path.abspath(scenario.path) if scenario.path else None, "year": state["year"],
           "aim": state["aim"], "heliostats": len(scenario.plant.field.ids),
           "site": {"latitude_deg": s.latitude_deg, "longitude_deg": s.longitude_deg, "altitude_m": s.altitude_m},
           "time_convention": state["time_convention"], "weather": state["weather"],
           "annual": bool(inst["annual"]), "annual_energy_mwh": state["annual_energy_mwh"],
           "annual_dni_energy_on_mirrors_mwh": state["annual_dni_energy_on_mirrors_mwh"],
           "dni_share_below_horizon": float(below),
           "field_efficiency": state["annual_energy_mwh"] / max(state["annual_dni_energy_on_mirrors_mwh"], 1e-30),
           "monthly_energy_mwh": np.asarray(state["monthly_energy_mwh"]).tolist(),
           "tracking_loss_mwh": float(np.nansum(track)), "tracking_loss_unknown_heliostats": int(uncal),
           "surface_loss_mwh": float(np.sum(hel["surface_loss_mwh"])), "surface_learned_heliostats": len(surf_ids),
           "table": {"nodes": int(nodes.numel()), "azimuth_step_deg": float(360.0 / grid.shape[1]),
                     "elevations_deg": [float(e) for e in grid.elevations_deg]},
           "interpolation": state.get("interpolation"), "coverage": inst["coverage"], "notes": notes,
           "seconds": seconds}
    return rep
