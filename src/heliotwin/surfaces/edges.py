"""Facet edges and corners: the slope-deviation penalty, the edge-ridge metric and the normal-deviation map.

Control points on a facet's border are constrained by fewer mirror samples than inner ones, and a Laplacian on
the control grid padded by linear extrapolation leaves the border curvature free: learned surfaces then grow
ridges of 15-25 mrad along edges and inner corners that no image asks for. Here the penalty acts on the
*sampled surface normals* (every sample weighs the same, edge samples included) and separates two parts of
the slope deviation ``dn = n - n0`` from the start surface ``n0``:

* the **low-order** part: per facet the affine function of (u, v) that fits ``dn`` best (least squares) --
  the slope field of a facet tilt (canting) plus a quadratic bowl/saddle (focusing, astigmatism). It is
  physical and weakly constrained (by the ridge on the displacements);
* the **residual** ``r = dn - low-order``: bumps, waves and edge ridges. Penalised
  ``w * mean(|r|^2) / (1 mrad)^2 + HINGE_WEIGHT * mean(relu(|r|^2 - RIDGE^2)) / (1 mrad)^2``,
  ``w`` chosen by leave-one-training-image-out validation; the hinge makes residual slopes beyond
  ``RIDGE`` (5 mrad, the facet-edge limit) expensive, so they appear only where the images pay for them.

``|dn|`` is the chord of the angle (equal to it to third order; no square root, finite gradient at 0).

Metric. :func:`edge_ridge_mrad`: the largest residual deviation in each facet's border band (the outer
``EDGE_BAND`` of the parameter range on every side), over all facets [mrad]; the total deviation (low-order
included) is reported beside it.

Shapes: F facets, (su, sv) samples per facet. Units: radians (mrad where named).
"""
from __future__ import annotations

from functools import lru_cache

import torch

from ..field import facets as facet_ops
from ..field.plant import Facets, Surfaces
from .learning import normal_heights

__all__ = ["slope_penalty", "edge_ridge_mrad", "deviation_map_mrad", "residual_map_mrad", "high_order",
           "RIDGE_RAD", "HINGE_WEIGHT", "EDGE_BAND", "slope_penalties"]

#: Largest slope deviation accepted without the images demanding it [rad] (5 mrad).
RIDGE_RAD = 5e-3
#: Weight of the hinge above ``RIDGE_RAD`` (per mrad^2; large against the data loss's ~1e-3 per mrad^2 scale).
HINGE_WEIGHT = 1.0
#: Border band of each facet counted as "edge" (fraction of the parameter range on each side).
EDGE_BAND = 0.125


def _normals(surf: Surfaces, facets: Facets, samples) -> torch.Tensor:
    _, n = normal_heights(facets, surf.control_points, (surf.degree_u, surf.degree_v), samples, surf.weights)
    return n


