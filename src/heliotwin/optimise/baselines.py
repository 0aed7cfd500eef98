"""The aim-point baselines the optimiser is judged against, on the same exact model and flux limit.

* equator aiming (:func:`heliotwin.raytrace.field.equator_aim_points`, SolarPILOT's "simple");
* :func:`aiming_factor`: the one-parameter aiming strategy of Sánchez-González et al. (Solar Energy 157
  (2017) 1130): heliostats alternately aim above and below the equator, displaced by
  ``k (h/2 - image half-height)``; the smallest ``k`` in [0, 1] that meets the limit (bisection on the exact
  check);
* :func:`image_size_priority`: SolarPILOT's image-size-priority aiming as described by Wagner & Wendelin
  (Solar Energy 171 (2018) 185) and the SolarPILOT manual: heliostats sorted by image size, the largest
  placed first, each at the height of its column where the flux so far is lowest (against each cell's own
  limit, for an allowable-flux map), within ``|y| <= h/2 - k sigma_y``; batched here (groups of heliostats placed
  at once on the image model), with the largest ``k`` (least spillage) that meets the limit found by bisection on
  the exact check.

Both take one :class:`~heliotwin.optimise.problem.AimProblem` (its flux limit a map or one peak limit) and one
options object.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from .. import sunshape as _ss
from ..field.targets import CylinderTarget
from ..raytrace.field import equator_aim_points, reuse_mirror_samples
from .images import _SQ2, ImageModel, _local, _world, calibrate_images
from .problem import AimProblem, AimResult, FluxLimit, evaluate

__all__ = ["BaselineOptions", "aiming_factor", "image_size_priority", "is_cylinder"]


@dataclass(frozen=True)
class BaselineOptions:
    """The heuristics' knobs: map ``resolution`` (rows, cols), bisection ``steps`` on the exact check; for image-size
    priority the placement ``groups``, ``candidates`` heights per heliostat and the largest ``k_max`` [-]."""

    resolution: tuple[int, int] = (20, 48)
    steps: int = 8
    groups: int = 40
    candidates: int = 11
    k_max: float = 3.0


def _bisect(evaluate_at, held, bounds, steps, increasing):
    """Bisection for the parameter nearest the spill-free end that meets the limit on the exact check.

    ``held(result)``: whether a result holds the limit; ``bounds = (lo, hi)``. ``increasing``: the peak grows with
    the parameter (search the largest feasible one); else it falls (search the smallest). Returns the best feasible
    result, or the least violating end.
    """
    lo, hi = bounds
    safe = lo if increasing else hi
    r = evaluate_at(safe)
    r.parameter = safe
    if not held(r):
        return r
    best = r
    a, b = lo, hi
    for _ in range(int(steps)):
        mid = 0.5 * (a + b)
        r = evaluate_at(mid)
        r.parameter = mid
        if held(r):
            best = r
            a, b = (mid, b) if increasing else (a, mid)
        else:
            a, b = (a, mid) if increasing else (mid, b)
    return best


def _held(limit: FluxLimit):
    """``evaluate_at``'s result -> whether it holds ``limit`` (for :func:`_bisect`)."""
    return lambda r: limit.held(r.flux)


@reuse_mirror_samples()  # the rounds' exact checks move the heliostats, never their surfaces
def aiming_factor(problem: AimProblem, options: BaselineOptions = BaselineOptions(), *,
                  model: ImageModel | None = None) -> AimResult:
    """Sánchez-González et al. (2017) aiming factor ``k``: alternate up/down displacement ``k (h/2 - r_img)``.

    The image half-height ``r_img`` is ``2.5`` vertical image standard deviations (the calibrated
    :class:`ImageModel` when given; else the Gaussian beam spread times the slant range plus a quarter of
    the mirror height). ``k`` is the smallest value in [0, 1] that meets the limit (bisection), or 1.
    """
    t0 = time.perf_counter()
    plant, sun, atmosphere, resolution = problem.plant, problem.sun, problem.atmosphere, options.resolution
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    equator = equator_aim_points(rec, pos)
    if model is not None and model.sy.shape[0] == pos.shape[0]:
        r_img = 2.5 * model.sy.to(pos)
    else:
        s = plant.sun
        spread = math.sqrt(_ss.second_moment(s.sunshape, sigma=s.sigma, radius=s.radius, csr=s.csr,
                                             slope_error=s.slope_error))
        slant = torch.linalg.vector_norm(equator - pos, dim=-1)
        r_img = 2.5 * spread * slant + 0.25 * plant.field.height.to(pos)
    room = (0.5 * float(rec.height) - r_img).clamp_min(0.0)
    sign = (1 - 2 * (torch.arange(pos.shape[0], device=pos.device) % 2)).to(pos)
    x0, _ = _local(rec, equator)

    def at(k):
        return evaluate(plant, sun, _world(rec, x0, k * sign * room), atmosphere, resolution)

    limit = FluxLimit.of(problem.limit, resolution)
    best = _bisect(at, _held(limit), (0.0, 1.0), options.steps, increasing=False)
    best.seconds = time.perf_counter() - t0
    return best


