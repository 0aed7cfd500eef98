"""Images of one heliostat's surface for its observations: the learner's forward model and evaluation.

Per image: heliostat-frame mirror samples (:func:`heliotwin.field.facets.surface_points`) -> world frame by the
observation's pose, optionally times a small learned orientation correction
(:func:`heliotwin.scene.to_world`) -> flux in the PAINT-style centred window by the ``conv`` integrator
(:func:`heliotwin.raytrace.conv.render_centered`; exact sunshape, noise-free) or, for training with noise,
the ``mc`` tracer in the same window.

Shapes: B images, N mirror samples, R window pixels per side. Units: metres, radians, W/m^2.
"""
from __future__ import annotations

import torch

from ..errors import HeliotwinError
from ..field import facets as facet_ops
from ..field import kinematics as kin_ops
from ..field.plant import SunSettings, Surfaces
from ..field.targets import PlanarTarget
from ..io.images import CENTERED_WINDOW_M
from ..raytrace.conv import mean_footprint_kernel, render_centered
from ..raytrace.flux import cross_correlation
from ..raytrace.montecarlo import RaySampling, trace_mc
from ..scene import check_integrator, to_world
from . import losses
from .observations import Observations

__all__ = ["correction_rotation", "predict_images", "evaluate_images", "trace_mc_centered", "LEARNING_INTEGRATORS",
           "check_learning_integrator"]

#: Integrators the surface learner can render with (``mc`` for noisy training; ``conv`` otherwise).
LEARNING_INTEGRATORS = ("conv", "mc")


def correction_rotation(delta: torch.Tensor) -> torch.Tensor:
    """Small rotation in the heliostat frame from two angles (about its x then y axis).

    Parameters
    ----------
    delta : torch.Tensor, [B, 2]
        [rad].

    Returns
    -------
    torch.Tensor, [B, 3, 3]
        ``R_x(delta_0) R_y(delta_1)``; right-multiplied onto ``R_world_heliostat``.
    """
    return kin_ops.rot_e(delta[:, 0]) @ kin_ops.rot_n(delta[:, 1])


def _groups(targets: list) -> list[tuple[PlanarTarget, list[int]]]:
    out: dict[int, tuple] = {}
    for i, t in enumerate(targets):
        out.setdefault(id(t), (t, []))[1].append(i)
    return list(out.values())


def _world_samples(surfaces: Surfaces, obs: Observations, samples, delta):
    """World-frame float32 mirror samples [B, N, 3] x2, areas [B, N], sun [B, 3] (rays are float32)."""
    pts, nrm, area = facet_ops.surface_points(surfaces, samples)  # [1, N, 3]
    rot = obs.rotation.to(pts)
    if delta is not None:
        rot = rot @ correction_rotation(delta.to(pts))
    pw, nw = to_world(rot, obs.concentrator.to(pts), pts, nrm, torch.float32)
    return pw, nw, area.to(torch.float32).expand(len(obs), -1), obs.sun.to(pw)


def check_learning_integrator(integrator: str) -> None:
    """One-line :class:`HeliotwinError` unless ``integrator`` is one of :data:`LEARNING_INTEGRATORS`."""
    check_integrator(integrator)
    if integrator not in LEARNING_INTEGRATORS:
        raise HeliotwinError(f"surface learning renders with {' or '.join(LEARNING_INTEGRATORS)}, got {integrator!r}")