@lru_cache(maxsize=16)
def _affine_basis(su: int, sv: int, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    # ([P, 3] affine fields in (u, v) on the su x sv midpoint grid, their [3, P] pseudo-inverse); fixed by the
    # grid, so built once rather than at every optimiser step (shared: never modified in place).
    u = (torch.arange(su, dtype=dtype, device=device) + 0.5) / su - 0.5
    v = (torch.arange(sv, dtype=dtype, device=device) + 0.5) / sv - 0.5
    a = torch.stack((torch.ones(su, sv, dtype=dtype, device=device), u[:, None].expand(su, sv),
                     v[None, :].expand(su, sv)), -1).reshape(-1, 3)  # [P, 3]
    return a, torch.linalg.pinv(a)


def high_order(dn: torch.Tensor) -> torch.Tensor:
    """Residual of ``dn`` ``[F, su, sv, 3]`` after each facet's least-squares affine fit in (u, v) (same shape)."""
    f, su, sv, _ = dn.shape
    a, a_pinv = _affine_basis(su, sv, dn.dtype, dn.device)
    # Every facet and component a column of one [P, 3F] matrix: x - A (A^+ x), two thin matmuls (not a [P, P]
    # projector per facet).
    x = dn.reshape(f, su * sv, 3).transpose(0, 1).reshape(su * sv, f * 3)
    r = x - a @ (a_pinv @ x)
    return r.reshape(su * sv, f, 3).transpose(0, 1).reshape(dn.shape)


def slope_penalty(surf: Surfaces, reference_normals: torch.Tensor, facets: Facets, weight: float,
                  samples=(16, 16)) -> torch.Tensor:
    """Residual slope penalty (module docstring) of ``surf`` against ``reference_normals`` ``[F, su, sv, 3]``."""
    n = _normals(surf, facets, samples)
    d2 = high_order(n - reference_normals.to(n)).pow(2).sum(-1) / 1e-6  # [mrad^2]
    hinge = torch.relu(d2 - (RIDGE_RAD / 1e-3) ** 2)
    return weight * d2.mean() + HINGE_WEIGHT * hinge.mean()


def slope_penalties(surf: Surfaces, reference_normals: torch.Tensor, weights: torch.Tensor,
                    samples=(16, 16)) -> torch.Tensor:
    """:func:`slope_penalty` of K surfaces at once (one per row of ``surf``), ``[K]``.

    ``surf``: control points ``[K, F, nu, nv, 3]`` [m]; ``reference_normals`` ``[F, su, sv, 3]`` (shared) or
    ``[K, F, su, sv, 3]``; ``weights`` ``[K]`` (per mrad^2; 0 gives 0, as the fit then leaves the penalty out).
    """
    su, sv = samples
    cp = surf.control_points
    k, nf = cp.shape[0], cp.shape[1]
    _, nrm, _ = facet_ops.surface_points(surf, samples)
    n = nrm.reshape(k, nf, su, sv, 3)
    dn = (n - reference_normals.to(n)).reshape(k * nf, su, sv, 3)
    d2 = (high_order(dn).pow(2).sum(-1) / 1e-6).reshape(k, -1)  # [mrad^2]
    hinge = torch.relu(d2 - (RIDGE_RAD / 1e-3) ** 2)
    w = weights.to(d2)
    return torch.where(w != 0, w * d2.mean(-1) + HINGE_WEIGHT * hinge.mean(-1), torch.zeros_like(w))


def deviation_map_mrad(surf: Surfaces, reference: Surfaces, facets: Facets, samples=(48, 48)) -> torch.Tensor:
    """Angle between ``surf``'s and ``reference``'s normals, ``[F, su, sv]`` [mrad] (detached)."""
    with torch.no_grad():
        n = _normals(surf, facets, samples)
        n0 = _normals(reference, facets, samples).to(n)
        cos = (n * n0).sum(-1).clamp(-1.0, 1.0)
        sin = torch.linalg.cross(n, n0, dim=-1).norm(dim=-1)
        return torch.atan2(sin, cos) * 1e3


def residual_map_mrad(surf: Surfaces, reference: Surfaces, facets: Facets, samples=(48, 48)) -> torch.Tensor:
    """``|high_order(n - n0)|`` ``[F, su, sv]`` [mrad] (detached): deviation beyond canting + quadratic shape."""
    with torch.no_grad():
        n = _normals(surf, facets, samples)
        n0 = _normals(reference, facets, samples).to(n)
        return high_order(n - n0).norm(dim=-1) * 1e3


def edge_ridge_mrad(surf: Surfaces, reference: Surfaces, facets: Facets, samples=(48, 48)) -> dict:
    """Largest residual deviation (beyond each facet's tilt + quadratic) in the border bands and inside [mrad].

    Returns
    -------
    dict
        ``edge_max_mrad``, ``interior_max_mrad``, ``mean_mrad`` (residual), ``total_edge_max_mrad`` and
        ``total_max_mrad`` (normal deviation including the low-order part) and ``edge_band``.
    """
    dev = residual_map_mrad(surf, reference, facets, samples)
    tot = deviation_map_mrad(surf, reference, facets, samples)
    su, sv = dev.shape[-2:]
    bu, bv = max(1, round(EDGE_BAND * su)), max(1, round(EDGE_BAND * sv))
    edge = torch.zeros(su, sv, dtype=torch.bool, device=dev.device)
    edge[:bu], edge[-bu:], edge[:, :bv], edge[:, -bv:] = True, True, True, True
    return {"edge_max_mrad": float(dev[:, edge].max()), "interior_max_mrad": float(dev[:, ~edge].max()),
            "mean_mrad": float(dev.mean()), "total_edge_max_mrad": float(tot[:, edge].max()),
            "total_max_mrad": float(tot.max()), "edge_band": EDGE_BAND}
