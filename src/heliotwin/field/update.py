"""Writing what was learned back into a plant: calibrated kinematics and learned surfaces.

A learner works on a few heliostats; the plant it read has all of them. These functions return a new
:class:`~heliotwin.field.plant.Plant` whose chosen heliostats carry the learned values and whose other
heliostats are untouched, so that the next step (trace, validate, another learner) sees one plant.
"""
from __future__ import annotations

from dataclasses import fields, replace

import torch

from .. import nurbs
from ..errors import HeliotwinError
from .plant import Kinematics, Plant, Surfaces

#: Parameter grid per direction used to carry a surface over to another control net (dense enough that
#: the least-squares refit of a cubic 7x7 net is exact to round-off for the flat ideal facets).
RESAMPLE_GRID = 24


def _positions(plant: Plant, heliostat_ids) -> torch.Tensor:
    ids = list(heliostat_ids)
    if len(set(ids)) != len(ids):
        raise HeliotwinError(f"duplicate heliostat ids in {ids}")
    at = {h: i for i, h in reversed(list(enumerate(plant.field.ids)))}  # one pass: index_of per id is quadratic
    return torch.tensor([at[h] if h in at else plant.field.index_of(h) for h in ids], dtype=torch.long)


def with_kinematics(plant: Plant, heliostat_ids, kinematics: Kinematics) -> Plant:
    """The plant with the kinematics of ``heliostat_ids`` replaced.

    Parameters
    ----------
    plant : Plant
        H heliostats.
    heliostat_ids : list of str, length K
        Heliostats to update (each in ``plant``).
    kinematics : Kinematics
        K heliostats, in the order of ``heliostat_ids`` (detached; cast to the plant's dtypes).

    Returns
    -------
    Plant
        A new plant; ``plant`` is not modified.
    """
    pos = _positions(plant, heliostat_ids)
    if kinematics.num_heliostats != len(pos):
        raise HeliotwinError(f"{kinematics.num_heliostats} calibrated kinematics for {len(pos)} heliostats")
    old = plant.field.kinematics
    new = {}
    for f in fields(Kinematics):
        t = getattr(old, f.name).clone()
        t[pos] = getattr(kinematics, f.name).detach().to(device=t.device, dtype=t.dtype)
        new[f.name] = t
    return replace(plant, field=replace(plant.field, kinematics=Kinematics(**new)))


def select_heliostats(plant: Plant, heliostat_ids) -> Plant:
    """The plant restricted to ``heliostat_ids`` (in that order); targets, site and optics unchanged."""
    pos = _positions(plant, heliostat_ids)
    fl = plant.field
    sf = fl.surfaces
    field = replace(fl, ids=[fl.ids[i] for i in pos.tolist()], kinematics=fl.kinematics.index(pos),
                    facets=type(fl.facets)(*(getattr(fl.facets, f.name)[pos] for f in fields(fl.facets))),
                    surfaces=Surfaces(sf.control_points[pos], sf.degree_u, sf.degree_v,
                                      None if sf.weights is None else sf.weights[pos]),
                    width=fl.width[pos], height=fl.height[pos],
                    renovation=[fl.renovation[i] for i in pos.tolist()] if fl.renovation else [])
    return replace(plant, field=field)


def resample_surfaces(surfaces: Surfaces, num_control_points: tuple[int, int], degree: tuple[int, int],
                      grid: int = RESAMPLE_GRID) -> Surfaces:
    """The same mirror shapes on another control net (least-squares refit on a parameter grid).

    Exact (to round-off) where the old surface lies in the new spline space — in particular for the
    flat ideal facets — and the best approximation otherwise.

    Parameters
    ----------
    surfaces : Surfaces
        ``control_points`` [H, F, nu, nv, 3] [m], non-rational.
    num_control_points, degree : (int, int)
        The new net size and degrees.
    grid : int
        Samples per direction of the refit (>= the new net size).

    Returns
    -------
    Surfaces
        [H, F, nu2, nv2, 3], dtype/device of the input.
    """
    if surfaces.weights is not None:
        raise HeliotwinError("cannot resample rational (weighted) surfaces to another control net")
    cp = surfaces.control_points
    nu2, nv2 = (int(x) for x in num_control_points)
    if (cp.shape[2], cp.shape[3], surfaces.degree_u, surfaces.degree_v) == (nu2, nv2, *degree):
        return surfaces
    g = max(int(grid), nu2, nv2)
    u = torch.linspace(0.0, 1.0, g, dtype=cp.dtype, device=cp.device)
    points, _, _ = nurbs.evaluate(cp, surfaces.degree_u, surfaces.degree_v, u, u)  # [H, F, g*g, 3]
    uv = torch.stack(torch.meshgrid(u, u, indexing="ij"), -1).reshape(-1, 2)
    h, f = cp.shape[:2]
    flat = points.reshape(h * f, g * g, 3)
    # Every facet on the one parameter grid: one system, a right-hand side per facet (a loop of per-facet fits
    # took 10.8 s for a 2,000-heliostat field).
    nets = nurbs.fit(flat, uv, (nu2, nv2), degree, ridge=0.0)
    return Surfaces(nets.reshape(h, f, nu2, nv2, 3).to(cp), int(degree[0]), int(degree[1]))


def with_surfaces(plant: Plant, heliostat_ids, surfaces: Surfaces) -> Plant:
    """The plant with the mirror surfaces of ``heliostat_ids`` replaced.

    The field shares one control-net size and degree; when the learned net differs from the plant's,
    every other heliostat's surface is carried over to the learned net by :func:`resample_surfaces`
    (exact for ideal facets).

    Parameters
    ----------
    plant : Plant
    heliostat_ids : list of str, length K
    surfaces : Surfaces
        ``control_points`` [K, F, nu, nv, 3] [m], heliostat frame, same facet count as the plant.

    Returns
    -------
    Plant
    """
    pos = _positions(plant, heliostat_ids)
    cp = surfaces.control_points.detach()
    old = plant.field.surfaces
    if cp.shape[0] != len(pos) or cp.shape[1] != old.control_points.shape[1]:
        raise HeliotwinError(f"learned surfaces of shape {list(cp.shape)} do not fit {len(pos)} heliostats with "
                             f"{old.control_points.shape[1]} facets")
    if surfaces.weights is not None:
        raise HeliotwinError("learned surfaces must be non-rational (no weights)")
    base = resample_surfaces(old, (cp.shape[2], cp.shape[3]), (surfaces.degree_u, surfaces.degree_v))
    net = base.control_points.clone()
    net[pos] = cp.to(net)
    new = Surfaces(net, int(surfaces.degree_u), int(surfaces.degree_v), None)
    return replace(plant, field=replace(plant.field, surfaces=new))


__all__ = ["with_kinematics", "with_surfaces", "resample_surfaces", "select_heliostats"]
