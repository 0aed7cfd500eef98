"""Aim points under a peak-flux limit, checked on the exact field model.

Every heliostat gets an aim point on the receiver surface with two degrees of freedom, its unrolled local
coordinates ``(x, y)`` (arc length, height [m]); the height stays on the receiver (projected onto
``|y| <= h/2``), the lateral coordinate within the part of the receiver the heliostat sees. The problem, at one sun,

    maximise P(a)  subject to  F_c(a) <= limit for every cell c of the reporting map

(or: minimise the mismatch of ``F / P`` to a target shape, subject to the same limit) is judged on the
*exact* field model: :func:`heliotwin.raytrace.field.field_optics` with hard occlusion and the map as
``heliotwin field`` draws it (:func:`check_settings`) on the reporting grid. That model costs about a second
for 2000 heliostats and is not smooth in the aim points (hard occlusion, footprint classes),
so the optimisation runs on a cheap differentiable *image model* corrected by the exact one, in rounds
(surrogate-based optimisation with defect correction; first-order model management as in Alexandrov et al.,
Structural Optimization 15 (1998) 16):

1. the exact model at the current aim points ``a_k`` gives the map ``F_k``, the power per heliostat (with its
   shading, blocking, cosine, attenuation) and its intercept;
2. the image model ``S(a)``: per heliostat one Gaussian image centred on its aim point, power = the exact
   model's power before spillage, spreads = the second moments of the exact model's own footprints at the
   current aim points (:func:`image_moments`: sunshape, slope error, mirror size and focus, and the incidence
   on the receiver's surface, so a tilted or curved receiver and a partial cylinder's edges are the exact
   model's); cell-integrated (erf differences), so the map is a ``[rows, H] x [H, cols]`` product (closed
   around a full cylinder);
3. the corrected model ``S(a) + (F_k - S(a_k))`` equals the exact map at ``a_k``; an augmented Lagrangian
   (Hestenes-Powell; multipliers per cell, ``lambda_c <- max(0, lambda_c + rho g_c)``, kept across rounds)
   with Adam steps solves the problem on it against the internal limit ``(1 - m) limit``;
4. the exact model re-checks the new aim points; the margin ``m`` grows by the observed excess when the
   check fails. Rounds stop when the check passes and the power settles.

With ``field_gradient=True`` the corrected power is also first-order exact at ``a_k``: the difference between
the smooth differentiable field model's power gradient (soft shading and blocking, cosine, attenuation,
intercept; one backward pass through :func:`~heliotwin.raytrace.field.field_optics`) and the image model's is
added as a linear term, so the optimiser sees how occlusion and cosine move with the aim points.

Each aim point stays on the receiver's height and, on a cylinder, within :data:`VISIBLE_HALF_ANGLE` of the
generator line facing its heliostat (a point on the far side is hidden behind the near one).

The answer is the best aim points whose *exact* check passed. When none did (the limit cannot be held with
every heliostat's light on the receiver), the fewest heliostats that make the least violating aim points hold
it go to standby (aimed above the receiver; :attr:`AimResult.standby` counts them): less power, the limit held.
Only when even the whole field on standby violates it is the least violating result returned, with the
violation reported as it is, never clipped.

Sharding (:mod:`heliotwin.distributed`): with a process group every rank holds the parameters of its
contiguous shard of heliostats; image maps and powers are all-reduced at every step, the exact check is
:func:`heliotwin.distributed.field_optics_sharded`; the multipliers and every decision use the reduced
values, so all ranks take the same steps as one process (up to the summation order).
:func:`run_aimpoints_sharded` spawns N local gloo processes for it.

Baselines:

* equator aiming (:func:`heliotwin.raytrace.field.equator_aim_points`, SolarPILOT's "simple");
* :func:`aiming_factor`: the one-parameter aiming strategy of Sánchez-González et al. (Solar Energy 157
  (2017) 1130): heliostats alternately aim above and below the equator, displaced by
  ``k (h/2 - image half-height)``; the smallest ``k`` in [0, 1] that meets the limit (bisection on the exact
  check);
* :func:`image_size_priority`: SolarPILOT's image-size-priority aiming as described by Wagner & Wendelin
  (Solar Energy 171 (2018) 185) and the SolarPILOT manual: heliostats sorted by image size, the largest
  placed first, each at the height of its column where the flux so far is lowest, within
  ``|y| <= h/2 - k sigma_y``; batched here (groups of heliostats placed at once on the image model), with the
  largest ``k`` (least spillage) that meets the limit found by bisection on the exact check.

Shapes: H heliostats; aim points [H, 3] ENU [m]; maps [rows, cols] [W/m^2] (row 0 = top); powers [W].
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import torch
import torch.distributed as dist

from .. import sunshape as _ss
from ..atmosphere import Atmosphere
from ..devices import to_device
from ..distributed import field_optics_sharded, gather_rows, run_spawned, shard
from ..errors import HeliotwinError
from ..field.plant import Plant
from ..field.targets import CylinderTarget
from ..geometry import reflect
from ..raytrace.field import (
    FieldSettings,
    _footprints,
    equator_aim_points,
    field_optics,
    reuse_mirror_samples,
    tracked_mirror_samples,
    tracking_normals,
)
from ..raytrace.flux import target_extent

__all__ = ["AimResult", "AimSettings", "ImageModel", "optimise_aimpoints", "calibrate_images", "to_device",
           "aiming_factor", "image_size_priority", "evaluate", "check_settings", "uniform_target", "load_target",
           "target_mismatch", "run_aimpoints_sharded"]

_SQ2 = math.sqrt(2.0)
_LN_SQRT_PI = 0.5 * math.log(math.pi)  # exp(-v^2) / sqrt(pi) = exp(-v^2 - ln sqrt(pi))


@dataclass
class AimResult:
    """Aim points [H, 3] and what the exact model gives for them: receiver power [W], peak [W/m^2], map."""

    aim: torch.Tensor
    power_w: float
    peak_flux_w_m2: float
    flux: torch.Tensor
    seconds: float = 0.0
    iterations: int = 0
    parameter: float | None = None
    history: list = field(default_factory=list)
    standby: int = 0  #: heliostats sent off the receiver (standby) so that the limit holds
    #: the augmented Lagrangian's multipliers per map cell [rows, cols] [-] at the end (a warm start's)
    multipliers: torch.Tensor | None = None
    #: the power [W] the objective was relative to: equator aiming's on the exact model, or (a warm start without
    #: the equator check) the corrected image model's estimate of it
    reference_power_w: float | None = None
    #: exact field-model evaluations made (the rounds' checks, the warm start's, the standby search's)
    exact_checks: int = 0
    #: the exact model's :class:`~heliotwin.raytrace.field.FieldResult` of these aim points (the next instant's
    #: ``start_field``)
    exact: object = None

    def violation(self, limit: float) -> float:
        """Relative excess of the peak over the limit (0 when met)."""
        return max(0.0, self.peak_flux_w_m2 / float(limit) - 1.0)


# ------------------------------------------------------------------------------------------ exact model
class _Group:
    """All-reduce and field model of one process group (or of one process when ``group`` is None)."""

    def __init__(self, group=None):
        self.group = group
        if group is None:
            self.rank, self.world = 0, 1
        else:
            self.rank, self.world = dist.get_rank(group), dist.get_world_size(group)

    def rows(self, h: int, device) -> torch.Tensor:
        if self.group is None:
            return torch.arange(h, device=device)
        return shard(h, self.rank, self.world).to(device)

    def sum(self, t: torch.Tensor) -> torch.Tensor:
        """Sum over ranks, keeping the gradient of this rank's part (straight-through)."""
        if self.group is None:
            return t
        total = t.detach().clone()
        dist.all_reduce(total, group=self.group)
        return t + (total - t.detach())

    def gather(self, t: torch.Tensor, h: int) -> torch.Tensor:
        if self.group is None:
            return t
        return gather_rows(t.detach(), [len(shard(h, k, self.world)) for k in range(self.world)], self.group)

    def field(self, plant, sun, atmosphere, aim, settings):
        with torch.no_grad():
            if self.group is None:
                return field_optics(plant, sun, atmosphere=atmosphere, aim=aim, settings=settings)
            return field_optics_sharded(plant, sun, group=self.group, atmosphere=atmosphere, aim=aim,
                                        settings=settings)


def check_settings(resolution=(20, 48)) -> FieldSettings:
    """The exact model every result is judged with: hard occlusion on the reporting grid, the map exactly as
    ``heliotwin field`` draws it (``flux_mode="auto"``: every flux sample's own Gaussian on small fields,
    footprint classes on large ones, where one map costs ~15 s per-sample against ~0.5 s; the map is the same
    in one process and sharded), in float64: the rounds feed it back into the optimiser, and a float32 map's
    summation order (one process or shards) changed the sharded aim points by millimetres."""
    return FieldSettings(resolution=tuple(int(r) for r in resolution), dtype=torch.float64)


