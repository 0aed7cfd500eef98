"""Plant-level composition: kinematics + mirror surfaces -> world-frame mirror samples -> tracer.

The scene (a :class:`~heliotwin.field.plant.Plant`) is plain data; the integrators in
:mod:`heliotwin.raytrace` are separate and never mutate it. This module only glues the steps:

    motor steps --kinematics.forward--> (R_world_heliostat, concentrator)
    control points --facets.surface_points--> heliostat-frame points, normals, areas
    --> world points, normals (ENU) --> trace(integrator="mc" | "gaussian" | "conv") --> FluxImage

Shapes: B samples (a sample is one heliostat under one sun position; a heliostat may appear in many),
P surface points per heliostat.
"""
from __future__ import annotations

from dataclasses import replace

import torch

from .errors import HeliotwinError
from .field import facets as facet_ops
from .field import kinematics as kin_ops
from .field.plant import Kinematics, Surfaces
from .field.targets import PlanarTarget
from .geometry import ray_plane, reflect
from .raytrace import conv, gaussian, montecarlo


def heliostat_frame_surface(surfaces: Surfaces, samples: tuple[int, int] = (32, 32)):
    """Mirror samples of every heliostat in its own frame.

    Returns
    -------
    points, normals : torch.Tensor, [H, F*P, 3]
        Heliostat frame [m] / unit.
    areas : torch.Tensor, [H, F*P]
        [m²] per sample.
    """
    return facet_ops.surface_points(surfaces, samples)


def to_world(R_world_heliostat: torch.Tensor, concentrator: torch.Tensor, points: torch.Tensor,
             normals: torch.Tensor, dtype=torch.float32):
    """Heliostat-frame samples -> ENU.

    Parameters
    ----------
    R_world_heliostat : torch.Tensor, [B, 3, 3]
    concentrator : torch.Tensor, [B, 3]
        ENU [m].
    points, normals : torch.Tensor, [B, P, 3]
        Heliostat frame [m] / unit.
    dtype : torch.dtype
        Output dtype (rays are float32; the rotation itself is done in the inputs' precision).

    Returns
    -------
    points, normals : torch.Tensor, [B, P, 3]
        ENU [m] / unit.
    """
    R = R_world_heliostat.to(points.dtype)
    pw = concentrator.to(points.dtype).unsqueeze(-2) + points @ R.transpose(-1, -2)
    nw = normals @ R.transpose(-1, -2)
    return pw.to(dtype), nw.to(dtype)


def world_surface(kinematics: Kinematics, surfaces: Surfaces, heliostat_index, motor_steps,
                  samples: tuple[int, int] = (32, 32), dtype=torch.float32):
    """World-frame mirror samples for B (heliostat, motor steps) samples.

    Parameters
    ----------
    kinematics : Kinematics
        H heliostats.
    surfaces : Surfaces
        H heliostats' facets.
    heliostat_index : tensor-like of int, [B]
        Which heliostat each sample is.
    motor_steps : tensor-like, [B, 2]
        [steps].
    samples : (int, int)
        Surface samples per facet and direction.

    Returns
    -------
    points, normals : torch.Tensor, [B, F*P, 3]
        ENU [m] / unit, ``dtype``.
    areas : torch.Tensor, [B, F*P]
        [m²].
    R_world_heliostat : torch.Tensor, [B, 3, 3]
    concentrator : torch.Tensor, [B, 3]
    """
    idx = torch.as_tensor(heliostat_index, dtype=torch.long).reshape(-1)
    kin = kinematics.index(idx)
    R, c = kin_ops.forward(kin, torch.as_tensor(motor_steps, dtype=kin.position.dtype).reshape(-1, 2))
    pts, nrm, area = heliostat_frame_surface(surfaces, samples)
    pw, nw = to_world(R, c, pts[idx], nrm[idx], dtype)
    return pw, nw, area[idx].to(dtype), R, c


#: Integrator names accepted by :func:`trace`: Monte-Carlo, Gaussian footprints, exact-sunshape convolution.
INTEGRATORS = ("mc", "gaussian", "conv")


