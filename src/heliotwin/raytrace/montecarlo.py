"""Monte-Carlo ray tracer (heliostat-side rays) onto planar targets and the cylindrical receiver.

Model
-----
Each mirror point ``p`` with unit normal ``n`` and area ``A`` reflects the sun (direction ``s`` towards
the sun) into ``r = reflect(-s, n)``. ``K`` rays per point carry the power
``DNI * A * max(n . s, 0) * reflectivity / K`` each (the incidence cosine is part of the radiometry; a
point whose normal faces away from the sun is shaded and carries nothing). Ray ``k`` leaves along
``r + a_k u + b_k v`` where ``(u, v)`` is an orthonormal frame of ``r`` (the ray's *own* frame, not world
axes) and ``(a_k, b_k) = tan`` of angular offsets drawn from the sunshape plus the mirror slope error
(``2 sigma_slope`` per axis, see :mod:`heliotwin.sunshape`). The flux bitmap is the landed power per
pixel divided by the pixel area [W/m^2], so ``sum(bitmap) * pixel_area`` is the intercepted power.

Shared offset pattern
---------------------
One set of K offsets is drawn per call and shared by all points; each point instead gets an independent
uniformly random rotation ``psi_p`` of its frame ``(u, v)``. The sunshapes are rotationally symmetric, so
each point's K rays are still exactly distributed as the sunshape: the estimator of every pixel is
unbiased (only the correlation between points changes). This makes the per-ray work tiny: no per-ray
random numbers and no per-ray 3-D vectors.

Planar fast path
----------------
For a plane the hit of ``r + a u + b v`` is *projective* in ``(a, b)``: the pixel coordinates are
``(N_x . q) / (D . q)`` and ``(N_y . q) / (D . q)`` with ``q = (1, a, b)`` and nine per-point
coefficients (target origin, basis, pixel size and window folded in; the offsets of the points from the
target are formed in float64, the rest in the ray precision). Per chunk of rays that is one small GEMM
plus a multiplication by ``1 / (D . q)``, followed by the bilinear splat of
:func:`heliotwin.raytrace.splat.projective_splat` (custom autograd: recompute-in-backward; only the int32
landing index is kept per ray). Rays with ``D . q >= -1e-6`` (parallel to or leaving the plane) and points
behind the target get weight 0.

Generic path
------------
For the cylindrical receiver (or ``RaySampling(method="generic")``) per-ray 3-D directions are intersected with
:func:`heliotwin.geometry.ray_cylinder` / :func:`~heliotwin.geometry.ray_plane`, converted to the target's
unrolled ``(arc, axial)`` / ``(x, y)`` coordinates and splatted with
:func:`~heliotwin.raytrace.splat.splat_bilinear`; chunks are checkpointed so memory stays bounded with
gradients.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch.utils.checkpoint import checkpoint

from .. import sunshape as _sunshape
from ..errors import HeliotwinError, OutOfRangeError
from ..field.plant import SunSettings
from ..field.targets import CylinderTarget, PlanarTarget
from ..geometry import orthonormal_frame, ray_cylinder, ray_plane, reflect, safe_normalize
from .flux import FluxImage, target_extent
from .splat import DEFAULT_MAX_RAYS_PER_CHUNK, projective_splat, projective_splat_hard, splat_bilinear, splat_hard

__all__ = ["trace_mc", "RaySampling", "offset_pattern", "planar_coefficients", "MirrorBatch", "prepare_mirror"]

_F64 = torch.float64  # positions (only differences of them are taken in the ray precision)


@dataclass(frozen=True)
class RaySampling:
    """How the Monte-Carlo tracer draws, lands and bins its rays (defaults: 100 rays per mirror point, one
    shared random offset pattern, bilinear splat, the projective fast path where the target allows it).

    Attributes
    ----------
    rays_per_point : int
        K, rays drawn per mirror point (the image noise falls as ``1 / sqrt(K)``).
    stratified : bool
        Latin-hypercube stratification of the shared offset pattern.
    splat : {"bilinear", "hard"}
        Bilinear (differentiable) or nearest-pixel (not differentiable) binning.
    method : {"auto", "projective", "generic"}
        ``auto``: projective for planar targets, generic for the cylinder.
    max_rays_per_chunk : int
        Bound on rays processed at once (memory: ~25 buffers of this many float32 per worker, plus the
        int32 landing index of up to ``splat.INDEX_CACHE_RAYS`` rays kept for the backward pass).
    workers : int, optional
        None (default): chunks run in the calling thread, ops use PyTorch's intra-op threads. ``n``: chunks
        run on ``n`` worker threads with one intra-op thread each (more robust when other processes
        compete for the cores).
    """

    rays_per_point: int = 100
    stratified: bool = False
    splat: str = "bilinear"
    method: str = "auto"
    max_rays_per_chunk: int = DEFAULT_MAX_RAYS_PER_CHUNK
    workers: int | None = None

    def __post_init__(self):
        if int(self.rays_per_point) <= 0:
            raise HeliotwinError(f"rays_per_point must be positive, got {self.rays_per_point!r}")
        if self.splat not in ("bilinear", "hard"):
            raise HeliotwinError(f"splat must be 'bilinear' or 'hard', got {self.splat!r}")
        if self.method not in ("auto", "projective", "generic"):
            raise HeliotwinError(f"unknown method {self.method!r}; expected 'auto', 'projective' or 'generic'")


@dataclass
class MirrorBatch:
    """Per-point quantities shared by the tracers (B samples x P points).

    Attributes
    ----------
    points : torch.Tensor, shape (B, P, 3), float64
        Mirror points, ENU [m] (kept in float64: only their offsets from a target are formed in the ray
        precision).
    reflected : torch.Tensor, shape (B, P, 3)
        Unit reflected central ray directions (ray precision).
    power : torch.Tensor, shape (B, P)
        Reflected power per point ``DNI A max(n.s, 0) rho`` [W] (ray precision).
    """

    points: torch.Tensor
    reflected: torch.Tensor
    power: torch.Tensor

    @property
    def batch(self) -> int:
        """B, the number of samples."""
        return int(self.points.shape[0])

    @property
    def num_points(self) -> int:
        """P, the mirror points per sample."""
        return int(self.points.shape[1])


def prepare_mirror(points, normals, areas, sun_direction, sun: SunSettings,
                   dtype: torch.dtype = torch.float32) -> MirrorBatch:
    """Validate/broadcast inputs, apply the incidence cosine and shading, reflect the sun.

    Parameters
    ----------
    points, normals : torch.Tensor, shape (B, P, 3) or (P, 3)
        Mirror points [m] and unit normals, world ENU.
    areas : torch.Tensor, shape (B, P) or (P,)
        Area represented by each point [m^2].
    sun_direction : torch.Tensor, shape (B, 3) or (3,)
        Unit vector towards the sun.
    sun : SunSettings
        Uses ``dni`` and ``reflectivity``.
    dtype : torch.dtype
        Precision of the directions and powers (the ray precision).

    Returns
    -------
    MirrorBatch
    """
    points = torch.as_tensor(points)
    normals = torch.as_tensor(normals)
    areas = torch.as_tensor(areas)
    sun_direction = torch.as_tensor(sun_direction)
    if points.dim() == 2:
        points = points.unsqueeze(0)
    if normals.dim() == 2:
        normals = normals.unsqueeze(0)
    if areas.dim() == 1:
        areas = areas.unsqueeze(0)
    if sun_direction.dim() == 1:
        sun_direction = sun_direction.unsqueeze(0)
    if points.shape[-1] != 3 or normals.shape[-1] != 3 or sun_direction.shape[-1] != 3:
        raise HeliotwinError("points, normals and sun_direction must have a last dimension of 3")
    b = max(points.shape[0], normals.shape[0], areas.shape[0], sun_direction.shape[0])
    p = max(points.shape[1], normals.shape[1], areas.shape[1])
    points = points.to(_F64).expand(b, p, 3)
    normals = normals.to(dtype).expand(b, p, 3)
    areas = areas.to(dtype).expand(b, p)
    s = safe_normalize(sun_direction.to(dtype)).expand(b, 3).unsqueeze(1)
    cos = (normals * s).sum(-1)
    lit = torch.clamp(cos, min=0.0)  # shaded (n.s <= 0) -> 0 with zero gradient
    power = float(sun.dni) * float(sun.reflectivity) * areas * lit
    reflected = reflect(-s, normals)
    return MirrorBatch(points, reflected, power)


def offset_pattern(rays_per_point: int, generator: torch.Generator, sun: SunSettings, stratified: bool = False,
                   dtype=torch.float32) -> torch.Tensor:
    """Shared ray-offset pattern: rows ``1, tan(alpha_k), tan(beta_k)``.

    Parameters
    ----------
    rays_per_point : int
        K.
    generator : torch.Generator
    sun : SunSettings
        Sunshape and slope error.
    stratified : bool
        Latin-hypercube draw of the sunshape.
    dtype : torch.dtype

    Returns
    -------
    torch.Tensor, shape (3, K)
    """
    off = _sunshape.sample_with_slope_error(sun.sunshape, int(rays_per_point), generator,
                                            slope_error=float(sun.slope_error), sigma=float(sun.sigma),
                                            radius=float(sun.radius), csr=float(sun.csr), dtype=torch.float64,
                                            stratified=stratified)
    t = torch.tan(off)
    return torch.cat((torch.ones(1, t.shape[0], dtype=torch.float64, device=t.device), t.t()), 0).to(dtype)


def _rotated_frames(reflected: torch.Tensor, generator: torch.Generator | None):
    """Orthonormal frames (u, v) [..., 3] of the reflected rays, each turned by a random angle psi_p."""
    u, v = orthonormal_frame(reflected)
    if generator is None:
        return u, v
    psi = torch.rand(reflected.shape[:-1], generator=generator, dtype=_F64, device=generator.device)
    psi = (2.0 * math.pi * psi).to(reflected.device, reflected.dtype).unsqueeze(-1)
    c, s = torch.cos(psi), torch.sin(psi)
    return c * u + s * v, c * v - s * u


def _target_tensors(target: PlanarTarget, b: int, device, dtype=_F64):
    def vec(t):
        t = torch.as_tensor(t, dtype=dtype, device=device)
        return t.reshape(-1, 3).expand(b, 3)

    return vec(target.center), vec(target.normal), vec(target.right), vec(target.up)


def planar_coefficients(points, reflected, u, v, target: PlanarTarget, extent: torch.Tensor, rows: int, cols: int):
    """Projective pixel-coordinate coefficients of the rays ``r + a u + b v`` on a planar target.

    Parameters
    ----------
    points, reflected, u, v : torch.Tensor, shape (B, P, 3)
        Ray origins [m] (any precision; offsets are taken in float64), central directions and the (rotated)
        frame vectors (their dtype is the precision of the result).
    target : PlanarTarget
        Tensors may be batched [B, 3].
    extent : torch.Tensor, shape (B, 4)
        Local rectangle ``(x_min, x_max, y_min, y_max)`` the bitmap covers [m].
    rows, cols : int

    Returns
    -------
    coef : torch.Tensor, shape (B, P, 3, 3)
        ``coef[..., 0, :] = N_col``, ``[..., 1, :] = N_row``, ``[..., 2, :] = D`` over the basis
        ``(1, a, b)``: ``col = N_col . q / D . q`` (pixel centres at integers), likewise ``row``.
    in_front : torch.Tensor, shape (B, P), bool
        The point lies on the field side of the plane.
    """
    b, p = points.shape[:2]
    dt = reflected.dtype
    c = _target_tensors(target, b, points.device)[0]
    _, nt, er, eu = _target_tensors(target, b, points.device, dt)
    tmat = torch.stack((er, eu, nt), dim=-1)  # [B, 3(xyz), 3(t)]
    # local coordinates of the origins (x, y, z) and of the basis directions (r, u, v) in the target frame;
    # the offsets from the target centre are formed in float64, then rounded to the ray precision
    rel = (points.to(_F64) - c.unsqueeze(1)).to(dt)
    loc = torch.bmm(rel, tmat)  # [B, P, 3]
    proj = torch.bmm(torch.stack((reflected, u, v), dim=-2).reshape(b, 3 * p, 3), tmat).view(b, p, 3, 3)
    e_r, e_u, den = proj.unbind(-1)  # [B, P, 3] each, over the basis (r, u, v)
    ext = extent.to(device=points.device, dtype=dt)
    pw = ((ext[:, 1] - ext[:, 0]) / cols).view(b, 1)
    ph = ((ext[:, 3] - ext[:, 2]) / rows).view(b, 1)
    x0, y0, z0 = loc.unbind(-1)  # z0 = distance in front of the plane (> 0 on the field side)
    # hit: x = x0 - z0 (d.e_r)/(d.n), y likewise; pixel col = (x - x_min)/pw - 0.5, row = (y_max - y)/ph - 0.5
    alpha = ((x0 - ext[:, :1]) / pw - 0.5).unsqueeze(-1)
    gamma = ((ext[:, 3:4] - y0) / ph - 0.5).unsqueeze(-1)
    ncol = alpha * den - (z0 / pw).unsqueeze(-1) * e_r
    nrow = gamma * den + (z0 / ph).unsqueeze(-1) * e_u
    return torch.stack((ncol, nrow, den), dim=-2), z0 > 0


def _landing_bounds(target, extent, rows, cols, b, p):
    """Pixel-coordinate bounds [B*P, 4] of the target inside a window (None if the window is inside it)."""
    full = target_extent(target, b).to(extent)
    inside = bool(((extent[:, 0] >= full[:, 0]) & (extent[:, 1] <= full[:, 1]) &
                   (extent[:, 2] >= full[:, 2]) & (extent[:, 3] <= full[:, 3])).all())
    if inside:
        return None
    pw = (extent[:, 1] - extent[:, 0]) / cols
    ph = (extent[:, 3] - extent[:, 2]) / rows
    lox = (full[:, 0] - extent[:, 0]) / pw - 0.5
    hix = (full[:, 1] - extent[:, 0]) / pw - 0.5
    loy = (extent[:, 3] - full[:, 3]) / ph - 0.5
    hiy = (extent[:, 3] - full[:, 2]) / ph - 0.5
    return torch.stack((lox, hix, loy, hiy), -1).unsqueeze(1).expand(b, p, 4).reshape(b * p, 4)


def _resolution(resolution) -> tuple[int, int]:
    if isinstance(resolution, int):
        return resolution, resolution
    rows, cols = (int(x) for x in resolution)
    if rows <= 0 or cols <= 0:
        raise HeliotwinError(f"resolution must be positive, got {resolution!r}")
    return rows, cols


def trace_mc(points, normals, areas, sun_direction, target: PlanarTarget | CylinderTarget, *,
             resolution=(256, 256), sun: SunSettings | None = None, sampling: RaySampling | None = None,
             generator: torch.Generator | None = None, window=None, clip_to_target: bool = True,
             dtype: torch.dtype = torch.float32) -> FluxImage:
    """Monte-Carlo flux image of mirror points on a target.

    Parameters
    ----------
    points, normals : torch.Tensor, shape (B, P, 3) (or (P, 3))
        Mirror surface points [m] and unit normals, world ENU (after kinematics).
    areas : torch.Tensor, shape (B, P) (or (P,))
        Mirror area represented by each point [m^2].
    sun_direction : torch.Tensor, shape (B, 3) (or (3,))
        Unit vector towards the sun.
    target : PlanarTarget or CylinderTarget
        A planar target's tensors may be batched [B, 3] with width/height float or [B].
    resolution : int or (rows, cols)
    sun : SunSettings, optional
        Sunshape, slope error, DNI [W/m^2], reflectivity (default ``SunSettings()``).
    sampling : RaySampling, optional
        Rays per point, stratification, splat, path, chunking and worker threads (default ``RaySampling()``:
        K = 100).
    generator : torch.Generator
        Required; all randomness comes from it (same seed -> identical bitmap).
    window : (x0, y0, width, height) or torch.Tensor, shape (4,) or (B, 4), optional
        Trace into this local rectangle [m] (``(x0, y0)`` = lower-left corner) instead of the whole target.
    clip_to_target : bool
        With a window reaching beyond the target, drop rays that miss the physical target.
    dtype : torch.dtype
        Ray / bitmap precision (float32 default, float64 for gradchecks).

    Returns
    -------
    FluxImage
        ``bitmap [B, rows, cols]`` in W/m^2 (PAINT orientation), ``total_power_w`` (reflected) and
        ``intercepted_power_w`` per sample.
    """
    if generator is None:
        raise HeliotwinError("trace_mc needs an explicit torch.Generator (no global seeding)")
    sun = sun or SunSettings()
    sampling = sampling or RaySampling()
    rows, cols = _resolution(resolution)
    k = int(sampling.rays_per_point)
    splat, method = sampling.splat, sampling.method
    max_rays_per_chunk, workers = sampling.max_rays_per_chunk, sampling.workers
    mirror = prepare_mirror(points, normals, areas, sun_direction, sun, dtype)
    b, p = mirror.batch, mirror.num_points
    extent = target_extent(target, b, window).to(mirror.points.device)
    pixel_area = (extent[:, 1] - extent[:, 0]) / cols * (extent[:, 3] - extent[:, 2]) / rows
    pattern = offset_pattern(k, generator, sun, sampling.stratified, dtype).to(mirror.points.device)
    u, v = _rotated_frames(mirror.reflected, generator)
    if method == "auto":
        method = "projective" if isinstance(target, PlanarTarget) else "generic"
    if method == "projective" and not isinstance(target, PlanarTarget):
        raise HeliotwinError("the projective fast path needs a planar target")
    weights = mirror.power / (k * pixel_area.to(mirror.power).unsqueeze(1))  # [B, P] W/m^2 per ray
    if method == "projective":
        coef, in_front = planar_coefficients(mirror.points, mirror.reflected, u, v, target, extent, rows, cols)
        weights = torch.where(in_front, weights, torch.zeros_like(weights))
        coef = coef.reshape(b * p, 3, 3).to(dtype)
        if not bool(torch.isfinite(coef.detach()).all()):
            raise OutOfRangeError("trace_mc: non-finite mirror points, normals or sun direction")
        bounds = _landing_bounds(target, extent, rows, cols, b, p) if (window is not None and clip_to_target) else None
        wflat = weights.reshape(b * p).to(dtype)
        if splat == "hard":
            bitmap = projective_splat_hard(coef, wflat, pattern, rows, cols, b, p, bounds, max_rays_per_chunk, workers)
        else:
            bitmap = projective_splat(coef, wflat, pattern, rows, cols, b, p, bounds, max_rays_per_chunk, workers)
    else:  # generic (RaySampling admits no other name)
        bitmap = _trace_generic(mirror, u, v, weights, pattern, target, extent, rows, cols,
                                window is not None and clip_to_target, sampling, dtype)
    intercepted = bitmap.sum((-2, -1)) * pixel_area.to(bitmap)
    return FluxImage(bitmap, target, extent, mirror.power.to(_F64).sum(-1), intercepted, "mc")


# ----------------------------------------------------------------------------------------------------
# generic path
# ----------------------------------------------------------------------------------------------------

def _local_hits(origins, dirs, target):
    """Ray hits in local target coordinates. origins [n,1,3] (relative to the target ``center``), dirs [n,K,3]."""
    if isinstance(target, CylinderTarget):
        nrm, right, up = (t.to(dirs) for t in (target.normal, target.right, target.up))
        axis_point = -float(target.radius) * nrm  # relative to the apex
        t, hit, _ = ray_cylinder(origins, dirs, axis_point, up, float(target.radius))
        pts = origins + t.unsqueeze(-1) * dirs - axis_point
        ang = torch.atan2((pts * right).sum(-1), (pts * nrm).sum(-1))
        return float(target.radius) * ang, (pts * up).sum(-1), hit
    raise AssertionError


def _trace_generic(mirror, u, v, weights, pattern, target, extent, rows, cols, clip, sampling: RaySampling, dtype):
    splat, max_rays, workers = sampling.splat, sampling.max_rays_per_chunk, sampling.workers
    b, p, k = mirror.batch, mirror.num_points, pattern.shape[1]
    dev = mirror.points.device
    ext = extent.to(dtype)
    planar = isinstance(target, PlanarTarget)
    if planar:
        c, nt, er, eu = _target_tensors(target, b, dev)
    full = target_extent(target, b).to(dtype)
    step = max(1, int(max_rays) // k)

    def chunk_pixels(o, r, uu, vv, w, bi):
        # o, r, uu, vv: [n, 3] (o relative to the target centre, float64 -> dtype); w: [n]
        dirs = r.unsqueeze(1) + pattern[1].view(1, k, 1) * uu.unsqueeze(1) + pattern[2].view(1, k, 1) * vv.unsqueeze(1)
        o = o.unsqueeze(1)
        if planar:
            n_ = nt[bi].to(dtype)
            t, hit = ray_plane(o, dirs, torch.zeros_like(n_), n_, eps=1e-9)
            front = (o.squeeze(1) * n_).sum(-1) > 0
            hitp = o + t.unsqueeze(-1) * dirs
            x = (hitp * er[bi].to(dtype)).sum(-1)
            y = (hitp * eu[bi].to(dtype)).sum(-1)
            hit = hit & front.unsqueeze(1) & ((dirs * n_).sum(-1) < 0)
        else:
            x, y, hit = _local_hits(o, dirs, target)
        if clip:
            hit = hit & (x >= full[bi, 0]) & (x <= full[bi, 1]) & (y >= full[bi, 2]) & (y <= full[bi, 3])
        pw = (ext[bi, 1] - ext[bi, 0]) / cols
        ph = (ext[bi, 3] - ext[bi, 2]) / rows
        px = (x - ext[bi, 0]) / pw - 0.5
        py = (ext[bi, 3] - y) / ph - 0.5
        far = torch.full_like(px, -1e30)
        px = torch.where(hit, px, far)
        py = torch.where(hit, py, far)
        wr = torch.where(hit, w.unsqueeze(1).expand_as(px), torch.zeros_like(px))
        return px, py, wr

    def chunk_bitmap(o, r, uu, vv, w, bi):
        px, py, wr = chunk_pixels(o, r, uu, vv, w, bi)
        if splat == "hard":
            return splat_hard(px.reshape(1, -1), py.reshape(1, -1), wr.reshape(1, -1), rows, cols)[0]
        return splat_bilinear(px.reshape(1, -1), py.reshape(1, -1), wr.reshape(1, -1), rows, cols,
                              max_rays_per_chunk=max_rays, workers=workers)[0]

    grad = torch.is_grad_enabled() and any(t.requires_grad for t in (mirror.points, mirror.reflected, weights))
    center = target.center.to(dev, _F64).reshape(-1, 3).expand(b, 3)
    images = []
    for bi in range(b):
        img = torch.zeros(rows, cols, dtype=dtype, device=dev)
        rel = mirror.points[bi] - center[bi]
        for s0 in range(0, p, step):
            s1 = min(p, s0 + step)
            args = (rel[s0:s1].to(dtype), mirror.reflected[bi, s0:s1].to(dtype), u[bi, s0:s1].to(dtype),
                    v[bi, s0:s1].to(dtype), weights[bi, s0:s1].to(dtype))
            if grad and splat != "hard":
                img = img + checkpoint(chunk_bitmap, *args, bi, use_reentrant=False)
            else:
                img = img + chunk_bitmap(*args, bi)
        images.append(img)
    return torch.stack(images)