def evaluate(plant: Plant, sun: torch.Tensor, aim: torch.Tensor, atmosphere=None, resolution=(20, 48), *,
             group=None) -> AimResult:
    """The exact (hard-occlusion, per-sample map) field model at fixed aim points.

    ``sun`` is the unit vector towards the sun, shape (3,), ENU; ``aim`` the aim points, shape (H, 3), ENU [m];
    ``resolution`` the receiver map's ``(rows, cols)``. The result holds the receiver power [W], the peak
    [W/m^2] and the map, shape (rows, cols) [W/m^2].
    """
    r = _Group(group).field(plant, sun, atmosphere, aim, check_settings(resolution))
    return AimResult(aim.detach(), float(r.power_w.sum()), float(r.flux.max()), r.flux)


# ------------------------------------------------------------------------------------------ image model
def _axis_profile(t: torch.Tensor, box: torch.Tensor, sd: torch.Tensor, consts=None):
    """CDF and density at ``t`` (offsets from the centre [m], [h, ...]) of a uniform box of half-width ``box``
    convolved with a Gaussian of standard deviation ``sd`` ([h, 1, ...] each, [m]).

    CDF ``(G(t + b) - G(t - b)) / 2b`` with ``G(u) = u Phi(u / s) + s phi(u / s)`` (the integral of the Gaussian
    CDF) [1], written with ``v = u / (sqrt(2) s)`` as ``G = u / 2 + (s / sqrt(2)) H(v)``, ``H(v) = v erf(v) +
    exp(-v^2) / sqrt(pi)``: ``CDF = 1/2 + sqrt(2) s (H(v+) - H(v-)) / 4b``; density ``(erf(v+) - erf(v-)) / 4b``
    [1/m] (the same two erfs). ``consts``: :func:`_profile_consts` of ``box``, ``sd`` when the caller keeps them
    (the same numbers).

    One erf, one exp and five arithmetic passes per side, in place where no gradient is recorded: the
    optimiser's inner loop evaluates this a few hundred times per round on ``[h, edges]`` arrays (at 2,000
    heliostats 1.5-3x faster than the textbook form's thirty passes, whose temporaries left the cache).
    """
    inv_s2, c_up, c_lo, scale, dens = _profile_consts(box, sd) if consts is None else consts
    record = torch.is_grad_enabled() and any(v.requires_grad for v in (t, inv_s2, c_up, scale))
    v0 = t * inv_s2

    def side(c):
        v = v0 + c
        e = torch.erf(v)
        # exponents capped at -50 (e^-50 ~ 2e-22): beyond, exp runs through subnormal floats (float32 below
        # e^-87), which a CPU computes ~5x slower, for terms that cancel in the difference anyway
        if record:
            return torch.addcmul(torch.exp(-v.square().clamp_max(50.0) - _LN_SQRT_PI), v, e), e
        return v.square().clamp_max_(50.0).neg_().sub_(_LN_SQRT_PI).exp_().addcmul_(v, e), e

    h_up, e_up = side(c_up)
    h_lo, e_lo = side(c_lo)
    if record:
        return (h_up - h_lo) * scale + 0.5, (e_up - e_lo) * dens
    return h_up.sub_(h_lo).mul_(scale).add_(0.5), e_up.sub_(e_lo).mul_(dens)


def _profile_consts(box: torch.Tensor, sd: torch.Tensor):
    """``(1 / (sqrt(2) sd) [1/m], box / (sqrt(2) sd), -box / (sqrt(2) sd) [-], sqrt(2) sd / 4 box [-],
    1 / 4 box [1/m])`` of :func:`_axis_profile` ([h, 1, ...] each)."""
    inv_s2 = 1.0 / (_SQ2 * sd)
    c = box * inv_s2
    return inv_s2, c, -c, 0.25 * _SQ2 * sd / box, 0.25 / box


@dataclass
class ImageModel:
    """One image per heliostat on the unrolled receiver map (cell-integrated): per axis a uniform box (the
    mirror's own extent as seen on the receiver) convolved with a Gaussian (sunshape and slope error).

    Attributes
    ----------
    power : torch.Tensor, [h]
        Power arriving at the receiver surface before spillage [W] (the exact model's ``power_w / intercept``).
    sx, sy : torch.Tensor, [h]
        Lateral and vertical image standard deviations [m] (box and Gaussian together).
    x_edges, y_edges : torch.Tensor, [cols + 1], [rows + 1]
        Cell edges [m], ascending (map rows run from the top, so the map is flipped in ``y``).
    period : float
        The map's circumference [m] when it closes on itself (a full cylinder: an image crossing the seam
        comes back on the other side, as the exact map's); 0 for a partial cylinder or a plane.
    bx, by : torch.Tensor, [h], optional
        Half-widths [m] of the boxes, ``b^2 / 3 < s^2`` (the rest of the variance is the Gaussian's);
        None: a pure Gaussian image.
    profile_dtype : torch.dtype, optional
        Evaluate the profiles at the cell edges (element-wise) in this precision, the rest in the model's.
    """

    power: torch.Tensor
    sx: torch.Tensor
    sy: torch.Tensor
    x_edges: torch.Tensor
    y_edges: torch.Tensor
    period: float = 0.0
    bx: torch.Tensor | None = None
    by: torch.Tensor | None = None
    profile_dtype: torch.dtype | None = None

    def _profile(self, axis: int):
        """Box half-width and Gaussian sd [h] along ``axis`` (0: x, 1: y); the box at least 1e-3 sd (a
        vanishing box is a Gaussian, and its difference quotient stays accurate)."""
        s, b = (self.sx, self.bx) if axis == 0 else (self.sy, self.by)
        b = torch.zeros_like(s) if b is None else b.to(s)
        b = torch.minimum(b, 0.999 * math.sqrt(3.0) * s)
        g = (s * s - b * b / 3.0).clamp_min(1e-12).sqrt()
        return b.clamp_min(1e-3 * g), g

    def _axis(self, axis: int, dt):
        """Box half-widths and Gaussian sds [h, 1] in ``dt`` along ``axis`` and their :func:`_profile_consts`:
        the same every step of a round, so kept (keyed by the very tensors, not a dataclass field: a replaced
        or reassigned ``sx`` ... starts afresh) unless they need a gradient."""
        s, b = (self.sx, self.bx) if axis == 0 else (self.sy, self.by)
        key = (axis, dt, id(s), s._version, None if b is None else (id(b), b._version))
        cache = self.__dict__.setdefault("_axis_cache", {})
        hit = cache.get(key)
        if hit is not None and hit[0] is s and hit[1] is b:
            return hit[2]
        box, sd = self._profile(axis)
        box, sd = box[:, None].to(dt), sd[:, None].to(dt)
        out = (box, sd, _profile_consts(box, sd))
        if not (torch.is_grad_enabled() and (s.requires_grad or (b is not None and b.requires_grad))):
            if len(cache) >= 8:  # reassigned spreads: drop the old ones
                cache.clear()
            cache[key] = (s, b, out)
        return out

    def _tx(self, x: torch.Tensor, dt: torch.dtype) -> torch.Tensor:
        """Column edges minus each centre [h, cols + 1] [m] in ``dt``; on a closed map wrapped into ``[-period/2,
        period/2)`` (each edge's offset from the copy of the image nearest to it). The centres are wrapped in
        their own precision, the offsets formed in ``dt``."""
        edges = self.x_edges.to(dt)
        if self.period <= 0.0:
            return edges[None, :] - x.to(dt)[:, None]
        p = float(self.period)
        t = edges[None, :] - (torch.remainder(x + 0.5 * p, p) - 0.5 * p).to(dt)[:, None]  # in [-p, p]
        return torch.where(t >= 0.5 * p, t - p, torch.where(t < -0.5 * p, t + p, t))

    def _cells(self, x: torch.Tensor, y: torch.Tensor):
        """Mass per column [h, cols] and per row (ascending y) [h, rows] of the images centred at ``(x, y)`` [h],
        and the profiles' densities at the column and row edges, [h, cols + 1] and [h, rows + 1] [1/m], all in
        ``profile_dtype`` (default: the centres' precision).

        A cell's mass is the CDF's difference across it. On a closed map the edges' offsets are wrapped (one
        profile evaluation per edge, not one per edge and copy of the image): the one column whose offsets wrap
        (upper below lower: half a period from the centre) holds ``C(upper) + 1 - C(lower)``, its own light and
        all light beyond half a period (on the far side of the cylinder, where it lands).
        """
        dt = self.profile_dtype or x.dtype
        tx, ty = self._tx(x, dt), self.y_edges.to(dt)[None, :] - y.to(dt)[:, None]
        cx, px = _axis_profile(tx, *self._axis(0, dt))
        cy, py = _axis_profile(ty, *self._axis(1, dt))
        gx = cx[:, 1:] - cx[:, :-1]
        if self.period > 0.0:
            gx = gx + (tx[:, 1:] < tx[:, :-1]).to(gx)
        return gx, cy[:, 1:] - cy[:, :-1], px, py

    @property
    def cell_area(self) -> float:
        """Area of one map cell [m^2] (the edges are uniform), a float scalar."""
        return float((self.x_edges[1] - self.x_edges[0]) * (self.y_edges[1] - self.y_edges[0]))

    def marginals(self, x: torch.Tensor, y: torch.Tensor):
        """Mass per column [h, cols] and per row (ascending y) [h, rows] of the images centred at ``(x, y)`` [h],
        in the centres' precision."""
        gx, gy, _, _ = self._cells(x, y)
        return gx.to(x.dtype), gy.to(x.dtype)

    def flux(self, x: torch.Tensor, y: torch.Tensor):
        """Map [rows, cols] [W/m^2] (row 0 = top) and intercepted power per heliostat [h] [W]."""
        params = (self.power, self.sx, self.sy, self.x_edges, self.y_edges, self.bx, self.by)
        if not any(t is not None and t.requires_grad for t in params):
            return _ImageFlux.apply(x, y, self)  # gradients to the aim points only: the hand-fused backward
        gx, gy = self.marginals(x, y)
        mx = gx.sum(1)
        p = self.power * mx  # light that misses the unrolled map sideways (a partial cylinder) is lost
        img = (gy * self.power[:, None]).transpose(0, 1) @ gx / self.cell_area
        return img.flip(0), p * gy.sum(1)


