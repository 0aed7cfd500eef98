"""The image model of the aim-point optimiser: one cell-integrated image per heliostat on the unrolled receiver map.

Per heliostat one image centred on its aim point, power = the exact model's power before spillage, spreads = the
second moments of the exact model's own footprints at the current aim points (:func:`image_moments`: sunshape,
slope error, mirror size and focus, and the incidence on the receiver's surface, so a tilted or curved receiver
and a partial cylinder's edges are the exact model's); per axis a uniform box convolved with a Gaussian,
cell-integrated (erf differences), so the map is a ``[rows, H] x [H, cols]`` product (closed around a full
cylinder). The solver (:mod:`heliotwin.optimise.solver`) corrects it to the exact model every round.

Shapes: H heliostats (h of them on this rank); aim points [H, 3] ENU [m]; maps [rows, cols] [W/m^2] (row 0 = top).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .. import sunshape as _ss
from ..field.plant import Plant
from ..field.targets import CylinderTarget
from ..geometry import reflect
from ..raytrace.field import (
    _footprints,
    equator_aim_points,
    reuse_mirror_samples,
    tracked_mirror_samples,
    tracking_normals,
)
from ..raytrace.flux import target_extent
from .problem import _Group, check_settings

__all__ = ["ImageModel", "image_moments", "calibrate_images"]

_SQ2 = math.sqrt(2.0)
_LN_SQRT_PI = 0.5 * math.log(math.pi)  # exp(-v^2) / sqrt(pi) = exp(-v^2 - ln sqrt(pi))


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
