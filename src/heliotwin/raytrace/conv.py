"""Exact-sunshape convolution integrator ("conv"): mirror-point splat * sun-cone kernel, noise-free.

Model
-----
Every mirror sample ``p`` (unit normal ``n``, area ``A``) reflects the *central* sun ray ``-s`` into
``r = reflect(-s, n)``, which hits the target plane at ``h(p)``. The flux is the sum over samples of the
sun-cone footprint centred on ``h(p)``. Across one heliostat (a few metres at tens of metres slant range)
the footprint is the same up to a few per cent, so the image is

    E = (DNI rho / pixel_area) * [ sum_p A_p max(n_p . s, 0) tent(x - h_p) ]  (*)  K

with ``tent`` the bilinear splat (:func:`heliotwin.raytrace.splat.splat_bilinear`) and ``K`` the footprint
of the angular distribution (sunshape convolved with the slope-error Gaussian, ``2 sigma_slope`` per axis
on the reflected ray) projected obliquely onto the plane through the mean ray. Unlike a per-point Gaussian
this keeps the *real* sunshape (Buie disc + aureole, or pillbox) and costs one FFT per image, independent
of the number of mirror samples; gradients w.r.t. the hit positions are exact (no sampling noise).

Why not the "gaussian" integrator
---------------------------------
:func:`heliotwin.raytrace.trace_gaussian` replaces the sun cone by its *Gaussian-equivalent* second moment,
footprint per point (or one mean Gaussian convolved with the splat). That is right for field flux maps,
but a Buie sun is a sharp-edged disc plus a faint wide aureole, not a Gaussian: with a Gaussian of the same
variance the spot of a near-focused heliostat has the wrong edge and tail, and a surface learned against
real images would absorb that error as fake shape ("learned blur"). Here the kernel is the *exact*
tabulated angular density (sunshape convolved with the slope-error Gaussian) projected onto the target,
applied by one FFT per image, and the window is centred like PAINT's. For a Gaussian sun both integrators
estimate the same image: ``tests/test_raytrace.py`` checks that their normalised L1 stays below 0.03
(measured 0.013-0.016 at 32x32 px; the residual is the Gaussian-vs-tabulated kernel discretisation and
the per-point vs mean footprint). The Monte-Carlo tracer remains the independent check.

Centred window
--------------
PAINT's ``-flux-centered.png`` is a 6 m x 6 m window (:data:`heliotwin.raytrace.flux.CENTERED_WINDOW_M`)
centred on the *measured* spot's own centroid. We do the same with the prediction (window centred on the
predicted power-weighted centroid of the hits, which a centrally symmetric kernel leaves unchanged), so a
tracking error never reads as surface shape.

Shapes: B images, N mirror samples; R window pixels per side. Units: metres, radians, W/m^2.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import torch
import torch.nn.functional as F

from .. import sunshape as sunshape_ops
from ..errors import HeliotwinError
from ..field.plant import SunSettings
from ..field.targets import PlanarTarget
from ..geometry import ray_plane, reflect
from .flux import CENTERED_WINDOW_M, FluxImage
from .splat import splat_bilinear

__all__ = ["reflect_to_plane", "angular_density", "footprint_kernel", "mean_footprint_kernel", "render_centered",
           "RenderResult", "trace_conv", "fft_size", "kernel_spectrum"]

#: Angular grid step of the tabulated sunshape [rad].
_ANG_STEP = 0.2e-3


def fft_size(resolution: int) -> int:
    """Side [px] of the FFT grid of :func:`render_centered` for an ``R``-pixel window (R even): ``5 R / 2``.

    The splat and the kernel are ``2R x 2R`` and the window is ``full[q]`` for ``q`` in ``[3R/2, 5R/2)`` of their
    linear convolution ``full[q] = sum_m splat[m] K[q - m]`` (per axis), where ``m + k`` spans ``[0, 4R - 2]``.
    An FFT of side ``n`` (at least ``2R``, so neither input is cut) gives the *circular* convolution, in which
    every term with ``m + k = q + j n`` (any integer ``j``) lands on ``q``. The window is alias-free when only
    ``j = 0`` is in range for all its ``q``: ``3R/2 + n > 4R - 2`` (``n >= 5R/2 - 1``) and ``5R/2 - 1 - n < 0``
    (``n >= 5R/2``). So ``n = 5R/2`` (160 for R = 64, instead of the full linear size ``4R = 256``) gives the
    window exactly (``tests/test_raytrace.py`` checks it against ``4R`` to float precision, and that ``5R/2 - 1``
    aliases) at ``(160/256)^2 = 0.39`` of the FFT work.
    """
    return 5 * int(resolution) // 2


def kernel_spectrum(kernel: torch.Tensor, resolution: int) -> torch.Tensor:
    """The kernel's spectrum as :func:`render_centered` uses it (for callers that reuse one kernel across steps).

    Parameters
    ----------
    kernel : torch.Tensor, [B, 2R, 2R]
        Footprint kernel (:func:`mean_footprint_kernel`, ``size = 2 * resolution``).
    resolution : int
        R, window pixels per side.

    Returns
    -------
    torch.Tensor, [B, n, m], complex
        ``rfft2`` on the ``n x n`` grid of :func:`fft_size` (``m = n // 2 + 1``), in the kernel's precision
        (complex64 for float32).
    """
    n = fft_size(resolution)
    return torch.fft.rfft2(kernel, s=(n, n))


def reflect_to_plane(points: torch.Tensor, normals: torch.Tensor, sun_direction: torch.Tensor,
                     target: PlanarTarget) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Central-ray hits of mirror samples on a plane.

    Parameters
    ----------
    points, normals : torch.Tensor, [B, N, 3]
        World ENU [m] / unit.
    sun_direction : torch.Tensor, [B, 3]
    target : PlanarTarget

    Returns
    -------
    local : torch.Tensor, [B, N, 2]
        Hit ``(x, y)`` in target coordinates [m] (rays leaving the plane are pushed far away).
    reflected : torch.Tensor, [B, N, 3]
        Unit reflected directions.
    distance : torch.Tensor, [B, N]
        Slant range mirror -> hit [m] (>= 0).
    """
    s = sun_direction.to(points).unsqueeze(1)
    r = reflect(-s, normals)
    nrm = target.normal.to(points)
    t, _ = ray_plane(points, r, target.center.to(points), nrm, eps=1e-6)
    # Rays not travelling towards the plane (r . n >= 0) would divide by ~0 or hit from behind: give them a
    # huge finite range, which puts the hit far outside any window (weight 0 after the splat) with finite
    # gradients.
    toward = (r * nrm).sum(-1) < -1e-6
    t = torch.where(toward, t, torch.full_like(t, 1e6))
    hits = points + t.unsqueeze(-1) * r
    return target.to_local(hits), r, t


@lru_cache(maxsize=8)
def _angular_density_cached(sunshape: str, sigma: float, radius: float, csr: float, slope_error: float):
    spread = 2.0 * slope_error  # per axis on the reflected ray
    extent = sunshape_ops.angular_extent(sunshape, sigma=sigma, radius=radius)
    half = extent + 4.5 * spread + 2 * _ANG_STEP
    n = int(math.ceil(half / _ANG_STEP))
    # One quadrant (a, b >= 0), mirrored: the profile is radially symmetric and the sub-samples below are
    # symmetric about each cell centre, so the grid is even in a and in b (a quarter of the profile evaluations).
    ax = torch.arange(0, n + 1, dtype=torch.float64) * _ANG_STEP
    a, b = torch.meshgrid(ax, ax, indexing="ij")
    # 3x3 supersampling of the radial profile so the sharp disc edge is area-weighted, not aliased.
    sub = (torch.arange(3, dtype=torch.float64) - 1.0) / 3.0 * _ANG_STEP
    quad = torch.zeros_like(a)
    for da in sub:
        for db in sub:
            th = torch.sqrt((a + da) ** 2 + (b + db) ** 2)
            quad += sunshape_ops.radial_profile(sunshape, th, sigma=sigma, radius=radius, csr=csr)
    mirror = (torch.arange(2 * n + 1) - n).abs()
    dens = quad[mirror][:, mirror]
    if spread > 0:
        # Separable Gaussian blur = convolution with the slope-error scatter.
        k = int(math.ceil(4.5 * spread / _ANG_STEP))
        g = torch.exp(-0.5 * ((torch.arange(-k, k + 1, dtype=torch.float64) * _ANG_STEP) / spread) ** 2)
        g = g / g.sum()
        # The zero-padded separable convolution as band @ dens @ band^T: the same sums as conv2d, whose im2col
        # buffer (G^2 x (2k+1) values, ~3 GB at slope error 5 mrad) set the learner's peak memory.
        i = torch.arange(dens.shape[-1])
        off = i[None, :] - i[:, None] + k
        band = torch.where((off >= 0) & (off <= 2 * k), g[off.clamp(0, 2 * k)], torch.zeros((), dtype=g.dtype))
        dens = band @ dens @ band.T
    dens = dens / (dens.sum() * _ANG_STEP ** 2)
    return dens, float(n * _ANG_STEP)


def angular_density(sun: SunSettings) -> tuple[torch.Tensor, float]:
    """Tabulated angular density of a reflected ray (sunshape * slope error), radially symmetric.

    Parameters
    ----------
    sun : SunSettings
        ``sunshape`` (gaussian/pillbox/buie), ``sigma``, ``radius``, ``csr``, ``slope_error``.

    Returns
    -------
    density : torch.Tensor, [G, G], float64
        [1/rad^2] on a square grid of step 0.2 mrad (integrates to 1).
    half_width : float
        Grid half width [rad] (centre of the first/last cell).
    """
    return _angular_density_cached(str(sun.sunshape), float(sun.sigma), float(sun.radius), float(sun.csr),
                                   float(sun.slope_error))


def footprint_kernel(sun: SunSettings, mean_ray: torch.Tensor, distance: torch.Tensor, target: PlanarTarget,
                     pixel: float, size: int, supersample: int = 4) -> torch.Tensor:
    """Sun-cone footprint on the target plane on a pixel grid (the kernel ``K`` of the module docs).

    Parameters
    ----------
    sun : SunSettings
    mean_ray : torch.Tensor, [B, 3]
        Power-weighted mean reflected direction (unit).
    distance : torch.Tensor, [B]
        Mean slant range [m].
    target : PlanarTarget
    pixel : float
        Pixel side [m].
    size : int
        Kernel side [px] (even; the centre is pixel ``size // 2``).
    supersample : int
        Sub-samples per pixel and axis.

    Returns
    -------
    torch.Tensor, [B, size, size], float64
        Fraction of a ray bundle's power per pixel (sums to <= 1; the rest falls outside the kernel).
        Row index grows downwards (-y), column index along +x (PAINT orientation).
    """
    dens, half = angular_density(sun)
    r = mean_ray.to(torch.float64)
    nrm, right, up = (t.to(r) for t in (target.normal, target.right, target.up))
    # Any orthonormal frame of r works (the density is radially symmetric).
    helper = torch.where((r[:, 2].abs() < 0.9)[:, None], r.new_tensor([0.0, 0.0, 1.0]).expand_as(r),
                         r.new_tensor([1.0, 0.0, 0.0]).expand_as(r))
    u = torch.linalg.cross(helper, r)
    u = u / u.norm(dim=-1, keepdim=True)
    v = torch.linalg.cross(r, u)
    rn = (r @ nrm).unsqueeze(-1)
    gu = u - r * (u @ nrm).unsqueeze(-1) / rn
    gv = v - r * (v @ nrm).unsqueeze(-1) / rn
    dist = distance.to(torch.float64)
    m = torch.stack((torch.stack((gu @ right, gv @ right), -1), torch.stack((gu @ up, gv @ up), -1)), -2)
    m = m * dist[:, None, None]  # [B, 2, 2]: angle (a, b) -> local displacement (dx, dy)
    minv = torch.linalg.inv(m)
    jac = minv.det().abs()  # d(angle area) / d(target area)
    s = int(supersample)
    dev = r.device
    off = (torch.arange(size, dtype=torch.float64, device=dev) - size // 2)
    sub = (torch.arange(s, dtype=torch.float64, device=dev) + 0.5) / s - 0.5
    cx = (off[:, None] + sub[None, :]).reshape(-1) * pixel  # [size*s]
    # angle = minv @ (dx, dy) with dx = cx along columns and dy = -cx along rows (row grows downwards);
    # built by broadcasting in float32 (no [B, P, 2] float64 intermediates: this is the costly part).
    mi = (minv / half).to(torch.float32)  # grid_sample coordinates: -1/+1 = first/last cell centre
    c32 = cx.to(torch.float32)
    grid = torch.empty(mi.shape[0], c32.numel(), c32.numel(), 2, dtype=torch.float32, device=dev)
    # grid_sample: x indexes the last (column) axis = b (angle 1), y the row axis = a (angle 0).
    for k, row in ((0, 1), (1, 0)):
        grid[..., k] = (mi[:, row, 0, None, None] * c32[None, None, :] - mi[:, row, 1, None, None] * c32[None, :, None])
    vals = F.grid_sample(dens.to(dev, torch.float32).expand(grid.shape[0], 1, -1, -1), grid, mode="bilinear",
                         padding_mode="zeros", align_corners=True)[:, 0].to(torch.float64)
    vals = vals.reshape(-1, size, s, size, s).mean((2, 4))
    return vals * jac[:, None, None] * pixel * pixel


@torch.no_grad()
def _mean_kernel(w, refl, dist, target, sun, pixel, size, supersample=4):
    # The kernel of the power-weighted mean ray and slant range; it depends on the surface only to second
    # order, so it is built without autograd (and callers may cache it across optimiser steps).
    wsum = w.sum(-1).clamp_min(1e-12)
    mean_ray = (w.unsqueeze(-1) * refl).sum(1) / wsum.unsqueeze(-1)
    mean_ray = mean_ray / mean_ray.norm(dim=-1, keepdim=True)
    mdist = (w * dist).sum(1) / wsum
    return footprint_kernel(sun, mean_ray, mdist, target, pixel, size, supersample)


def mean_footprint_kernel(points: torch.Tensor, normals: torch.Tensor, areas: torch.Tensor,
                          sun_direction: torch.Tensor, target: PlanarTarget, sun: SunSettings, pixel: float,
                          size: int, supersample: int = 4) -> torch.Tensor:
    """The kernel :func:`render_centered` builds when none is passed (for callers that cache it).

    Parameters
    ----------
    points, normals : torch.Tensor, [B, N, 3]
        World ENU [m] / unit normals of the mirror samples.
    areas : torch.Tensor, [B, N]
        [m^2].
    sun_direction : torch.Tensor, [B, 3]
    target : PlanarTarget
    sun : SunSettings
    pixel : float
        Pixel side [m] (window side / resolution).
    size : int
        Kernel side [px] (``2 * resolution`` for :func:`render_centered`).
    supersample : int
        Sub-samples per pixel and axis.

    Returns
    -------
    torch.Tensor, [B, size, size], float64
        See :func:`footprint_kernel` (no autograd graph).
    """
    _, refl, dist = reflect_to_plane(points, normals, sun_direction, target)
    w = areas * (normals * sun_direction.to(points).unsqueeze(1)).sum(-1).clamp_min(0.0)
    return _mean_kernel(w, refl, dist, target, sun, pixel, size, supersample)


@dataclass
class RenderResult:
    """Output of :func:`render_centered`.

    Attributes
    ----------
    image : torch.Tensor, [B, R, R]
        Flux [W/m^2] in the centred window (PAINT orientation).
    center : torch.Tensor, [B, 2]
        Window centre (local target coordinates [m]).
    power : torch.Tensor, [B]
        Reflected power [W] (all samples).
    miss : torch.Tensor, []
        Soft miss penalty: mean squared overshoot [m^2] of hits beyond the window, power-weighted, averaged
        over the B images.
    miss_per_image : torch.Tensor, [B]
        The same per image (``miss`` is its mean) [m^2].
    """

    image: torch.Tensor
    center: torch.Tensor
    power: torch.Tensor
    miss: torch.Tensor
    miss_per_image: torch.Tensor | None = None


def render_centered(points: torch.Tensor, normals: torch.Tensor, areas: torch.Tensor,
                    sun_direction: torch.Tensor, target: PlanarTarget, sun: SunSettings, *,
                    size_m: float = CENTERED_WINDOW_M, resolution: int = 64, center: torch.Tensor | None = None,
                    kernel: torch.Tensor | None = None, spectrum: torch.Tensor | None = None) -> RenderResult:
    """Flux of B mirror poses in a square window (centred on the predicted centroid by default).

    Parameters
    ----------
    points, normals : torch.Tensor, [B, N, 3]
        World ENU [m] / unit normals of the mirror samples.
    areas : torch.Tensor, [B, N]
        [m^2].
    sun_direction : torch.Tensor, [B, 3]
    target : PlanarTarget
    sun : SunSettings
    size_m : float
        Window side [m].
    resolution : int
        Pixels per side (even).
    center : torch.Tensor, [B, 2], optional
        Window centre (local [m]); default the power-weighted centroid of the hits.
    kernel : torch.Tensor, [B, 2R, 2R], optional
        Precomputed :func:`footprint_kernel` (its dependence on the surface is second order, so callers
        may reuse it across optimiser steps).
    spectrum : torch.Tensor, [B, n, m], optional
        (``n`` = :func:`fft_size`, ``m = n // 2 + 1``) :func:`kernel_spectrum` of the kernel cast to the splat's
        precision (float32 rays: float32 kernel, as ``kernel`` is used); it replaces ``kernel`` (the caller keeps
        the two consistent).

    Returns
    -------
    RenderResult
    """
    if not isinstance(target, PlanarTarget):
        raise HeliotwinError("the conv integrator supports planar targets only (use --integrator mc)")
    res = int(resolution)
    if res % 2:
        raise HeliotwinError(f"resolution must be even, got {res}")
    local, refl, dist = reflect_to_plane(points, normals, sun_direction, target)
    cosine = (normals * sun_direction.to(points).unsqueeze(1)).sum(-1).clamp_min(0.0)
    w = areas * cosine  # [B, N] m^2 (projected)
    wsum = w.sum(-1).clamp_min(1e-12)
    if center is None:
        center = (w.unsqueeze(-1) * local).sum(1) / wsum.unsqueeze(-1)
    pix = size_m / res
    # Splat on a grid twice the window (the kernel spreads power from outside into the window).
    big = 2 * res
    x0 = center[:, :1] - size_m  # left edge of the big grid
    y1 = center[:, 1:] + size_m  # top edge
    px = (local[..., 0] - x0) / pix - 0.5
    py = (y1 - local[..., 1]) / pix - 0.5
    img = splat_bilinear(px, py, w, big, big)  # [B, 2R, 2R] m^2 per pixel
    if spectrum is None:
        if kernel is None:
            kernel = _mean_kernel(w, refl, dist, target, sun, pix, big)
        spectrum = kernel_spectrum(kernel.to(img.dtype), res)
    n = fft_size(res)  # alias-free for the window (see fft_size), not the full linear size 2 * big
    spec = torch.fft.rfft2(img, s=(n, n))
    full = torch.fft.irfft2(spec * spectrum.to(spec), s=(n, n))
    # out[q] = sum_m img[m] K[q - m + big/2]; the window starts at big-grid index res/2.
    start = big // 2 + res // 2
    window = full[:, start:start + res, start:start + res].clamp_min(0.0)
    flux = window * (float(sun.dni) * float(sun.reflectivity) / (pix * pix))
    over = (local - center.unsqueeze(1)).abs() - size_m / 2
    miss = (w * over.clamp_min(0.0).pow(2).sum(-1)).sum(1) / wsum
    return RenderResult(flux, center, float(sun.dni) * float(sun.reflectivity) * w.sum(-1), miss.mean(), miss)


def trace_conv(points, normals, areas, sun_direction, target: PlanarTarget, *, resolution=64,
               sun: SunSettings | None = None, window=None, kernel: torch.Tensor | None = None,
               dtype: torch.dtype = torch.float32) -> FluxImage:
    """The conv integrator behind the :func:`heliotwin.scene.trace` interface (square windows only).

    Parameters
    ----------
    points, normals : torch.Tensor, [B, N, 3] or [N, 3]
        World ENU [m] / unit normals.
    areas : torch.Tensor, [B, N] or [N]
        [m^2].
    sun_direction : torch.Tensor, [B, 3] or [3]
        Unit, towards the sun.
    target : PlanarTarget
    resolution : int or (int, int)
        Pixels per side (square, even).
    sun : SunSettings, optional
        Default ``SunSettings()``.
    window : (x0, y0, width, height), optional
        Square local window [m] (its centre is held fixed). Default: the PAINT-style window of
        :data:`~heliotwin.raytrace.flux.CENTERED_WINDOW_M` centred on the predicted centroid.
    kernel : torch.Tensor, [B, 2R, 2R], optional
        Precomputed :func:`mean_footprint_kernel`.
    dtype : torch.dtype
        Ray precision of the splat (float32 by default, like the other integrators).

    Returns
    -------
    FluxImage
        ``method="conv"``; ``intercepted_power_w`` is the flux summed over the window.
    """
    rows, cols = (resolution, resolution) if isinstance(resolution, int) else tuple(resolution)
    if rows != cols:
        raise HeliotwinError(f"the conv integrator renders square windows only, got resolution {rows}x{cols}")
    sun = sun or SunSettings()
    pts, nrm = torch.as_tensor(points), torch.as_tensor(normals)
    pts = pts.unsqueeze(0) if pts.dim() == 2 else pts
    nrm = nrm.unsqueeze(0) if nrm.dim() == 2 else nrm
    ar = torch.as_tensor(areas)
    ar = ar.unsqueeze(0) if ar.dim() == 1 else ar
    sdir = torch.as_tensor(sun_direction).reshape(-1, 3)
    b = max(pts.shape[0], nrm.shape[0], ar.shape[0], sdir.shape[0])
    p = pts.shape[1]
    pts, nrm = pts.to(dtype).expand(b, p, 3), nrm.to(dtype).expand(b, p, 3)
    ar, sdir = ar.to(dtype).expand(b, p), sdir.to(dtype).expand(b, 3)
    center, size_m = None, CENTERED_WINDOW_M
    if window is not None:
        x0, y0, w, h = (float(v) for v in window)
        if abs(w - h) > 1e-9 * max(w, h):
            raise HeliotwinError(f"the conv integrator renders square windows only, got {w} m x {h} m")
        size_m = w
        center = pts.new_tensor([x0 + w / 2, y0 + h / 2]).expand(b, 2)
    res = render_centered(pts, nrm, ar, sdir, target, sun, size_m=size_m, resolution=rows, center=center,
                          kernel=kernel)
    c = res.center.detach().to(torch.float64)
    half = size_m / 2
    extent = torch.stack((c[:, 0] - half, c[:, 0] + half, c[:, 1] - half, c[:, 1] + half), -1)
    pixel_area = (size_m / rows) ** 2
    return FluxImage(res.image, target, extent, res.power.to(torch.float64),
                     res.image.detach().to(torch.float64).sum((-1, -2)) * pixel_area, "conv")
