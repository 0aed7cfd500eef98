"""Images of one heliostat's surface for its observations: the learner's forward model and evaluation.

Per image: heliostat-frame mirror samples (:func:`heliotwin.field.facets.surface_points`) -> world frame by the
observation's pose (:func:`heliotwin.scene.to_world`) -> flux in the PAINT-style centred window by the ``conv``
integrator (:func:`heliotwin.raytrace.conv.render_centered`; exact sunshape, noise-free).

Shapes: B images, N mirror samples, R window pixels per side. Units: metres, radians, W/m^2.
"""
from __future__ import annotations

import torch

from ..field import facets as facet_ops
from ..field.plant import SunSettings, Surfaces
from ..field.targets import PlanarTarget
from ..io.images import CENTERED_WINDOW_M
from ..raytrace.conv import kernel_spectrum, mean_footprint_kernel, render_centered
from ..raytrace.flux import cross_correlation
from ..scene import to_world
from . import losses
from .observations import Observations

__all__ = ["predict_images", "render_samples", "evaluate_images"]


def _groups(targets: list) -> list[tuple[PlanarTarget, list[int]]]:
    out: dict[int, tuple] = {}
    for i, t in enumerate(targets):
        out.setdefault(id(t), (t, []))[1].append(i)
    return list(out.values())


def _world_samples(surfaces: Surfaces, obs: Observations, samples):
    """World-frame float32 mirror samples [B, N, 3] x2, areas [B, N], sun [B, 3] (rays are float32)."""
    pts, nrm, area = facet_ops.surface_points(surfaces, samples)  # [1, N, 3]
    rot = obs.rotation.to(pts)
    pw, nw = to_world(rot, obs.concentrator.to(pts), pts, nrm, torch.float32)
    return pw, nw, area.to(torch.float32).expand(len(obs), -1), obs.sun.to(pw)


def predict_images(surfaces: Surfaces, obs: Observations, sun: SunSettings, *, samples=(24, 24), resolution: int = 64,
                   size_m: float = CENTERED_WINDOW_M, kernels: dict | None = None,
                   kernel_supersample: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Centred-window images of one heliostat for B poses (conv integrator; differentiable w.r.t. the surface).

    Parameters
    ----------
    surfaces : Surfaces
        One heliostat (control points ``[1, F, nu, nv, 3]`` [m], heliostat frame).
    obs : Observations
        The B recordings (poses, sun directions, targets; optional fixed window centres).
    sun : SunSettings
        Sunshape, DNI and reflectivity of the rays.
    samples : (int, int)
        Mirror samples per facet and direction (N = F * samples[0] * samples[1]).
    resolution, size_m : int, float
        Window pixels per side and side [m].
    kernels : dict, optional
        Cache ``image index -> footprint kernel``, filled on first use (the kernel is a second-order
        function of the surface; reusing it keeps the optimisation cheap and deterministic); also holds the
        kernels' spectra under ``("spectrum", image index)`` (derived from the kernels: a cache restored with
        the kernels alone rebuilds them identically).
    kernel_supersample : int
        Supersampling of the footprint kernel (:func:`heliotwin.raytrace.conv.mean_footprint_kernel`).

    Returns
    -------
    images : torch.Tensor, [B, R, R]
        Flux [W/m^2].
    centers : torch.Tensor, [B, 2]
        Window centres (local target coordinates [m]).
    miss : torch.Tensor, shape ()
        Soft miss penalty [m^2]: power-weighted mean squared overshoot of hits beyond the window, averaged over
        the B images (a scalar, differentiable).
    """
    pw, nw, ar, sund = _world_samples(surfaces, obs, samples)
    images, centers, _, miss = render_samples(pw, nw, ar, sund, obs, sun, resolution=resolution, size_m=size_m,
                                              kernels=kernels, kernel_supersample=kernel_supersample)
    return images, centers, miss


def render_samples(pw: torch.Tensor, nw: torch.Tensor, ar: torch.Tensor, sund: torch.Tensor, obs: Observations,
                   sun: SunSettings, *, resolution: int = 64, size_m: float = CENTERED_WINDOW_M,
                   kernels: dict | None = None, kernel_supersample: int = 4
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`predict_images` from world-frame mirror samples: each image its own samples (its own surface).

    Parameters
    ----------
    pw, nw : torch.Tensor, [B, N, 3]
        World ENU mirror samples [m] / unit normals (float32 rays), one set per image.
    ar : torch.Tensor, [B, N]
        Areas [m^2].
    sund : torch.Tensor, [B, 3]
        Unit sun directions.
    obs : Observations
        The B recordings (targets; optional fixed window centres).
    sun, resolution, size_m, kernels, kernel_supersample
        As :func:`predict_images`.

    Returns
    -------
    images : torch.Tensor, [B, R, R]
        Flux [W/m^2].
    centers : torch.Tensor, [B, 2]
        Window centres (local [m]).
    miss_per_image : torch.Tensor, [B]
        Soft miss penalty per image [m^2].
    miss : torch.Tensor, shape ()
        Its mean over the B images (per target group, as :func:`predict_images` returns it).
    """
    b = len(obs)
    groups = _groups(obs.targets)
    order = [i for _, idx in groups for i in idx]
    whole = order == list(range(b))  # one target, or the groups already in order: no gather at all
    images, centers, per_image, misses = [], [], [], []
    for target, idx in groups:
        take = slice(idx[0], idx[-1] + 1) if whole else idx
        spectrum = None
        if kernels is not None:
            if not all(i in kernels for i in idx):  # computed once, then reused (also by render_centered now)
                kern_new = mean_footprint_kernel(pw[idx], nw[idx], ar[idx], sund[idx], target, sun,
                                                 size_m / resolution, 2 * resolution, kernel_supersample)
                for j, i in enumerate(idx):
                    kernels[i] = kern_new[j]
            if not all(("spectrum", i) in kernels for i in idx):  # the FFT of the kernel, once, not every step
                spec_new = kernel_spectrum(torch.stack([kernels[i] for i in idx]).to(pw.dtype), resolution)
                for j, i in enumerate(idx):
                    kernels[("spectrum", i)] = spec_new[j]
            spectrum = torch.stack([kernels[("spectrum", i)] for i in idx])
        fixed = None if obs.centers is None else obs.centers[take].to(pw)
        res = render_centered(pw[take], nw[take], ar[take], sund[take], target, sun, size_m=size_m,
                              resolution=resolution, spectrum=spectrum, center=fixed)
        images.append(res.image)
        centers.append(res.center)
        per_image.append(res.miss_per_image)
        misses.append(res.miss * len(idx))
    # Groups joined, then one gather back to image order: per-image selects would each cost a full-size zero
    # tensor in the backward pass.
    out = [x[0] if len(x) == 1 else torch.cat(x) for x in (images, centers, per_image)]
    if not whole:
        back = torch.empty(b, dtype=torch.long, device=pw.device)  # made once where the images are
        back[torch.tensor(order, device=pw.device)] = torch.arange(b, device=pw.device)
        out = [x[back] for x in out]
    return out[0], out[1], out[2], sum(misses) / b


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