def trace(points, normals, areas, sun_direction, target, *, integrator: str = "gaussian", resolution=(256, 256),
          sun=None, window=None, rays_per_point: int | None = None, generator: torch.Generator | None = None,
          **kwargs):
    """The one integrator dispatcher: ``"mc"``, ``"gaussian"`` or ``"conv"`` -> FluxImage.

    ``"mc"``: :func:`heliotwin.raytrace.trace_mc` (needs ``generator``; ``rays_per_point`` K, default 100,
    overrides that of a ``sampling=RaySampling(...)`` passed along);
    ``"gaussian"``: :func:`heliotwin.raytrace.trace_gaussian` (Gaussian-equivalent sun, any target);
    ``"conv"``: :func:`heliotwin.raytrace.trace_conv` (exact tabulated sunshape, planar targets, square
    windows; default window the PAINT-style centred one). Other parameters are those of the integrator.

    Parameters
    ----------
    points, normals : torch.Tensor, [B, P, 3]
        World ENU [m] / unit.
    areas : torch.Tensor, [B, P]
        [m^2].
    sun_direction : torch.Tensor, [B, 3]
        Unit, towards the sun.
    target : PlanarTarget or CylinderTarget
    integrator : {"mc", "gaussian", "conv"}

    Returns
    -------
    FluxImage
        Flux [W/m^2], ``method`` = the integrator name.
    """
    check_integrator(integrator)
    if integrator == "mc":
        if generator is None:
            raise HeliotwinError("the Monte-Carlo integrator needs a torch.Generator (pass a seed)")
        sampling = kwargs.pop("sampling", None) or montecarlo.RaySampling()
        if rays_per_point is not None:
            sampling = replace(sampling, rays_per_point=int(rays_per_point))
        return montecarlo.trace_mc(points, normals, areas, sun_direction, target, resolution=resolution, sun=sun,
                                   window=window, sampling=sampling, generator=generator, **kwargs)
    if integrator == "gaussian":
        return gaussian.trace_gaussian(points, normals, areas, sun_direction, target, resolution=resolution, sun=sun,
                                       window=window, **kwargs)
    if not isinstance(target, PlanarTarget):
        raise HeliotwinError("the conv integrator supports planar targets only (use 'gaussian' or 'mc')")
    return conv.trace_conv(points, normals, areas, sun_direction, target, resolution=resolution, sun=sun,
                           window=window, **kwargs)


def check_integrator(name: str) -> str:
    """``name`` if it is one of :data:`INTEGRATORS`, else a one-line :class:`HeliotwinError`."""
    if name in INTEGRATORS:
        return name
    hint = " ('analytic' is now 'gaussian' or 'conv')" if name == "analytic" else ""
    raise HeliotwinError(f"unknown integrator {name!r}; expected one of {', '.join(INTEGRATORS)}{hint}")


def central_ray_spot(R_world_heliostat: torch.Tensor, concentrator: torch.Tensor, sun_direction: torch.Tensor, target):
    """Where the ray reflected at the concentrator by the mirror normal meets the target plane.

    Parameters
    ----------
    R_world_heliostat : torch.Tensor, [B, 3, 3]
    concentrator : torch.Tensor, [B, 3]
        ENU [m].
    sun_direction : torch.Tensor, [B, 3]
        Unit, towards the sun.
    target : PlanarTarget

    Returns
    -------
    torch.Tensor, [B, 3]
        ENU [m] (float64). Rays parallel to or leaving the plane give NaN (no intersection).
    """
    n = kin_ops.mirror_normal(R_world_heliostat).to(torch.float64)
    r = reflect(-sun_direction.to(torch.float64), n)
    tn = target.normal.to(r)
    conc = concentrator.to(r)
    t, _ = ray_plane(conc, r, target.center.to(r), tn, eps=0.0)
    hit = conc + t.unsqueeze(-1) * r
    # Only rays travelling towards the (one-sided) target face count; the rest have no spot.
    return torch.where(((r * tn).sum(-1) < 0).unsqueeze(-1), hit, torch.full_like(hit, float("nan")))