def predict_images(surfaces: Surfaces, obs: Observations, sun: SunSettings, *, samples=(24, 24), resolution: int = 64,
                   size_m: float = CENTERED_WINDOW_M, delta: torch.Tensor | None = None, kernels: dict | None = None,
                   integrator: str = "conv", generator: torch.Generator | None = None, rays_per_point: int = 32,
                   kernel_supersample: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Centred-window images of one heliostat for B poses (differentiable w.r.t. the surface and ``delta``).

    Parameters
    ----------
    surfaces : Surfaces
        One heliostat (``[1, F, nu, nv, 3]``).
    obs : Observations
    sun : SunSettings
    samples : (int, int)
    resolution, size_m : int, float
        Window pixels per side and side [m].
    delta : torch.Tensor, [B, 2], optional
        Orientation corrections [rad].
    kernels : dict, optional
        Cache ``image index -> footprint kernel``, filled on first use (the kernel is a second-order
        function of the surface; reusing it keeps the optimisation cheap and deterministic).
    integrator : {"conv", "mc"}
        ``conv``: splat * sun-cone kernel (:mod:`heliotwin.raytrace.conv`, noise-free);
        ``mc``: :func:`heliotwin.raytrace.trace_mc` in the same window (``generator``, default seed 0 on
        the surface's device; the window centre is then held fixed within a step).

    Returns
    -------
    images : torch.Tensor, [B, R, R]
        Flux [W/m^2].
    centers : torch.Tensor, [B, 2]
        Window centres (local target coordinates [m]).
    miss : torch.Tensor, []
        Soft miss penalty [m^2].
    """
    check_learning_integrator(integrator)
    pw, nw, ar, sund = _world_samples(surfaces, obs, samples, delta)
    b = len(obs)
    images, centers, misses = [None] * b, [None] * b, []
    for target, idx in _groups(obs.targets):
        kern = None
        if kernels is not None:
            if not all(i in kernels for i in idx):  # computed once, then reused (also by render_centered now)
                kern_new = mean_footprint_kernel(pw[idx], nw[idx], ar[idx], sund[idx], target, sun,
                                                 size_m / resolution, 2 * resolution, kernel_supersample)
                for j, i in enumerate(idx):
                    kernels[i] = kern_new[j]
            kern = torch.stack([kernels[i] for i in idx])
        fixed = None if obs.centers is None else obs.centers[idx].to(pw)
        res = render_centered(pw[idx], nw[idx], ar[idx], sund[idx], target, sun, size_m=size_m,
                              resolution=resolution, kernel=kern, center=fixed)
        img = res.image
        if integrator == "mc":
            c = res.center.detach().to(torch.float64)
            win = torch.stack((c[:, 0] - size_m / 2, c[:, 1] - size_m / 2, torch.full_like(c[:, 0], size_m),
                               torch.full_like(c[:, 0], size_m)), -1)
            gen = generator or torch.Generator(device=pw.device).manual_seed(0)
            img = trace_mc(pw[idx], nw[idx], ar[idx], sund[idx], target, resolution=(resolution, resolution), sun=sun,
                           sampling=RaySampling(rays_per_point), generator=gen, window=win, clip_to_target=False).bitmap
        for j, i in enumerate(idx):
            images[i] = img[j]
            centers[i] = res.center[j]
        misses.append(res.miss * len(idx))
    return torch.stack(images), torch.stack(centers), sum(misses) / b


def evaluate_images(surfaces: Surfaces, obs: Observations, sun: SunSettings, *, samples=(24, 24),
                    resolution: int = 64, size_m: float = CENTERED_WINDOW_M) -> dict:
    """Per-image L1 (unit-sum images) and cross-correlation against ``obs.images`` (conv integrator).

    Returns
    -------
    dict with ``l1`` [B], ``cc`` [B] (lists of float), ``images`` [B, R, R] (predicted, detached, W/m^2) and
    ``centers`` [B, 2] (window centres, local [m]).
    """
    with torch.no_grad():
        pred, centers, _ = predict_images(surfaces, obs, sun, samples=samples, resolution=resolution, size_m=size_m)
        meas = obs.images.to(pred)
        return {"l1": losses.l1(pred, meas).tolist(),
                "cc": cross_correlation(losses.normalize(pred), losses.normalize(meas)).tolist(),
                "images": pred, "centers": centers}


def trace_mc_centered(surfaces: Surfaces, obs: Observations, sun: SunSettings, *, samples=(24, 24),
                      resolution: int = 64, size_m: float = CENTERED_WINDOW_M, rays_per_point: int = 64,
                      seed: int = 0) -> torch.Tensor:
    """Monte-Carlo images (:func:`heliotwin.raytrace.trace_mc`) in the same centred windows.

    The window centre is the one the conv images use (the predicted centroid of the central-ray hits,
    or ``obs.centers`` when fixed), so both integrators are compared on identical windows. One image at a
    time from one generator (seeded ``seed`` on the surface's device), so image i's noise does not depend
    on how many images are traced with it.

    Returns
    -------
    torch.Tensor, [B, R, R]
        Flux [W/m^2].
    """
    with torch.no_grad():
        pw, nw, ar, sund = _world_samples(surfaces, obs, samples, None)
        gen = torch.Generator(device=pw.device).manual_seed(int(seed))
        _, centers, _ = predict_images(surfaces, obs, sun, samples=samples, resolution=resolution, size_m=size_m)
        out = []
        for i in range(len(obs)):
            c = centers[i].to(torch.float64)
            window = (float(c[0]) - size_m / 2, float(c[1]) - size_m / 2, size_m, size_m)
            img = trace_mc(pw[i], nw[i], ar[i], sund[i], obs.targets[i], resolution=(resolution, resolution), sun=sun,
                           sampling=RaySampling(rays_per_point), generator=gen, window=window, clip_to_target=False)
            out.append(img.bitmap[0])
        return torch.stack(out)
