"""Synthetic calibration fixtures shared by the ``test_calibrate_*`` modules (no real data needed).

A PAINT-typical Jülich heliostat (:func:`jueliche_like`), known Stone/Jülich deviations (:data:`TRUE`) and
records simulated from any kinematics by inverse kinematics (:func:`simulate`): the exact answer of every
calibration is known.
"""
from __future__ import annotations

import torch

from heliotwin.calibrate.fitloop import early_stopping_fit, tensor_state
from heliotwin.field import kinematics as K
from heliotwin.field.plant import Kinematics
from heliotwin.field.targets import PlanarTarget
from heliotwin.io.records import RecordTable

F64 = torch.float64

#: Known Stone/Jülich deviations (rad; relative for increments), in the order of ``params.STONE8``.
TRUE = {"initial_angle_1": -0.011, "initial_angle_2": 0.004, "joint_tilt_1_n": 0.003, "joint_tilt_1_u": -0.02,
        "joint_tilt_2_n": 0.002, "concentrator_tilt_e": 0.009, "increment_1": 0.004, "increment_2": -0.003}

#: Calibration target on the tower's north face, 40 m up.
TARGET = PlanarTarget.from_center_normal("synthetic_target", [0.0, -3.24, 40.0], [0.0, 1.0, 0.0], 6.0, 6.0)


def jueliche_like(h: int = 1) -> Kinematics:
    """PAINT-typical Jülich heliostat(s) north of the tower (values as in the PAINT properties files)."""
    def t(v):
        v = torch.tensor(v, dtype=F64)
        return v.expand(h, *v.shape).clone()

    pos = torch.tensor([[8.0 * i - 10.0, 60.0 + 5 * i, 1.5] for i in range(h)], dtype=F64)
    return Kinematics(position=pos, joint_translation=torch.zeros(h, 2, 3, dtype=F64),
                      concentrator_translation=t([0.0, 0.175, 0.0]), joint_tilt=torch.zeros(h, 2, 3, dtype=F64),
                      concentrator_tilt=torch.zeros(h, 3, dtype=F64), increment=t([154166.6667, 154166.6667]),
                      offset=t([0.33531, 0.34077]), pivot_radius=t([0.33809, 0.3191]), initial_angle=t([0.0135, 0.937]),
                      initial_stroke_length=t([0.0757, 0.077]), clockwise=torch.tensor([[False, True]] * h),
                      linear=torch.tensor([[True, True]] * h), min_steps=t([0.0, 0.0]), max_steps=t([69000.0, 75000.0]),
                      min_angle=t([0.0, 0.0]), max_angle=t([1.0, 1.0]))


def simulate(kin_true: Kinematics, n: int, seed: int, noise: float = 0.0, target: PlanarTarget = TARGET) -> RecordTable:
    """``n`` records per heliostat: sun over a year-like range, aim at ``target``'s centre +-1 m.

    ``noise`` [rad] moves each measured spot by a pointing noise of that size (at ~60 m slant range).
    """
    from heliotwin.sun import direction_from_paint_angles

    g = torch.Generator().manual_seed(seed)
    h = kin_true.num_heliostats
    az = (torch.rand(h * n, generator=g, dtype=F64) - 0.5) * 2.4
    el = 0.15 + torch.rand(h * n, generator=g, dtype=F64) * 0.9
    hidx = torch.arange(h).repeat_interleave(n)
    sun = direction_from_paint_angles(az, el)
    jit = (torch.rand(h * n, 2, generator=g, dtype=F64) - 0.5) * 2
    spot = target.to_world(jit)
    steps, ok = K.inverse(kin_true.index(hidx), spot, sun, strict=False)
    assert bool(ok.all())
    if noise:
        spot = spot + target.to_world(torch.randn(h * n, 2, generator=g, dtype=F64) * noise * 2 * 60) - target.center
    return RecordTable.from_arrays([f"S{i}" for i in range(h)], hidx, az, el, steps, spot, target)


def with_weekly_times(batch: RecordTable, start: float = 1.6e9) -> RecordTable:
    """``batch`` with one record a week from ``start`` [s, UNIX], in record order (changed in place)."""
    batch.time = start + torch.arange(len(batch), dtype=F64) * 86400.0 * 7
    return batch


def plant_of(kin: Kinematics, ids=None):
    """A plant (demo site, targets and facets) around synthetic kinematics, to carry a calibration in a
    scenario file."""
    from dataclasses import replace

    from heliotwin.field.demo import demo_plant
    from heliotwin.field.update import select_heliostats

    h = kin.num_heliostats
    plant = demo_plant(num_heliostats=max(h, 2))
    plant = select_heliostats(plant, plant.field.ids[:h])
    ids = list(ids or [f"S{i}" for i in range(h)])
    return replace(plant, field=replace(plant.field, ids=ids, kinematics=kin))


