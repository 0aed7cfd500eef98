"""Facet placement, canting and ideal (flat, canted) facet surfaces, heliostat frame.

A facet is described PAINT-style by its centre ``translation`` and two half-span vectors ``canting_e``
(about east) and ``canting_n`` (about north) whose directions carry the canting. The ideal facet is the
flat parallelogram ``translation + s canting_e + t canting_n``, s, t in [-1, 1]. Its NURBS form puts
the control points at the Greville abscissae, which makes the parametrisation *linear*
(``s = 2u - 1``, ``t = 2v - 1``): surface samples then carry exactly equal areas and
``S(0.5, 0.5) = translation``. The first net index (u) runs along ``canting_e``, the second (v) along
``canting_n``.

Shapes: H heliostats, F facets, (nu, nv) control points, P samples per facet. Units: metres, m².
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch

from .. import nurbs
from ..errors import HeliotwinError, InputFileError
from .plant import Facets, Surfaces


def facet_normals(canting_e: torch.Tensor, canting_n: torch.Tensor) -> torch.Tensor:
    """Unit normals of flat canted facets.

    Parameters
    ----------
    canting_e, canting_n : torch.Tensor, [..., F, 3]
        Half-span vectors [m].

    Returns
    -------
    torch.Tensor, [..., F, 3]
        ``normalize(canting_e x canting_n)`` (points to +z for PAINT facets, i.e. out of the mirror
        when it lies flat facing the zenith). Zero vector (finite gradient) for degenerate spans.
    """
    c = torch.linalg.cross(canting_e, canting_n, dim=-1)
    return c / torch.linalg.vector_norm(c, dim=-1, keepdim=True).clamp_min(nurbs.NORM_EPS)


def flat_control_points(facets: Facets, num_control_points: tuple[int, int] = (4, 4),
                        degree: tuple[int, int] = (2, 2)) -> torch.Tensor:
    """Control net of the ideal flat, canted facet.

    Parameters
    ----------
    facets : Facets
        ``translation``, ``canting_e``, ``canting_n`` of shape [H, F, 3] (any leading shape works).
    num_control_points : (int, int)
        (nu, nv).
    degree : (int, int)
        (p, q).

    Returns
    -------
    torch.Tensor, [H, F, nu, nv, 3]
        ``translation + s_a canting_e + t_b canting_n`` [m] with s_a, t_b = 2 xi - 1 at the Greville
        abscissae xi, so ``S(u, v) = translation + (2u - 1) canting_e + (2v - 1) canting_n`` exactly
        (uniformly spaced control points would not give a linear parametrisation for p >= 2).
        Dtype/device follow ``facets.translation``.
    """
    nu, nv = (int(x) for x in num_control_points)
    p, q = (int(x) for x in degree)
    tr = facets.translation
    like = dict(dtype=tr.dtype, device=tr.device)
    s = 2.0 * nurbs.greville_abscissae(nu, p, **like) - 1.0
    t = 2.0 * nurbs.greville_abscissae(nv, q, **like) - 1.0
    e = facets.canting_e.to(**like)[..., None, None, :]
    n = facets.canting_n.to(**like)[..., None, None, :]
    return tr[..., None, None, :] + s[:, None, None] * e + t[None, :, None] * n


def ideal_surfaces(facets: Facets, num_control_points: tuple[int, int] = (4, 4),
                   degree: tuple[int, int] = (2, 2)) -> Surfaces:
    """Ideal (flat, canted) NURBS surfaces for every facet.

    Parameters
    ----------
    facets : Facets
        [H, F, 3] placement.
    num_control_points : (int, int)
        (nu, nv), default (4, 4).
    degree : (int, int)
        (p, q), default (2, 2).

    Returns
    -------
    Surfaces
        ``control_points`` [H, F, nu, nv, 3], non-rational (weights None).
    """
    cp = flat_control_points(facets, num_control_points, degree)
    return Surfaces(control_points=cp, degree_u=int(degree[0]), degree_v=int(degree[1]), weights=None)


def displace_along_normal(control_points: torch.Tensor, displacement: torch.Tensor, facets: Facets) -> torch.Tensor:
    """Move each control point along its facet's (flat, canted) normal.

    This is the parametrisation surface learning optimises: in-plane control-point motion only
    reparametrises a nearly flat facet, so the normal offset is the physically meaningful degree of
    freedom.

    Parameters
    ----------
    control_points : torch.Tensor, [..., F, nu, nv, 3]
        Control net [m], e.g. from :func:`flat_control_points`.
    displacement : torch.Tensor, [..., F, nu, nv]
        Offset along the facet normal [m] (positive = towards the reflective side).
    facets : Facets
        Canting vectors [..., F, 3] that define the normals.

    Returns
    -------
    torch.Tensor, [..., F, nu, nv, 3]
        ``control_points + displacement * facet_normal``; differentiable w.r.t. all inputs.
    """
    normal = facet_normals(facets.canting_e, facets.canting_n).to(control_points.dtype)
    return control_points + displacement[..., None] * normal[..., None, None, :]


def surface_points(surfaces: Surfaces, samples: tuple[int, int] = (32, 32)
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sample all facet surfaces of all heliostats at cell midpoints, heliostat frame.

    Parameters
    ----------
    surfaces : Surfaces
        ``control_points`` [H, F, nu, nv, 3] (optional weights [H, F, nu, nv]).
    samples : (int, int)
        (su, sv) samples per facet and direction; P = su * sv.

    Returns
    -------
    points : torch.Tensor, [H, F*P, 3]
        Surface points [m]; facet-major, then u-major within a facet (index ``f*P + i*sv + j``).
    normals : torch.Tensor, [H, F*P, 3]
        Unit normals (reflective side, +z for a flat heliostat facing the zenith).
    areas : torch.Tensor, [H, F*P]
        Area per sample [m²]; per facet they sum to the (midpoint-rule) facet area.
    """
    cp = surfaces.control_points
    if cp.dim() != 5 or cp.shape[-1] != 3:
        raise HeliotwinError(f"surface control_points must have shape [H, F, nu, nv, 3], got {tuple(cp.shape)}")
    su, sv = (int(x) for x in samples)
    pts, nrm, area = nurbs.surface_samples(cp, surfaces.degree_u, surfaces.degree_v, su, sv, surfaces.weights)
    h = cp.shape[0]
    return pts.reshape(h, -1, 3), nrm.reshape(h, -1, 3), area.reshape(h, -1)


