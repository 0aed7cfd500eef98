"""An in-silico plant: true kinematics, their drift and steps, a calibration schedule and the records it yields.

:func:`simulate_plant` draws everything from one seed (a private ``numpy.random.Generator``; no global state):

* **the plant** -- the embedded Jülich-like demo field (:func:`heliotwin.field.demo.demo_plant`; the
  radial-staggered demo field beyond :data:`JUELICH_ROWS_MAX` heliostats), or the positions of a layout CSV,
  optionally with the site and targets of a PAINT tower file;
* **true static deviations** of the 8 Stone/Jülich parameters (:data:`heliotwin.calibrate.params.STONE8`) per
  heliostat, from a Gaussian plant prior: the one learned from PAINT's Jülich records (:func:`paint_prior`,
  embedded) or any :class:`~heliotwin.calibrate.priors.PlantPrior` passed in;
* **drift** of the two encoder offsets (``initial_angle_1/2``): a random walk plus steps at a Poisson rate per
  heliostat-year with Gaussian sizes (a motor exchange, a re-referenced encoder);
* **the calibration schedule** of a tower: daytime only (sun above ``min_elevation_deg``), one heliostat per
  planar calibration target per time slot, each heliostat a Poisson number of records per month;
* **the records**: the plant's controller aims at the target centre with its own earlier calibration (the
  true static kinematics with ``controller_error_mrad`` on each encoder offset), motor steps are rounded to
  whole steps, the *true* heliostat (static + drift at that instant) reflects the sun's centre onto the target
  plane, and two cameras measure the spot with centroid noise; the second camera (UTIS) has a per-target
  offset and is missing at a rate, the timestamp is missing at a rate. A spot off its target, a pose outside
  the motor range or a sun below ``min_elevation_deg`` gives no record (counted in the report);
* optionally **flux-centred images** of a few heliostats with defective true surfaces (:mod:`.images`).

Everything is batched over heliostats and records (loops run over months and record chunks only).

Notes
-----
Default magnitudes and where they come from (PAINT's Jülich records, ``../shared/data/paint``):

* static deviations: the plant prior of PAINT's 25 Jülich heliostats with enough records (:data:`PAINT_PRIOR_MEAN`
  etc.; what ``--prior-from ../shared/data/paint`` learns): means of -10 to +11 mrad, spreads of 5-14 mrad
  (47 mrad for the poorly determined first-axis tilt about up), gear ratios 0.1-0.2 %, so the nominal
  kinematics point ~10 mrad off as PAINT's do. ``--prior-from`` takes another PAINT folder or a stored prior.
* centroid noise 0.15 mrad (per in-plane coordinate, as the angle the error subtends at the heliostat).
* UTIS missing in 26 % of records, timestamps missing in 1.4 % (444 and 23 of PAINT's 1704 records); the
  median HeliOS - UTIS offset per target is 2-9 cm (-4, 0, 8 cm; -3, 0, -2 cm; 0, 0, 4 cm for the three
  targets): drawn here per target with 4 cm per in-plane coordinate.
* drift 0.01 mrad/sqrt(day) per encoder offset (0.3 mrad after 3 years), steps 0.2 per heliostat-year of
  1 mrad per axis: assumptions of this simulator, to be replaced by measured values.
"""
from __future__ import annotations

import contextlib
import math
import os
import shutil
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd
import torch
from scipy.interpolate import CubicSpline

from ..calibrate.params import STONE8, apply_deviations
from ..calibrate.priors import PlantPrior
from ..errors import HeliotwinError
from ..field import kinematics as K
from ..field.demo import demo_field_positions, demo_plant
from ..field.facets import ideal_surfaces, receiver_canting
from ..field.layout import read_layout
from ..field.plant import Kinematics, Plant, Surfaces
from ..geometry import ray_plane, reflect
from ..io.paint import read_tower
from ..sun import direction_from_paint_angles, paint_angles_from_direction, solar_position
from . import images as imaging

try:  # POSIX only: the address-space limit (ulimit -v) a simulation must fit
    import resource
except ImportError:  # pragma: no cover
    resource = None

#: The plant prior learned from PAINT's Jülich records (``../shared/data/paint``: 25 heliostats with >= 9 records,
#: one loose lm fit each, :class:`heliotwin.calibrate.protocol.archive.PriorArchive`, full covariance shrunk 0.2
#: towards its diagonal; two heliostats' suspicious actuator values corrected first), over :data:`STONE8`:
#: mean and standard deviation [mrad; 1e-3 relative for increments], and the correlation (rounded to 0.01).
PAINT_PRIOR_MEAN = (-9.932, -2.149, -1.157, 11.295, -0.474, 9.308, -0.018, -0.841)
PAINT_PRIOR_SD = (5.447, 13.867, 9.678, 46.668, 5.208, 5.909, 1.944, 1.214)
PAINT_PRIOR_CORRELATION = (
    (1.0, -0.18, 0.21, 0.29, -0.08, -0.59, 0.23, 0.34), (-0.18, 1.0, -0.2, -0.02, -0.27, 0.13, -0.25, -0.14),
    (0.21, -0.2, 1.0, -0.07, -0.35, -0.29, -0.06, 0.1), (0.29, -0.02, -0.07, 1.0, -0.18, -0.04, 0.34, 0.01),
    (-0.08, -0.27, -0.35, -0.18, 1.0, 0.04, -0.15, -0.01), (-0.59, 0.13, -0.29, -0.04, 0.04, 1.0, 0.12, -0.36),
    (0.23, -0.25, -0.06, 0.34, -0.15, 0.12, 1.0, -0.14), (0.34, -0.14, 0.1, 0.01, -0.01, -0.36, -0.14, 1.0))


