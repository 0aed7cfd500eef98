"""The whole field on the receiver: per-heliostat optical efficiency and the receiver flux, for one sun.

For every heliostat, as SolarPILOT reports them (Wagner & Wendelin, Solar Energy 171 (2018) 185):

``cosine``        ``n . s``: tracking normal (bisecting the sun and the aim direction) against the sun.
``shading``       unshaded fraction of the mirror (rays towards the sun stopped by other heliostats);
                  the tower's shadow is reported separately (``tower_shading``, not in the product).
``blocking``      fraction of the unshaded mirror's reflected light that no other heliostat stops (so the
                  product counts light that is both shaded and blocked once; the whole-mirror reading,
                  as if all of it were lit, is in ``extras["blocking_whole_mirror"]``).
``attenuation``   :func:`heliotwin.atmosphere.attenuation` over the heliostat -> aim point slant range.
``intercept``     fraction of the light arriving at the receiver that lands on it.
``reflectance``   the mirror reflectivity.
``efficiency``    the product; ``power_w = DNI * mirror area * efficiency``.

Shading and blocking come from the exact ray test (default) or, with ``occlusion_model="solarpilot"``,
from SolarPILOT's analytic estimate (whole-mirror factors, for comparing with its reports; docs/physics.md).

Model
-----
Heliostats track ideally about azimuth-elevation axes (the mirror's width edge stays horizontal): the
normal bisects the sun and the aim direction seen from the pivot, which is the mirror centre. The mirror
surfaces are the plant's NURBS facets (flat or canted; learned surfaces included), sampled on a grid of
``flux_samples`` points per facet and direction; shading and blocking are ray-tested
(:mod:`heliotwin.raytrace.occlusion`) on a ``occlusion_oversampling`` times finer grid and pooled onto
the flux samples. Each flux sample's reflected sun cone (sunshape plus slope error, Gaussian of equal
second moment, :func:`heliotwin.sunshape.second_moment`) lands on the receiver as the Gaussian footprint of
:mod:`heliotwin.raytrace.gaussian` (exact central hit, tangent-plane spread). The intercept of a sample is
that Gaussian's mass on the receiver: its axial marginal between the top and bottom edge (and for a partial
cylinder or a planar receiver, times the lateral marginal; exact for the full cylinder, the lateral
correlation is neglected otherwise); a central ray that misses the receiver contributes nothing.

The flux map sums the footprints: ``window`` mode evaluates every sample's own Gaussian (exact, cost ~ samples x
window pixels); ``grouped`` mode sorts the samples into ``groups^2`` equal classes of similar footprint size
(:func:`_footprint_classes`), splats each class's mean hits bilinearly and convolves it (FFT) with the class's
power-weighted mean Gaussian (cost ~ samples + groups x pixels log pixels); ``auto`` takes ``window`` when its
cost is small. With ``integrator="mc"`` the map is a Monte-Carlo trace of the same samples (occlusion and
attenuation as weights); the per-heliostat intercept stays the Gaussian one. The unrolled map of a full cylinder
is periodic: Gaussian footprints that reach over its seam continue at the other edge (the Monte-Carlo map does
not wrap).

With ``integrator="conv"`` the map keeps the *exact* sunshape (limb-darkened, Buie, pillbox) instead of its
Gaussian-equivalent: the grouped map with, per footprint class, the tabulated angular density of a reflected
ray (:func:`heliotwin.raytrace.conv.angular_density`) mapped through the class's mean footprint (the density
is radially symmetric, so the footprint covariance fixes the map from angle to pixels); the per-heliostat
intercept stays the Gaussian one.

Everything is batched over heliostats (no loop over heliostats or points) and differentiable with
``softness`` set (smooth occlusion): w.r.t. aim points, positions and the sun.
"""
from __future__ import annotations

import math
import weakref
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field, replace

import numpy as np
import torch
import torch.distributed as dist

from .. import sunshape as _sunshape
from ..atmosphere import Atmosphere, attenuation
from ..errors import HeliotwinError
from ..field.facets import surface_points
from ..field.plant import Plant
from ..field.targets import CylinderTarget, PlanarTarget
from ..geometry import orthonormal_frame, ray_cylinder, reflect, safe_normalize
from .conv import angular_density
from .flux import target_extent
from .gaussian import _cylinder_moments, _fft_convolve, _gaussian_kernels, _projective_moments, gaussian_footprints
from .montecarlo import RaySampling, planar_coefficients, trace_mc
from .occlusion import (
    OccluderSet,
    mirror_blocks,
    mirror_frame,
    occluder_candidates,
    solarpilot_interference,
    solarpilot_neighbours,
    unoccluded,
    unoccluded_tracked,
)
from .splat import splat_bilinear

__all__ = ["FieldSettings", "FieldResult", "equator_aim_points", "tracking_normals", "field_optics", "summary",
           "tracked_mirror_samples", "reuse_mirror_samples",
           "per_heliostat_rows", "FACTORS"]

#: Per-heliostat factors whose product is the optical efficiency (SolarPILOT's breakdown).
FACTORS = ("cosine", "shading", "blocking", "attenuation", "intercept", "reflectance")


@dataclass
class FieldSettings:
    """Numerical settings of :func:`field_optics`.

    Attributes
    ----------
    resolution : (int, int)
        Receiver map (rows, cols); for a cylinder the columns run around the circumference.
    integrator : {"gaussian", "conv", "mc"}
    flux_samples : int
        Flux samples per facet and direction (per heliostat ``F * flux_samples^2``).
    occlusion_oversampling : int
        Occlusion rays per flux sample and direction.
    softness : float or None
        None: exact (hard) occlusion; a length [m]: smooth, differentiable occlusion.
    occlusion_model : {"exact", "solarpilot"}
        ``exact`` (default): shading and blocking ray-tested point by point (the physics).
        ``solarpilot``: SolarPILOT's analytic per-pair estimate
        (:func:`heliotwin.raytrace.occlusion.solarpilot_interference`), whole-mirror shading and blocking
        applied uniformly to the mirror; for comparing with SolarPILOT's reports (docs/physics.md).
    flux_mode : {"auto", "window", "grouped", "none"}
        ``none``: no receiver map (zeros), the per-heliostat factors alone -- what the year's tables need.
    groups : int
        Footprint classes per axis in ``grouped`` mode (``groups^2`` classes).
    smoothing : float
        Variance [px^2] added to every footprint (1/12: a pixel-box average).
    n_sigma : float
        Footprint window half-size in standard deviations.
    rays_per_point, seed : int
        Monte-Carlo settings.
    dtype : torch.dtype
        Precision of rays, footprints and maps (float64 for gradient checks).
    """

    resolution: tuple = (20, 48)
    integrator: str = "gaussian"
    flux_samples: int = 8
    occlusion_oversampling: int = 2
    softness: float | None = None
    occlusion_model: str = "exact"
    flux_mode: str = "auto"
    groups: int = 4
    smoothing: float = 1.0 / 12.0
    n_sigma: float = 3.5
    rays_per_point: int = 64
    seed: int = 0
    dtype: torch.dtype = torch.float32


