"""Shading and blocking between heliostats: rays from mirror points against neighbouring mirror rectangles.

A point of a mirror is *shaded* when the ray from it towards the sun meets another heliostat, and its
reflected light is *blocked* when the reflected ray meets another heliostat on its way to the receiver.
Every heliostat is an occluder rectangle (its overall ``width`` x ``height``, centred at its pivot, in its
mirror plane); a ray ``o + t d`` is stopped by rectangle ``k`` when ``t > 0`` and its crossing of the plane
lies inside the rectangle.

Occluder candidates come from a uniform 2-D grid over east/north (:func:`occluder_candidates`): a heliostat
can only be stopped by heliostats inside the corridor its rays sweep before they rise above the tallest
mirror, so each heliostat looks up the grid cells along that corridor (a fixed number of cells per
heliostat), keeps the candidates whose bounding spheres reach its rays, and only those are ray-tested.
The hard test first drops, per heliostat and candidate, the pairs that no ray can join: every test quantity
is affine in the ray origin, so its range over the box holding the mirror's points (widened by the spread
of the rays' directions) bounds it; most candidates go, and the rest are tested ray by ray as before.
The cost is about linear in the number of heliostats; there is no all-pairs test.

Two tests share the geometry:

* hard (:func:`unoccluded`, ``softness=None``): the exact indicator, for reporting;
* smooth (``softness=tau`` [m]): the indicator's three conditions become logistic steps of width ``tau``
  (``sigmoid((w/2 - |u|) / tau) sigmoid((h/2 - |v|) / tau) sigmoid(t / tau)``) and the union over
  occluders is ``1 - prod_k (1 - stop_k)``; differentiable in every position, normal and direction, and
  equal to the hard test as ``tau -> 0``.

A third, :func:`solarpilot_interference`, restates SolarPILOT's analytic per-pair estimate (two projected
corners, parallel mirrors, summed pair losses; with :func:`solarpilot_neighbours`, its neighbour grid) so
that reports can be compared with SolarPILOT's on equal terms: it reproduces SolarPILOT's per-heliostat
shading and blocking on the shared reference field to the 1e-4 its files are rounded to. It is a modelling
choice, not the physics: docs/physics.md ("Shading and blocking against SolarPILOT") shows where it
departs from the exact test and why.

Shapes: H heliostats, P points per heliostat, K candidates per heliostat. Units: metres.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..geometry import reflect, safe_normalize

__all__ = ["mirror_frame", "occluder_candidates", "unoccluded", "unoccluded_tracked", "mirror_blocks", "MirrorBlocks",
           "OccluderSet",
           "solarpilot_neighbours", "solarpilot_interference"]


def mirror_frame(normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """In-plane axes of azimuth-elevation tracked mirrors: the width edge stays horizontal.

    Parameters
    ----------
    normal : torch.Tensor, [..., 3]
        Unit mirror normals (ENU).

    Returns
    -------
    width_axis, height_axis : torch.Tensor, [..., 3]
        Unit vectors [1], ENU: ``normalize(e_up x normal)`` (east for a mirror facing the zenith or straight south) and
        ``normal x width_axis``. Together with ``normal`` they form ``R_world_heliostat``'s columns.
    """
    up = torch.zeros_like(normal)
    up[..., 2] = 1.0
    w = torch.linalg.cross(up, normal, dim=-1)
    flat = (w * w).sum(-1, keepdim=True) < 1e-18
    east = torch.zeros_like(normal)
    east[..., 0] = 1.0
    w = torch.where(flat, east, safe_normalize(w))
    return w, torch.linalg.cross(normal, w, dim=-1)


class OccluderSet:
    """The field's heliostats as occluder rectangles.

    Parameters
    ----------
    center : torch.Tensor, [H, 3]
        Rectangle centres (pivots), ENU [m].
    normal : torch.Tensor, [H, 3]
        Unit mirror normals.
    width, height : torch.Tensor, [H]
        Full rectangle sizes [m] (along :func:`mirror_frame`'s width / height axes).
    """

    def __init__(self, center, normal, width, height):
        self.center, self.normal = center, normal
        self.width_axis, self.height_axis = mirror_frame(normal)
        self.half_width, self.half_height = 0.5 * width, 0.5 * height

    @property
    def radius(self) -> torch.Tensor:
        """Bounding-sphere radius [H] [m] (half diagonal)."""
        return torch.sqrt(self.half_width ** 2 + self.half_height ** 2)


def _grid_table(xy: torch.Tensor, cell: float):
    """Heliostats binned in square cells: (origin, shape (nx, ny), table [nx*ny, M] of indices or -1)."""
    lo = xy.min(0).values - cell
    ij = torch.floor((xy - lo) / cell).long()
    nx, ny = int(ij[:, 0].max()) + 2, int(ij[:, 1].max()) + 2
    cid = ij[:, 0] * ny + ij[:, 1]
    order = torch.argsort(cid, stable=True)
    sorted_cid = cid[order]
    counts = torch.bincount(sorted_cid, minlength=nx * ny)
    start = torch.cumsum(counts, 0) - counts
    rank = torch.arange(len(order), device=xy.device) - start[sorted_cid]
    m = int(counts.max())
    table = torch.full((nx * ny, m), -1, dtype=torch.long, device=xy.device)
    table[sorted_cid, rank] = order
    return lo, (nx, ny), table


def occluder_candidates(occluders: OccluderSet, direction: torch.Tensor, *, max_rise: float | None = None,
                        angular_margin: float = 0.02, queries: torch.Tensor | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """Heliostats that may stop rays leaving each heliostat along (about) ``direction``; spatial-grid lookup.

    Parameters
    ----------
    occluders : OccluderSet
        H heliostats.
    direction : torch.Tensor, [Q, 3] or [3]
        Representative unit ray direction per querying heliostat (towards the sun; towards the aim point). Rays of
        the heliostat's points may deviate from it by ``angular_margin`` [rad] (canting, slope).
    max_rise : float, optional
        Height [m] the rays must climb above their start before no mirror can stop them; default: the
        field's pivot height range plus two bounding radii.
    angular_margin : float
        [rad], widens the corridor with distance.
    queries : torch.Tensor, [Q], long, optional
        The heliostats whose rays are tested (default all H; a shard of the field in
        :mod:`heliotwin.distributed`); every heliostat of ``occluders`` can stop them.

    Returns
    -------
    index : torch.Tensor, [Q, K], long
        Candidate occluders (K = the largest count over heliostats; padded with 0).
    valid : torch.Tensor, [Q, K], bool
        False for padding. A heliostat is never its own candidate.
    """
    c = occluders.center.detach().to(torch.float64)
    if queries is None:
        queries = torch.arange(c.shape[0], device=c.device)
    own_index = queries.to(c.device)
    h = own_index.shape[0]
    d = safe_normalize(direction.detach().to(torch.float64).expand(h, 3))
    rad_all = occluders.radius.detach().to(torch.float64)
    rad = rad_all[own_index]
    r_max = float(rad_all.max())
    if max_rise is None:
        max_rise = float(c[:, 2].max() - c[:, 2].min()) + 2.0 * r_max
    horiz = torch.linalg.vector_norm(d[:, :2], dim=-1).clamp_min(1e-12)
    tan_el = d[:, 2] / horiz
    # Horizontal distance after which the rays are above every mirror (rays going down: the whole field).
    reach = torch.where(tan_el > 1e-3, max_rise / tan_el.clamp_min(1e-3), torch.full_like(tan_el, 1e4)) + 2 * r_max
    reach = torch.minimum(reach, torch.full_like(reach, 1e4))
    half_corridor = 2.0 * r_max + angular_margin * float(reach.max())
    cell = max(half_corridor / 0.85, 1e-3)  # 3x3 cells around a corridor sample cover the corridor's width
    lo, (nx, ny), table = _grid_table(c[:, :2], cell)
    steps = int(math.ceil(float(reach.max()) / cell)) + 1
    dxy = d[:, :2] / horiz.unsqueeze(-1)
    along = torch.arange(steps, dtype=torch.float64, device=c.device) * cell
    along = torch.minimum(along.unsqueeze(0), reach.unsqueeze(1))  # [H, S]
    q = c[own_index, None, :2] + along.unsqueeze(-1) * dxy.unsqueeze(1)  # corridor samples [Q, S, 2]
    qi = torch.floor((q - lo) / cell).long()
    off = torch.tensor([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)], device=c.device)
    cells = qi.unsqueeze(2) + off  # [H, S, 9, 2]
    inside = (cells[..., 0] >= 0) & (cells[..., 0] < nx) & (cells[..., 1] >= 0) & (cells[..., 1] < ny)
    cid = (cells[..., 0].clamp(0, nx - 1) * ny + cells[..., 1].clamp(0, ny - 1)).reshape(h, -1)
    cand = torch.where(inside.reshape(h, -1).unsqueeze(-1), table[cid], torch.full_like(table[cid], -1))
    cand = cand.reshape(h, -1)
    # Unique per row: sort, drop repeats, drop self and padding.
    cand, _ = torch.sort(cand, dim=1)
    repeat = torch.zeros_like(cand, dtype=torch.bool)
    repeat[:, 1:] = cand[:, 1:] == cand[:, :-1]
    own = cand == own_index.unsqueeze(1)
    keep = (cand >= 0) & ~repeat & ~own
    # Conservative sphere test: the occluder's bounding sphere reaches the ray bundle (a cylinder about the
    # central ray, widened by the angular margin) ahead of the heliostat.
    safe = cand.clamp_min(0)
    rel = c[safe] - c[own_index].unsqueeze(1)  # [Q, C, 3]
    t = (rel * d.unsqueeze(1)).sum(-1)
    perp = torch.linalg.vector_norm(rel - t.unsqueeze(-1) * d.unsqueeze(1), dim=-1)
    reach_r = rad.unsqueeze(1) + rad_all[safe] + angular_margin * t.abs()
    keep = keep & (perp <= reach_r) & (t >= -(rad.unsqueeze(1) + rad_all[safe]))
    k = max(int(keep.sum(1).max()) if h else 0, 1)
    order = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)[:, :k]
    index = torch.gather(cand, 1, order).clamp_min(0)
    valid = torch.gather(keep, 1, order)
    return index, valid


def unoccluded(origins: torch.Tensor, directions: torch.Tensor, occluders: OccluderSet, index: torch.Tensor,
               valid: torch.Tensor, *, softness: float | None = None, eps: float = 1e-6,
               max_tests_per_chunk: int = 2 ** 22, owners: torch.Tensor | None = None) -> torch.Tensor:
    """Fraction of each ray that no candidate occluder stops (1 = free, 0 = stopped).

    Parameters
    ----------
    origins : torch.Tensor, [H, P, 3]
        Ray origins on heliostat h's mirror, ENU [m].
    directions : torch.Tensor, [H, P, 3] or [H, 1, 3]
        Unit ray directions.
    occluders : OccluderSet
        All heliostats (H rectangles).
    index, valid : torch.Tensor, [H, K]
        From :func:`occluder_candidates`.
    softness : float, optional
        None: the exact (hard) test, a 0/1 float. A length [m]: the smooth test (module docstring).
    eps : float
        Minimum ray parameter [m] of a hit (a ray never stops on its own start point).
    max_tests_per_chunk : int
        Memory bound: rays x candidates per chunk of heliostats.
    owners : torch.Tensor, [H_rays], long, optional
        Which heliostat each row of ``origins`` belongs to (default: row i = heliostat i).

    Returns
    -------
    torch.Tensor, [H, P]
        Unoccluded fraction, dtype of ``origins``; differentiable with ``softness``.
    """
    h, p = origins.shape[:2]
    owners = torch.arange(h, device=origins.device) if owners is None else owners
    if softness is None:
        return _unoccluded_hard(origins, directions, occluders, index, valid, owners, eps, max_tests_per_chunk)
    k = index.shape[1]
    step = max(1, int(max_tests_per_chunk) // max(1, p * k))
    out = []
    for s0 in range(0, h, step):
        sl = slice(s0, min(h, s0 + step))
        out.append(_unoccluded_chunk(origins[sl], directions[sl], occluders, index[sl], valid[sl], owners[sl],
                                     softness, eps))
    return torch.cat(out, 0)


def _pairs_that_may_hit(rel, directions, occ: OccluderSet, index, valid, owners) -> torch.Tensor:
    """Conservative pair test [H, K] (bool): False only where no ray of row h can meet candidate k's rectangle.

    ``rel`` [H, P, 3]: the ray origins relative to the own pivot. Every ray-test quantity is affine in the
    origin for a fixed direction, so its range over a mirror's points is bounded by its range over their
    bounding box; the spread of the rows' directions about their mean (``delta``) widens the bounds by
    interval arithmetic. Pairs seen nearly edge-on (their crossing ill-conditioned) are always kept. The
    bounds are padded by far more than the float32 rounding of the per-point test, so culling never changes
    its answer, only what it costs.
    """
    f64 = torch.float64
    # the box of the origins in the own mirror frame (tight for a flat mirror)
    own_axes = torch.stack([t[owners].detach() for t in (occ.width_axis, occ.height_axis, occ.normal)], 1)  # [H, 3, 3]
    local = torch.bmm(rel, own_axes.to(rel.dtype).transpose(1, 2))  # [H, P, 3]
    hi, lo = local.amax(1).to(f64), local.amin(1).to(f64)
    d = directions.detach()
    d0 = safe_normalize(d.mean(1).to(f64))  # [H, 3]
    delta = torch.linalg.vector_norm(d - d0.unsqueeze(1).to(d.dtype), dim=-1).amax(1).to(f64) + 1e-6  # [H]
    return _box_pairs_that_may_hit(0.5 * (hi + lo), 0.5 * (hi - lo), own_axes.to(f64), d0, delta, occ, index,
                                   valid, owners)


def _box_pairs_that_may_hit(mid_local, half, own_axes, d0, delta, occ: OccluderSet, index, valid,
                            owners) -> torch.Tensor:
    """:func:`_pairs_that_may_hit` from the bounds themselves: ray origins in a box (centre ``mid_local``,
    half sizes ``half`` [R, 3] along the own mirror axes ``own_axes`` [R, 3, 3] (rows: width, height,
    normal), relative to the pivot of heliostat ``owners`` [R]) and directions within ``delta`` [R] of the
    unit ``d0`` [R, 3]; ``index``, ``valid`` [R, K]. Returns [R, K] bool."""
    f64 = torch.float64
    base = occ.center[owners].detach().to(f64)  # [R, 3]
    mid = torch.einsum("hi,hij->hj", mid_local, own_axes)  # box centre relative to the pivot, ENU [R, 3]
    half = half + 1e-6  # [R, 3] half sizes along the own axes
    c = occ.center[index].detach().to(f64) - base.unsqueeze(1)  # [R, K, 3]
    n_k, ew_k, eh_k = (t[index].detach().to(f64) for t in (occ.normal, occ.width_axis, occ.height_axis))

    def span(g):
        """Range (lo, hi) [H, K] of (c - o) . g over the box of the own mirror's points, g [H, K, 3]."""
        centre = ((c - mid.unsqueeze(1)) * g).sum(-1)
        radius = (torch.einsum("hkj,hij->hki", g, own_axes).abs() * half.unsqueeze(1)).sum(-1)
        return centre - radius, centre + radius

    dl = delta.unsqueeze(1)
    dn0 = (d0.unsqueeze(1) * n_k).sum(-1)
    edge_on = dn0.abs() <= dl + 0.05
    dn_safe = torch.where(edge_on, torch.ones_like(dn0), dn0)
    wn_lo, wn_hi = span(n_k)
    # t = w_n / d_n > 0 needs w_n of the sign of d_n somewhere
    ahead = torch.where(dn_safe > 0, wn_hi > 0, wn_lo < 0)
    wn_abs = torch.maximum(wn_lo.abs(), wn_hi.abs())
    reach = wn_abs / (dn_safe.abs() - dl).clamp_min(1e-3)  # largest ray parameter of a crossing
    keep = ahead
    for axis, half_size in ((ew_k, occ.half_width[index]), (eh_k, occ.half_height[index])):
        da0 = (d0.unsqueeze(1) * axis).sum(-1)
        ratio0 = da0 / dn_safe
        spread = torch.zeros_like(ratio0)
        for s1 in (-1.0, 1.0):
            for s2 in (-1.0, 1.0):
                spread = torch.maximum(spread, ((da0 + s1 * dl) / (dn_safe + s2 * dl) - ratio0).abs())
        # in-plane coordinate of the crossing: (c - o) . (ratio0 n_k - axis) + w_n (ratio - ratio0)
        lo_a, hi_a = span(ratio0.unsqueeze(-1) * n_k - axis)
        pad = wn_abs * spread + 1e-3 + 1e-4 * reach
        hs = half_size.detach().to(f64)
        keep = keep & (lo_a - pad <= hs) & (hi_a + pad >= -hs)
    return valid & (keep | edge_on)


def _unoccluded_hard(origins, directions, occ: OccluderSet, index, valid, owners, eps, max_tests_per_chunk):
    """The exact test in float32 relative to the own pivot (a 0/1 decision: rays precision), run only on the
    (row, candidate) pairs that :func:`_pairs_that_may_hit` keeps."""
    h, p = origins.shape[:2]
    dt = torch.float32
    rel = (origins - occ.center[owners].unsqueeze(1)).to(dt)  # [H, P, 3]
    pairs = torch.nonzero(_pairs_that_may_hit(rel, directions, occ, index, valid, owners))  # [n, 2]
    hits = torch.zeros(h, p, dtype=dt, device=origins.device)
    step = max(1, int(max_tests_per_chunk) // max(1, p))
    for s0 in range(0, pairs.shape[0], step):
        row, slot = pairs[s0:s0 + step].unbind(1)
        stop = _ray_stops(rel[row], directions[row], occ, owners[row], index[row, slot], eps)
        hits.index_add_(0, row, stop.to(dt))
    return (hits == 0).to(origins.dtype)


def _ray_stops(rel, directions, occ: OccluderSet, owner, k, eps) -> torch.Tensor:
    """[n, P] bool: ray ``rel[i, j] + t directions[i, j]`` (origins relative to heliostat ``owner[i]``'s pivot,
    float32) stops on heliostat ``k[i]``'s rectangle at some ``t > eps``."""
    dt = torch.float32
    c = (occ.center[k] - occ.center[owner]).to(dt)  # [n, 3]
    axes = torch.stack((occ.normal[k], occ.width_axis[k], occ.height_axis[k]), dim=1).to(dt)  # [n, 3, 3]
    c_ax = (axes * c.unsqueeze(1)).sum(-1)  # [n, 3]: c . (n, ew, eh)
    w_ax = c_ax.unsqueeze(1) - torch.bmm(rel, axes.transpose(1, 2))  # (c - o) . axis, [n, P, 3]
    d_ax = torch.bmm(directions.to(dt), axes.transpose(1, 2))  # [n, P or 1, 3]
    denom = d_ax[..., 0]
    ok = denom.abs() > 1e-9
    t = w_ax[..., 0] / torch.where(ok, denom, torch.ones_like(denom))
    u = t * d_ax[..., 1] - w_ax[..., 1]
    v = t * d_ax[..., 2] - w_ax[..., 2]
    return (t > eps) & (u.abs() <= occ.half_width[k].to(dt).unsqueeze(1)) & \
        (v.abs() <= occ.half_height[k].to(dt).unsqueeze(1)) & ok


def _normal_bound(lo, hi):
    """Unit ``n0`` [..., 3] (the normalised centre of the box ``lo``, ``hi`` [..., 3]) and ``e`` [...]: no
    vector in the box is farther than ``e`` from ``n0``."""
    n0 = safe_normalize(0.5 * (lo + hi))
    return n0, torch.linalg.vector_norm(torch.maximum((hi - n0).abs(), (lo - n0).abs()), dim=-1)


def _reflected(n0, e, rot, s):
    """Directions ``d0`` [R, 3] of the sun ``s`` reflected about ``R n0`` (``n0`` [R, 3] heliostat frame, unit;
    ``rot`` [R, 3, 3]) and the bound ``delta`` [R] on any reflected ray's distance from it when the normal is
    within ``e`` [R] of ``n0``: ``2 e + 4 e^2`` (plus a margin)."""
    n0w = torch.einsum("ri,rji->rj", n0, rot)
    return 2.0 * (n0w @ s).unsqueeze(-1) * n0w - s, 2.0 * e + 4.0 * e * e + 1e-6


@dataclass
class MirrorBlocks:
    """Mirror samples of tracked heliostats in their own frame, grouped in square blocks of neighbours, with
    each block's bounds (what :func:`unoccluded_tracked` culls with); from :func:`mirror_blocks`.

    ``points``, ``normals`` [H, N, 3] (heliostat frame); ``index`` [B, b*b] the samples of each block;
    ``lo``, ``hi`` [H', B, 3] the block's box; ``n0`` [H', B, 3] its mean normal (unit) and ``e`` [H', B] the
    largest distance of a normal from it; ``n0_all`` [H', 3], ``e_all`` [H'] the same over the whole mirror.
    ``H' = 1`` when every heliostat has the same samples (an expanded tensor), else H.
    """

    points: torch.Tensor
    normals: torch.Tensor
    index: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    n0: torch.Tensor
    e: torch.Tensor
    n0_all: torch.Tensor
    e_all: torch.Tensor


def mirror_blocks(points: torch.Tensor, normals: torch.Tensor, facets: int, per_direction: int,
                  block: int = 4) -> MirrorBlocks:
    """Group the samples of :func:`heliotwin.field.facets.surface_points` (``facets`` facets, ``per_direction``
    samples per facet and direction, index ``f*S^2 + i*S + j``) in ``b`` x ``b`` blocks, ``b`` the divisor of
    ``per_direction`` nearest ``block``; ``points`` [H, N, 3] [m] and unit ``normals`` [H, N, 3] [1] in the
    heliostat frame."""
    f64 = torch.float64
    h, n = points.shape[:2]
    s = int(per_direction)
    if n != int(facets) * s * s:
        raise ValueError(f"{n} samples per heliostat are not {facets} facets of {s} x {s}")
    b = min((d for d in range(1, s + 1) if s % d == 0), key=lambda d: (abs(d - block), -d))
    q = s // b
    dev = points.device
    i = torch.arange(s, device=dev)
    blk = (i // b).view(-1, 1) * q + (i // b).view(1, -1)  # [S, S]: block of sample (i, j) in its facet
    order = torch.argsort(blk.reshape(-1), stable=True).view(-1, b * b)  # [q^2, b*b], i-major within a block
    index = (torch.arange(int(facets), device=dev).view(-1, 1, 1) * s * s + order).reshape(-1, b * b)
    with torch.no_grad():
        shared = h > 1 and points.stride(0) == 0 and normals.stride(0) == 0
        p, nr = (points[:1], normals[:1]) if shared else (points, normals)
        hp = p.shape[0]
        grid = (hp, int(facets), q, b, q, b, 3)  # blocks as views of the sample grid: no copy
        p, nr = p.detach().to(f64).reshape(grid), nr.detach().to(f64).reshape(grid)
        lo, hi = p.amin(5).amin(3).reshape(hp, -1, 3), p.amax(5).amax(3).reshape(hp, -1, 3)
        # the normals' box per block bounds their distance from its normalised centre
        n_lo, n_hi = nr.amin(5).amin(3).reshape(hp, -1, 3), nr.amax(5).amax(3).reshape(hp, -1, 3)
        n0, e = _normal_bound(n_lo, n_hi)
        n0_all, e_all = _normal_bound(n_lo.amin(1), n_hi.amax(1))
    return MirrorBlocks(points, normals, index, lo, hi, n0, e, n0_all, e_all)


def unoccluded_tracked(blocks: MirrorBlocks, rotation: torch.Tensor, occluders: OccluderSet, index: torch.Tensor,
                       valid: torch.Tensor, sun: torch.Tensor, *, reflected: bool, owners: torch.Tensor | None = None,
                       eps: float = 1e-6, max_tests_per_chunk: int = 2 ** 22) -> torch.Tensor:
    """The hard test of :func:`unoccluded` for tracked mirrors given in their own frame, culled block by block.

    The rays start at ``R points`` (relative to the pivot) and go towards the sun (``reflected=False``:
    shading) or along the sun reflected about ``R normals`` (``reflected=True``: blocking), ``R`` the
    heliostat's rotation. The bounds of :func:`_pairs_that_may_hit` are taken first for the whole mirror
    against each candidate occluder, then for each block of neighbouring samples against the candidates the
    mirror may meet: the box of the block's points in the mirror frame, and the spread of its rays'
    directions bounded from its normals' (a reflected direction turns by at most ``2 e + 4 e^2`` when the
    normal turns by ``e``). Neither the world samples nor the rays of the whole field are formed: only the
    rays of the blocks a candidate may reach, ray-tested exactly as :func:`unoccluded` does.

    Parameters
    ----------
    blocks : MirrorBlocks
        The mirror samples [H, N, 3] (float64) and their blocks, :func:`mirror_blocks`.
    rotation : torch.Tensor, [H, 3, 3]
        ``R_world_heliostat`` (columns: the width axis, height axis and normal of :func:`mirror_frame`).
    occluders : OccluderSet
        All heliostats.
    index, valid : torch.Tensor, [H, K]
        From :func:`occluder_candidates`.
    sun : torch.Tensor, [3]
        Unit vector towards the sun.
    reflected : bool
    owners : torch.Tensor, [H], long, optional
        Which heliostat each row belongs to (default: row i = heliostat i).

    Returns
    -------
    torch.Tensor, [H, N]
        1 where the ray is free, 0 where a candidate stops it; dtype of the points.
    """
    f64 = torch.float64
    points, normals = blocks.points, blocks.normals
    h, n = points.shape[:2]
    nb, pb = blocks.index.shape
    dev = points.device
    owners = torch.arange(h, device=dev) if owners is None else owners
    if h == 0 or index.shape[1] == 0:
        return torch.ones(h, n, dtype=points.dtype, device=dev)
    with torch.no_grad():
        rot = rotation.detach().to(f64)
        s = sun.detach().to(f64).reshape(3)
        shared = blocks.lo.shape[0] == 1 and h > 1
        own_axes = rot.transpose(1, 2)
        # level 1: the whole mirror against each candidate
        box_lo, box_hi = blocks.lo.amin(1).expand(h, 3), blocks.hi.amax(1).expand(h, 3)
        if reflected:
            d0, delta = _reflected(blocks.n0_all.expand(h, 3), blocks.e_all.expand(h), rot, s)
        else:
            d0, delta = s.expand(h, 3), torch.full((h,), 1e-6, dtype=f64, device=dev)
        pair_row, pair_slot = torch.nonzero(_box_pairs_that_may_hit(
            0.5 * (box_hi + box_lo), 0.5 * (box_hi - box_lo), own_axes, d0, delta, occluders, index, valid,
            owners)).unbind(1)
        # level 2: every block of the mirror against each candidate the whole mirror may meet
        pr = pair_row.repeat_interleave(nb)  # [pairs * B]
        blk = torch.arange(nb, device=dev).repeat(pair_row.shape[0])
        src = torch.zeros_like(pr) if shared else pr
        lo, hi = blocks.lo[src, blk], blocks.hi[src, blk]
        if reflected:
            d0, delta = _reflected(blocks.n0[src, blk], blocks.e[src, blk], rot[pr], s)
        else:
            d0, delta = s.expand(pr.shape[0], 3), torch.full(pr.shape, 1e-6, dtype=f64, device=dev)
        kk = index[pair_row, pair_slot].repeat_interleave(nb).unsqueeze(1)
        keep = _box_pairs_that_may_hit(0.5 * (hi + lo), 0.5 * (hi - lo), own_axes[pr], d0, delta, occluders, kk,
                                       torch.ones_like(kk, dtype=torch.bool), owners[pr])[:, 0]
        row, blk, k = pr[keep], blk[keep], kk[keep, 0]
    dt = torch.float32
    hits = torch.zeros(h * n, dtype=dt, device=dev)
    step = max(1, int(max_tests_per_chunk) // max(1, pb))
    s = sun.to(f64).reshape(3)
    for s0 in range(0, row.shape[0], step):
        r, pidx, kk = row[s0:s0 + step], blocks.index[blk[s0:s0 + step]], k[s0:s0 + step]
        rt = rotation[r].to(f64).transpose(1, 2)
        rel = torch.bmm(points[r.unsqueeze(1), pidx].to(f64), rt).to(dt)  # [m, b, 3] world, from the pivot
        if reflected:
            nw = torch.bmm(normals[r.unsqueeze(1), pidx].to(f64), rt)
            dirs = reflect(-s.expand_as(nw), nw)
        else:
            dirs = s.expand(r.shape[0], 1, 3)
        stop = _ray_stops(rel, dirs, occluders, owners[r], kk, eps)
        hits.index_add_(0, (r * n).unsqueeze(1).add(pidx).reshape(-1), stop.reshape(-1).to(dt))
    return (hits.view(h, n) == 0).to(points.dtype)


def _unoccluded_chunk(o, d, occ: OccluderSet, idx, valid, own, softness, eps):
    # Work relative to the own pivot (small numbers in any precision); every dot product with the candidates'
    # three axes (normal, width, height) is one batched matrix product, never a [h, P, K, 3] tensor.
    dt = o.dtype if softness is not None else torch.float32  # the hard test is a 0/1 decision: rays precision
    base = occ.center[own].unsqueeze(1)
    c = (occ.center[idx] - base).to(dt)  # [h, K, 3]
    axes = torch.stack((occ.normal[idx], occ.width_axis[idx], occ.height_axis[idx]), dim=2).to(dt)  # [h, K, 3, 3]
    hk = axes.shape[:2]
    flat = axes.reshape(hk[0], hk[1] * 3, 3)  # [h, 3K, 3]
    c_ax = (axes * c.unsqueeze(2)).sum(-1)  # [h, K, 3]: c . (n, ew, eh)
    o_ax = torch.bmm((o - base).to(dt), flat.transpose(1, 2)).view(o.shape[0], o.shape[1], hk[1], 3)
    d = d.to(dt).expand(o.shape[0], o.shape[1], 3) if d.shape[1] == 1 else d.to(dt)
    d_ax = torch.bmm(d, flat.transpose(1, 2)).view(o.shape[0], o.shape[1], hk[1], 3)
    w_ax = c_ax.unsqueeze(1) - o_ax  # (c - o) . axis, [h, P, K, 3]
    denom = d_ax[..., 0]
    ok = denom.abs() > 1e-9
    t = w_ax[..., 0] / torch.where(ok, denom, torch.ones_like(denom))
    # in-plane coordinates of the crossing relative to the occluder centre: (o + t d - c) . axis
    u = t * d_ax[..., 1] - w_ax[..., 1]
    v = t * d_ax[..., 2] - w_ax[..., 2]
    hw = occ.half_width[idx].unsqueeze(1).to(dt)
    hh = occ.half_height[idx].unsqueeze(1).to(dt)
    mask = valid.unsqueeze(1) & ok
    if softness is None:
        stop = (t > eps) & (u.abs() <= hw) & (v.abs() <= hh) & mask
        return (~stop.any(-1)).to(o.dtype)
    tau = float(softness)
    stop = torch.sigmoid((hw - u.abs()) / tau) * torch.sigmoid((hh - v.abs()) / tau) * torch.sigmoid((t - eps) / tau)
    stop = torch.where(mask, stop, torch.zeros_like(stop))
    return torch.prod(1.0 - stop, dim=-1)


def solarpilot_neighbours(center: torch.Tensor, height: torch.Tensor, width: torch.Tensor, sun_elevation: float,
                          index: torch.Tensor, valid: torch.Tensor, queries: torch.Tensor | None = None
                          ) -> torch.Tensor:
    """SolarPILOT's neighbour restriction: only heliostats in the same or an adjacent cell of a coarse grid.

    SolarPILOT (``SolarField::UpdateNeighborList``, read for its facts) bins the heliostats into square
    cells of side
    ``r = min(max(2 r_c / tan(elevation), 3 r_c, 10 h/2), 200 h/2)`` (``r_c`` the half diagonal, ``h`` the
    mirror height; the cells tile the field extent including the tower base) and lets only heliostats of
    the 3 x 3 cells around a heliostat's cell interact with it. This filters a candidate list.

    Parameters
    ----------
    center : torch.Tensor, [H, 3]
        Pivots, ENU [m].
    height, width : torch.Tensor, [H]
        Mirror sizes [m].
    sun_elevation : float
        [rad].
    index, valid : torch.Tensor, [Q, K]
        Candidate occluders per querying heliostat (:func:`occluder_candidates`).
    queries : torch.Tensor, [Q], long, optional
        The querying heliostats (default all H).

    Returns
    -------
    torch.Tensor, [Q, K], bool
        ``valid`` and in a neighbouring cell.
    """
    c = center.detach().to(torch.float64)
    queries = torch.arange(c.shape[0], device=c.device) if queries is None else queries.to(c.device)
    rc = float(torch.sqrt((height / 2) ** 2 + (width / 2) ** 2).mean())
    hm = float(height.mean()) / 2
    r_shade = max(2 * rc / max(math.tan(sun_elevation), 1e-9), 3 * rc)
    r_cell = min(max(r_shade, 10 * hm), 200 * hm)
    lo = torch.minimum(c[:, :2].min(0).values, torch.zeros(2, dtype=c.dtype, device=c.device))
    hi = torch.maximum(c[:, :2].max(0).values, torch.zeros(2, dtype=c.dtype, device=c.device))
    lo = torch.where(lo < 0, lo * 1.01, lo * 0.99)
    hi = torch.where(hi > 0, hi * 1.01, hi * 0.99)
    n = torch.clamp(torch.floor((hi - lo) / r_cell), min=1)
    size = (hi - lo) / n
    cell = torch.minimum(torch.floor((c[:, :2] - lo) / size).clamp_min(0), n - 1).long()
    near = ((cell[index] - cell[queries].unsqueeze(1)).abs() <= 1).all(-1)
    return valid & near


def solarpilot_interference(center: torch.Tensor, normal: torch.Tensor, width: torch.Tensor, height: torch.Tensor,
                            direction: torch.Tensor, index: torch.Tensor, valid: torch.Tensor,
                            queries: torch.Tensor | None = None, *, interaction_limit: float = 50.0,
                            corner_rule: bool = True, distance_cutoff: bool = True, combine: str = "sum",
                            edge_samples: int = 65
                            ) -> torch.Tensor:
    """SolarPILOT's per-pair shading / blocking estimate, summed over neighbours: the unoccluded fraction.

    The analytic model of SolarPILOT (Wagner, M.S. thesis, U. Wisconsin 2008; as implemented in SolarPILOT's
    ``SolarField::calcShadowBlock``, read for its facts, not copied), restated so that the field model can
    be compared with SolarPILOT's reports on equal terms.
    For a heliostat ``q`` and a neighbour ``k`` (direction ``d``: towards the sun for shading, towards
    ``q``'s aim point for blocking):

    * no interaction when ``k`` lies behind ``q`` along ``d`` or farther than
      ``l_max = (z_k - z_q + h_k sin(zen_k)) / tan(el_d) + h_k cos(zen_k)`` (``zen_k`` the tilt of ``k``'s
      mirror, ``el_d`` the elevation of ``d``; at most ``interaction_limit`` mirror heights);
    * only ``k``'s two *upper* corners are projected along ``d`` onto ``q``'s mirror plane; if neither lands
      inside ``q``'s rectangle the pair counts as no interaction at all (even when ``k``'s outline crosses
      ``q`` between them);
    * the lost fraction is the rectangle from the projected upper edge down to ``q``'s lower edge, with the
      two heliostats taken as parallel: both corners inside -> ``(h/2 + mean v)/h * |u_0 - u_1|/w``; one
      inside -> ``(h/2 + v_on)/h`` times the part of the width between that corner and the edge the other
      corner spills over;
    * the pair losses are *summed* (overlapping shadows counted twice) and ``1 - sum`` is clipped to [0, 1];
      shading and blocking are computed independently over the whole mirror (light that is both shaded and
      blocked is lost twice in the product).

    Parameters
    ----------
    center, normal : torch.Tensor, [H, 3]
        Pivots (mirror centres) ENU [m] and unit mirror normals.
    width, height : torch.Tensor, [H]
        Mirror sizes [m].
    direction : torch.Tensor, [Q, 3] or [3]
        Unit interference direction per querying heliostat.
    index, valid : torch.Tensor, [Q, K]
        Candidate neighbours (:func:`occluder_candidates`, optionally :func:`solarpilot_neighbours`).
    queries : torch.Tensor, [Q], long, optional
        The querying heliostats (default all H).
    interaction_limit : float
        Cap of ``l_max`` in mirror heights.
    distance_cutoff : bool
        True: SolarPILOT's ``l_max`` test above; False (a diagnostic): every neighbour ahead interacts.
    corner_rule : bool
        True: SolarPILOT's rule above. False (a diagnostic): the area under the projected upper edge within
        ``q``'s rectangle, whether or not a corner lands inside (``edge_samples`` points along the edge).
    combine : {"sum", "independent"}
        ``sum``: SolarPILOT's sum of pair losses; ``independent`` (a diagnostic): ``prod_k (1 - loss_k)``,
        which stops counting overlapping shadows twice.

    Returns
    -------
    torch.Tensor, [Q]
        ``clip(1 - sum_k loss_k, 0, 1)``, dtype of ``center``. Not differentiable in a useful way (a report).
    """
    queries = torch.arange(center.shape[0], device=center.device) if queries is None else queries.to(center.device)
    q = queries
    d = safe_normalize(direction.to(center).expand(q.shape[0], 3)).unsqueeze(1)  # [Q, 1, 3]
    ew, eh = mirror_frame(normal)
    cq, nq, ewq, ehq = (t[q].unsqueeze(1) for t in (center, normal, ew, eh))
    ck, nk, ewk, ehk = center[index], normal[index], ew[index], eh[index]  # [Q, K, 3]
    wq, hq = width[q].unsqueeze(1), height[q].unsqueeze(1)
    wk, hk = width[index], height[index]
    rel = ck - cq
    hdist = torch.linalg.vector_norm(rel, dim=-1)
    tan_el = d[..., 2] / torch.linalg.vector_norm(d[..., :2], dim=-1).clamp_min(1e-12)
    cos_k = nk[..., 2]
    sin_k = torch.sqrt((1 - cos_k ** 2).clamp_min(0))
    l_max = (rel[..., 2] + hk * sin_k) / tan_el + hk * cos_k
    l_max = torch.minimum(l_max, interaction_limit * hk)
    ahead = (rel * d).sum(-1) >= 0
    active = valid & ahead & ((hdist <= l_max) | (not distance_cutoff))
    uv = []
    for sign in (-1.0, 1.0):  # the two upper corners of k
        corner = ck + (sign * 0.5 * wk).unsqueeze(-1) * ewk + (0.5 * hk).unsqueeze(-1) * ehk
        den = (d * nq).sum(-1)
        ok = den.abs() > 1e-12
        t = ((cq - corner) * nq).sum(-1) / torch.where(ok, den, torch.ones_like(den))
        p = corner + t.unsqueeze(-1) * d - cq
        u, v = (p * ewq).sum(-1), (p * ehq).sum(-1)
        inside = ok & (u.abs() <= wq / 2) & (v.abs() <= hq / 2)
        uv.append((u, v, inside))
    (u0, v0, in0), (u1, v1, in1) = uv
    both = in0 & in1
    loss_both = (hq / 2 + 0.5 * (v0 + v1)) / hq * (u0 - u1).abs() / wq
    u_on = torch.where(in0, u0, u1)
    v_on = torch.where(in0, v0, v1)
    u_off = torch.where(in0, u1, u0)
    # SolarPILOT measures across from its own x axis, which is minus ours: "spills past its +x edge" is
    # u_off < -w/2 here, and anything else is taken as spilling past the other edge.
    dx = torch.where(u_off < -wq / 2, 0.5 + u_on / wq, 0.5 - u_on / wq)
    loss_one = (hq / 2 + v_on) / hq * dx
    loss = torch.where(both, loss_both, torch.where(in0 | in1, loss_one, torch.zeros_like(loss_one)))
    if not corner_rule:
        s = torch.linspace(0.0, 1.0, int(edge_samples), dtype=u0.dtype, device=u0.device)
        u = u0.unsqueeze(-1) + (u1 - u0).unsqueeze(-1) * s
        v = v0.unsqueeze(-1) + (v1 - v0).unsqueeze(-1) * s
        hq3, wq3 = hq.unsqueeze(-1), wq.unsqueeze(-1)
        covered = (torch.minimum(torch.maximum(v, -hq3 / 2), hq3 / 2) + hq3 / 2) * (u.abs() <= wq3 / 2)
        loss = covered.mean(-1) * (u1 - u0).abs() / (wq * hq)
    loss = torch.where(active, loss, torch.zeros_like(loss))
    if combine == "independent":
        return torch.prod(1.0 - loss.clamp(0.0, 1.0), dim=-1)
    if combine != "sum":
        raise ValueError(f"combine must be 'sum' or 'independent', got {combine!r}")
    return (1.0 - loss.sum(-1)).clamp(0.0, 1.0)