def paint_prior() -> PlantPrior:
    """:data:`PAINT_PRIOR_MEAN` / ``_SD`` / ``_CORRELATION`` as a :class:`PlantPrior` (physical units)."""
    sd = torch.tensor(PAINT_PRIOR_SD, dtype=torch.float64) * 1e-3
    cov = torch.tensor(PAINT_PRIOR_CORRELATION, dtype=torch.float64) * sd[:, None] * sd[None, :]
    return PlantPrior(STONE8, torch.tensor(PAINT_PRIOR_MEAN, dtype=torch.float64) * 1e-3, cov, [],
                      {"source": "PAINT Juelich records (embedded)"})


#: The deviations that drift and step: the two encoder offsets.
DRIFTING = ("initial_angle_1", "initial_angle_2")
#: Spacing [s] of the grid on which the sun is computed (NREL SPA); records interpolate it (cubic spline of
#: the direction: error ~1e-7 rad at 20 minutes, far below the centroid noise).
SUN_GRID_SECONDS = 1200
#: Weather of a record with a weather row: column -> (distribution, parameters); wind speed [m/s] is |normal|,
#: direction [deg] uniform, DNI [W/m^2] uniform over a calibration day's range, temperature [degC] and
#: pressure [hPa] normal, humidity [%] uniform.
WEATHER = {"wind_speed": ("absnormal", 3.0, 2.0), "wind_direction": ("uniform", 0.0, 360.0),
           "dni": ("uniform", 300.0, 950.0), "temperature": ("normal", 15.0, 8.0),
           "humidity": ("uniform", 30.0, 90.0), "pressure": ("normal", 1005.0, 8.0)}
#: Records are generated in chunks of this many (bounded memory: ~1 kB per record in flight).
CHUNK = 100_000


@dataclass(frozen=True)
class SimulationSettings:
    """What to simulate (``heliotwin simulate``'s options, same defaults).

    Attributes
    ----------
    heliostats : int
        N heliostats of the demo field (ignored when ``layout`` gives the positions).
    seed : int
    years : float
        Length of the calibration history [years], from ``start``.
    start : str
        UTC date of the first day.
    records_per_month : float
        Mean records per heliostat and month (Poisson).
    min_elevation_deg : float
        No calibration below this sun elevation [deg].
    slot_seconds : int
        One calibration occupies a target this long [s]; a month holds at most its daytime slots per target.
    centroid_noise_mrad : float
        Centroid noise per in-plane coordinate, as the angle at the heliostat [mrad].
    camera_offset_m : float
        Std of the per-target UTIS offset per in-plane coordinate [m].
    utis_missing, time_missing : float
        Fraction of records without a UTIS centroid / without a timestamp.
    drift_mrad_per_sqrt_day : float
        Random-walk std of each encoder offset [mrad / sqrt(day)].
    step_rate_per_year : float
        Offset steps per heliostat-year (Poisson).
    step_size_mrad : float
        Std of a step per encoder offset [mrad].
    controller_error_mrad : float
        The plant's controller aims with its own earlier calibration: the true static kinematics with this
        error [mrad] on each encoder offset (the motor steps are whatever it commanded, so this only sets
        how far from the target centre the spots land, and which miss the target).
    weather_fraction : float
        Fraction of records with a weather row (PAINT: 590 of 1704); the values are plausible for Jülich
        (:data:`WEATHER`), not fitted to PAINT's.
    images : int
        Heliostats with a defective true surface whose records get flux-centred images (:mod:`.images`).
    images_per_heliostat : int
        Most images per such heliostat (a random subset of its records).
    layout : str or None
        Layout CSV (``x,y,z[,id]`` ENU [m]): the heliostat positions instead of the demo field's.
    paint_tower : str or None
        A PAINT tower file: its site and targets instead of the embedded Jülich tower.
    """

    heliostats: int = 100
    seed: int = 0
    years: float = 3.0
    start: str = "2021-01-01"
    records_per_month: float = 2.8
    min_elevation_deg: float = 10.0
    slot_seconds: int = 60
    centroid_noise_mrad: float = 0.15
    camera_offset_m: float = 0.04
    utis_missing: float = 0.26
    time_missing: float = 0.014
    drift_mrad_per_sqrt_day: float = 0.01
    step_rate_per_year: float = 0.2
    step_size_mrad: float = 1.0
    controller_error_mrad: float = 1.0
    weather_fraction: float = 0.35
    images: int = 0
    images_per_heliostat: int = 10
    layout: str | None = None
    paint_tower: str | None = None

    def check(self) -> None:
        """One-line :class:`HeliotwinError` naming the option that is out of range."""
        rules = [("heliostats", self.heliostats >= 1), ("years", 0 < self.years <= 50),
                 ("records_per_month", 0 < self.records_per_month <= 1000),
                 ("min_elevation_deg", 0 <= self.min_elevation_deg < 90), ("slot_seconds", self.slot_seconds >= 1),
                 ("centroid_noise_mrad", self.centroid_noise_mrad >= 0), ("camera_offset_m", self.camera_offset_m >= 0),
                 ("utis_missing", 0 <= self.utis_missing <= 1), ("time_missing", 0 <= self.time_missing <= 1),
                 ("drift_mrad_per_sqrt_day", self.drift_mrad_per_sqrt_day >= 0),
                 ("step_rate_per_year", self.step_rate_per_year >= 0), ("step_size_mrad", self.step_size_mrad >= 0),
                 ("controller_error_mrad", self.controller_error_mrad >= 0), ("images", self.images >= 0),
                 ("weather_fraction", 0 <= self.weather_fraction <= 1),
                 ("images_per_heliostat", self.images_per_heliostat >= 1)]
        for name, ok in rules:
            if not ok:
                raise HeliotwinError(f"simulate: {name} = {getattr(self, name)!r} is out of range")
        try:
            pd.Timestamp(self.start, tz="UTC")
        except (ValueError, TypeError):
            raise HeliotwinError(f"simulate: start = {self.start!r} is not a date (e.g. 2021-01-01)") from None


