"""Deflectometry as a surface for tracing, and surface-vs-surface comparison.

PAINT deflectometry HDF5 (:func:`heliotwin.io.deflectometry.read_deflectometry`) is fitted per facet with a
NURBS net (:func:`heliotwin.io.deflectometry.fit_deflectometry`); the net can be traced like any other
surface (``Surfaces([1, F, nu, nv, 3])``), used as the starting surface of the learning
(:class:`~heliotwin.surfaces.learning.LearnableSurface` ``initial=``), and compared with a learned surface in
millimetres (piston-free height RMS along the facet normal) and milliradians (angle between normals).

Shapes: F facets; (nu, nv) control points; (su, sv) comparison grid per facet.
"""
from __future__ import annotations

import statistics

import torch

from ..field.plant import Facets, Surfaces
from ..geometry import angle_between
from ..io.deflectometry import fit_deflectometry, read_deflectometry
from .fit import evaluate_with_camera
from .learning import normal_heights

__all__ = ["deflectometry_surface", "compare_surfaces", "deflectometry_report"]


def deflectometry_surface(path, facets: Facets, num_control_points=(8, 8), degree=(3, 3)) -> tuple[Surfaces, dict]:
    """Read a PAINT deflectometry file and fit one NURBS net per facet.

    Parameters
    ----------
    path : str or Path
    facets : Facets
        One heliostat's placement, ``[1, F, 3]`` (its facet order is the file's ``facet1..facetF``).
    num_control_points, degree : (int, int)

    Returns
    -------
    surfaces : Surfaces
        ``[1, F, nu, nv, 3]`` float64, heliostat frame [m].
    fit : dict
        Per-facet fit residuals (``rms_mm``, ``max_mm``, ``normal_rms_mrad``, ``outside_fraction``, ``points``).
    """
    meas = read_deflectometry(path)
    cp, rep = fit_deflectometry(meas, facets, tuple(num_control_points), tuple(degree))
    fit = {"rms_mm": (rep.rms_m * 1e3).tolist(), "max_mm": (rep.max_m * 1e3).tolist(),
           "normal_rms_mrad": rep.normal_rms_mrad.tolist(), "outside_fraction": rep.outside_fraction.tolist(),
           "points": list(rep.num_points)}
    return Surfaces(cp.unsqueeze(0), int(degree[0]), int(degree[1])), fit


def compare_surfaces(facets: Facets, a: Surfaces, b: Surfaces, grid=(48, 48)) -> dict:
    """Difference of two surfaces of one heliostat (``control_points`` [1, F, nu, nv, 3] [m], ``facets`` [1, F, 3]
    [m]) on each facet's parameter grid.

    Returns
    -------
    dict
        ``normal_deviation_mrad`` (mean angle between normals), ``normal_deviation_p95_mrad``,
        ``height_rms_mm`` (RMS of the height difference along the facet normal after removing each facet's
        mean: a piston changes no image), ``height_max_mm`` (same, max abs) and per-facet lists
        ``facet_normal_deviation_mrad``, ``facet_height_rms_mm``.
    """
    with torch.no_grad():
        ha, na = normal_heights(facets, a.control_points.to(torch.float64), (a.degree_u, a.degree_v), grid,
                                None if a.weights is None else a.weights.to(torch.float64))
        hb, nb = normal_heights(facets, b.control_points.to(torch.float64), (b.degree_u, b.degree_v), grid,
                                None if b.weights is None else b.weights.to(torch.float64))
        ang = angle_between(na, nb) * 1e3
        dh = ha - hb
        dh = (dh - dh.mean((-2, -1), keepdim=True)) * 1e3
    return {"normal_deviation_mrad": float(ang.mean()),
            "normal_deviation_p95_mrad": float(ang.flatten().quantile(0.95)),
            "height_rms_mm": float(dh.pow(2).mean().sqrt()), "height_max_mm": float(dh.abs().max()),
            "facet_normal_deviation_mrad": ang.mean((-2, -1)).tolist(),
            "facet_height_rms_mm": dh.pow(2).mean((-2, -1)).sqrt().tolist()}


def deflectometry_report(path, facets: Facets, learned: Surfaces, ideal: Surfaces, test, info: dict, settings,
                         rows: list) -> dict:
    """The deflectometry file at ``path`` beside a reconstruction: its NURBS fit evaluated on the test images as
    the ideal and learned surfaces are (same optics, camera model and blur, from the learner's ``info``:
    :func:`heliotwin.surfaces.generalise.reconstruct_generalising`), and compared with both surfaces.

    Adds ``l1_deflectometry`` to each test row of ``rows``; returns ``{"file", "fit" (per-facet fit residuals),
    "learned_vs_deflectometry", "ideal_vs_deflectometry" (:func:`compare_surfaces`: mrad, mm),
    "median_l1_deflectometry"}``.
    """
    f64 = Facets(*(t.to(torch.float64) for t in facets))
    defl, fit = deflectometry_surface(path, f64)
    defl = Surfaces(defl.control_points.to(f64.translation.device), defl.degree_u, defl.degree_v)
    l1 = evaluate_with_camera(defl, test, info["optics"], info["test_camera"], info["test_sigma"], settings)["l1"]
    for row, v in zip(rows, l1):
        row["l1_deflectometry"] = v
    return {"file": str(path), "fit": fit, "learned_vs_deflectometry": compare_surfaces(f64, learned, defl),
            "ideal_vs_deflectometry": compare_surfaces(f64, ideal, defl),
            "median_l1_deflectometry": statistics.median(l1)}