def receiver_canting(translation: torch.Tensor, half_width: float, half_height: float,
                     focal_length: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Canting span vectors of facets tilted to focus at ``focal_length`` (on-axis "receiver canting").

    Each flat facet's normal is set to the normal of the paraboloid ``z = (x^2 + y^2) / (4 f)`` at the
    facet centre, ``normalize(-t_x / (2 f), -t_y / (2 f), 1)``, by the rotation ``R_N(beta) R_E(alpha)``
    (PAINT's construction: ``canting_e`` keeps a zero north component).

    Parameters
    ----------
    translation : torch.Tensor, [..., F, 3]
        Facet centres, heliostat frame [m].
    half_width, half_height : float
        Half-spans along east / north [m].
    focal_length : torch.Tensor, [...]
        Focal distance per heliostat [m].

    Returns
    -------
    canting_e, canting_n : torch.Tensor, [..., F, 3]
        Half-span vectors [m] (lengths ``half_width`` / ``half_height``).
    """
    f = focal_length[..., None]
    n = torch.stack((-translation[..., 0] / (2 * f), -translation[..., 1] / (2 * f),
                     torch.ones_like(translation[..., 0])), dim=-1)
    n = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)
    sin_a = -n[..., 1]
    cos_a = torch.sqrt(1.0 - sin_a * sin_a)
    beta = torch.atan2(n[..., 0], n[..., 2])
    sin_b, cos_b = torch.sin(beta), torch.cos(beta)
    zero = torch.zeros_like(sin_a)
    e = torch.stack((cos_b, zero, -sin_b), dim=-1)  # R_N(beta) R_E(alpha) e_x
    nn = torch.stack((sin_b * sin_a, cos_a, cos_b * sin_a), dim=-1)  # R_N(beta) R_E(alpha) e_y
    return half_width * e, half_height * nn


_PAINT_KEYS = (("translation_vector", "translation"), ("canting_e", "canting_e"), ("canting_n", "canting_n"))


def facets_from_paint(facet_properties: Sequence[Mapping], path=None
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Facet placement from PAINT's ``facet_properties.facets`` list.

    Parameters
    ----------
    facet_properties : list of dict
        Each with ``translation_vector``, ``canting_e``, ``canting_n`` (3 numbers each, heliostat
        frame [m]).
    path : str or Path, optional
        Source file; when given, errors are :class:`~heliotwin.errors.InputFileError` naming it.

    Returns
    -------
    translation, canting_e, canting_n : torch.Tensor, [F, 3], float64
        Facet centre and its two canting (edge) vectors, heliostat frame [m].

    Raises
    ------
    HeliotwinError / InputFileError
        Empty list, missing key, or a vector that is not 3 finite numbers (message names the field,
        e.g. ``facet_properties.facets[2].canting_n``).
    """
    def fail(message: str, field: str):
        if path is not None:
            raise InputFileError(path, message, field=field)
        raise HeliotwinError(f"[{field}] {message}")

    if not isinstance(facet_properties, Sequence) or isinstance(facet_properties, (str, bytes)) \
            or len(facet_properties) == 0:
        fail("expected a non-empty list of facets", "facet_properties.facets")
    out = {name: [] for _, name in _PAINT_KEYS}
    for i, facet in enumerate(facet_properties):
        for key, name in _PAINT_KEYS:
            field = f"facet_properties.facets[{i}].{key}"
            if not isinstance(facet, Mapping) or key not in facet:
                fail(f"missing key {key!r}", field)
            try:
                vec = torch.as_tensor(facet[key], dtype=torch.float64)
            except (TypeError, ValueError):
                fail("expected 3 numbers", field)
            if vec.shape != (3,) or not bool(torch.isfinite(vec).all()):
                fail(f"expected 3 finite numbers, got {facet[key]!r}", field)
            out[name].append(vec)
    return tuple(torch.stack(out[name]) for _, name in _PAINT_KEYS)
