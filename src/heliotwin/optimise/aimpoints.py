"""Aim points under a flux limit (one peak limit or an allowable-flux map), checked on the exact field model.

This module is the entry point the workflows call (:func:`optimise_aimpoints`, the baselines with their
long-standing signatures, :func:`run_aimpoints_sharded`); the work is done in

* :mod:`heliotwin.optimise.problem`: the problem (plant, sun, :class:`FluxLimit`, target) and the exact model;
* :mod:`heliotwin.optimise.images`: the image model;
* :mod:`heliotwin.optimise.solver` and :mod:`heliotwin.optimise.alm`: the rounds and their augmented Lagrangian
  (options: one :class:`AimSettings`; a warm start: one :class:`WarmStart`);
* :mod:`heliotwin.optimise.baselines`: the aiming factor and image-size priority;
* :mod:`heliotwin.optimise.fluxmap`: allowable-flux maps (HALOS CSV, per-panel limits with a flow-path derating).


Every heliostat gets an aim point on the receiver surface with two degrees of freedom, its unrolled local
coordinates ``(x, y)`` (arc length, height [m]); the height stays on the receiver (projected onto
``|y| <= h/2``), the lateral coordinate within the part of the receiver the heliostat sees. The problem, at one sun,

    maximise P(a)  subject to  F_c(a) <= L_c for every cell c of the reporting map

(or: minimise the mismatch of ``F / P`` to a target shape, subject to the same limit) is judged on the
*exact* field model: :func:`heliotwin.raytrace.field.field_optics` with hard occlusion and the map as
``heliotwin field`` draws it (:func:`check_settings`) on the reporting grid. That model costs about a second
for 2000 heliostats and is not smooth in the aim points (hard occlusion, footprint classes),
so the optimisation runs on a cheap differentiable *image model* corrected by the exact one, in rounds
(surrogate-based optimisation with defect correction; first-order model management as in Alexandrov et al.,
Structural Optimization 15 (1998) 16):

1. the exact model at the current aim points ``a_k`` gives the map ``F_k``, the power per heliostat (with its
   shading, blocking, cosine, attenuation) and its intercept;
2. the image model ``S(a)``: per heliostat one Gaussian image centred on its aim point, power = the exact
   model's power before spillage, spreads = the second moments of the exact model's own footprints at the
   current aim points (:func:`image_moments`: sunshape, slope error, mirror size and focus, and the incidence
   on the receiver's surface, so a tilted or curved receiver and a partial cylinder's edges are the exact
   model's); cell-integrated (erf differences), so the map is a ``[rows, H] x [H, cols]`` product (closed
   around a full cylinder);
3. the corrected model ``S(a) + (F_k - S(a_k))`` equals the exact map at ``a_k``; an augmented Lagrangian
   (Hestenes-Powell; multipliers per cell, ``lambda_c <- max(0, lambda_c + rho g_c)``, kept across rounds)
   with Adam steps solves the problem on it against the internal limit map ``(1 - m) L``;
4. the exact model re-checks the new aim points; the margin ``m`` grows by the observed excess when the
   check fails. Rounds stop when the check passes and the power settles.

With ``field_gradient=True`` the corrected power is also first-order exact at ``a_k``: the difference between
the smooth differentiable field model's power gradient (soft shading and blocking, cosine, attenuation,
intercept; one backward pass through :func:`~heliotwin.raytrace.field.field_optics`) and the image model's is
added as a linear term, so the optimiser sees how occlusion and cosine move with the aim points.

Each aim point stays on the receiver's height and, on a cylinder, within :data:`VISIBLE_HALF_ANGLE` of the
generator line facing its heliostat (a point on the far side is hidden behind the near one).

The answer is the best aim points whose *exact* check passed. When none did (the limit cannot be held with
every heliostat's light on the receiver), the fewest heliostats that make the least violating aim points hold
it go to standby (aimed above the receiver; :attr:`AimResult.standby` counts them): less power, the limit held.
Only when even the whole field on standby violates it is the least violating result returned, with the
violation reported as it is, never clipped.

Sharding (:mod:`heliotwin.distributed`): with a process group every rank holds the parameters of its
contiguous shard of heliostats; image maps and powers are all-reduced at every step, the exact check is
:func:`heliotwin.distributed.field_optics_sharded`; the multipliers and every decision use the reduced
values, so all ranks take the same steps as one process (up to the summation order).
:func:`run_aimpoints_sharded` spawns N local gloo processes for it.

Baselines:

* equator aiming (:func:`heliotwin.raytrace.field.equator_aim_points`, SolarPILOT's "simple");
* :func:`aiming_factor`: the one-parameter aiming strategy of Sánchez-González et al. (Solar Energy 157
  (2017) 1130): heliostats alternately aim above and below the equator, displaced by
  ``k (h/2 - image half-height)``; the smallest ``k`` in [0, 1] that meets the limit (bisection on the exact
  check);
* :func:`image_size_priority`: SolarPILOT's image-size-priority aiming as described by Wagner & Wendelin
  (Solar Energy 171 (2018) 185) and the SolarPILOT manual: heliostats sorted by image size, the largest
  placed first, each at the height of its column where the flux so far is lowest, within
  ``|y| <= h/2 - k sigma_y``; batched here (groups of heliostats placed at once on the image model), with the
  largest ``k`` (least spillage) that meets the limit found by bisection on the exact check.

Shapes: H heliostats; aim points [H, 3] ENU [m]; maps [rows, cols] [W/m^2] (row 0 = top); powers [W].
"""
from __future__ import annotations