@dataclass
class SimulatedRecords:
    """R simulated records (structure of arrays, CPU, float64), sorted by time; record ids ascend with time.

    Attributes
    ----------
    record_id : [R] long
    heliostat_index : [R] long
        Into the plant's heliostat axis.
    time : [R]
        UTC POSIX seconds (also for records whose timestamp is written as missing).
    target : list of str, R
    sun_azimuth, sun_elevation : [R]
        [rad], PAINT convention.
    motor_steps : [R, 2]
        Whole steps.
    true_spot : [R, 3]
        Where the true heliostat's central ray meets the target plane, ENU [m].
    focal_spots : [R, 2, 3]
        Measured HeliOS and UTIS centroids, ENU [m]; NaN where missing.
    has_time : [R] bool
        False where the metadata row is left out (a missing timestamp).
    drift : [R, 2]
        The drifting deviations (:data:`DRIFTING`) at the record's instant [rad].
    weather : [R, 6] or None
        :data:`WEATHER`'s columns; NaN rows for records without a weather row.
    """

    record_id: torch.Tensor
    heliostat_index: torch.Tensor
    time: torch.Tensor
    target: list
    sun_azimuth: torch.Tensor
    sun_elevation: torch.Tensor
    motor_steps: torch.Tensor
    true_spot: torch.Tensor
    focal_spots: torch.Tensor
    has_time: torch.Tensor
    drift: torch.Tensor
    weather: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.record_id.shape[0])


@dataclass
class SimulatedPlant:
    """What :func:`simulate_plant` returns.

    Attributes
    ----------
    plant : Plant
        Nominal plant (what the PAINT properties files hold).
    names : tuple of str
        The deviation parameters (:data:`STONE8`).
    static : torch.Tensor, [H, P]
        True static deviations from nominal (rad; relative for increments).
    steps : dict
        ``heliostat`` [S] long, ``time`` [S] POSIX s, ``size`` [S, 2] rad: every offset step.
    end_time : float
        POSIX s of the end of the history (the truth scenario's instant).
    end_drift : torch.Tensor, [H, 2]
        The drifting deviations at ``end_time`` [rad].
    records : SimulatedRecords
    camera_offsets : dict
        Target -> UTIS offset [3] ENU [m].
    settings : SimulationSettings
    report : dict
        Counts (scheduled, unreachable, off target, months at capacity).
    surfaces : Surfaces or None
        True surfaces [H, ...] when images were rendered (else the plant's ideal ones are the truth).
    images : dict
        Record id -> flux-centred camera image [R, R] (max 1).
    """

    plant: Plant
    names: tuple
    static: torch.Tensor
    steps: dict
    end_time: float
    end_drift: torch.Tensor
    records: SimulatedRecords
    camera_offsets: dict
    settings: SimulationSettings
    report: dict = field(default_factory=dict)
    surfaces: Surfaces | None = None
    images: dict = field(default_factory=dict)

    def true_kinematics(self, drift: torch.Tensor | None = None) -> Kinematics:
        """True kinematics [H] with the drifting deviations ``drift`` [H, 2] (default: at the end time)."""
        return true_kinematics(self.plant.field.kinematics, self.static, self.names,
                               self.end_drift if drift is None else drift)


def true_kinematics(nominal: Kinematics, static: torch.Tensor, names, drift: torch.Tensor) -> Kinematics:
    """Nominal kinematics [N] with static deviations [N, P] and the drifting ones [N, 2] (:data:`DRIFTING`)
    added (N heliostats or N records)."""
    kin = apply_deviations(nominal, static, names)
    return apply_deviations(kin, drift, DRIFTING)