@dataclass
class FieldResult:
    """Per-heliostat factors [H] (see module docstring), aim points and normals [H, 3], the receiver map.

    ``flux`` [rows, cols] [W/m^2] (PAINT orientation: row 0 = top), ``extent`` (4,) its local rectangle
    [m], ``mirror_area`` [H] [m^2], ``power_w`` [H] [W], ``sun`` (3,), ``dni`` [W/m^2].
    """

    aim: torch.Tensor
    normal: torch.Tensor
    cosine: torch.Tensor
    shading: torch.Tensor
    tower_shading: torch.Tensor
    blocking: torch.Tensor
    attenuation: torch.Tensor
    intercept: torch.Tensor
    reflectance: torch.Tensor
    efficiency: torch.Tensor
    power_w: torch.Tensor
    mirror_area: torch.Tensor
    flux: torch.Tensor
    extent: torch.Tensor
    sun: torch.Tensor
    dni: float
    extras: dict = field(default_factory=dict)

    @property
    def pixel_area(self) -> float:
        """[m^2] of one map cell."""
        rows, cols = self.flux.shape[-2:]
        e = self.extent
        return float((e[1] - e[0]) * (e[3] - e[2])) / (rows * cols)


def equator_aim_points(receiver: PlanarTarget | CylinderTarget, position: torch.Tensor) -> torch.Tensor:
    """SolarPILOT's "simple" aiming: the receiver point facing each heliostat, at mid-height.

    Parameters
    ----------
    receiver : CylinderTarget or PlanarTarget
    position : torch.Tensor, [H, 3]
        Heliostat pivots, ENU [m].

    Returns
    -------
    torch.Tensor, [H, 3]
        Cylinder: ``axis_point + radius * horizontal unit vector towards the heliostat`` (clamped to the
        segment for a partial cylinder); planar: the receiver centre. Dtype of ``position``.
    """
    if isinstance(receiver, PlanarTarget):
        return receiver.center.to(position).expand_as(position).clone()
    axis = receiver.axis_point.to(position)
    up = receiver.up.to(position)
    d = position - axis
    d = d - (d * up).sum(-1, keepdim=True) * up
    d = safe_normalize(d)
    if receiver.opening_angle < 2 * math.pi - 1e-9:
        n, r = receiver.normal.to(position), receiver.right.to(position)
        ang = torch.atan2((d * r).sum(-1), (d * n).sum(-1)).clamp(-receiver.opening_angle / 2,
                                                                   receiver.opening_angle / 2)
        d = torch.cos(ang).unsqueeze(-1) * n + torch.sin(ang).unsqueeze(-1) * r
    return axis + float(receiver.radius) * d


def tracking_normals(position: torch.Tensor, aim: torch.Tensor, sun_direction: torch.Tensor) -> torch.Tensor:
    """Ideal tracking: the mirror normal bisects the sun and the aim direction.

    Parameters
    ----------
    position, aim : torch.Tensor, [H, 3]
        Mirror centres and aim points, ENU [m].
    sun_direction : torch.Tensor, [3]
        Unit, towards the sun.

    Returns
    -------
    torch.Tensor, [H, 3]
        Unit normals ``normalize(s + normalize(aim - position))``.
    """
    return safe_normalize(sun_direction.to(position) + safe_normalize(aim - position))


def tracked_mirror_samples(plant: Plant, normal: torch.Tensor, per_direction: int, dtype,
                           rows: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World mirror samples of heliostats tracking with mirror normals ``normal``.

    Parameters
    ----------
    plant : Plant
    normal : torch.Tensor, shape (h, 3)
        Unit mirror normals of the heliostats ``rows`` (of all heliostats when ``rows`` is None).
    per_direction : int
        Samples per facet and direction (``F * per_direction^2`` per heliostat).
    dtype : torch.dtype
        Of the returned normals.
    rows : torch.Tensor, shape (h,), optional
        Heliostat indices (default: all).

    Returns
    -------
    points : torch.Tensor, shape (h, N, 3), float64
        ENU [m].
    normals : torch.Tensor, shape (h, N, 3), ``dtype``
    areas : torch.Tensor, shape (h, N)
        Mirror area per sample [m^2].
    """
    pts, nrm, area = _local_mirror_samples(plant.field.surfaces, per_direction, rows)
    ew, eh = mirror_frame(normal)
    rot = torch.stack((ew, eh, normal), dim=-1)  # R_world_heliostat [h, 3, 3], columns = heliostat x, y, z
    pos = plant.field.kinematics.position.to(normal)
    pos = pos if rows is None else pos[rows]
    pw = pos.unsqueeze(1) + pts.to(normal) @ rot.transpose(-1, -2)
    nw = nrm.to(normal) @ rot.transpose(-1, -2)
    return pw, nw.to(dtype), area.to(normal)


_REUSED_SAMPLES: ContextVar[dict | None] = ContextVar("heliotwin_reused_mirror_samples", default=None)


@contextmanager
def reuse_mirror_samples():
    """Within this block :func:`field_optics` samples each plant's mirror surfaces (heliostat frame) once per
    sample grid and reuses them: repeated evaluations of one plant (the rounds of the aim-point optimiser)
    move the heliostats, never their surfaces. Surfaces that require a gradient are sampled afresh every time.
    Nested blocks share the outermost one's samples; they are dropped when it ends."""
    if _REUSED_SAMPLES.get() is not None:
        yield
        return
    token = _REUSED_SAMPLES.set({})
    try:
        yield
    finally:
        _REUSED_SAMPLES.reset(token)


def _local_mirror_samples(sf, per_direction: int, rows: torch.Tensor | None, reuse: bool = True):
    """:func:`heliotwin.field.facets.surface_points` of heliostats ``rows`` on a ``per_direction`` grid, reused
    within :func:`reuse_mirror_samples` (unless ``reuse`` is False)."""
    cache = _REUSED_SAMPLES.get() if reuse else None
    tensors = [sf.control_points] + ([] if sf.weights is None else [sf.weights])
    if cache is not None and not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors)):
        key = (tuple((id(t), t._version) for t in tensors), int(per_direction),
               None if rows is None else hash(rows.detach().cpu().numpy().tobytes()))
        hit = cache.get(key)
        if hit is not None and all(r() is t for r, t in zip(hit[0], tensors)):
            return hit[1]
    if rows is not None:
        sf = replace(sf, control_points=sf.control_points[rows],
                     weights=None if sf.weights is None else sf.weights[rows])
    cp, w = sf.control_points, sf.weights
    h = cp.shape[0]
    if h > 1 and bool((cp == cp[:1]).all()) and (w is None or bool((w == w[:1]).all())) and \
            not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors)):
        # one mirror shape for the whole field (ideal heliostats): sample it once
        one = surface_points(replace(sf, control_points=cp[:1], weights=None if w is None else w[:1]),
                             (per_direction, per_direction))
        out = tuple(t.expand(h, *t.shape[1:]) for t in one)
    else:
        out = surface_points(sf, (per_direction, per_direction))
    if cache is not None and not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors)):
        cache[key] = ([weakref.ref(t) for t in tensors], out)
    return out