import torch

from ..devices import to_device
from ..distributed import run_spawned
from . import baselines as _baselines
from .alm import ALM_PROFILE_DTYPE, ALM_SETTLE, _Adam
from .baselines import BaselineOptions, _bisect, _greedy_heights, is_cylinder
from .images import (
    ImageModel,
    _axis_profile,
    _edges,
    _image_model_at,
    _local,
    _period,
    _world,
    calibrate_images,
    image_moments,
)
from .problem import (
    AimProblem,
    AimResult,
    FluxLimit,
    WarmStart,
    _Group,
    check_settings,
    evaluate,
    load_target,
    target_mismatch,
    uniform_target,
)
from .solver import VISIBLE_HALF_ANGLE, AimSettings, Calibration, _field_power_gradient, _visible_arc, solve

__all__ = ["AimResult", "AimSettings", "AimProblem", "FluxLimit", "WarmStart", "Calibration", "BaselineOptions",
           "ImageModel", "optimise_aimpoints", "solve", "calibrate_images", "to_device", "aiming_factor",
           "image_size_priority", "evaluate", "check_settings", "uniform_target", "load_target", "target_mismatch",
           "run_aimpoints_sharded", "image_moments", "is_cylinder", "VISIBLE_HALF_ANGLE", "ALM_PROFILE_DTYPE",
           "ALM_SETTLE"]

# the private names tests and sibling modules reach for, kept importable from here
_PRIVATE = (_Adam, _Group, _axis_profile, _bisect, _edges, _field_power_gradient, _greedy_heights, _image_model_at,
            _local, _period, _visible_arc, _world)

#: :func:`optimise_aimpoints`' keyword arguments (each one a field of the problem, the warm start or the calibration)
AIM_KEYWORDS = ("atmosphere", "target", "group", "equator", "model", "progress", "device", "start_aim",
                "start_multipliers", "start_margin", "start_field")


def _keywords(kwargs: dict, allowed, where: str) -> None:
    unknown = sorted(set(kwargs) - set(allowed))
    if unknown:
        raise TypeError(f"{where}() got unexpected keyword argument(s) {', '.join(unknown)}")


def optimise_aimpoints(plant, sun: torch.Tensor, peak_limit, settings: AimSettings = AimSettings(),
                       **kwargs) -> AimResult:
    """Aim points that maximise intercepted power (or match ``target``) with every map cell at or below its limit
    on the exact model: :func:`heliotwin.optimise.solver.solve` of the problem these arguments make.

    Parameters
    ----------
    plant : Plant
        Field and ``receiver`` target.
    sun : torch.Tensor, [3]
        Unit vector towards the sun.
    peak_limit : float or FluxLimit or torch.Tensor [rows, cols]
        One peak limit [W/m^2] on every cell, or an allowable-flux map on the settings' resolution.
    settings : AimSettings
        The optimiser's knobs.
    **kwargs
        ``atmosphere``, ``target`` (unit-sum shape [rows, cols]), ``group`` (shard over this process group):
        the problem's; ``equator``, ``model``: the calibration (:func:`calibrate_images`); ``start_aim`` [H, 3],
        ``start_multipliers``, ``start_margin``, ``start_field``: the warm start (:class:`WarmStart`);
        ``progress`` (called with a line per round); ``device`` (move the plant and sun there first).

    Returns
    -------
    AimResult
        As :func:`~heliotwin.optimise.solver.solve`'s.
    """
    _keywords(kwargs, AIM_KEYWORDS, "optimise_aimpoints")
    device = kwargs.get("device")
    if device is not None:
        plant, sun = to_device(plant, device), torch.as_tensor(sun).to(device)
    problem = AimProblem(plant, sun, peak_limit, kwargs.get("atmosphere"), kwargs.get("target"), kwargs.get("group"))
    warm = None
    if kwargs.get("start_aim") is not None:
        warm = WarmStart(kwargs["start_aim"], kwargs.get("start_multipliers"), kwargs.get("start_margin"),
                         kwargs.get("start_field"))
    return solve(problem, settings, warm, calibration=Calibration(kwargs.get("model"), kwargs.get("equator")),
                 progress=kwargs.get("progress"))