class _ImageFlux(torch.autograd.Function):
    """:meth:`ImageModel.flux` with its gradient w.r.t. the image centres ``x``, ``y`` [h] written out: the
    optimiser's inner loop calls it hundreds of times, and one fused backward (the profiles' densities at the
    cell edges times the map's and the powers' adjoints) costs a fraction of the recorded graph's."""

    @staticmethod
    def forward(ctx, x, y, model):
        # per heliostat in the profiles' precision (float32 in the optimiser), every sum over heliostats (the map)
        # in the centres': a sharded run's all-reduced map is then one process's to float64 rounding, and its
        # steps are one process's (the backward's contractions run over cells, each heliostat on its own)
        gx, gy, px, py = model._cells(x, y)  # [h, cols], [h, rows], densities [h, cols + 1], [h, rows + 1]
        power = model.power.to(gx.dtype)
        mx, my = gx.sum(1), gy.sum(1)
        pgy = gy * power[:, None]
        img = pgy.to(x.dtype).transpose(0, 1) @ gx.to(x.dtype) / model.cell_area
        ctx.save_for_backward(px, py, gx, pgy, mx, my, power)  # densities at the edges
        ctx.model, ctx.dtype = model, x.dtype
        return img.flip(0), (power * mx * my).to(x.dtype)

    @staticmethod
    def backward(ctx, g_img, g_p):
        px, py, gx, pgy, mx, my, power = ctx.saved_tensors
        m = ctx.model
        g_gx = g_gy = None
        if g_img is not None:
            g = g_img.to(gx.dtype).flip(0) / m.cell_area
            g_gx = pgy @ g  # [h, cols]
            g_gy = power[:, None] * (gx @ g.transpose(0, 1))  # [h, rows]
        if g_p is not None:
            gp = g_p.to(gx.dtype) * power
            g_gx = (gp * my)[:, None] if g_gx is None else g_gx + (gp * my)[:, None]
            g_gy = (gp * mx)[:, None] if g_gy is None else g_gy + (gp * mx)[:, None]

        def centre_gradient(g_cells, pdf):
            # d(cell mass)/d(centre) = density at the lower edge - density at the upper edge
            return ((pdf[:, :-1] - pdf[:, 1:]) * g_cells).sum(1).to(ctx.dtype)

        gx_out = centre_gradient(g_gx, px) if ctx.needs_input_grad[0] else None
        gy_out = centre_gradient(g_gy, py) if ctx.needs_input_grad[1] else None
        return gx_out, gy_out, None


def _local(receiver, aim: torch.Tensor):
    xy = receiver.to_local(aim)
    return xy[..., 0], xy[..., 1]


def _world(receiver, x, y):
    return receiver.to_world(torch.stack((x, y), dim=-1))


def _edges(receiver, resolution, like: torch.Tensor):
    rows, cols = (int(r) for r in resolution)
    w, h = float(receiver.width), float(receiver.height)
    return (torch.linspace(-w / 2, w / 2, cols + 1, dtype=like.dtype, device=like.device),
            torch.linspace(-h / 2, h / 2, rows + 1, dtype=like.dtype, device=like.device))


def image_moments(plant: Plant, sun: torch.Tensor, aim: torch.Tensor, resolution, rows: torch.Tensor | None = None,
                  per_direction: int = 4):
    """Centre and spread of every heliostat's image on the receiver map, from the exact model's own footprints.

    Each mirror sample's reflected central ray lands where :func:`~heliotwin.raytrace.field.field_optics` puts
    its footprint, with the footprint covariance ``var J J^T`` (``var`` the sunshape's and slope error's
    second moment [rad^2], ``J`` the hit's Jacobian w.r.t. the ray angle on the receiver's tangent plane, so
    the incidence on a tilted or curved receiver is in it) plus the map's pixel-box smoothing. A heliostat's
    image is the weighted sum of its samples' footprints (weights: mirror area times the cosine, no
    occlusion); its centre and second moments are those of that mixture, the spread of the samples' centres
    (a box) apart from their footprints' mean covariance (a Gaussian).

    Parameters
    ----------
    plant : Plant
        With the ``receiver`` target.
    sun : torch.Tensor, [3]
        Unit vector towards the sun, ENU.
    aim : torch.Tensor, [H, 3]
        Aim points of all heliostats, ENU [m].
    resolution : (int, int)
        Map ``(rows, cols)`` (sets the smoothing, one pixel box).
    rows : torch.Tensor, shape (h,), long, optional
        Only these heliostats (a shard); default all.
    per_direction : int
        Mirror samples per facet and direction.

    Returns
    -------
    offset : torch.Tensor, [h, 2]
        Image centre minus the aim point in map coordinates ``(x, y)`` [m] (arc, height).
    sd : torch.Tensor, [h, 2]
        Image standard deviations along ``x`` and ``y`` [m], float64.
    box : torch.Tensor, [h, 2]
        Half-widths [m] of the uniform boxes with the variance of the samples' centres (the mirror's extent on
        the receiver; :class:`ImageModel`'s ``bx``, ``by``).
    """
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    aim = aim.to(pos)
    sun = torch.as_tensor(sun).to(pos)
    rows = torch.arange(pos.shape[0], device=pos.device) if rows is None else rows
    normal = tracking_normals(pos, aim, sun)[rows]
    with torch.no_grad():
        pw, nw, area = tracked_mirror_samples(plant, normal, int(per_direction), torch.float64, rows)
        h, n = area.shape
        reflected = reflect(-sun.expand_as(nw), nw)
        r_px, c_px = (int(v) for v in resolution)
        extent = target_extent(rec, 1).to(pos)
        mu, jac, ok = _footprints(pw.reshape(1, h * n, 3), reflected.reshape(1, h * n, 3), rec, extent, r_px, c_px)
        mu, jac, ok = mu[0].reshape(h, n, 2), jac[0].reshape(h, n, 2, 2), ok[0].reshape(h, n)
        s = plant.sun
        var = _ss.second_moment(s.sunshape, sigma=float(s.sigma), radius=float(s.radius), csr=float(s.csr),
                                slope_error=float(s.slope_error))
        cov = var * (jac @ jac.transpose(-1, -2))  # [h, n, 2, 2] [px^2]
        e = extent[0]
        px = torch.stack(((e[1] - e[0]) / c_px, (e[3] - e[2]) / r_px))  # [2] [m/px]
        # pixel -> map coordinates [m]: x grows with the column, y with the height (rows run from the top)
        xy = torch.stack((e[0] + (mu[..., 0] + 0.5) * px[0], e[3] - (mu[..., 1] + 0.5) * px[1]), dim=-1)
        var_xy = (torch.diagonal(cov, dim1=-2, dim2=-1) + 1.0 / 12.0) * px ** 2  # [h, n, 2] [m^2]
        local = torch.stack(_local(rec, aim[rows]), dim=-1)  # [h, 2]
        d = xy - local[:, None, :]
        if isinstance(rec, CylinderTarget) and rec.opening_angle >= 2 * math.pi - 1e-9:
            w = float(rec.width)
            d[..., 0] = torch.remainder(d[..., 0] + 0.5 * w, w) - 0.5 * w  # across the seam of a full cylinder
        cos_p = (nw * sun).sum(-1).clamp_min(0.0)
        wt = torch.where(ok, area * cos_p, torch.zeros_like(area))
        wsum = wt.sum(1, keepdim=True).clamp_min(1e-30)
        d = torch.where(ok[..., None], d, torch.zeros_like(d))
        var_xy = torch.where(ok[..., None], var_xy, torch.zeros_like(var_xy))
        offset = (wt[..., None] * d).sum(1) / wsum
        centres = (wt[..., None] * (d - offset[:, None, :]) ** 2).sum(1) / wsum  # the mirror's own extent
        spread = (wt[..., None] * var_xy).sum(1) / wsum + centres
        # a heliostat none of whose rays reach the receiver's surface: a wide image (its power is ~0 anyway)
        hit = wt.sum(1, keepdim=True) > 0
        spread = torch.where(hit, spread, torch.full_like(spread, float(rec.height) ** 2))
        box = torch.where(hit, (3.0 * centres).sqrt(), torch.zeros_like(centres))
    return offset, spread.clamp_min(1e-8).sqrt(), box


