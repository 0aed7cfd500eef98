"""Ray tracing: Monte-Carlo and analytic flux integrators, splatting, flux images.

Entry points
------------
:func:`trace_mc`
    Monte-Carlo tracer (projective fast path for planar targets, generic path for the cylinder).
:func:`trace_analytic`
    Noise-free Gaussian-footprint integrator (cost independent of any ray count).
:class:`FluxImage`
    The result: bitmap [B, rows, cols] in W/m^2 (PAINT orientation) plus target, extent and powers.
:func:`centered_crop`, :func:`to_png`, :func:`read_png`, :func:`normalized_l1`, :func:`cross_correlation`
    PAINT-style image handling and comparison.
"""
from .analytic import trace_analytic
from .flux import FluxImage, centered_crop, cross_correlation, normalized_l1, read_png, target_extent, to_png
from .montecarlo import trace_mc
from .splat import projective_splat, splat_bilinear, splat_hard

__all__ = [
    "FluxImage",
    "centered_crop",
    "cross_correlation",
    "normalized_l1",
    "read_png",
    "target_extent",
    "to_png",
    "trace_analytic",
    "trace_mc",
    "projective_splat",
    "splat_bilinear",
    "splat_hard",
]