def _baseline_args(kwargs: dict, where: str):
    allowed = ("atmosphere", "resolution", "steps", "model", "groups", "candidates", "k_max")
    _keywords(kwargs, allowed, where)
    options = BaselineOptions(**{k: v for k, v in kwargs.items() if k in ("resolution", "steps", "groups",
                                                                             "candidates", "k_max")})
    return options, kwargs.get("model")


def aiming_factor(plant, sun: torch.Tensor, peak_limit, **kwargs) -> AimResult:
    """:func:`heliotwin.optimise.baselines.aiming_factor` of this plant, sun [3] (unit vector, ENU) and limit (a
    float [W/m^2] or a :class:`FluxLimit`); keywords ``atmosphere``, ``resolution``, ``steps``, ``model``."""
    options, model = _baseline_args(kwargs, "aiming_factor")
    problem = AimProblem(plant, sun, peak_limit, kwargs.get("atmosphere"))
    return _baselines.aiming_factor(problem, options, model=model)


def image_size_priority(plant, sun: torch.Tensor, peak_limit, **kwargs) -> AimResult:
    """:func:`heliotwin.optimise.baselines.image_size_priority` of this plant, sun [3] (unit vector, ENU) and limit
    (a float [W/m^2] or a :class:`FluxLimit`); keywords
    ``atmosphere``, ``resolution``, ``model``, ``steps``, ``groups``, ``candidates``, ``k_max``."""
    options, model = _baseline_args(kwargs, "image_size_priority")
    problem = AimProblem(plant, sun, peak_limit, kwargs.get("atmosphere"))
    return _baselines.image_size_priority(problem, options, model=model)


def _optimise_shard(job: dict, group) -> AimResult:
    """One rank of :func:`run_aimpoints_sharded`: this rank's image model (unless a warm start makes its own) and
    aim points of this rank's shard."""
    kw, settings = dict(job["kwargs"]), job["settings"]
    model, equator = None, job["equator"]
    if equator is not None or kw.get("start_aim") is None:
        model, equator = calibrate_images(job["plant"], job["sun"], kw.get("atmosphere"), settings.resolution,
                                          group=group, equator=equator)
    return optimise_aimpoints(job["plant"], job["sun"], job["limit"], settings, group=group, equator=equator,
                              model=model, **kw)


def run_aimpoints_sharded(plant, sun_direction, peak_limit, nproc: int, settings: AimSettings = AimSettings(),
                          **kwargs) -> AimResult:
    """:func:`optimise_aimpoints` sharded over ``nproc`` spawned local gloo processes (CPU); rank 0's result
    (every rank holds the same aim points). ``settings`` and ``kwargs`` as for it (a warm start's ``start_aim``
    ... included), without ``group``, ``model`` and ``progress``. ``equator`` (a keyword): the exact equator result
    (a :class:`~heliotwin.raytrace.field.FieldResult` of :func:`calibrate_images`) the ranks calibrate their image
    models on instead of making the check again; without it the ranks make it, unless a warm start's own check
    serves (as in one process)."""
    equator = kwargs.pop("equator", None)
    _keywords(kwargs, [k for k in AIM_KEYWORDS if k not in ("group", "model", "progress", "equator")],
              "run_aimpoints_sharded")
    limit = peak_limit if isinstance(peak_limit, (FluxLimit, torch.Tensor)) else float(peak_limit)
    job = {"plant": plant, "sun": sun_direction, "limit": limit, "settings": settings, "kwargs": kwargs,
           "equator": equator}
    return run_spawned(_optimise_shard, job, nproc)