@reuse_mirror_samples()  # the rounds' exact checks move the heliostats, never their surfaces
def calibrate_images(plant: Plant, sun, atmosphere, resolution, *, group=None, equator=None):
    """Image model of the field at this sun from the exact model at equator aiming (one evaluation).

    The power per heliostat is the exact model's power before spillage (``power_w / intercept``), the image
    spreads are the moments of the exact model's own footprints at the equator aim points
    (:func:`image_moments`: sunshape, slope error, mirror size and focus, the incidence on the receiver's
    surface whatever its tilt or curvature).

    Returns
    -------
    model : ImageModel
        For this rank's heliostats.
    equator_result : FieldResult
        The exact model at equator aiming (all heliostats).
    """
    grp = _Group(group)
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    h = pos.shape[0]
    rows = grp.rows(h, pos.device)
    eq_aim = equator_aim_points(rec, pos)
    ex = equator if equator is not None else grp.field(plant, sun, atmosphere, eq_aim, check_settings(resolution))
    return _image_model_at(plant, sun, eq_aim, ex, resolution, rows), ex


def _image_model_at(plant: Plant, sun, aim: torch.Tensor, exact, resolution, rows) -> ImageModel:
    """Image model of heliostats ``rows`` [h] from the exact model's result ``exact`` at the aim points ``aim``
    [H, 3] ENU [m]: power before spillage per heliostat [W], spreads from :func:`image_moments` there."""
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    _, sd, box = image_moments(plant, sun, aim, resolution, rows)
    power = (exact.power_w.to(pos) / exact.intercept.to(pos).clamp_min(1e-6))
    xe, ye = _edges(rec, resolution, pos)
    return ImageModel(power[rows], sd[:, 0], sd[:, 1], xe, ye, _period(rec), box[:, 0], box[:, 1])


def _period(receiver) -> float:
    """The unrolled map's circumference [m] for a full cylinder, else 0 (see :class:`ImageModel`)."""
    full = isinstance(receiver, CylinderTarget) and receiver.opening_angle >= 2 * math.pi - 1e-9
    return float(receiver.width) if full else 0.0


# ------------------------------------------------------------------------------------------ targets
def uniform_target(equator_flux: torch.Tensor) -> torch.Tensor:
    """Target shape [rows, cols]: flat over the receiver height, laterally the equator map's column profile
    (an external receiver is lit only on the side facing the field), normalised to unit sum [1].

    ``equator_flux`` is the map with every heliostat aimed at the equator, shape (rows, cols) [W/m^2]; the
    result has the same shape, float64.
    """
    col = equator_flux.to(torch.float64).sum(0, keepdim=True).clamp_min(0.0)
    t = col.expand(equator_flux.shape[0], -1).clone()
    return t / t.sum().clamp_min(1e-30)