# ------------------------------------------------------------------------------------------------ plant
def _paint_id(i: int) -> str:
    return chr(ord("A") + (i // 2600) % 26) + chr(ord("A") + (i // 100) % 26) + f"{i % 100:02d}"


#: Up to this many heliostats the demo field's Jülich-like rows within 150 m of the tower hold the plant (PAINT-like
#: ids such as ``AA39``); larger plants stand on the radial-staggered demo field (:func:`demo_field_positions`).
JUELICH_ROWS_MAX = 400


#: The most heliostats the radial-staggered demo field places (:func:`demo_field_positions`' rings end 40 tower
#: heights, 2200 m, from the tower; ``tests/test_simulate_grow.py`` checks the figure against it).
DEMO_FIELD_MAX = 25213

#: What a simulation costs per record while it runs [bytes] (measured: 0.40 GB more for 300,000 more records,
#: with a margin), per heliostat, and before any record (the interpreter, torch, the plant); and on disk per
#: record [bytes] (one small JSON file, a 4 kB block, its metadata row) and per heliostat (two folders and the
#: properties file).
MEMORY_PER_RECORD, MEMORY_PER_HELIOSTAT, MEMORY_BASE = 1600, 20_000, 600 * 2**20
DISK_PER_RECORD, DISK_PER_HELIOSTAT = 4300, 12_300


def expected_records(settings: SimulationSettings, heliostats: int, planar_targets: int) -> float:
    """About how many records ``settings`` schedules for ``heliostats`` heliostats and ``planar_targets``
    calibration targets: heliostats x records per month x months, at most the daytime slots of the history (half
    of every day, an upper bound at any latitude over a year)."""
    seconds = 365.25 * 86400 * settings.years
    per_cell = max(SUN_GRID_SECONDS // int(settings.slot_seconds), 1)
    capacity = 0.5 * seconds / SUN_GRID_SECONDS * per_cell * planar_targets
    return min(heliostats * settings.records_per_month * 12 * settings.years, capacity)


def _memory_available() -> float | None:
    """Bytes this process may still allocate: the least of the system's available memory, the address-space
    limit (``ulimit -v``) less what is mapped, and the cgroup's limit less its use (None where none is known)."""
    limits = []
    with contextlib.suppress(OSError, ValueError, IndexError):
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    limits.append(int(line.split()[1]) * 1024)
    with contextlib.suppress(OSError, ValueError, IndexError, AttributeError):
        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            with open("/proc/self/status", encoding="ascii") as fh:
                vm = next(int(ln.split()[1]) * 1024 for ln in fh if ln.startswith("VmSize:"))
            limits.append(soft - vm)
    with contextlib.suppress(OSError, ValueError):
        with open("/sys/fs/cgroup/memory.max", encoding="ascii") as fh:
            top = fh.read().strip()
        if top != "max":
            with open("/sys/fs/cgroup/memory.current", encoding="ascii") as fh:
                limits.append(int(top) - int(fh.read().strip()))
    return float(min(limits)) if limits else None


def check_size(settings: SimulationSettings, heliostats: int, planar_targets: int, out=None) -> dict:
    """Refuse, in one line and before anything is drawn, a simulation that would not fit this machine's memory
    (:func:`_memory_available`) or the free disk of the folder ``out`` is written to; returns the estimate
    (``records``, ``memory_bytes``, ``disk_bytes``)."""
    r = expected_records(settings, heliostats, planar_targets)
    memory = MEMORY_BASE + MEMORY_PER_RECORD * r + MEMORY_PER_HELIOSTAT * heliostats
    disk = DISK_PER_RECORD * r + DISK_PER_HELIOSTAT * heliostats
    what = (f"about {r:,.0f} records ({heliostats} heliostats x {settings.records_per_month:g} records per month "
            f"for {settings.years:g} years)")
    fix = "simulate fewer heliostats, years or records per month"
    free = _memory_available()
    if free is not None and memory > MEMORY_BASE and memory > free:
        raise HeliotwinError(f"simulate: {what} need about {memory / 2**30:.1f} GiB of memory and this machine has "
                             f"{max(free, 0) / 2**30:.1f} GiB available; {fix}")
    if out is not None:
        parent = os.path.dirname(os.path.abspath(os.fspath(out)))
        with contextlib.suppress(OSError):
            room = shutil.disk_usage(parent).free
            if disk > room:
                raise HeliotwinError(f"simulate: {what} need about {disk / 2**30:.1f} GiB of disk and {parent} has "
                                     f"{room / 2**30:.1f} GiB free; {fix}")
    return {"records": r, "memory_bytes": memory, "disk_bytes": disk}


def _moved(plant: Plant, position: torch.Tensor, ids: list) -> Plant:
    """``plant``'s heliostats moved to ``position`` [H, 3] ENU [m] and renamed, facets re-canted to the new
    slant range to the receiver."""
    kin = plant.field.kinematics.replace(position=position.to(torch.float64))
    fac = plant.field.facets
    slant = torch.linalg.vector_norm(plant.targets["receiver"].center - kin.position, dim=-1)
    ce, cn = receiver_canting(fac.translation, float(fac.canting_e[0, 0].norm()), float(fac.canting_n[0, 0].norm()),
                              slant)
    fac = replace(fac, canting_e=ce, canting_n=cn)
    cp = plant.field.surfaces.control_points
    surf = ideal_surfaces(fac, num_control_points=tuple(cp.shape[2:4]),
                          degree=(plant.field.surfaces.degree_u, plant.field.surfaces.degree_v))
    return replace(plant, field=replace(plant.field, ids=list(ids), kinematics=kin, facets=fac, surfaces=surf))


def nominal_plant(settings: SimulationSettings) -> Plant:
    """The nominal plant: the demo field (Jülich-like rows up to :data:`JUELICH_ROWS_MAX` heliostats, the
    radial-staggered field beyond, ids ``AA00``, ``AA01``, ...), or ``settings.layout``'s positions (ids in layout
    order), with ``settings.paint_tower``'s site and targets. Each heliostat keeps the demo's Jülich-like
    variations (pivot height, actuator zero points, motor ranges)."""
    if settings.layout:
        layout = read_layout(settings.layout)
        n = len(layout.ids)
        position = layout.position.to(torch.float64)
    else:
        n = int(settings.heliostats)
        position = None
    if n > 26 * 26 * 100:
        raise HeliotwinError(f"simulate: {n} heliostats exceed PAINT's id pattern (at most 67600)")
    if position is None and n > DEMO_FIELD_MAX:
        raise HeliotwinError(f"simulate: --heliostats {n}: the demo field holds at most {DEMO_FIELD_MAX} heliostats "
                             f"(its rings reach 2200 m from the tower); give the positions of more with --layout")
    plant = demo_plant(n, settings.seed) if n <= JUELICH_ROWS_MAX else _demo_variations(n, settings.seed)
    if position is None and n > JUELICH_ROWS_MAX:
        position = demo_field_positions(n, max_east=135.0 if n <= 2200 else None)
        position = position + torch.stack([torch.zeros(n), torch.zeros(n), plant.field.kinematics.position[:, 2]], -1)
    if position is not None:
        plant = _moved(plant, position, [_paint_id(i) for i in range(n)])
    if settings.paint_tower:
        site, targets = read_tower(settings.paint_tower)
        plant = replace(plant, site=site, targets=targets)
    if not any(t.kind == "planar" for t in plant.targets.values()):
        raise HeliotwinError("simulate: the tower has no planar calibration target")
    return plant


def _demo_variations(n: int, seed: int) -> Plant:
    """A demo plant of ``n`` heliostats for its per-heliostat variations only (positions are replaced): drawn
    in blocks of :data:`JUELICH_ROWS_MAX` so that any ``n`` fits the demo's row layout."""
    blocks = [demo_plant(min(JUELICH_ROWS_MAX, n - a), seed + a) for a in range(0, n, JUELICH_ROWS_MAX)]
    if len(blocks) == 1:
        return blocks[0]
    first = blocks[0]
    kin = Kinematics.concatenate([b.field.kinematics for b in blocks])
    fac = type(first.field.facets)(*(torch.cat([getattr(b.field.facets, a) for b in blocks])
                                     for a in ("translation", "canting_e", "canting_n")))
    sf = first.field.surfaces
    surf = Surfaces(torch.cat([b.field.surfaces.control_points for b in blocks]), sf.degree_u, sf.degree_v)
    fl = replace(first.field, ids=[_paint_id(i) for i in range(n)], kinematics=kin, facets=fac, surfaces=surf,
                 width=torch.cat([b.field.width for b in blocks]), height=torch.cat([b.field.height for b in blocks]),
                 renovation=[""] * n)
    return replace(first, field=fl)


def draw_static(rng: np.random.Generator, h: int, prior: PlantPrior | None = None) -> tuple[torch.Tensor, tuple]:
    """True static deviations [H, P] ~ N(prior mean, prior covariance) and their names (default prior:
    :func:`paint_prior`)."""
    prior = prior or paint_prior()
    names = tuple(prior.names)
    chol = np.linalg.cholesky(prior.covariance.double().numpy())
    z = rng.standard_normal((h, len(names)))
    return torch.from_numpy(prior.mean.double().numpy() + z @ chol.T), names


# --------------------------------------------------------------------------------------------- schedule
def _posix(index: pd.DatetimeIndex) -> np.ndarray:
    """POSIX seconds (float64) of a UTC index, whatever its resolution."""
    return (index - pd.Timestamp(0, tz="UTC")).total_seconds().to_numpy()


def _month_starts(start: pd.Timestamp, end: pd.Timestamp) -> list:
    months = list(pd.date_range(start.normalize().replace(day=1), end, freq="MS", tz="UTC"))
    if not months or months[0] > start:
        months.insert(0, start)
    months[0] = max(months[0], start)
    return months + [end]


def draw_schedule(rng: np.random.Generator, h: int, targets: list, settings: SimulationSettings, sun_grid
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Calibration slots: for each month each heliostat gets Poisson(``records_per_month``) records, each in a
    distinct (time slot, target) of that month's daytime.

    Daytime is judged on the sun grid (sun above ``min_elevation_deg`` at a cell's start); a month whose
    demand exceeds its daytime slots takes what fits (reported in ``months_at_capacity``).

    Returns
    -------
    heliostat : [R] int, time : [R] POSIX s (whole seconds), target : [R] int (into ``targets``), report : dict
    """
    slot = int(settings.slot_seconds)
    start = pd.Timestamp(settings.start, tz="UTC")
    end = start + pd.Timedelta(days=365.25 * settings.years)
    coarse = SUN_GRID_SECONDS
    grid, el = sun_grid
    day_cells = grid[el > math.radians(settings.min_elevation_deg)]
    per_cell = max(coarse // slot, 1)
    nt = len(targets)
    edges = [m.timestamp() for m in _month_starts(start, end)]
    hs, ts, tg, full = [], [], [], 0
    for a, b in zip(edges[:-1], edges[1:]):
        cells = day_cells[(day_cells >= a) & (day_cells < b)]
        frac = (b - a) / (30.44 * 86400)
        counts = rng.poisson(settings.records_per_month * frac, h)
        demand = int(counts.sum())
        capacity = len(cells) * per_cell * nt
        if demand == 0 or capacity == 0:
            continue
        if demand > capacity:
            full += 1
        who = np.repeat(np.arange(h), counts)
        rng.shuffle(who)
        who = who[:capacity]
        pick = rng.choice(capacity, size=len(who), replace=False)
        cell, rest = np.divmod(pick, per_cell * nt)
        sub, target = np.divmod(rest, nt)
        hs.append(who)
        ts.append(cells[cell] + sub * slot + np.floor(rng.uniform(0, min(slot, coarse) * 0.5, len(who))))
        tg.append(target)
    cat = (lambda x, dt: np.concatenate(x) if x else np.zeros(0, dt))  # noqa: E731
    report = {"months": len(edges) - 1, "months_at_capacity": full, "end_time": float(edges[-1])}
    return cat(hs, np.int64), cat(ts, np.float64), cat(tg, np.int64), report


def sun_grid(settings: SimulationSettings, site) -> tuple[np.ndarray, np.ndarray, CubicSpline]:
    """The sun over the whole history every :data:`SUN_GRID_SECONDS`: grid times [T] POSIX s, apparent
    elevation [T] rad, and a cubic spline of the ENU direction (time -> [..., 3])."""
    start = pd.Timestamp(settings.start, tz="UTC")
    end = start + pd.Timedelta(days=365.25 * settings.years + 1)
    grid = pd.date_range(start, end, freq=f"{SUN_GRID_SECONDS}s", tz="UTC", inclusive="left")
    az, el = solar_position(grid, site.latitude_deg, site.longitude_deg, site.altitude_m)
    t = _posix(grid)
    return t, el.numpy(), CubicSpline(t, direction_from_paint_angles(az, el, check_horizon=False).numpy(), axis=0)


def sun_at(spline: CubicSpline, times: np.ndarray) -> torch.Tensor:
    """Unit vectors towards the sun [R, 3] ENU at ``times`` (R,), UTC POSIX seconds [s] (interpolated,
    renormalised); ``spline`` interpolates the ENU sun direction over time, float64."""
    d = torch.from_numpy(spline(times))
    return d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)


# ---------------------------------------------------------------------------------------------- drift
def draw_steps(rng: np.random.Generator, h: int, t0: float, t1: float, settings: SimulationSettings) -> dict:
    """Offset steps: Poisson(``step_rate_per_year`` x years) per heliostat at uniform times, N(0, size) per
    drifting deviation. Returns ``heliostat`` [S], ``time`` [S] POSIX s, ``size`` [S, 2] rad (time-sorted)."""
    years = (t1 - t0) / (365.25 * 86400)
    n = rng.poisson(settings.step_rate_per_year * years, h)
    who = np.repeat(np.arange(h), n)
    when = rng.uniform(t0, t1, len(who))
    size = rng.normal(0.0, settings.step_size_mrad * 1e-3, (len(who), len(DRIFTING)))
    order = np.argsort(when, kind="stable")
    return {"heliostat": torch.from_numpy(who[order]), "time": torch.from_numpy(when[order]),
            "size": torch.from_numpy(size[order])}


def drift_at(rng: np.random.Generator, heliostat: np.ndarray, time: np.ndarray, h: int, t0: float,
             steps: dict, walk_per_sqrt_day: float) -> np.ndarray:
    """The drifting deviations [R, 2] at each (heliostat, time) query (one sample path of the random walk
    per heliostat, shared by its queries; plus the steps before the query's time).

    One sort over the heliostat's queries and steps together, then cumulative sums within each heliostat:
    no loop over records.

    Parameters
    ----------
    rng : numpy.random.Generator
        Draws the walk.
    heliostat : numpy.ndarray, shape (R,), int
        Heliostat of each query (< ``h``).
    time : numpy.ndarray, shape (R,)
        UTC POSIX seconds [s] of each query (>= ``t0``).
    h : int
        H, the number of heliostats.
    t0 : float
        Start of every walk (deviations zero) [s], UTC POSIX.
    steps : dict
        :func:`draw_steps`'s offset steps (``time`` [s], ``size`` [rad]).
    walk_per_sqrt_day : float
        Random-walk standard deviation after one day [mrad].

    Returns
    -------
    numpy.ndarray, shape (R, 2)
        The drifting deviations at the queries [rad].
    """
    q = len(time)
    sh, st, ss = steps["heliostat"].numpy(), steps["time"].numpy(), steps["size"].numpy()
    hh = np.concatenate([heliostat, sh])
    tt = np.concatenate([time, st])
    is_query = np.concatenate([np.ones(q, bool), np.zeros(len(sh), bool)])
    order = np.lexsort((~is_query, tt, hh))  # by heliostat, then time
    hh, tt, is_query = hh[order], tt[order], is_query[order]
    step_sizes = np.zeros((len(order), len(DRIFTING)))
    step_sizes[~is_query] = ss[order[~is_query] - q]
    first = np.r_[True, hh[1:] != hh[:-1]]
    prev_t = np.where(first, t0, np.r_[t0, tt[:-1]])
    dt_days = np.clip(tt - prev_t, 0.0, None) / 86400.0
    walk = rng.standard_normal((len(order), len(DRIFTING))) * (walk_per_sqrt_day * 1e-3) * np.sqrt(dt_days)[:, None]
    inc = walk + step_sizes
    cum = np.cumsum(inc, axis=0)
    start_idx = np.maximum.accumulate(np.where(first, np.arange(len(order)), 0))
    within = cum - cum[start_idx] + inc[start_idx]  # each heliostat's path starts at zero at t0
    out = np.empty((q, len(DRIFTING)))
    out[order[is_query]] = within[is_query]
    return out


# -------------------------------------------------------------------------------------------- records
def _records_chunk(nominal: Kinematics, static: torch.Tensor, names, controller: torch.Tensor, drift: torch.Tensor,
                   hidx: torch.Tensor, sun: torch.Tensor, center: torch.Tensor, normal: torch.Tensor):
    """Motor steps [R, 2] (the controller's kinematics aiming at ``center``, whole steps), the true spot [R, 3]
    on the plane and the slant range [R], plus [R] bool: reachable and hitting the plane."""
    nom = nominal.index(hidx)
    steps, reachable = K.inverse(true_kinematics(nom, static[hidx], names, controller[hidx]), center, sun,
                                 iterations=3, tolerance=0.0, strict=False)
    steps = torch.round(steps)
    reachable &= ((steps >= nom.min_steps) & (steps <= nom.max_steps)).all(-1)
    true = true_kinematics(nom, static[hidx], names, drift)
    rot, conc = K.forward(true, steps)
    ray = reflect(-sun, K.mirror_normal(rot))
    t, hit = ray_plane(conc, ray, center, normal)
    spot = conc + t.unsqueeze(-1) * ray
    return steps, spot, torch.linalg.vector_norm(spot - conc, dim=-1), reachable & hit


def simulate_plant(settings: SimulationSettings = SimulationSettings(), *, prior: PlantPrior | None = None,
                   out=None) -> SimulatedPlant:
    """Draw a plant's truth and its calibration history from ``settings.seed`` (module docstring).

    Parameters
    ----------
    settings : SimulationSettings
    prior : PlantPrior, optional
        Distribution of the static deviations (default: :func:`paint_prior`).
    out : path, optional
        Where the folder will be written: its free disk is checked with the memory (:func:`check_size`) before
        anything is drawn.

    Returns
    -------
    SimulatedPlant
        Records sorted by time (ids ascending), CPU float64.
    """
    settings.check()
    rng = np.random.default_rng(settings.seed)
    plant = nominal_plant(settings)
    h = len(plant.field.ids)
    check_size(settings, h, sum(t.kind == "planar" for t in plant.targets.values()), out)
    static, names = draw_static(rng, h, prior)
    planar = [name for name, t in plant.targets.items() if t.kind == "planar"]
    grid_t, grid_el, spline = sun_grid(settings, plant.site)
    hs, ts, tg, sched = draw_schedule(rng, h, planar, settings, (grid_t, grid_el))
    order = np.argsort(ts, kind="stable")
    hs, ts, tg = hs[order], ts[order], tg[order]
    t0 = pd.Timestamp(settings.start, tz="UTC").timestamp()
    t_end = sched["end_time"]
    steps = draw_steps(rng, h, t0, t_end, settings)
    walk = settings.drift_mrad_per_sqrt_day
    drift_all = drift_at(rng, np.concatenate([hs, np.arange(h)]), np.concatenate([ts, np.full(h, t_end)]), h, t0,
                         steps, walk)
    drift, end_drift = torch.from_numpy(drift_all[:len(hs)]), torch.from_numpy(drift_all[len(hs):])
    sun_all = sun_at(spline, ts)
    az, el = paint_angles_from_direction(sun_all)
    day = (el > math.radians(settings.min_elevation_deg)).numpy()
    tgt = [plant.targets[n] for n in planar]
    centers = torch.stack([t.center for t in tgt]).double()
    normals = torch.stack([t.normal for t in tgt]).double()
    rights = torch.stack([t.right for t in tgt]).double()
    ups = torch.stack([t.up for t in tgt]).double()
    half = torch.tensor([[t.width / 2, t.height / 2] for t in tgt], dtype=torch.float64)
    hidx_all, tg_t = torch.from_numpy(hs), torch.from_numpy(tg)
    kin = plant.field.kinematics
    controller = torch.from_numpy(rng.normal(0.0, settings.controller_error_mrad * 1e-3, (h, len(DRIFTING))))
    parts = {"steps": [], "spot": [], "slant": [], "ok": []}
    for a in range(0, len(hs), CHUNK):
        sl = slice(a, a + CHUNK)
        s, sp, sr, ok = _records_chunk(kin, static, names, controller, drift[sl], hidx_all[sl], sun_all[sl],
                                       centers[tg_t[sl]], normals[tg_t[sl]])
        for k, v in zip(parts, (s, sp, sr, ok)):
            parts[k].append(v)
    cat = {k: torch.cat(v) if v else torch.zeros(0) for k, v in parts.items()}
    rel = cat["spot"] - centers[tg_t] if len(hs) else torch.zeros(0, 3, dtype=torch.float64)
    local = torch.stack(((rel * rights[tg_t]).sum(-1), (rel * ups[tg_t]).sum(-1)), -1) if len(hs) else rel[:, :2]
    on_target = (local.abs() <= half[tg_t]).all(-1) if len(hs) else torch.zeros(0, dtype=torch.bool)
    ok = cat["ok"].bool() & torch.from_numpy(day) & on_target if len(hs) else torch.zeros(0, dtype=torch.bool)
    keep = ok.nonzero().flatten()
    r = len(keep)
    tgk = tg_t[keep]
    # Cameras: HeliOS is the reference; UTIS carries a per-target offset in the target plane.
    cam = rng.normal(0.0, settings.camera_offset_m, (len(tgt), 2))
    cam_enu = torch.from_numpy(cam[:, :1]) * rights + torch.from_numpy(cam[:, 1:]) * ups
    sigma = settings.centroid_noise_mrad * 1e-3 * cat["slant"][keep] if r else torch.zeros(0)
    noise = torch.from_numpy(rng.standard_normal((r, 2, 2))) * sigma.reshape(-1, 1, 1)
    in_plane = noise[..., :1] * rights[tgk].unsqueeze(1) + noise[..., 1:] * ups[tgk].unsqueeze(1)
    spot = cat["spot"][keep]
    spots = spot.unsqueeze(1) + in_plane
    spots[:, 1] += cam_enu[tgk]
    utis_gone = torch.from_numpy(rng.random(r) < settings.utis_missing)
    spots[utis_gone, 1] = float("nan")
    has_time = torch.from_numpy(rng.random(r) >= settings.time_missing)
    keep_np = keep.numpy()
    weather = np.full((r, len(WEATHER)), np.nan)
    has_weather = rng.random(r) < settings.weather_fraction
    m = int(has_weather.sum())
    for j, (kind, a, b) in enumerate(WEATHER.values()):
        draw = rng.uniform(a, b, m) if kind == "uniform" else rng.normal(a, b, m)
        weather[has_weather, j] = np.abs(draw) if kind == "absnormal" else draw
    records = SimulatedRecords(
        record_id=torch.arange(r, dtype=torch.long) + 100_000, heliostat_index=hidx_all[keep],
        time=torch.from_numpy(ts[keep_np]), target=[planar[i] for i in tgk.tolist()],
        sun_azimuth=az[keep], sun_elevation=el[keep], motor_steps=cat["steps"][keep], true_spot=spot,
        focal_spots=spots, has_time=has_time, drift=drift[keep], weather=torch.from_numpy(weather))
    report = {"heliostats": h, "scheduled": int(len(hs)), "records": r,
              "dropped_unreachable": int((~cat["ok"].bool()).sum()) if len(hs) else 0,
              "dropped_off_target": int((cat["ok"].bool() & ~on_target).sum()) if len(hs) else 0,
              "dropped_below_min_elevation": int((~torch.from_numpy(day)).sum()),
              "months": sched["months"], "months_at_capacity": sched["months_at_capacity"],
              "steps": int(len(steps["time"])), "targets": planar}
    sim = SimulatedPlant(plant, tuple(names), static, steps, float(t_end), end_drift, records,
                         {n: cam_enu[i] for i, n in enumerate(planar)}, settings, report)
    if settings.images:
        _add_images(sim, rng)
    return sim


def _add_images(sim: SimulatedPlant, rng: np.random.Generator) -> None:
    """Defective true surfaces for ``settings.images`` heliostats and camera images of some of their records."""
    s, rec, plant = sim.settings, sim.records, sim.plant
    h = len(plant.field.ids)
    chosen = sorted(rng.choice(h, size=min(s.images, h), replace=False).tolist())
    gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
    sim.surfaces = imaging.true_surfaces(plant.field.facets, chosen, gen)
    for k in chosen:  # a few heliostats; each one's records are rendered in one batch
        rows = (rec.heliostat_index == k).nonzero().flatten().numpy()
        if not len(rows):
            continue
        rows = torch.from_numpy(np.sort(rng.choice(rows, size=min(s.images_per_heliostat, len(rows)),
                                                   replace=False)))
        idx = rec.heliostat_index[rows]
        kin = true_kinematics(plant.field.kinematics.index(idx), sim.static[idx], sim.names, rec.drift[rows])
        sun = direction_from_paint_angles(rec.sun_azimuth[rows], rec.sun_elevation[rows], check_horizon=False)
        one = Surfaces(sim.surfaces.control_points[k:k + 1], sim.surfaces.degree_u, sim.surfaces.degree_v)
        imgs = imaging.render(one, kin, rec.motor_steps[rows], sun, [plant.targets[rec.target[i]] for i in
                                                                    rows.tolist()], plant.sun, rng)
        for r, img in zip(rec.record_id[rows].tolist(), imgs):
            sim.images[int(r)] = img
    sim.report["images"] = len(sim.images)
    sim.report["image_heliostats"] = [plant.field.ids[k] for k in chosen]