def _block_side(per_direction: int) -> int:
    """Samples per side of an occlusion culling block: two by two blocks per facet. With 16 samples per facet
    side, 4 x 4-sample blocks (16 per facet) made the second culling level cost more than the ray tests it
    saved: 8 x 8 took a 2,000-heliostat field's node from 0.64 to 0.44 s (2 cores, same answer: culling only
    skips rays no occluder can stop)."""
    return max(2, int(per_direction) // 2)


def _in_dtype(t: torch.Tensor, dtype) -> torch.Tensor:
    """``t`` in ``dtype``; a tensor expanded over its first axis (one mirror shape for the field) stays one."""
    if t.shape[0] > 1 and t.stride(0) == 0:
        return t[:1].to(dtype).expand_as(t)
    return t.to(dtype)


def _occlusion_samples(sf, facets: int, per_direction: int, rows: torch.Tensor, hard: bool):
    """The occlusion's mirror samples of heliostats ``rows`` in the heliostat frame: points and normals
    [h, N, 3] float64, areas [h, N], and for the hard test their blocks
    (:func:`heliotwin.raytrace.occlusion.mirror_blocks`; None for the smooth test).

    Within :func:`reuse_mirror_samples` they are kept between evaluations as float32 with their blocks (built on
    the float32 samples, which the hard test rays from: its ray tests are float32 anyway) and handed out as
    float64 copies: 10,000 heliostats' oversampled mirrors held 1.1 GB in float64 in every process of the
    year's tables."""
    cache = _REUSED_SAMPLES.get()
    tensors = [sf.control_points] + ([] if sf.weights is None else [sf.weights])
    grad = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    if cache is None or grad:
        pts, nrm, area = _local_mirror_samples(sf, per_direction, rows)
        blocks = mirror_blocks(pts, nrm, facets, per_direction, _block_side(per_direction)) if hard else None
        return pts, nrm, area, blocks
    key = ("occlusion", tuple((id(t), t._version) for t in tensors), int(per_direction), bool(hard),
           hash(rows.detach().cpu().numpy().tobytes()))
    hit = cache.get(key)
    if hit is None or not all(r() is t for r, t in zip(hit[0], tensors)):
        pts, nrm, area = _local_mirror_samples(sf, per_direction, rows, reuse=False)
        pts, nrm = _in_dtype(pts, torch.float32), _in_dtype(nrm, torch.float32)
        blocks = mirror_blocks(pts, nrm, facets, per_direction, _block_side(per_direction)) if hard else None
        hit = ([weakref.ref(t) for t in tensors], (pts, nrm, area, blocks))
        cache[key] = hit
    pts, nrm, area, blocks = hit[1]
    return _in_dtype(pts, torch.float64), _in_dtype(nrm, torch.float64), area, blocks


def _pool(x: torch.Tensor, weight: torch.Tensor, facets: int, m: int, k: int) -> torch.Tensor:
    """Weighted mean of fine-grid values [H, F*(m k)^2] over each k x k block -> [H, F*m^2].

    As two average pools (the 1/k^2 cancels): 5x faster than summing a [H, F, m, k, m, k] view over its
    strided axes (77 -> 14 ms on 1,773 heliostats' occluded mirrors, one node of a 2,000-heliostat year)."""
    h, side = x.shape[0], m * k
    num = torch.nn.functional.avg_pool2d((x * weight).reshape(h * facets, 1, side, side), k)
    den = torch.nn.functional.avg_pool2d(weight.reshape(h * facets, 1, side, side), k)
    return (num / den.clamp_min(1e-30)).reshape(h, -1)


def _blocking_candidates(plant: Plant, occ: OccluderSet, aim: torch.Tensor, rows: torch.Tensor):
    """:func:`~heliotwin.raytrace.occlusion.occluder_candidates` along each heliostat's line to its aim point,
    reused within :func:`reuse_mirror_samples` while the aim points and the field are the same tensors (the
    year's tables: one aim for every sun, so the blocking corridors are the same at every node; ~45 ms of a
    2,000-heliostat node). Only the latest is kept, so an optimiser moving its aim points holds one."""
    pos = occ.center
    direction = safe_normalize(aim[rows] - pos[rows])
    cache = _REUSED_SAMPLES.get()
    if cache is None:
        return occluder_candidates(occ, direction, queries=rows)
    fl = plant.field
    sources = (aim, fl.kinematics.position, fl.width, fl.height)
    key = (tuple((id(t), t._version) for t in sources), str(pos.dtype),
           hash(rows.detach().cpu().numpy().tobytes()))
    hit = cache.get("blocking-candidates")
    if hit is not None and hit[0] == key and all(r() is t for r, t in zip(hit[1], sources)):
        return hit[2]
    out = occluder_candidates(occ, direction, queries=rows)
    cache["blocking-candidates"] = (key, [weakref.ref(t) for t in sources], out)
    return out


def _occlusion(plant: Plant, normal, aim, sun, settings: FieldSettings, rows: torch.Tensor):
    """Shading, blocking (pooled onto the flux samples [h, N]) and per-heliostat factors [h] of heliostats
    ``rows``; every heliostat of the field (``normal``, ``aim`` [H, 3]) can occlude them.

    The mirror samples stay in the heliostat frame (``R_world_heliostat`` per heliostat): the hard test
    (:func:`heliotwin.raytrace.occlusion.unoccluded_tracked`) forms world rays only for the blocks of samples
    an occluder may reach; the smooth test traces every sample."""
    fl = plant.field
    nf = fl.facets.translation.shape[1]
    h = rows.shape[0]
    m, k = int(settings.flux_samples), int(settings.occlusion_oversampling)
    hard = settings.softness is None and settings.occlusion_model == "exact"
    pts, nrm, area, blocks = _occlusion_samples(fl.surfaces, nf, m * k, rows, hard)
    pts, nrm, area = pts.to(normal), nrm.to(normal), area.to(normal)
    nr = normal[rows]
    ew, eh = mirror_frame(nr)
    rot = torch.stack((ew, eh, nr), dim=-1)  # R_world_heliostat [h, 3, 3]
    pos = fl.kinematics.position.to(normal)
    occ = OccluderSet(pos, normal, fl.width.to(normal), fl.height.to(normal))
    s = sun.to(normal)
    cos_p = torch.einsum("hnc,hc->hn", nrm, s @ rot).clamp_min(0.0)  # n . s in the heliostat frame
    lit = area * cos_p
    tower = _tower_shading(plant, pos[rows], pts, rot, s, lit)
    if settings.occlusion_model == "solarpilot":
        return _occlusion_solarpilot(plant, occ, normal, aim, s, lit, tower, nf, m, rows)
    idx, valid = occluder_candidates(occ, s, queries=rows)
    idx_b, valid_b = _blocking_candidates(plant, occ, aim, rows)
    if settings.softness is None:
        free_sun = unoccluded_tracked(blocks, rot, occ, idx, valid, s, reflected=False, owners=rows)
        free_rx = unoccluded_tracked(blocks, rot, occ, idx_b, valid_b, s, reflected=True, owners=rows)
        free_sun, free_rx = free_sun.to(normal), free_rx.to(normal)  # 0/1 in the samples' dtype (float32 reused)
    else:
        pw = pos[rows].unsqueeze(1) + pts @ rot.transpose(-1, -2)
        nw = nrm @ rot.transpose(-1, -2)
        free_sun = unoccluded(pw, s.expand(h, 1, 3), occ, idx, valid, softness=settings.softness, owners=rows)
        free_rx = unoccluded(pw, reflect(-s.expand_as(nw), nw), occ, idx_b, valid_b, softness=settings.softness,
                             owners=rows)
    shading = (lit * free_sun).sum(1) / lit.sum(1).clamp_min(1e-30)
    blocking = (lit * free_sun * free_rx).sum(1) / (lit * free_sun).sum(1).clamp_min(1e-30)
    both = free_sun * free_rx
    if settings.softness is None:  # hard: a mirror no ray of which is stopped pools to exactly 1
        free = torch.ones((h, nf * m * m), dtype=both.dtype, device=both.device)
        hit = torch.nonzero((both == 0).any(1)).flatten()
        if hit.numel():
            free[hit] = _pool(both[hit], lit[hit].detach() + 1e-30, nf, m, k)
    else:
        free = _pool(both, lit.detach() + 1e-30, nf, m, k)
    # SolarPILOT's reading: blocking of the whole mirror's light as if it were all lit (counts the light that
    # is both shaded and blocked twice in a product, so it is only reported, never multiplied in)
    blocking_whole = (lit * free_rx).sum(1) / lit.sum(1).clamp_min(1e-30)
    return shading, blocking, tower, free, blocking_whole


def _in_blocks(run, n: int, block: int, dim: int = 0) -> tuple:
    """``run(sl)`` over consecutive slices ``sl`` of ``n`` items, ``block`` at a time, its tuple of tensors joined
    along ``dim`` (one call when ``n <= block``): a memory bound for work that is item by item."""
    if n <= block:
        return run(slice(0, n))
    parts = [run(slice(i, i + block)) for i in range(0, n, block)]
    return tuple(torch.cat(p, dim=dim) for p in zip(*parts))


def _occlusion_in_blocks(plant: Plant, normal, aim, sun, settings: FieldSettings, rows: torch.Tensor):
    """:func:`_occlusion` of heliostats ``rows`` in blocks of :data:`OCCLUSION_BLOCK` heliostats, concatenated:
    its oversampled mirror samples (``F (flux_samples x oversampling)^2`` per heliostat, a dozen [H, N] tensors
    in flight) are what bounds the field model's memory, ~2 GB at 10,000 heliostats in one piece."""
    return _in_blocks(lambda sl: _occlusion(plant, normal, aim, sun, settings, rows[sl]), rows.numel(),
                      OCCLUSION_BLOCK)


#: Heliostats per block of the occlusion test (:func:`_occlusion_in_blocks`): a memory bound, not a tuning knob
#: (the occluders are every heliostat of the field in every block, so the result does not depend on it).
OCCLUSION_BLOCK = 2048


def _occlusion_solarpilot(plant: Plant, occ: OccluderSet, normal, aim, sun, lit, tower, nf, m, rows):
    """SolarPILOT's analytic shading and blocking (whole mirror, per heliostat [h]), spread uniformly over the
    flux samples; the same outputs as :func:`_occlusion`."""
    fl = plant.field
    pos, width, height = occ.center, fl.width.to(normal), fl.height.to(normal)
    elevation = math.asin(max(-1.0, min(1.0, float(sun[2]))))
    idx, valid = occluder_candidates(occ, sun, queries=rows)
    valid = solarpilot_neighbours(pos, height, width, elevation, idx, valid, rows)
    shading = solarpilot_interference(pos, normal, width, height, sun, idx, valid, rows)
    tower_dir = safe_normalize(aim[rows] - pos[rows])
    idx_b, valid_b = occluder_candidates(occ, tower_dir, queries=rows)
    valid_b = solarpilot_neighbours(pos, height, width, elevation, idx_b, valid_b, rows)
    blocking = solarpilot_interference(pos, normal, width, height, tower_dir, idx_b, valid_b, rows)
    free = (shading * blocking).unsqueeze(1).expand(rows.shape[0], nf * m * m)
    return shading, blocking, tower, free, blocking


def _tower_shading(plant: Plant, pivot, points, rot, sun, lit) -> torch.Tensor:
    """Unshaded fraction [H] by the tower: a vertical cylinder of the receiver's radius up to its top edge.

    ``pivot`` [H, 3] ENU, ``points`` [H, N, 3] in the heliostat frame, ``rot`` [H, 3, 3] ``R_world_heliostat``.
    Only heliostats whose sun ray passes near the tower (a per-heliostat bounding test) are ray-tested.
    """
    rec = plant.targets["receiver"]
    out = torch.ones(points.shape[0], dtype=points.dtype, device=points.device)
    if not isinstance(rec, CylinderTarget):
        return out
    axis = rec.axis_point.to(points)
    up = rec.up.to(points)
    top = float(rec.height) / 2
    with torch.no_grad():
        centre = pivot.detach()
        shared = points.shape[0] > 1 and points.stride(0) == 0
        reach = torch.linalg.vector_norm((points[:1] if shared else points).detach(), dim=-1).amax(1)
        reach = reach.expand(points.shape[0]) if shared else reach
        rel = axis - centre
        horiz = sun - (sun @ up) * up
        hn = horiz.norm().clamp_min(1e-12)
        along = rel @ (horiz / hn)
        perp = (rel - along.unsqueeze(-1) * (horiz / hn) - (rel @ up).unsqueeze(-1) * up).norm(dim=-1)
        # height the sun ray gains before it can reach the tower wall (a lower bound)
        rise = (along - float(rec.radius) - reach).clamp_min(0) * float(sun @ up) / float(hn)
        near = (along > -float(rec.radius)) & (perp < float(rec.radius) + reach) & \
            (((centre - axis) @ up) + rise - reach <= top)
        rows = torch.nonzero(near).flatten()
    if rows.numel() == 0:
        return out
    p = pivot[rows].unsqueeze(1) + points[rows] @ rot[rows].transpose(-1, -2)
    t, hit, _ = ray_cylinder(p, sun.expand_as(p), axis, up, float(rec.radius))
    height = ((p + t.unsqueeze(-1) * sun - axis) * up).sum(-1)
    shaded = hit & (height <= top)
    frac = (lit[rows] * (~shaded)).sum(1) / lit[rows].sum(1).clamp_min(1e-30)
    return out.index_put((rows,), frac)


def _footprints(points, reflected, target, extent, rows, cols):
    """Mean hits mu [1, N, 2] and Jacobians [1, N, 2, 2] in pixels, ok [1, N] (central ray lands), in blocks of
    :data:`FOOTPRINT_BLOCK` samples (each sample's own; a whole field's in one piece held ~400 bytes of
    temporaries per sample: 1 GB at 10,000 heliostats)."""
    return _in_blocks(lambda sl: _footprint_block(points[:, sl], reflected[:, sl], target, extent, rows, cols),
                      points.shape[1], FOOTPRINT_BLOCK, dim=1)


#: Samples per block of :func:`_footprints` (a memory bound; the result does not depend on it).
FOOTPRINT_BLOCK = 1 << 18


def _footprint_block(points, reflected, target, extent, rows, cols):
    """:func:`_footprints` of one block."""
    u, v = orthonormal_frame(reflected)
    if isinstance(target, PlanarTarget):
        coef, in_front = planar_coefficients(points, reflected, u, v, target, extent, rows, cols)
        mu, jac, ok = _projective_moments(coef)
        return mu, jac, ok & in_front
    if isinstance(target, CylinderTarget):
        return _cylinder_moments(points, reflected, u, v, target, extent, rows, cols)
    raise HeliotwinError(f"unsupported receiver type {type(target).__name__}")


def _intercept(mu, cov, ok, target, rows, cols):
    """Mass [N] of each footprint Gaussian on the receiver (pixel space; the bitmap covers the whole target)."""
    sq2 = math.sqrt(2.0)

    def band(m, var, n):
        sd = torch.sqrt(var.clamp_min(1e-12)) * sq2
        return 0.5 * (torch.erf((n - 0.5 - m) / sd) - torch.erf((-0.5 - m) / sd))

    frac = band(mu[..., 1], cov[..., 1, 1], rows)
    full = isinstance(target, CylinderTarget) and target.opening_angle >= 2 * math.pi - 1e-9
    if not full:
        frac = frac * band(mu[..., 0], cov[..., 0, 0], cols)
    return torch.where(ok, frac, torch.zeros_like(frac))


def _quantile(x: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """``torch.quantile(x, q)`` (linear interpolation); on the CPU by NumPy's selection instead of a full sort
    (the same numbers, ~3x faster on the field's ~10^6 samples)."""
    if x.device.type != "cpu":
        return _sorted_quantile(x, q)
    return torch.from_numpy(np.asarray(np.quantile(x.numpy(), q.numpy()), dtype=x.numpy().dtype))


def _sorted_quantile(x: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """``torch.quantile(x, q)`` (linear interpolation) of a 1-D ``x`` by one sort: ``torch.quantile`` refuses
    inputs of more than 2^24 elements, which a field of 60,000 heliostats' flux samples exceeds (a GPU's path)."""
    v = torch.sort(x).values
    pos = q.to(torch.float64) * (v.numel() - 1)
    lo = pos.floor().long().clamp(0, v.numel() - 1)
    hi = (lo + 1).clamp(max=v.numel() - 1)
    frac = (pos - lo.to(torch.float64)).to(v.dtype)
    return v[lo] + frac * (v[hi] - v[lo])


def _footprint_classes(lx, ly, all_x, all_y, groups: int) -> torch.Tensor:
    """Class [n] in ``0..groups^2-1`` of each footprint by its log variances ``lx``, ``ly`` [n] (columns, rows):
    ``groups`` quantile bins of ``lx``, each split into ``groups`` quantile bins of ``ly`` *within it*, so the
    classes hold about equal numbers of footprints (``all_x``, ``all_y``: every rank's values, whose quantiles
    set the bins). Independent bins per axis left most classes empty, as the two variances grow together with
    the slant range, so a few classes spanned wide ranges of footprint size and their padded layout grew with
    the largest class."""
    if groups <= 1:
        return torch.zeros_like(lx, dtype=torch.long)
    q = torch.linspace(0, 1, groups + 1, dtype=lx.dtype, device=lx.device)[1:-1]
    edges_x = _quantile(all_x, q)
    gx, all_gx = torch.bucketize(lx, edges_x), torch.bucketize(all_x, edges_x)
    # per x-bin quantiles of ly (a loop over the few bins, not over footprints); an empty bin takes any edges
    edges_y = torch.stack([_quantile(all_y[all_gx == b], q) if bool((all_gx == b).any()) else edges_x
                           for b in range(groups)])  # [groups, groups - 1]
    gy = torch.searchsorted(edges_y[gx], ly.unsqueeze(-1)).squeeze(-1)
    return gx * groups + gy


def _grouped_map(mu, cov, weights, rows, cols, groups, n_sigma, group=None, density=None):
    """Footprints in classes of similar covariance: per class a bilinear splat convolved with its mean Gaussian,
    or with ``density`` = (angular density [G, G], its half width [rad], the sun's variance [rad^2], the
    smoothing [px^2] in ``cov``) with the exact sun cone mapped through the class's mean footprint
    (:func:`_sun_cone_kernels`; the ``conv`` integrator).

    ``group`` (ranks each holding a shard of the samples): the class boundaries come from every rank's
    footprints and the class kernels from every rank's members, so the shards' maps sum to the one-process map.
    """
    n = mu.shape[0]
    with torch.no_grad():
        lx, ly = torch.log(cov[:, 0, 0].clamp_min(1e-12)), torch.log(cov[:, 1, 1].clamp_min(1e-12))
        all_x, all_y = (lx, ly) if group is None else _gather_all(torch.stack((lx, ly), -1), group).unbind(-1)
        g = _footprint_classes(lx, ly, all_x, all_y, groups)
        ng = groups * groups
        order = torch.argsort(g, stable=True)
        counts = torch.bincount(g, minlength=ng)
        start = torch.cumsum(counts, 0) - counts
        rank = torch.arange(n, device=mu.device) - start[g[order]]
        width = int(counts.max())
    slot = g[order] * width + rank
    lay_mu = mu.new_full((ng * width, 2), -1e9).index_copy(0, slot, mu[order]).view(ng, width, 2)
    lay_w = weights.new_zeros(ng * width).index_copy(0, slot, weights[order]).view(ng, width)
    wsum = lay_w.sum(1)
    lay_cov = cov.new_zeros(ng * width, 2, 2).index_copy(0, slot, cov[order]).view(ng, width, 2, 2)
    wcov = (lay_w[..., None, None] * lay_cov).sum(1)
    if group is not None:
        wsum, wcov = _sum_all(wsum, group), _sum_all(wcov, group)
    kcov = wcov / wsum.clamp_min(1e-30)[:, None, None]
    kcov = torch.where((wsum > 0)[:, None, None], kcov, torch.eye(2, dtype=cov.dtype, device=cov.device))
    with torch.no_grad():
        tr = kcov[:, 0, 0] + kcov[:, 1, 1]
        lam = 0.5 * tr + torch.sqrt(0.25 * (kcov[:, 0, 0] - kcov[:, 1, 1]) ** 2 + kcov[:, 0, 1] ** 2)
        half = int(min(max(rows, cols), max(1, math.ceil(n_sigma * float(lam.max().sqrt())))))
        if density is not None:  # the exact sun cone reaches its tabulated half width [rad] x the largest stretch
            var = density[2]
            half = int(min(max(rows, cols), max(1, math.ceil(density[1] * float((lam.max() / var).sqrt())) + 1)))
    canvas = splat_bilinear(lay_mu[..., 0] + half, lay_mu[..., 1] + half, lay_w, rows + 2 * half, cols + 2 * half)
    eye = torch.eye(2, dtype=cov.dtype, device=cov.device)
    if density is not None:
        kern = _sun_cone_kernels(kcov - density[3] * eye, density, half)
    else:
        # the bilinear splat already blurs by its tent kernel (variance 1/6 px^2): take it out of the class kernel
        with torch.no_grad():
            lam_min = 0.5 * tr - torch.sqrt(0.25 * (kcov[:, 0, 0] - kcov[:, 1, 1]) ** 2 + kcov[:, 0, 1] ** 2)
            sub = torch.minimum(torch.full_like(lam_min, 1.0 / 6.0), 0.9 * lam_min.clamp_min(0.0))
        kern = _gaussian_kernels(kcov - sub[:, None, None] * eye, half)
    return _fft_convolve(canvas, kern, half, rows, cols, summed=True)


def _flux_map(points, nw, reflected, weights, target, settings: FieldSettings, plant: Plant, sun, group=None):
    """Receiver map [rows, cols] [W/m^2], per-sample intercept [N], the map's extent (4,).

    ``group``: a ``torch.distributed`` process group whose ranks each draw a shard of the field; they agree on
    the footprint window and the map mode (largest window, total sample count), so that their maps sum to the
    one-process map exactly, not just within the window truncation."""
    rows, cols = (int(x) for x in settings.resolution)
    extent = target_extent(target, 1).to(points.device)
    pixel_area = float((extent[0, 1] - extent[0, 0]) * (extent[0, 3] - extent[0, 2])) / (rows * cols)
    dt = settings.dtype
    mu, jac, ok = _footprints(points.unsqueeze(0), reflected.unsqueeze(0).to(dt), target, extent, rows, cols)
    mu, jac, ok = mu[0], jac[0], ok[0]
    s = plant.sun
    var = _sunshape.second_moment(s.sunshape, sigma=float(s.sigma), radius=float(s.radius), csr=float(s.csr),
                                  slope_error=float(s.slope_error))
    eye = torch.eye(2, dtype=jac.dtype, device=jac.device)
    cov = var * (jac @ jac.transpose(-1, -2))
    cov = torch.where(ok[..., None, None], cov, eye)
    icpt = _intercept(mu, cov, ok, target, rows, cols)
    w = torch.where(ok, weights.to(dt) / pixel_area, torch.zeros_like(weights.to(dt)))
    mu = torch.where(ok.unsqueeze(-1), mu, torch.full_like(mu, -1e9))
    cov_s = cov + float(settings.smoothing) * eye
    if settings.integrator == "mc":
        img = trace_mc(points.unsqueeze(0), nw.unsqueeze(0), (weights / (_power_scale(plant, nw, sun))).unsqueeze(0),
                       sun.unsqueeze(0), target, resolution=(rows, cols), sun=plant.sun,
                       sampling=RaySampling(int(settings.rays_per_point)),
                       generator=torch.Generator().manual_seed(int(settings.seed)), dtype=dt)
        return img.bitmap[0], icpt, extent[0]
    if isinstance(target, CylinderTarget) and target.opening_angle >= 2 * math.pi - 1e-9:
        mu, cov_s, w = _wrap_seam(mu, cov_s, w, ok, cols, float(settings.n_sigma))
    mode = settings.flux_mode
    with torch.no_grad():
        sd = torch.sqrt(torch.where(mu[:, 0] > -1e8, cov_s[:, 0, 0].maximum(cov_s[:, 1, 1]),
                                    torch.zeros_like(cov_s[:, 0, 0])))
        half = int(min(64, max(1, math.ceil(settings.n_sigma * float(sd.max())))))
        total = mu.shape[0]
        if group is not None:
            half, total = _agree(half, total, group)
    density = None
    if settings.integrator == "conv":  # the exact sun cone per footprint class: always the grouped map
        dens, half_width = angular_density(s)
        density, mode = (dens.to(mu.device), half_width, var, float(settings.smoothing)), "grouped"
    if mode == "auto":
        mode = "window" if total * (2 * half + 1) ** 2 <= 2e7 else "grouped"
    if mode == "none":  # the factors alone (the year's tables): the intercept needs the footprints, not the map
        img = torch.zeros(rows, cols, dtype=w.dtype, device=w.device)
    elif mode == "window":
        img = gaussian_footprints(mu, cov_s, w, rows, cols, 1, mu.shape[0], half)[0]
    elif mode == "grouped":
        img = _grouped_map(mu, cov_s, w, rows, cols, int(settings.groups), float(settings.n_sigma), group, density)
    else:
        raise HeliotwinError(f"flux_mode must be 'auto', 'window', 'grouped' or 'none', got {mode!r}")
    return img, icpt, extent[0]


def _sun_cone_kernels(cov: torch.Tensor, density, half: int, supersample: int = 4) -> torch.Tensor:
    """Kernels [B, 2h+1, 2h+1] (row = py offset, column = px offset) of the exact sun cone for classes whose
    mean footprint covariance is ``cov`` [B, 2, 2] [px^2].

    A reflected ray's angular density is radially symmetric (:func:`heliotwin.raytrace.conv.angular_density`:
    sunshape convolved with the slope-error scatter), and the footprint covariance is ``var J J^T`` for the
    Jacobian J [px/rad] of the hit w.r.t. the ray angle, so with ``L L^T = cov / var`` a pixel offset x comes
    from the angle ``L^-1 x`` whatever J's rotation: kernel(x) ~ density(L^-1 x). Each pixel averages
    ``supersample^2`` points (the box of the pixel, as the Gaussian kernels' smoothing); differentiable in cov.
    """
    dens, half_width, var = density[0], float(density[1]), float(density[2])
    b = cov.shape[0]
    eye = torch.eye(2, dtype=cov.dtype, device=cov.device)
    chol = torch.linalg.cholesky(cov / var + 1e-9 * eye)  # [B, 2, 2] [px/rad]
    sub = (torch.arange(supersample, dtype=cov.dtype, device=cov.device) + 0.5) / supersample - 0.5
    off = torch.arange(-half, half + 1, dtype=cov.dtype, device=cov.device)
    fine = (off[:, None] + sub[None, :]).reshape(-1)  # [S*s]
    dy, dx = torch.meshgrid(fine, fine, indexing="ij")
    xy = torch.stack((dx.reshape(-1), dy.reshape(-1)), 0).expand(b, 2, -1)  # [B, 2, P] pixel offsets
    ang = torch.linalg.solve_triangular(chol, xy, upper=False)  # [B, 2, P] [rad]
    grid = (ang / half_width).transpose(1, 2).reshape(b, fine.numel(), fine.numel(), 2).to(dens.dtype)
    img = torch.nn.functional.grid_sample(dens.to(grid).expand(b, 1, *dens.shape), grid, mode="bicubic",
                                          padding_mode="zeros", align_corners=True)[:, 0]
    side = 2 * half + 1
    img = img.reshape(b, side, supersample, side, supersample).mean((2, 4)).to(cov.dtype)
    return img / img.sum((-2, -1), keepdim=True).clamp_min(1e-30)


def _agree(half: int, count: int, group) -> tuple[int, int]:
    """The largest window half-size and the summed sample count over the ranks of ``group``."""
    device = "cuda" if dist.get_backend(group) == "nccl" else "cpu"
    t = torch.tensor([half, count], dtype=torch.long, device=device)
    dist.all_reduce(t[:1], op=dist.ReduceOp.MAX, group=group)
    dist.all_reduce(t[1:], group=group)
    return int(t[0]), int(t[1])


def _gather_all(t: torch.Tensor, group) -> torch.Tensor:
    """Every rank's rows of ``t`` [n_r, ...] concatenated in rank order (no gradient)."""
    world = dist.get_world_size(group)
    n = torch.tensor([t.shape[0]], dtype=torch.long, device=t.device)
    counts = [torch.zeros_like(n) for _ in range(world)]
    dist.all_gather(counts, n, group=group)
    counts = [int(c) for c in counts]
    pad = t.new_zeros((max(counts), *t.shape[1:]))
    pad[: t.shape[0]] = t.detach()
    parts = [torch.empty_like(pad) for _ in range(world)]
    dist.all_gather(parts, pad, group=group)
    return torch.cat([p[:c] for p, c in zip(parts, counts)])


def _sum_all(t: torch.Tensor, group) -> torch.Tensor:
    """``t`` summed over the ranks; the gradient flows to this rank's own term."""
    total = t.detach().clone()
    dist.all_reduce(total, group=group)
    return t + (total - t.detach())


def _wrap_seam(mu, cov, w, ok, cols: int, n_sigma: float):
    """A full cylinder's map is periodic in its columns: footprints reaching over the seam (left or right edge,
    ``cols`` pixels apart) get a copy shifted by one period, so the light that spills over one edge lands at
    the other. Only the samples within ``n_sigma`` footprint widths of an edge are copied."""
    with torch.no_grad():
        reach = n_sigma * torch.sqrt(cov[:, 0, 0].clamp_min(0.0)) + 1.0
        left = torch.nonzero(ok & (mu[:, 0] - reach < -0.5)).flatten()
        right = torch.nonzero(ok & (mu[:, 0] + reach > cols - 0.5)).flatten()
    if left.numel() + right.numel() == 0:
        return mu, cov, w
    period = torch.tensor([float(cols), 0.0], dtype=mu.dtype, device=mu.device)
    mu = torch.cat((mu, mu[left] + period, mu[right] - period))
    return mu, torch.cat((cov, cov[left], cov[right])), torch.cat((w, w[left], w[right]))


def _power_scale(plant: Plant, nw, sun):
    """DNI rho cos per sample: turns a sample's power back into the 'area' the Monte-Carlo tracer expects."""
    cos = (nw * sun.to(nw)).sum(-1).clamp_min(1e-12)
    return float(plant.sun.dni) * float(plant.sun.reflectivity) * cos


def field_optics(plant: Plant, sun_direction: torch.Tensor, *, atmosphere: Atmosphere | None = None,
                 aim: torch.Tensor | None = None, settings: FieldSettings | None = None,
                 receiver: str = "receiver", heliostats: torch.Tensor | None = None, group=None) -> FieldResult:
    """Optical efficiency of every heliostat and the receiver flux map for one sun.

    Parameters
    ----------
    plant : Plant
        H heliostats (``kinematics.position`` = mirror centres, ``width``/``height``, facets, surfaces), the
        target ``receiver``, ``sun`` settings (DNI, reflectivity, sunshape, slope error).
    sun_direction : torch.Tensor, [3]
        Unit vector towards the sun (ENU); the sun must be above the horizon.
    atmosphere : Atmosphere, optional
        Default: SolarPILOT's default coefficients.
    aim : torch.Tensor, [H, 3], optional
        Aim points ENU [m] (default: :func:`equator_aim_points`); gradients flow to it.
    settings : FieldSettings, optional
    receiver : str
        Target name.
    heliostats : torch.Tensor, shape (h,), long, optional
        Trace only these heliostats (a shard, :mod:`heliotwin.distributed`); all heliostats still shade and
        block them. The result's per-heliostat tensors are theirs and the map holds their light only.
    group : torch.distributed ProcessGroup, optional
        With ``heliostats`` = this rank's shard: the ranks agree on the footprint window, so the sum of their
        maps is the one-process map (:func:`heliotwin.distributed.field_optics_sharded` passes it).

    Returns
    -------
    FieldResult
    """
    settings = settings or FieldSettings()
    if settings.integrator not in ("gaussian", "conv", "mc"):
        raise HeliotwinError(f"unknown field integrator {settings.integrator!r}; expected gaussian, conv or mc")
    if settings.occlusion_model not in ("exact", "solarpilot"):
        raise HeliotwinError(f"unknown occlusion model {settings.occlusion_model!r}; expected exact or solarpilot")
    if settings.occlusion_model == "solarpilot" and settings.softness is not None:
        raise HeliotwinError("the solarpilot occlusion model is a report (not differentiable); use softness with "
                             "occlusion_model='exact'")
    target = plant.target(receiver)
    pos = plant.field.kinematics.position
    f64 = torch.float64  # geometry in float64; rays and maps in settings.dtype
    pos = pos.to(f64)
    sun = safe_normalize(torch.as_tensor(sun_direction, dtype=f64, device=pos.device).reshape(3))
    if float(sun[2]) <= 0:
        elevation = math.degrees(math.asin(float(sun[2])))
        raise HeliotwinError(f"the sun is below the horizon (elevation {elevation:.2f} deg)")
    aim = equator_aim_points(target, pos) if aim is None else aim.to(pos)
    normal = tracking_normals(pos, aim, sun)
    rows = torch.arange(pos.shape[0], device=pos.device) if heliostats is None else \
        torch.as_tensor(heliostats, dtype=torch.long, device=pos.device)
    shading, blocking, tower, free, blocking_whole = _occlusion_in_blocks(plant, normal, aim, sun, settings, rows)
    aim, normal, pos = aim[rows], normal[rows], pos[rows]
    cosine = (normal * sun).sum(-1)
    slant = torch.linalg.vector_norm(aim - pos, dim=-1)
    att = attenuation(slant, atmosphere)
    m = int(settings.flux_samples)
    pw, nw, area = tracked_mirror_samples(plant, normal, m, settings.dtype, rows)
    nw64 = nw.to(f64)
    cos_p = (nw64 @ sun).clamp_min(0.0)
    rho, dni = float(plant.sun.reflectivity), float(plant.sun.dni)
    # [H, N] power [W] leaving each sample towards the receiver
    weights = dni * rho * area * cos_p * free * att.unsqueeze(1)
    reflected = -sun - 2.0 * (nw64 @ -sun).unsqueeze(-1) * nw64  # reflect(-sun, nw64), the dot as a product
    h, n = weights.shape
    flux, icpt, extent = _flux_map(pw.reshape(h * n, 3), nw.reshape(h * n, 3), reflected.reshape(h * n, 3),
                                   weights.reshape(-1), target, settings, plant, sun, group)
    icpt = icpt.reshape(h, n).to(f64)
    intercept = (weights * icpt).sum(1) / weights.sum(1).clamp_min(1e-30)
    mirror_area = area.sum(1)
    reflectance = torch.full_like(cosine, rho)
    efficiency = cosine * shading * blocking * att * intercept * reflectance
    return FieldResult(aim, normal, cosine, shading, tower, blocking, att, intercept, reflectance, efficiency,
                       dni * mirror_area * efficiency, mirror_area, flux, extent, sun, dni,
                       {"blocking_whole_mirror": blocking_whole})


def summary(result: FieldResult, plant: Plant) -> dict:
    """JSON-ready report: field averages (unweighted as SolarPILOT, and power-weighted), receiver figures.

    The power-weighted factors chain (each weighted by the power reaching that stage), so their product is
    the field's total efficiency ``receiver power / (DNI x mirror area)``.
    """
    r = result
    a = r.mirror_area
    unweighted = {name: float(getattr(r, name).mean()) for name in FACTORS}
    unweighted["total"] = float(r.efficiency.mean())
    unweighted["tower_shading"] = float(r.tower_shading.mean())
    if "blocking_whole_mirror" in r.extras:
        unweighted["blocking_whole_mirror"] = float(r.extras["blocking_whole_mirror"].mean())
    stage = a.clone()
    weighted = {}
    for name in FACTORS:
        f = getattr(r, name)
        weighted[name] = float((stage * f).sum() / stage.sum().clamp_min(1e-30))
        stage = stage * f
    weighted["total"] = float((a * r.efficiency).sum() / a.sum())
    peak = float(r.flux.max())
    return {
        "heliostats": len(plant.field.ids),
        "sun": {"direction_enu": r.sun.tolist(),
                "azimuth_deg_paint": math.degrees(math.atan2(float(r.sun[0]), -float(r.sun[1]))),
                "elevation_deg": math.degrees(math.asin(float(r.sun[2])))},
        "dni_w_m2": r.dni,
        "mirror_area_m2": float(a.sum()),
        "field": {"efficiency": unweighted, "efficiency_power_weighted": weighted},
        "receiver": {"power_w": float(r.power_w.sum()), "peak_flux_w_m2": peak,
                     "map_power_w": float(r.flux.sum()) * r.pixel_area,
                     "map_shape": list(r.flux.shape), "cell_m": [(float(r.extent[1] - r.extent[0])) / r.flux.shape[1],
                                                                 (float(r.extent[3] - r.extent[2])) / r.flux.shape[0]]},
    }


def per_heliostat_rows(result: FieldResult, plant: Plant) -> list[dict]:
    """One dict per heliostat with the CSV columns ``id,x,y,z,aim_x,aim_y,aim_z,efficiency,<factors>,power_w``."""
    pos = plant.field.kinematics.position.detach().to(torch.float64)
    aim = result.aim.detach().to(torch.float64)
    cols = {name: getattr(result, name).detach().tolist() for name in ("efficiency",) + FACTORS + ("power_w",)}
    rows = []
    for i, hid in enumerate(plant.field.ids):
        row = {"id": hid, "x": float(pos[i, 0]), "y": float(pos[i, 1]), "z": float(pos[i, 2]),
               "aim_x": float(aim[i, 0]), "aim_y": float(aim[i, 1]), "aim_z": float(aim[i, 2])}
        row.update({k: v[i] for k, v in cols.items()})
        rows.append(row)
    return rows