def scenario_round_trip(tmp_path, kin: Kinematics, model):
    """Write ``model`` as a calibrated scenario of a plant around ``kin`` and read it back."""
    from heliotwin.calibrate.scenario import save_calibration
    from heliotwin.io.scenario import load_scenario

    return load_scenario(save_calibration(tmp_path / "calibrated.h5", plant_of(kin, model.heliostat_ids), model))


#: Spread of the Stone/Jülich deviations over a synthetic plant (rad; relative for increments), ``STONE8`` order:
#: the axis offsets share a plant-wide part (the installation's) plus a few mrad per heliostat.
PLANT_MEAN = (0.004, -0.006, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
PLANT_SPREAD = (3e-3, 3e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3)


def synthetic_plant(num_heliostats: int, records: int, *, seed: int = 0, noise: float = 1e-3,
                    days: float = 365.0):
    """A whole plant with known deviations and calibration records simulated from them (no real data).

    Parameters
    ----------
    num_heliostats : int
        H heliostats of :func:`~heliotwin.field.demo.demo_plant` (its nominal kinematics).
    records : int
        Records per heliostat (R = H x records), one every ``days / records`` days, sun over a year-like
        range, aimed at the lower Jülich target's centre +-1 m.
    noise : float
        Pointing noise per record [rad]: the measured centroid (HeliOS) moves by it on the target; the UTIS
        centroid of the same spot by another draw of half of it.

    Returns
    -------
    dataset : PaintDataset
        Root ``"synthetic"``; records with both centroids (``focal_spots``), so the pipeline runs as on PAINT.
    true_delta : torch.Tensor, [H, 8]
        The deviations the records were simulated with (``params.STONE8`` order).
    """
    from dataclasses import replace

    from heliotwin.calibrate.params import STONE8, apply_deviations
    from heliotwin.field.demo import demo_plant
    from heliotwin.io.paint import PaintDataset
    from heliotwin.sun import direction_from_paint_angles

    g = torch.Generator().manual_seed(seed)
    plant = demo_plant(num_heliostats=num_heliostats, seed=seed)
    h, n = num_heliostats, records
    nominal = plant.field.kinematics
    true = torch.tensor(PLANT_MEAN, dtype=F64) + torch.randn(h, 8, generator=g, dtype=F64) * torch.tensor(
        PLANT_SPREAD, dtype=F64)
    kin_true = apply_deviations(nominal, true, STONE8)
    target = plant.targets["solar_tower_juelich_lower"]
    hidx = torch.arange(h).repeat_interleave(n)
    t_day = torch.arange(n, dtype=F64).repeat(h) * (days / n) + torch.rand(h * n, generator=g, dtype=F64)
    az = (torch.rand(h * n, generator=g, dtype=F64) - 0.5) * 2.2
    el = 0.2 + torch.rand(h * n, generator=g, dtype=F64) * 0.8
    sun = direction_from_paint_angles(az, el)
    spot = target.to_world((torch.rand(h * n, 2, generator=g, dtype=F64) - 0.5) * 2)
    steps, ok = K.inverse(kin_true.index(hidx), spot, sun, strict=False)
    slant = (spot - kin_true.position[hidx]).norm(dim=-1, keepdim=True)
    heliOS = spot + (target.to_world(torch.randn(h * n, 2, generator=g, dtype=F64)) - target.center) * noise * slant
    utis = spot + (target.to_world(torch.randn(h * n, 2, generator=g, dtype=F64)) - target.center) * noise * slant / 2
    table = RecordTable.from_arrays(list(plant.field.ids), hidx, az, el, steps, heliOS, target,
                                    time=1.6e9 + 86400.0 * t_day)
    table.focal_spots = torch.stack([heliOS, utis], 1)
    table.source = ["HeliOS"] * len(table)
    table = table.subset(ok)
    return PaintDataset("synthetic", replace(plant, field=replace(plant.field, kinematics=nominal)), table), true


def walk_fit(targets, iterations, validated=None, **kw):
    """A toy run of the fit loop: x [H, 1] climbs by 1 per step; heliostat h's validation error is
    |x - targets[h]| (``validated``: which heliostats have validation records; default all). Returns (x, log)."""
    x = torch.zeros(len(targets), 1, dtype=torch.float64)
    t = torch.tensor(targets, dtype=torch.float64)

    def step():
        x.add_(1.0)
        return float(x.sum())

    ok = torch.ones(len(targets), dtype=torch.bool) if validated is None else torch.tensor(validated)
    log = early_stopping_fit(step, lambda: (x[:, 0] - t).abs(), tensor_state(x), iterations, validated=ok, **kw)
    return x, log