def _greedy_heights(model: ImageModel, x, room, order, options: BaselineOptions, limit: FluxLimit):
    """Image-size priority on the image model: heights [H] placing groups of heliostats (in ``order``) one
    group at a time, each heliostat at the candidate height within ``+/- room`` [m] where the map so far plus its
    own image peaks lowest (against each cell's limit when the limit is a map; ties: nearest the equator)."""
    h = x.shape[0]
    u = torch.linspace(-1.0, 1.0, int(options.candidates), dtype=x.dtype, device=x.device)
    y = torch.zeros_like(x)
    gx, _ = model.marginals(x, y)
    canvas = torch.zeros(model.y_edges.shape[0] - 1, model.x_edges.shape[0] - 1, dtype=x.dtype, device=x.device)
    # a uniform limit keeps the peak itself (dividing by it would change nothing but the rounding of ties)
    scale = None if limit.is_uniform else 1.0 / limit.on(x).flip(0)  # ascending y, like the canvas
    for part in torch.tensor_split(order, max(1, min(int(options.groups), h))):
        if part.numel() == 0:
            continue
        cand = u[None, :] * room[part, None]  # [g, C]
        n = part.numel()
        cy = 0.5 * (1.0 + torch.erf((model.y_edges[None, None, :] - cand[..., None])
                                    / (_SQ2 * model.sy[part, None, None])))
        gy = cy[..., 1:] - cy[..., :-1]  # [g, C, rows]
        img = (model.power[part, None, None, None] * gy[..., :, None] * gx[part, None, None, :]) / model.cell_area
        lit = canvas[None, None] + img
        peak = (lit if scale is None else lit * scale).amax(dim=(-2, -1))  # [g, C]
        pick = torch.argmin(peak * (1.0 + 1e-9 * u.abs()[None, :]), dim=1)
        y[part] = cand[torch.arange(n, device=x.device), pick]
        canvas = canvas + img[torch.arange(n, device=x.device), pick].sum(0)
    return y


@reuse_mirror_samples()  # the rounds' exact checks move the heliostats, never their surfaces
def image_size_priority(problem: AimProblem, options: BaselineOptions = BaselineOptions(), *,
                        model: ImageModel | None = None) -> AimResult:
    """SolarPILOT-style image-size-priority aiming (see the module docstring).

    Heliostats sorted by vertical image size (largest first) are placed in ``options.groups`` batches on the
    calibrated :class:`ImageModel`, each at the candidate height (``options.candidates`` across ``|y| <= h/2 - k
    sigma_y``, at its equator column) where the flux so far plus its own image peaks lowest. ``k`` in
    ``[0, k_max]`` is the largest (least spillage) whose aim points meet the limit on the exact check.
    """
    t0 = time.perf_counter()
    plant, sun, atmosphere, resolution = problem.plant, problem.sun, problem.atmosphere, options.resolution
    limit = FluxLimit.of(problem.limit, resolution)
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    if model is None:
        model, _ = calibrate_images(plant, sun, atmosphere, resolution)
    x0, _ = _local(rec, equator_aim_points(rec, pos))
    order = torch.argsort(model.sy, descending=True, stable=True)
    half = 0.5 * float(rec.height)

    def at(k):
        room = (half - k * model.sy).clamp_min(0.0)
        with torch.no_grad():
            y = _greedy_heights(model, x0, room, order, options, limit)
        return evaluate(plant, sun, _world(rec, x0, y), atmosphere, resolution)

    best = _bisect(at, _held(limit), (0.0, float(options.k_max)), options.steps, increasing=True)
    best.seconds = time.perf_counter() - t0
    return best


def is_cylinder(receiver) -> bool:
    """Whether the receiver is an (unrolled) cylinder."""
    return isinstance(receiver, CylinderTarget)