def load_target(path, resolution) -> torch.Tensor:
    """A target flux map (or shape) from a ``.npy`` or ``.csv`` file, [rows, cols] as the reporting grid (row
    0 = top), non-negative; returned normalised to unit sum (only the shape counts)."""
    rows, cols = (int(r) for r in resolution)
    text = str(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # numpy's "no data" warning: the shape check says it
            arr = np.load(text) if text.endswith(".npy") else np.loadtxt(text, delimiter=",", comments="#",
                                                                           ndmin=2)
    except (OSError, ValueError) as exc:
        raise HeliotwinError(f"{text}: cannot read the target flux map ({exc})") from None
    arr = np.asarray(arr, dtype=np.float64)
    if arr.shape != (rows, cols):
        raise HeliotwinError(f"{text}: target map has shape {arr.shape[0] if arr.ndim else 0}x"
                             f"{arr.shape[1] if arr.ndim > 1 else 0} (rows x cols), the receiver grid is "
                             f"{rows}x{cols}")
    if not np.isfinite(arr).all() or (arr < 0).any() or not (arr > 0).any():
        raise HeliotwinError(f"{text}: target map must be finite, non-negative and not all zero")
    t = torch.as_tensor(arr / arr.max())  # scaled first: a sum of values near 1e308 would overflow
    return t / t.sum()


def target_mismatch(flux: torch.Tensor, target: torch.Tensor) -> float:
    """Relative L2 mismatch ``|F / sum F - T| / |T|`` of a map to a unit-sum target shape.

    ``flux`` is a map, shape (rows, cols) [W/m^2] (only its shape counts); ``target`` the unit-sum target of
    the same shape [1]. Returns a float scalar [1].
    """
    f = flux.to(torch.float64)
    t = target.to(f)
    return float(torch.linalg.vector_norm(f / f.sum().clamp_min(1e-30) - t) / torch.linalg.vector_norm(t))


# ------------------------------------------------------------------------------------------ optimiser
#: Precision of the image profiles (erf, exp) in the augmented-Lagrangian steps: float32 is ~2.5x faster on a
#: CPU. Only these element-wise, per-heliostat terms: every sum over heliostats (the map, the power, their
#: all-reduce when sharded) stays in the aim points' float64, so a sharded run takes one process's steps.
ALM_PROFILE_DTYPE = torch.float32
#: The augmented-Lagrangian steps end once the model's limit holds and its objective (relative power, or the
#: target mismatch) moved by less than this over two multiplier updates [-].
ALM_SETTLE = 1e-5
#: Largest angle [rad] about a cylinder's axis between an aim point and the heliostat's own side of it.
VISIBLE_HALF_ANGLE = math.radians(70.0)


def _visible_arc(receiver, position: torch.Tensor):
    """Lateral bounds ``(lo, hi)`` [h] [m] of each heliostat's aim points on a cylinder: within
    :data:`VISIBLE_HALF_ANGLE` of the generator line facing it (an aim point on the far side is hidden behind
    the near side, where the exact model puts the light); None for a plane (any lateral aim point is seen)."""
    if not isinstance(receiver, CylinderTarget):
        return None
    d = position - receiver.axis_point.to(position)
    face = float(receiver.radius) * torch.atan2(d @ receiver.right.to(position), d @ receiver.normal.to(position))
    room = float(receiver.radius) * VISIBLE_HALF_ANGLE
    return face - room, face + room


def _field_power_gradient(plant, sun, atmosphere, rec, x_all, y_all, rows, grp, resolution, softness,
                          dtype=torch.float32):
    """d(receiver power)/d(x, y) [h], [h] of this rank's heliostats through the smooth field model (shading,
    blocking, cosine, attenuation and intercept all move with the aim points) [W/m]."""
    xa, ya = x_all.clone().requires_grad_(), y_all.clone().requires_grad_()
    settings = FieldSettings(resolution=tuple(int(r) for r in resolution), softness=float(softness), flux_samples=4,
                             flux_mode="window", dtype=dtype)
    r = field_optics(plant, sun, atmosphere=atmosphere, aim=_world(rec, xa, ya), settings=settings,
                     heliostats=None if grp.group is None else rows)
    gx, gy = torch.autograd.grad(r.power_w.sum(), (xa, ya))  # a shard's power also moves with its occluders
    return grp.sum(gx.detach())[rows], grp.sum(gy.detach())[rows]


@contextlib.contextmanager
def _intra_op_threads(n: int):
    """Run the block with ``n`` intra-op threads (restored after): the image model's steps are hundreds of
    small element-wise ops, for which a second thread only adds synchronisation, and on a loaded machine
    (more runnable processes than cores) its spin-waits multiplied the steps' CPU time 30-fold (measured:
    whole command 10 s with one thread against 251 s with two, 2 cores, load ~5)."""
    before = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(before)


class _Adam:
    """Adam (Kingma & Ba 2015; ``torch.optim.Adam``'s defaults and update, bias-corrected) on a few tensors.

    Written out because the first ``torch.optim`` optimiser of a process imports ``torch._dynamo`` (~1 s on a
    CPU, a fifth of a 2,000-heliostat ``aimpoints`` command) for two parameter tensors that need none of it.
    """

    def __init__(self, params, lr: float, betas=(0.9, 0.999), eps: float = 1e-8):
        self.params, self.lr, self.betas, self.eps, self.t = tuple(params), float(lr), betas, float(eps), 0
        self.m = [torch.zeros_like(p) for p in self.params]
        self.v = [torch.zeros_like(p) for p in self.params]

    def step(self, grads, scale: float = 1.0) -> None:
        """One update in place (call under ``torch.no_grad``) with ``grads`` (one per parameter, same shapes)
        and the step size ``scale * lr``."""
        self.t += 1
        b1, b2 = self.betas
        c1, c2 = 1.0 - b1 ** self.t, 1.0 - b2 ** self.t
        for p, g, m, v in zip(self.params, grads, self.m, self.v):
            m.mul_(b1).add_(g, alpha=1.0 - b1)
            v.mul_(b2).addcmul_(g, g, value=1.0 - b2)
            p.addcdiv_(m, (v.sqrt() / math.sqrt(c2)).add_(self.eps), value=-scale * self.lr / c1)


@_intra_op_threads(1)
def _alm(model: ImageModel, x, y, defect, power_defect, limit_int, lam, *, grp, steps, lr, rho, inner,
         half_height, p0, weight, target, linear=None, x_bounds=None, settle=ALM_SETTLE, restore=0):
    """Augmented-Lagrangian Adam steps on the corrected image model (``lam`` updated in place).

    ``linear = (cx, cy)``: a first-order power correction ``sum cx (x - x_k) + cy (y - y_k)`` [W] about the start.
    ``x_bounds = (lo, hi)``, [h] each [m]: the lateral range each aim point stays in. The image profiles are
    evaluated in :data:`ALM_PROFILE_DTYPE`. The steps end early once the model's limit holds (every cell
    within 0.1 % of ``limit_int``) and the objective moved by less than ``settle`` over the last two
    multiplier updates (an optimum of the model: more steps only shuffle aim points it cannot tell apart).
    Then at most ``restore`` steps on the excess over ``limit_int`` alone (:attr:`AimSettings.restore_steps`).

    Returns
    -------
    x, y : torch.Tensor, [h] each
        The new aim points' map coordinates [m].
    predicted : float
        The corrected model's objective key at them: ``P / p0`` (maximising power) or ``-mismatch`` (with a
        target), as :func:`optimise_aimpoints` keys the exact checks [-].
    done : int
        Steps taken.
    """
    model = dataclasses.replace(model, profile_dtype=ALM_PROFILE_DTYPE)
    x0, y0 = x.clone(), y.clone()
    x = x.clone().requires_grad_()
    y = y.clone().requires_grad_()
    adam = _Adam((x, y), lr)
    t = None if target is None else target / target.sum()

    def corrected(x, y):
        f_loc, p_loc = model.flux(x, y)
        f = grp.sum(f_loc) + defect
        p_loc = p_loc.sum()
        if linear is not None:
            p_loc = p_loc + (linear[0] * (x - x0) + linear[1] * (y - y0)).sum()
        p = grp.sum(p_loc) + power_defect
        mismatch = None if t is None else ((f / f.sum() - t) ** 2).sum() / (t ** 2).sum()
        return f, p, mismatch

    def step(opt: _Adam, gx, gy, scale: float) -> None:
        # one Adam step, then back onto the receiver's height and each heliostat's visible arc (under no_grad)
        opt.step((gx, gy), scale)
        y.clamp_(-half_height, half_height)
        if x_bounds is not None:
            x.copy_(torch.minimum(torch.maximum(x, x_bounds[0]), x_bounds[1]))

    check = 2 * int(inner)
    last, done = None, 0
    for it in range(int(steps)):
        f, p, mismatch = corrected(x, y)
        obj = -p / p0 if t is None else mismatch - 0.1 * p / p0
        g = f / limit_int - 1.0
        penalty = (torch.clamp(lam + rho * g, min=0.0) ** 2 - lam ** 2).sum() / (2 * rho)
        loss = weight * obj + penalty
        gx, gy = torch.autograd.grad(loss, (x, y))
        done = it + 1
        with torch.no_grad():
            step(adam, gx, gy, 1.0 - 0.9 * it / max(1, steps))
            if (it + 1) % int(inner) == 0:
                lam.copy_(torch.clamp(lam + rho * g.detach(), min=0.0))
            if (it + 1) % check == 0:
                now = float(obj)
                if last is not None and abs(now - last) < settle and float(g.max()) <= 1e-3:
                    break
                last = now
    # restoration: the multipliers lag where the limit binds hard, and the model's peak still stood 2-4 % over the
    # internal limit after the steps (2,000 heliostats on Jülich's tilted receiver): the exact checks then failed
    # and the margin grew a round at a time. Steps on the excess alone, at a tenth of the step size, with moments
    # of their own (the objective's moments point along its gradient, not the excess's)
    restoring = _Adam((x, y), lr) if restore else None
    for _ in range(int(restore)):
        f, _, _ = corrected(x, y)
        excess = f / limit_int - 1.0
        if float(excess.detach().max()) <= 0.0:
            break
        gx, gy = torch.autograd.grad((torch.clamp(excess, min=0.0) ** 2).sum(), (x, y))
        done += 1
        with torch.no_grad():
            step(restoring, gx, gy, 0.1)
    with torch.no_grad():
        _, p, mismatch = corrected(x, y)
    predicted = float(p) / p0 if t is None else -math.sqrt(float(mismatch))
    return x.detach(), y.detach(), predicted, done


@dataclass(frozen=True)
class AimSettings:
    """The aim-point optimiser's knobs (:func:`optimise_aimpoints`; the ``aimpoints`` command's defaults).

    Attributes
    ----------
    resolution : (int, int)
        Reporting map (rows, cols) on which the limit is enforced and checked.
    iterations : int
        Adam steps on the image model per round.
    rounds : int
        Exact checks (one per round) at most.
    inner : int
        Multiplier update every ``inner`` steps.
    lr : float
        Adam step size [m] (decays to a tenth within each round).
    rho : float
        Augmented-Lagrangian weight on the relative excess ``F_c / limit - 1`` [-].
    margin : float
        Starting internal margin ``m`` [-].
    tolerance : float
        Relative change of the power (or mismatch) below which the rounds stop [-].
    slack : float
        Maximising power, the rounds also stop at a feasible round, the best so far, whose peak is within this
        fraction below the limit (with a warm start, the start's own check too) [-].
    field_gradient : bool
        Make the power model first-order exact at every round's start (see :func:`optimise_aimpoints`).
    softness : float
        Occlusion width [m] of the smooth field model used by ``field_gradient``.
    restore_steps : int
        After each round's Adam steps, at most this many steps on the corrected model's excess over the internal
        limit alone (at a tenth of the step size; they stop once no cell exceeds it): where the limit binds hard
        the multipliers lag and the model's peak still stood 2-4 % over, so the exact checks failed and the margin
        grew a round at a time. Chosen by ``benchmarks/bench_aimpoints.py --testbed --candidates`` (its
        ``choose_candidate`` rule) on the generated plants at 150 and 1,000 heliostats: every limit met
        either way, mean power +0.09 / +0.08 %, exact checks 599 -> 590 and 249 -> 240. They run with Adam
        moments of their own (chosen the same way over reusing the objective's: every limit met, mean power
        -0.05 % on both beds, exact checks 581 -> 571 and 243 -> 221, Adam steps -13 % and -23 %).
    warm_iterations, warm_lr, warm_tolerance : int, float, float
        With a warm start (``start_aim``): Adam steps per round, step size [m] and the predicted relative gain
        [-] below which the rounds stop (the start is near an optimum already: smaller, fewer steps; an exact
        check is worth making only for a gain above ``warm_tolerance``).
    """

    resolution: tuple[int, int] = (20, 48)
    iterations: int = 300
    rounds: int = 8
    inner: int = 10
    lr: float = 0.03
    rho: float = 1.0
    margin: float = 0.005
    tolerance: float = 1e-3
    field_gradient: bool = False
    softness: float = 0.05
    slack: float = 0.01
    warm_iterations: int = 50
    warm_lr: float = 0.01
    warm_tolerance: float = 2e-3
    restore_steps: int = 100


def _predicted_start(plant, sun, start, start_field, resolution, grp: _Group, rows, x, y):
    """Image model at this sun and the predicted exact result at the aim points ``start`` [H, 3] from the exact
    result ``start_field`` of the same aim points at an earlier sun (``start_field.sun``), without evaluating
    the exact model: powers before spillage scaled by each heliostat's cosine ratio, spreads at this sun, and the
    earlier exact map plus the image model's change, ``F_prev + S_now(start) - S_prev(start)`` [rows, cols]."""
    pos = plant.field.kinematics.position.to(torch.float64)
    old_sun = torch.as_tensor(start_field.sun).to(pos)
    cos_old = (tracking_normals(pos, start, old_sun) * old_sun).sum(-1).clamp_min(1e-6)
    cos_new = (tracking_normals(pos, start, sun) * sun).sum(-1).clamp_min(0.0)
    old = _image_model_at(plant, old_sun, start, start_field, resolution, rows)
    now = dataclasses.replace(_image_model_at(plant, sun, start, start_field, resolution, rows),
                              power=old.power * (cos_new / cos_old)[rows])
    with torch.no_grad():
        f_new, p_new = now.flux(x, y)
        f_old, p_old = old.flux(x, y)
        flux = start_field.flux.to(pos) + grp.sum(f_new) - grp.sum(f_old)
        power = float(start_field.power_w.sum()) + float(grp.sum(p_new.sum())) - float(grp.sum(p_old.sum()))
    return now, SimpleNamespace(flux=flux, power_w=torch.tensor([power], dtype=torch.float64), predicted=True)


def _start(plant, sun, atmosphere, resolution, grp: _Group, rows, x0, x_bounds, equator, model, start_aim,
           start_field=None):
    """Where :func:`optimise_aimpoints`' rounds start: ``(x, y, kick, first, model, p_eq, spreads_at_start)``.

    Cold (``start_aim`` None): equator aiming (``x0`` [H] its lateral coordinates [m], heights 0) with a small
    alternating ``kick`` [h] [m] for the first steps; ``first`` the exact equator result (``equator``, or made
    with the image model by :func:`calibrate_images`). Warm: ``start_aim`` [H, 3] ENU [m] projected onto the
    receiver's height and each heliostat's visible arc (``x_bounds``), no kick, ``first`` its exact check;
    without ``model`` the image model is calibrated on that check (``spreads_at_start``). ``p_eq`` is equator
    aiming's power [W]: exact with ``equator``, else the image model's corrected to the start's exact power.
    With ``start_field`` (the start's exact result at an earlier sun) ``first`` is predicted, not evaluated
    (:func:`_predicted_start`; its ``predicted`` is True) and the image model is made at this sun.
    """
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    h, half = pos.shape[0], 0.5 * float(rec.height)
    spreads_at_start = False
    if start_aim is not None:
        start = torch.as_tensor(start_aim).to(pos)
        if start.shape != pos.shape:
            raise HeliotwinError(f"start aim points: expected shape {tuple(pos.shape)}, got {tuple(start.shape)}")
        xs, ys = _local(rec, start)
        x, y = xs[rows].clone(), ys[rows].clamp(-half, half)
        if x_bounds is not None:
            x = torch.minimum(torch.maximum(x, x_bounds[0]), x_bounds[1])
        start = _world(rec, grp.gather(x, h), grp.gather(y, h))
        if start_field is not None:
            model, first = _predicted_start(plant, sun, start, start_field, resolution, grp, rows, x, y)
            spreads_at_start = True
        else:
            first = grp.field(plant, sun, atmosphere, start, check_settings(resolution))  # round 0's exact check
        if model is None:
            model, spreads_at_start = _image_model_at(plant, sun, start, first, resolution, rows), True
        kick = torch.zeros_like(x)  # no symmetric point to leave
    else:
        if model is None or equator is None:
            model, equator = calibrate_images(plant, sun, atmosphere, resolution, group=grp.group, equator=equator)
        first = equator  # round 0 is equator aiming, whose exact check the image model was calibrated on
        x, y = x0[rows].clone(), torch.zeros_like(x0[rows])
        # the first steps start from a small alternating spread: equator aiming is a symmetric point of the problem
        kick = 0.05 * (1 - 2 * (rows % 2)).to(pos)
    model = dataclasses.replace(model)  # its power is refreshed every round: leave the caller's alone
    if equator is not None:
        p_eq = float(equator.power_w.sum())
    else:  # equator aiming's power on the image model corrected to the start's exact power
        with torch.no_grad():
            p_e, p_s = model.flux(x0[rows], torch.zeros_like(x))[1], model.flux(x, y)[1]
            p_eq = float(grp.sum(p_e.sum())) + float(first.power_w.sum()) - float(grp.sum(p_s.sum()))
    return x, y, kick, first, model, p_eq, spreads_at_start


@reuse_mirror_samples()  # the rounds' exact checks move the heliostats, never their surfaces
def optimise_aimpoints(plant: Plant, sun: torch.Tensor, peak_limit: float, settings: AimSettings = AimSettings(), *,
                       atmosphere: Atmosphere | None = None, target: torch.Tensor | None = None, group=None,
                       equator=None, model=None, progress=None, device=None,
                       start_aim: torch.Tensor | None = None, start_multipliers: torch.Tensor | None = None,
                       start_margin: float | None = None, start_field=None) -> AimResult:
    """Aim points that maximise intercepted power (or match ``target``) with every map cell at or below
    ``peak_limit`` [W/m^2] on the exact model.

    The optimiser's knobs (map resolution, Adam steps, rounds, step size, penalty, margin, tolerance, the
    field-gradient correction) are one :class:`AimSettings`.

    Parameters
    ----------
    plant : Plant
        Field and ``receiver`` target (tensors on the device the work runs on).
    sun : torch.Tensor, [3]
        Unit vector towards the sun.
    peak_limit : float
        [W/m^2].
    settings : AimSettings
        The optimiser's knobs (default: the ``aimpoints`` command's). With ``field_gradient`` the power model
        is also made first-order exact at every round's start: the difference between the smooth
        differentiable field model's power gradient (shading, blocking, cosine, attenuation, intercept;
        occlusion width ``softness`` [m]) and the image model's is added (one field-model backward per round).
    atmosphere : Atmosphere, optional
    target : torch.Tensor, [rows, cols], optional
        A target shape (unit sum; :func:`uniform_target`, :func:`load_target`): minimise
        ``|F/sum F - target|^2 / |target|^2 - 0.1 P / P_eq`` instead of maximising power.
    group : ProcessGroup, optional
        Shard the heliostats over this group (every rank calls with the same arguments).
    equator, model : optional
        The exact equator result and a calibrated :class:`ImageModel` (from :func:`calibrate_images`).
    progress : callable, optional
        Called with a one-line string after each round.
    device : str or torch.device, optional
        Run on this device (the plant, sun and target are moved there; ``equator``/``model`` must already be
        there). Default: where the plant's tensors are.
    start_aim : torch.Tensor, [H, 3], optional
        Warm start: the rounds start from these aim points (ENU [m]; e.g. the previous instant's optimised ones,
        projected onto the receiver's height and each heliostat's visible arc) instead of equator aiming. Round 0
        is then the exact check of them at this sun; without ``model`` the image model is calibrated on that
        check (power, spreads at these aim points) and without ``equator`` no equator check is made: the power
        the objective is relative to (:attr:`AimResult.reference_power_w`) is the corrected image model's
        estimate of equator aiming's.
    start_multipliers : torch.Tensor, [rows, cols], optional
        With ``start_aim``: the multipliers to start from (the previous instant's :attr:`AimResult.multipliers`).
    start_margin : float, optional
        With ``start_aim``: the internal margin to start from (the previous instant's final
        :attr:`AimResult.parameter`) [-].
    start_field : FieldResult, optional
        With ``start_aim``: the exact result of those aim points at an earlier sun (the previous instant's
        :attr:`AimResult.exact`): round 0 is then predicted from it (cosine-scaled powers, the earlier map plus
        the image model's change) instead of an exact check, and the first exact check is of the aim points
        optimised on that prediction; a prediction never counts as a result.

    Returns
    -------
    AimResult
        All aim points [H, 3] and the exact check of them; ``history`` has per round the exact peak, power,
        margin and whether the check passed; ``iterations`` the Adam steps done; ``exact_checks`` the exact
        evaluations made (not counting ``equator``); ``multipliers`` and ``parameter`` (the final margin) are
        the next instant's warm start.
    """
    t0 = time.perf_counter()
    resolution, iterations = settings.resolution, settings.iterations
    rounds, inner = settings.rounds, settings.inner
    lr, rho, margin, tolerance = settings.lr, settings.rho, settings.margin, settings.tolerance
    field_gradient, softness = settings.field_gradient, settings.softness
    if device is not None:
        plant, sun = to_device(plant, device), torch.as_tensor(sun).to(device)
    grp = _Group(group)
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    sun = torch.as_tensor(sun).to(pos)
    h = pos.shape[0]
    rows = grp.rows(h, pos.device)
    limit = float(peak_limit)
    eq_aim = equator_aim_points(rec, pos)
    x0, _ = _local(rec, eq_aim)
    x_bounds = _visible_arc(rec, pos[rows])
    half = 0.5 * float(rec.height)
    warm = start_aim is not None
    if warm:
        iterations, lr, tolerance = settings.warm_iterations, settings.warm_lr, settings.warm_tolerance
    x, y, kick, first, model, p_eq, spreads_at_start = _start(plant, sun, atmosphere, resolution, grp, rows, x0,
                                                             x_bounds, equator, model, start_aim, start_field)
    predicted = getattr(first, "predicted", False)  # round 0 a prediction, not an exact check
    checks = int(warm and not predicted)
    lam = torch.zeros(tuple(int(r) for r in resolution), dtype=torch.float64, device=pos.device)
    if warm and start_multipliers is not None:
        lam = start_multipliers.detach().to(lam).clone()
    tgt = None if target is None else target.to(pos)
    m = float(margin) if not warm or start_margin is None else max(float(margin), float(start_margin))
    best, best_key, least, history, steps = None, None, None, [], 0
    previous = None
    for k in range(int(rounds)):
        aim = _world(rec, grp.gather(x, h), grp.gather(y, h))
        if k == 0:
            ex = first  # equator aiming's check (cold) or the start's (warm), made above
        else:
            ex, checks = grp.field(plant, sun, atmosphere, aim, check_settings(resolution)), checks + 1
        peak, power = float(ex.flux.max()), float(ex.power_w.sum())
        guess = predicted and k == 0
        ok = peak <= limit and not guess  # a prediction is never a result
        key = power / p_eq if tgt is None else -target_mismatch(ex.flux, tgt)
        history.append({"round": k, "peak_flux_w_m2": peak, "power_w": power, "margin": m, "feasible": ok,
                        "objective": key})
        if guess:
            history[-1]["predicted"] = True
        if progress is not None:
            progress(f"round {k}: peak {peak / limit:.4f} of the limit, power {power / p_eq:.4f} of equator")
        res = AimResult(aim.detach(), power, peak, ex.flux, exact=None if guess else ex)
        if ok and (best is None or key > best_key):
            best, best_key = res, key
        if not guess and (least is None or peak < least.peak_flux_w_m2):
            least = res
        if ok and previous is not None and abs(key - previous) < tolerance:
            break
        if ok and (k > 0 or warm) and tgt is None and best is res and peak >= (1.0 - float(settings.slack)) * limit:
            break  # the limit binds within the slack at the best power so far: more rounds only trade noise
        previous = key if ok else None
        if not ok and k > 0:
            m += peak / limit - 1.0 + 0.5 * float(margin)
        elif ok and 1.0 - peak / limit > 2.0 * float(margin):
            # slack left on the table: give half of it back (the best feasible result is kept anyway)
            m = max(float(margin), m - 0.5 * (1.0 - peak / limit - float(margin)))
        if k == int(rounds) - 1:
            break
        # refresh the per-heliostat power (shading, blocking and cosine move with the aim points) and the image
        # spreads (the incidence on the receiver moves with them)
        if not guess:
            model.power = (ex.power_w.to(pos) / ex.intercept.to(pos).clamp_min(1e-6))[rows]
        if k > 0 or (warm and not spreads_at_start):  # else the calibration's own spreads at these aim points
            _, sd, box = image_moments(plant, sun, aim, resolution, rows)
            model.sx, model.sy, model.bx, model.by = sd[:, 0], sd[:, 1], box[:, 0], box[:, 1]
        with torch.no_grad():
            f_s, p_s = model.flux(x, y)
            f_s, p_s = grp.sum(f_s), grp.sum(p_s.sum())
        defect = ex.flux.to(pos) - f_s
        linear = None
        if field_gradient:
            # first-order model management: the corrected model's power gradient at a_k becomes the field model's
            xs, ys = x.clone().requires_grad_(), y.clone().requires_grad_()
            gsx, gsy = torch.autograd.grad(model.flux(xs, ys)[1].sum(), (xs, ys))
            gfx, gfy = _field_power_gradient(plant, sun, atmosphere, rec, grp.gather(x, h), grp.gather(y, h), rows,
                                             grp, resolution, softness)
            linear = (gfx - gsx, gfy - gsy)
        x_new, y_new, predicted, done = _alm(model, x, y + kick if k == 0 else y, defect, power - float(p_s),
                                             limit * (1.0 - m), lam, grp=grp, steps=iterations, lr=lr, rho=rho,
                                             inner=inner, half_height=half, p0=p_eq, weight=float(h), target=tgt,
                                             linear=linear, x_bounds=x_bounds, restore=settings.restore_steps)
        steps += done
        if ok and best is res and predicted - key < tolerance:
            # the corrected model equals the exact one here and sees no gain worth an exact check from here: the
            # next check would only confirm this result (or lose to it)
            history[-1]["stopped"] = "no predicted gain"
            break
        x, y = x_new, y_new
    out = best if best is not None else least
    if best is None:  # no aim point on the receiver held the limit: take the fewest heliostats off it that do
        out = _standby(plant, sun, atmosphere, rec, model, least, limit, grp, rows, resolution)
        checks += out.exact_checks
    out.seconds, out.iterations, out.history, out.parameter = time.perf_counter() - t0, steps, history, m
    out.multipliers, out.reference_power_w, out.exact_checks = lam.detach().clone(), p_eq, checks
    return out


def _standby(plant, sun, atmosphere, rec, model: ImageModel, least: AimResult, limit: float, grp: _Group, rows,
             resolution, bisections: int = 6) -> AimResult:
    """The least-violating aim points with the fewest heliostats sent to standby that hold the limit exactly.

    A heliostat on standby aims ``5 sy`` above the receiver's top edge, on the side facing it (its image
    passes above the receiver; it still shades and blocks as it tracks). The heliostats are ranked by their
    image-model flux in the cells over the limit (most first); the count is first predicted on the image
    model corrected to the exact map, grown by half until the exact check passes (all of them at most), then
    bisected down (``bisections`` exact checks at most, to half a per cent of the field) to keep as many on
    the receiver as hold it. Returns ``least`` unchanged (limit still violated) when even every heliostat on
    standby does not hold it; else the result with ``standby`` set.
    """
    h = least.aim.shape[0]
    aim = least.aim.to(torch.float64)
    x_all, y_all = _local(rec, aim)
    x, y = x_all[rows], y_all[rows]
    with torch.no_grad():
        gx, gy = model.marginals(x, y)
        over = (least.flux.to(x) > limit).flip(0).to(x)  # [rows, cols], ascending y like the marginals
        own = model.power * torch.einsum("hr,rc,hc->h", gy, over, gx) / model.cell_area  # [h] [W/m^2 x cells]
        mass = grp.gather(own, h)
        order = torch.argsort(mass, descending=True, stable=True)
        # the image model's prediction of how many must go: cumulative removal from the exact map
        img = (model.power[:, None, None] * gy[:, :, None] * gx[:, None, :]) / model.cell_area  # [h, rows, cols]
        local_rank = torch.empty_like(order)
        local_rank[order] = torch.arange(h, device=order.device)
        ranked = torch.zeros((h,) + tuple(img.shape[1:]), dtype=img.dtype, device=img.device)
        ranked[local_rank[rows]] = img
        ranked = grp.sum(ranked)
        remaining = least.flux.to(x).flip(0)[None] - torch.cumsum(ranked, 0)
        fits = (remaining.amax(dim=(-2, -1)) <= limit).nonzero()
        k = int(fits[0]) + 1 if fits.numel() else h
    sy_all = grp.gather(model.sy, h)
    x_eq, _ = _local(rec, equator_aim_points(rec, plant.field.kinematics.position.to(aim)))
    half = 0.5 * float(rec.height)

    def check(count):
        off = torch.zeros(h, dtype=torch.bool, device=aim.device)
        off[order[:count]] = True
        x_new = torch.where(off, x_eq, x_all)  # facing the heliostat: its beam passes above the receiver
        y_new = torch.where(off, half + 5.0 * sy_all.to(y_all), y_all)
        trial = _world(rec, x_new, y_new)
        ex = grp.field(plant, sun, atmosphere, trial, check_settings(resolution))
        out = AimResult(trial.detach(), float(ex.power_w.sum()), float(ex.flux.max()), ex.flux)
        out.standby = count
        return out

    fail, ok, calls = 0, None, 0
    while ok is None:  # grow from the prediction until the exact check passes
        r, calls = check(k), calls + 1
        if r.peak_flux_w_m2 <= limit:
            ok = r
        elif k >= h:
            least.exact_checks = calls
            return least
        else:
            fail, k = k, min(h, k + max(1, k // 2))
    for _ in range(int(bisections)):  # then fewer on standby while it still passes
        if ok.standby - fail <= max(1, h // 200):
            break
        r, calls = check((fail + ok.standby) // 2), calls + 1
        if r.peak_flux_w_m2 <= limit:
            ok = r
        else:
            fail = r.standby
    ok.exact_checks = calls
    return ok


# ------------------------------------------------------------------------------------------ baselines
def _optimise_shard(job: dict, group) -> AimResult:
    """One rank of :func:`run_aimpoints_sharded`: this rank's image model (unless a warm start makes its own) and
    aim points of this rank's shard."""
    kw, settings = dict(job["kwargs"]), job["settings"]
    model, equator = None, job["equator"]
    if equator is not None or kw.get("start_aim") is None:
        model, equator = calibrate_images(job["plant"], job["sun"], kw.get("atmosphere"), settings.resolution,
                                          group=group, equator=equator)
    return optimise_aimpoints(job["plant"], job["sun"], job["limit"], settings, group=group, equator=equator,
                              model=model, **kw)


def run_aimpoints_sharded(plant, sun_direction, peak_limit: float, nproc: int, settings: AimSettings = AimSettings(),
                          *, equator=None, **kwargs) -> AimResult:
    """:func:`optimise_aimpoints` sharded over ``nproc`` spawned local gloo processes (CPU); rank 0's result
    (every rank holds the same aim points). ``settings`` and ``kwargs`` as for it (a warm start's ``start_aim``
    ... included), without ``group``, ``model`` and ``progress``. ``equator``: the exact equator result (a
    :class:`~heliotwin.raytrace.field.FieldResult` of :func:`calibrate_images`) the ranks calibrate their image
    models on instead of making the check again; without it the ranks make it, unless a warm start's own check
    serves (as in one process)."""
    job = {"plant": plant, "sun": sun_direction, "limit": float(peak_limit), "settings": settings, "kwargs": kwargs,
           "equator": equator}
    return run_spawned(_optimise_shard, job, nproc)


def _bisect(evaluate_at, limit, lo, hi, steps, increasing):
    """Bisection for the parameter nearest the spill-free end that meets the limit on the exact check.

    ``increasing``: the peak grows with the parameter (search the largest feasible one); else it falls
    (search the smallest). Returns the best feasible result, or the least violating end.
    """
    safe = lo if increasing else hi
    r = evaluate_at(safe)
    r.parameter = safe
    if r.peak_flux_w_m2 > limit:
        return r
    best = r
    a, b = lo, hi
    for _ in range(int(steps)):
        mid = 0.5 * (a + b)
        r = evaluate_at(mid)
        r.parameter = mid
        if r.peak_flux_w_m2 <= limit:
            best = r
            a, b = (mid, b) if increasing else (a, mid)
        else:
            a, b = (a, mid) if increasing else (mid, b)
    return best


@reuse_mirror_samples()  # the rounds' exact checks move the heliostats, never their surfaces
def aiming_factor(plant: Plant, sun: torch.Tensor, peak_limit: float, *, atmosphere: Atmosphere | None = None,
                  resolution=(20, 48), steps: int = 8, model: ImageModel | None = None) -> AimResult:
    """Sánchez-González et al. (2017) aiming factor ``k``: alternate up/down displacement ``k (h/2 - r_img)``.

    The image half-height ``r_img`` is ``2.5`` vertical image standard deviations (the calibrated
    :class:`ImageModel` when given; else the Gaussian beam spread times the slant range plus a quarter of
    the mirror height). ``k`` is the smallest value in [0, 1] that meets the limit (bisection), or 1.
    """
    t0 = time.perf_counter()
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    equator = equator_aim_points(rec, pos)
    if model is not None and model.sy.shape[0] == pos.shape[0]:
        r_img = 2.5 * model.sy.to(pos)
    else:
        s = plant.sun
        spread = math.sqrt(_ss.second_moment(s.sunshape, sigma=s.sigma, radius=s.radius, csr=s.csr,
                                             slope_error=s.slope_error))
        slant = torch.linalg.vector_norm(equator - pos, dim=-1)
        r_img = 2.5 * spread * slant + 0.25 * plant.field.height.to(pos)
    room = (0.5 * float(rec.height) - r_img).clamp_min(0.0)
    sign = (1 - 2 * (torch.arange(pos.shape[0], device=pos.device) % 2)).to(pos)
    x0, _ = _local(rec, equator)

    def at(k):
        return evaluate(plant, sun, _world(rec, x0, k * sign * room), atmosphere, resolution)

    best = _bisect(at, float(peak_limit), 0.0, 1.0, steps, increasing=False)
    best.seconds = time.perf_counter() - t0
    return best


def _greedy_heights(model: ImageModel, x, room, order, groups: int, candidates: int):
    """Image-size priority on the image model: heights [H] placing groups of heliostats (in ``order``) one
    group at a time, each heliostat at the candidate height within ``+/- room`` [m] where the peak of the
    map so far plus its own image is lowest (ties: nearest the equator)."""
    h = x.shape[0]
    u = torch.linspace(-1.0, 1.0, int(candidates), dtype=x.dtype, device=x.device)
    y = torch.zeros_like(x)
    gx, _ = model.marginals(x, y)
    canvas = torch.zeros(model.y_edges.shape[0] - 1, model.x_edges.shape[0] - 1, dtype=x.dtype, device=x.device)
    for part in torch.tensor_split(order, max(1, min(int(groups), h))):
        if part.numel() == 0:
            continue
        cand = u[None, :] * room[part, None]  # [g, C]
        n = part.numel()
        cy = 0.5 * (1.0 + torch.erf((model.y_edges[None, None, :] - cand[..., None])
                                    / (_SQ2 * model.sy[part, None, None])))
        gy = cy[..., 1:] - cy[..., :-1]  # [g, C, rows]
        img = (model.power[part, None, None, None] * gy[..., :, None] * gx[part, None, None, :]) / model.cell_area
        peak = (canvas[None, None] + img).amax(dim=(-2, -1))  # [g, C]
        pick = torch.argmin(peak * (1.0 + 1e-9 * u.abs()[None, :]), dim=1)
        y[part] = cand[torch.arange(n, device=x.device), pick]
        canvas = canvas + img[torch.arange(n, device=x.device), pick].sum(0)
    return y


@reuse_mirror_samples()  # the rounds' exact checks move the heliostats, never their surfaces
def image_size_priority(plant: Plant, sun: torch.Tensor, peak_limit: float, *, atmosphere: Atmosphere | None = None,
                        resolution=(20, 48), model: ImageModel | None = None, steps: int = 8, groups: int = 40,
                        candidates: int = 11, k_max: float = 3.0) -> AimResult:
    """SolarPILOT-style image-size-priority aiming (see the module docstring).

    Heliostats sorted by vertical image size (largest first) are placed in ``groups`` batches on the
    calibrated :class:`ImageModel`, each at the candidate height (``candidates`` across ``|y| <= h/2 - k
    sigma_y``, at its equator column) where the flux so far plus its own image peaks lowest. ``k`` in
    ``[0, k_max]`` is the largest (least spillage) whose aim points meet the limit on the exact check.
    """
    t0 = time.perf_counter()
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    if model is None:
        model, _ = calibrate_images(plant, sun, atmosphere, resolution)
    x0, _ = _local(rec, equator_aim_points(rec, pos))
    order = torch.argsort(model.sy, descending=True, stable=True)
    half = 0.5 * float(rec.height)

    def at(k):
        room = (half - k * model.sy).clamp_min(0.0)
        with torch.no_grad():
            y = _greedy_heights(model, x0, room, order, groups, candidates)
        return evaluate(plant, sun, _world(rec, x0, y), atmosphere, resolution)

    best = _bisect(at, float(peak_limit), 0.0, float(k_max), steps, increasing=True)
    best.seconds = time.perf_counter() - t0
    return best


def is_cylinder(receiver) -> bool:
    """Whether the receiver is an (unrolled) cylinder."""
    return isinstance(receiver, CylinderTarget)
