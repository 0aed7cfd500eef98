"""Ray tracing: the three flux integrators, splatting, flux images.

Integrators (dispatched by name in :func:`heliotwin.scene.trace`, names in :data:`heliotwin.scene.INTEGRATORS`)
-----------------------------------------------------------------------------------------------------------
``"mc"`` -- :func:`trace_mc` (options: :class:`RaySampling`)
    Monte-Carlo tracer (projective fast path for planar targets, generic path for the cylinder).
``"gaussian"`` -- :func:`trace_gaussian` (options: :class:`FootprintSettings`)
    Noise-free Gaussian-footprint integrator (Gaussian-equivalent sun; cost independent of any ray count).
``"conv"`` -- :func:`trace_conv` / :func:`render_centered`
    Noise-free mirror-point splat convolved with the exact tabulated sunshape (planar targets, square
    windows); the surface learner's renderer.

Images
------
:class:`FluxImage`
    The result: bitmap [B, rows, cols] in W/m^2 (PAINT orientation) plus target, extent and powers.
:func:`centered_crop`, :func:`normalized_l1`, :func:`cross_correlation`
    PAINT-style image handling and comparison (PNG files in and out: :mod:`heliotwin.io.images`).
"""
from .conv import render_centered, trace_conv
from .flux import CENTERED_WINDOW_M, FluxImage, centered_crop, cross_correlation, normalized_l1, target_extent
from .gaussian import FootprintSettings, trace_gaussian
from .montecarlo import RaySampling, trace_mc
from .splat import projective_splat, splat_bilinear, splat_hard

__all__ = [
    "CENTERED_WINDOW_M",
    "FluxImage",
    "FootprintSettings",
    "RaySampling",
    "centered_crop",
    "cross_correlation",
    "normalized_l1",
    "render_centered",
    "target_extent",
    "trace_conv",
    "trace_gaussian",
    "trace_mc",
    "projective_splat",
    "splat_bilinear",
    "splat_hard",
]
