"""The year heliostat by heliostat: per-heliostat tables over sun positions, their DNI-weighted sums, and the
energy each heliostat loses to its own tracking error and to its own mirror.

Tables
------
The field model (:func:`heliotwin.raytrace.field.field_optics`) is evaluated once per *node* of a grid of sun
positions (PAINT azimuth x elevation): per heliostat its efficiency and each factor, ``[H, S]`` over the S
nodes the year's sun visits (the corners of the grid cells holding a daylight hour with DNI; the others are
never needed). An instant's value is the bilinear interpolation between the four corners of its cell (periodic
in azimuth, clamped in elevation) of the efficiency *over the cosine* (shading x blocking x attenuation x
intercept x reflectance), times the instant's exact cosine (:func:`hourly_cosine`: the mirror normal bisecting
the sun and the aim, as the field model tracks): the cosine is the factor that varies most over the sky and
costs nothing to take hour by hour, and taking it exactly let the grid be twice as coarse in azimuth for the
same error (``benchmarks/year_grid_choice.py``). The year is the sum over instants (:func:`hourly_sums`), in
chunks of heliostats, without a loop over hours.

Tracking loss
-------------
The energy a heliostat loses because it does not point where the twin aims it. The plant's controller aims
with the twin's **learned** kinematics (what ``calibrate`` and ``update`` write: the motor steps of an aim come
from the learned inverse kinematics), and the heliostat moves as its true kinematics say, which the twin knows
only through the calibration's Laplace posterior (``/learned/calibration/posterior/covariance``). Each of
``draws`` posterior draws (a seeded ``torch.Generator``) is a kinematics the heliostat may truly have: at each
sun its motors stand where the learned inverse kinematics put them, and its mirror, moving as the draw says,
reflects the sun's centre along a direction off the aim (:func:`tracking_tables`). A perfectly calibrated
heliostat at its place hits its aim point. The tracking loss of a draw is ``E(perfect) - E(draw)``; the
reported value is its mean over draws (the expected loss: what the remaining uncertainty of this heliostat's
calibration costs a year) and the interval the 5 and 95 % quantiles over draws. A heliostat the calibration did
not reach (nominal kinematics only), or a calibration without a posterior (the network methods), has an unknown
tracking loss: NaN, counted in the report. The same function with the simulator's true kinematics as the
"draw" gives the truth's figure (``benchmarks/bench_year.py``).

The mispointed heliostat's power is ``P_perfect x (cos / cos_perfect) x (I(d) / I(0))``: the cosine of the
actual mirror normal, and the intercept of the heliostat's own image shifted on the receiver by ``d``, the
pixel offset between the actual central ray's hit and the aim point's (both hit points from the field
model's own footprint geometry, so a tilted or curved receiver's incidence is included). ``I`` is the field
model's Gaussian intercept of each mirror sample's footprint (the image at the perfect aim, coarse samples,
weighted by lit area), moved by ``d``; shading and blocking are kept from the perfect heliostat (a pointing
error of milliradians turns the mirror by half that: the occlusion does not change measurably). A central ray
that misses the receiver loses all the heliostat's light. This is evaluated on the same table nodes (per
heliostat and node), so the loss is a table too.

Surface loss
------------
``E(ideal facets) - E(learned mirror)`` for each heliostat with a learned surface (``/learned/surfaces``): the
field model with that heliostat's ideal facets (flat or canted, :func:`heliotwin.field.facets.ideal_surfaces`)
against the learned control points the plant holds, traced for those heliostats only (every heliostat still
shades and blocks them). The surface state carries no uncertainty, so the interval is the point value twice.

Shapes: ``(h,)`` per heliostat, ``[h, S]`` tables over S nodes, ``(T,)`` instants; angles in radians inside,
degrees in ``*_deg`` names; energies in MWh, sums of DNI x hours in [Wh/m^2].
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from .. import sunshape as _sunshape
from ..atmosphere import Atmosphere
from ..field import facets as facet_ops
from ..field import kinematics as K
from ..field.plant import Kinematics, Plant
from ..field.targets import CylinderTarget
from ..geometry import safe_normalize
from ..sun import direction_from_paint_angles
from .field import (
    FACTORS,
    FieldSettings,
    _footprints,
    _intercept,
    field_optics,
    reuse_mirror_samples,
    tracked_mirror_samples,
)
from .flux import target_extent

__all__ = ["TableGrid", "DEFAULT_GRID", "bilinear_weights", "node_weights", "node_columns", "interpolate",
           "hour_weights", "hourly_cosine", "hourly_sums", "heliostat_tables", "tracking_tables", "surface_tables"]


@dataclass(frozen=True)
class TableGrid:
    """Sun positions of the per-heliostat tables: ``azimuth_step_deg`` [deg] around (PAINT, from -180) and
    ``elevations_deg`` (increasing, in (0, 90])."""

    azimuth_step_deg: float = 15.0
    elevations_deg: tuple = (1.0, 2.5, 4.0, 6.0, 8.0, 10.0, 13.0, 16.0, 20.0, 25.0, 30.0, 37.5, 45.0, 55.0, 65.0,
                             77.5, 90.0)

    @property
    def azimuths_deg(self) -> np.ndarray:
        """The Z node azimuths [deg] (PAINT), shape (Z,): ``360 / azimuth_step_deg`` rounded, evenly from -180."""
        z = int(round(360.0 / float(self.azimuth_step_deg)))
        return -180.0 + np.arange(z) * (360.0 / z)

    @property
    def shape(self) -> tuple[int, int]:
        """``(E, Z)``: elevation rows by azimuth columns of the node grid."""
        return len(self.elevations_deg), len(self.azimuths_deg)

    def suns(self, nodes: torch.Tensor) -> torch.Tensor:
        """Unit sun directions [S, 3] (ENU) of flat node indices ``nodes`` [S] (``i * Z + j``)."""
        e, z = self.shape
        el = torch.as_tensor(np.asarray(self.elevations_deg, dtype=np.float64))[nodes // z]
        az = torch.as_tensor(self.azimuths_deg)[nodes % z]
        return direction_from_paint_angles(torch.deg2rad(az), torch.deg2rad(el)).reshape(-1, 3)


#: The field model of the tables: the factors without a receiver map (``flux_mode="none"``: the intercept comes
#: from the footprints, not the map; drawing a map was half of a node's time at 2,000 heliostats).
TABLE_SETTINGS = FieldSettings(resolution=(4, 8), flux_mode="none")

#: The grid chosen on generated fields (benchmarks/year_grid_choice.py, 60 heliostats, radial field, every
#: clear-sky daylight hour of 2023 against the direct sum, the cosine taken hour by hour): 30 deg x these 17
#: elevations gave per-heliostat median 0.25-0.33 %, p95 0.91-1.08 %, field 0.11-0.17 % (cylinder, flat, tilted
#: flat; limits 1 %, 3 %, 0.3 %) with 125 nodes; 15 deg took 203 nodes for 0.10-0.17 % / 0.36-0.37 % / 0.14-0.16
#: %; 11 rows from 1 deg missed the field limit at any azimuth step (0.53-0.60 %): the low sun needs its rows.
DEFAULT_GRID = TableGrid(azimuth_step_deg=30.0)


def bilinear_weights(grid: TableGrid, azimuth: torch.Tensor, elevation: torch.Tensor) -> tuple[torch.Tensor,
                                                                                               torch.Tensor]:
    """Node indices [T, 4] (flat ``i * Z + j``) and weights [T, 4] of each instant's bilinear interpolation.

    ``azimuth``, ``elevation`` [T] [rad] (PAINT). Periodic in azimuth (the last column's right neighbour is the
    first); elevations outside the grid take the nearest row (clamped). Weights sum to 1 per instant.
    """
    e_n, z_n = grid.shape
    step = 360.0 / z_n
    a = (torch.rad2deg(azimuth.to(torch.float64)) + 180.0) % 360.0 / step
    j0 = torch.floor(a).long().clamp(0, z_n - 1)
    wa = (a - j0.to(a.dtype)).clamp(0.0, 1.0)
    j1 = (j0 + 1) % z_n
    el_grid = torch.as_tensor(np.asarray(grid.elevations_deg, dtype=np.float64))
    e = torch.rad2deg(elevation.to(torch.float64)).clamp(float(el_grid[0]), float(el_grid[-1]))
    if e_n == 1:
        i0 = i1 = torch.zeros_like(j0)
        we = torch.zeros_like(wa)
    else:
        i0 = (torch.searchsorted(el_grid, e, right=True) - 1).clamp(0, e_n - 2)
        i1 = i0 + 1
        we = ((e - el_grid[i0]) / (el_grid[i1] - el_grid[i0])).clamp(0.0, 1.0)
    idx = torch.stack((i0 * z_n + j0, i0 * z_n + j1, i1 * z_n + j0, i1 * z_n + j1), -1)
    w = torch.stack(((1 - we) * (1 - wa), (1 - we) * wa, we * (1 - wa), we * wa), -1)
    return idx, w


def node_weights(idx: torch.Tensor, w: torch.Tensor, energy: torch.Tensor, nodes: torch.Tensor,
                 groups: torch.Tensor | None = None, n_groups: int = 1) -> torch.Tensor:
    """Per node the sum of ``energy`` [T] (DNI x hours [Wh/m^2]) times the instants' bilinear weights: a table
    [..., S] times this is the year's sum of its interpolation (a factor's DNI-weighted sum).

    ``idx``, ``w`` [T, 4] (:func:`bilinear_weights`), ``nodes`` [S]: the flat node indices the tables hold
    (every index in ``idx`` with a weight must be among them). ``groups`` [T] (e.g. the month, 0..11) splits
    the sum: result [n_groups, S]; without it [S].
    """
    out = hour_weights(node_columns(nodes, idx, w), w, energy, nodes.numel(), groups, n_groups).sum(0)
    out = out.reshape(n_groups, nodes.numel())
    return out[0] if groups is None else out


def node_columns(nodes: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Columns [T, 4] of the tables (positions in ``nodes`` [S]) of each instant's interpolation nodes ``idx``
    [T, 4] (:func:`bilinear_weights`); a node without weight that the tables do not hold gets column 0 (its
    weight ``w`` [T, 4] is 0). Raises ValueError when an instant needs a node the tables do not hold."""
    pos = torch.full((max(int(idx.max()) if idx.numel() else 0, int(nodes.max()) if nodes.numel() else 0) + 1,),
                     -1, dtype=torch.long)
    pos[nodes] = torch.arange(nodes.numel())
    col = pos[idx]
    if bool((col[w > 0] < 0).any()):
        raise ValueError("an instant interpolates from a node the tables do not hold")
    return col.clamp_min(0)


def interpolate(table: torch.Tensor, col: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Bilinear interpolation of ``table`` [..., S] at T instants: columns ``col`` and weights ``w`` [T, 4]
    (:func:`node_columns`, :func:`bilinear_weights`) -> [..., T]."""
    return (table[..., col] * w.to(table.dtype)).sum(-1)


def hourly_cosine(position: torch.Tensor, aim: torch.Tensor, suns: torch.Tensor) -> torch.Tensor:
    """Cosine [h, T] [-] of each heliostat at each instant: the sun ``suns`` [T, 3] (unit, ENU) on the mirror
    normal that bisects the sun and the aim (:func:`heliotwin.raytrace.field.tracking_normals`, broadcast over
    instants); ``position`` [h, 3] and ``aim`` [h, 3] (one aim a year) or [h, T, 3] (each instant's) ENU [m]."""
    s = suns.to(position).unsqueeze(0)  # [1, T, 3]
    to_aim = safe_normalize(aim.to(position) - position.unsqueeze(1)) if aim.dim() == 3 else \
        safe_normalize(aim.to(position) - position).unsqueeze(1)
    return (safe_normalize(s + to_aim) * s).sum(-1)


def hour_weights(col: torch.Tensor, w: torch.Tensor, energy: torch.Tensor, n_nodes: int,
                 groups: torch.Tensor | None = None, n_groups: int = 1) -> torch.Tensor:
    """The interpolation as a matrix [T, G*S] float64: row t holds ``energy[t] x w[t, c]`` [Wh/m^2] in column
    ``g_t S + col[t, c]`` (``col``, ``w`` [T, 4]: :func:`node_columns`, :func:`bilinear_weights`; ``groups``
    (T,) the instants' group 0..G-1, e.g. the month; G = ``n_groups``, 1 without groups)."""
    t_n = col.shape[0]
    g = torch.zeros_like(col) if groups is None else groups.long().to(col.device).unsqueeze(-1).expand_as(col)
    val = (w.to(torch.float64) * energy.to(torch.float64).unsqueeze(-1))
    a = torch.zeros(t_n, int(n_groups) * int(n_nodes), dtype=torch.float64, device=col.device)
    return a.scatter_add_(1, g * int(n_nodes) + col, val)


def hourly_sums(over_cosine: torch.Tensor, cosine: torch.Tensor, col: torch.Tensor, w: torch.Tensor,
                energy: torch.Tensor, groups: torch.Tensor | None = None, n_groups: int = 1, *,
                weights: torch.Tensor | None = None) -> torch.Tensor:
    """The year of tables of the efficiency over the cosine ``over_cosine`` [..., h, S]: per heliostat
    ``sum_t q_t cos_ht x interp_t`` [Wh/m^2] -> [..., h]; with ``groups`` (T,) (e.g. the month 0..11) the sums
    per group [..., h, n_groups]. ``cosine`` [h, T] (:func:`hourly_cosine`), ``col``, ``w`` [T, 4],
    ``energy`` (T,) DNI x hours [Wh/m^2]; ``weights``: :func:`hour_weights` of them, when already at hand.

    The sum is reordered, ``sum_s table_hs (sum_t cos_ht A_ts)`` with ``A`` = :func:`hour_weights`: one
    [h, T] x [T, G S] product shared by every leading index (the posterior draws), never a [..., h, T]
    tensor of interpolated hours."""
    s_n = over_cosine.shape[-1]
    g_n = 1 if groups is None else int(n_groups)
    a = hour_weights(col, w, energy, s_n, groups, g_n) if weights is None else weights
    m = (cosine.to(torch.float64) @ a).reshape(cosine.shape[0], g_n, s_n)  # [h, G, S]
    out = (over_cosine.to(torch.float64).unsqueeze(-2) * m).sum(-1)  # [..., h, G]
    return out[..., 0] if groups is None else out


def needed_nodes(idx: torch.Tensor, w: torch.Tensor, energy: torch.Tensor) -> torch.Tensor:
    """The flat node indices [S] (sorted) that carry weight for some instant with energy: ``idx``, ``w`` [T, 4]
    (:func:`bilinear_weights`), ``energy`` [T] (DNI x hours [Wh/m^2])."""
    use = (w > 0) & (energy > 0).unsqueeze(-1)
    return torch.unique(idx[use])


def heliostat_tables(plant: Plant, suns: torch.Tensor, aims, *, atmosphere: Atmosphere | None = None,
                     settings: FieldSettings | None = None, rows: torch.Tensor | None = None,
                     progress=None) -> dict:
    """Per-heliostat efficiency and factors at each sun: the field model once per node.

    Parameters
    ----------
    plant : Plant
    suns : torch.Tensor, [S, 3]
        Unit vectors towards the sun (above the horizon).
    aims : torch.Tensor [H, 3] or callable
        Aim points ENU [m] for every sun, or ``aims(s, sun) -> [H, 3]`` per node (optimised aiming).
    settings : FieldSettings, optional
        Default: the field model with a 4 x 8 map (the intercept does not depend on the map).
    rows : torch.Tensor, shape (h,), optional
        Trace only these heliostats (every heliostat still shades and blocks them).
    progress : callable, optional
        Called with no argument after each node.

    Returns
    -------
    dict
        ``efficiency`` and every factor of :data:`FACTORS`: [h, S] float64 (h = H or ``len(rows)``),
        ``mirror_area`` [h] [m^2], ``aim`` [S, h, 3] (the aim points used; float64).
    """
    settings = settings or TABLE_SETTINGS
    s_n = suns.shape[0]
    out = {}
    aim_used = []
    with torch.no_grad(), reuse_mirror_samples():
        for s in range(s_n):
            aim = aims(s, suns[s]) if callable(aims) else aims
            r = field_optics(plant, suns[s], atmosphere=atmosphere, aim=aim, settings=settings, heliostats=rows)
            for name in ("efficiency",) + FACTORS:
                out.setdefault(name, []).append(getattr(r, name).detach().to(torch.float64))
            aim_used.append(r.aim.detach().to(torch.float64))
            area = r.mirror_area.detach().to(torch.float64)
            if progress is not None:
                progress()
    tables = {k: torch.stack(v, -1) for k, v in out.items()}
    tables["mirror_area"] = area if s_n else torch.zeros(0, dtype=torch.float64)
    tables["aim"] = torch.stack(aim_used) if s_n else torch.zeros(0, 0, 3, dtype=torch.float64)
    return tables


def _central_pixels(target, origin: torch.Tensor, direction: torch.Tensor, resolution) -> tuple[torch.Tensor,
                                                                                                  torch.Tensor]:
    """Pixel position [..., 2] of a ray's hit on the receiver (the field model's footprint centre) and ok [...]."""
    rows_px, cols_px = resolution
    shape = origin.shape[:-1]
    extent = target_extent(target, 1).to(origin.device)
    mu, _, ok = _footprints(origin.reshape(1, -1, 3).to(torch.float64), direction.reshape(1, -1, 3).to(torch.float64),
                            target, extent, rows_px, cols_px)
    return mu[0].reshape(*shape, 2), ok[0].reshape(shape)


def _sample_images(plant: Plant, normal: torch.Tensor, sun: torch.Tensor, rows: torch.Tensor, resolution,
                   samples: int):
    """Each traced heliostat's image at its perfect aim as its mirror samples' footprints (the field model's
    Gaussians): centres mu [h, N, 2] and covariances [h, N, 2, 2] [px], ok [h, N], lit-area weights [h, N]."""
    target = plant.target("receiver")
    pw, nw, area = tracked_mirror_samples(plant, normal, int(samples), torch.float64, rows)
    s = sun.to(nw)
    reflected = -s - 2.0 * (nw @ -s).unsqueeze(-1) * nw
    h, n = area.shape
    rows_px, cols_px = resolution
    extent = target_extent(target, 1).to(pw.device)
    mu, jac, ok = _footprints(pw.reshape(1, h * n, 3), reflected.reshape(1, h * n, 3), target, extent, rows_px,
                              cols_px)
    ps = plant.sun
    var = _sunshape.second_moment(ps.sunshape, sigma=float(ps.sigma), radius=float(ps.radius), csr=float(ps.csr),
                                  slope_error=float(ps.slope_error))
    cov = var * (jac[0] @ jac[0].transpose(-1, -2))
    eye = torch.eye(2, dtype=cov.dtype)
    cov = torch.where(ok[0][..., None, None], cov, eye)
    weight = area * (nw @ s).clamp_min(0.0)
    return mu[0].reshape(h, n, 2), cov.reshape(h, n, 2, 2), ok[0].reshape(h, n), weight


def _shifted_intercept(images, shift: torch.Tensor, target, resolution) -> torch.Tensor:
    """Lit-area weighted intercept [K, h] of the images moved by ``shift`` [K, h, 2] pixels."""
    mu, cov, ok, weight = images
    rows_px, cols_px = resolution
    k = shift.shape[0]
    m = (mu.unsqueeze(0) + shift.unsqueeze(2))  # [K, h, N, 2]
    icpt = _intercept(m, cov.unsqueeze(0).expand(k, *cov.shape), ok.unsqueeze(0).expand(k, *ok.shape), target,
                      rows_px, cols_px)
    return (icpt * weight).sum(-1) / weight.sum(-1).clamp_min(1e-30)


#: Pixel shift standing for "the central ray misses the receiver" (its image lands nowhere on it).
_MISS_PX = 1.0e4


def tracking_tables(plant: Plant, suns: torch.Tensor, aim: torch.Tensor, rows: torch.Tensor, controller: Kinematics,
                    variants: list[Kinematics], *, resolution=(4, 8), samples: int = 4, progress=None) -> torch.Tensor:
    """Power of mispointed heliostats relative to a perfectly aimed one, per node: ``[V, h, S]`` in [0, ~1].

    Parameters
    ----------
    plant : Plant
    suns : torch.Tensor, [S, 3]
    aim : torch.Tensor, [S, H, 3]
        Each node's aim points ENU [m] (all heliostats).
    rows : torch.Tensor, shape (h,)
        The heliostats with learned kinematics (indices into the plant).
    controller : Kinematics
        The kinematics the controller aims those h heliostats with (the twin's learned ones).
    variants : list of Kinematics
        V kinematics of those h heliostats as they may truly move (posterior draws; the simulator's truth).
    resolution, samples
        The pixel grid the offsets are measured on and the mirror samples per facet and direction of the
        image (the ratio ``I(d) / I(0)`` needs few).

    Returns
    -------
    torch.Tensor, [V, h, S], float64
        ``(cos / cos_perfect) x I(d) / I(0)`` (module docstring); multiply the perfect heliostat's power.
    """
    s_n, h = suns.shape[0], rows.numel()
    out = torch.ones(len(variants), h, s_n, dtype=torch.float64)
    if h == 0 or s_n == 0:
        return out
    # nodes a few at a time: the variants' poses are [V, S, h, ...] tensors (16 draws at 10,000 heliostats and
    # 63 nodes: ~1 GB in one piece)
    step = max(1, TRACKING_BUDGET // max(1, len(variants) * h))
    for s0 in range(0, s_n, step):
        sl = slice(s0, s0 + step)
        out[:, :, sl] = _tracking_chunk(plant, suns[sl], aim[sl], rows, controller, variants, resolution, samples,
                                        progress)
    return out


#: Variant-heliostat-nodes of one chunk of :func:`tracking_tables` (a memory bound, not a tuning knob).
TRACKING_BUDGET = 1 << 21


def _tracking_chunk(plant: Plant, suns, aim, rows, controller, variants, resolution, samples, progress):
    """:func:`tracking_tables` of the nodes ``suns`` [s, 3] (``aim`` [s, H, 3]) -> [V, h, s]."""
    target = plant.target("receiver")
    full = isinstance(target, CylinderTarget) and target.opening_angle >= 2 * math.pi - 1e-9
    s_n, h = suns.shape[0], rows.numel()
    out = torch.ones(len(variants), h, s_n, dtype=torch.float64)
    a = aim[:, rows].to(torch.float64)  # [S, h, 3]
    with torch.no_grad():
        sun_sh = suns.to(torch.float64).unsqueeze(1).expand(s_n, h, 3)
        # the controller's motor steps (its inverse kinematics), once for every variant: the same steps as
        # heliotwin.evaluation.pointing_errors takes, the variants only move differently on them
        steps, reach = K.inverse(controller, a, sun_sh, strict=False)
        shifts, cos_ratio = [], []
        for kin in variants:  # the point value and a handful of draws, each batched over nodes and heliostats
            rot, conc = K.forward(kin, steps)
            n_act = K.mirror_normal(rot)
            ray = -sun_sh + 2.0 * (sun_sh * n_act).sum(-1, keepdim=True) * n_act  # the reflected central ray
            ideal = (a - conc) / torch.linalg.vector_norm(a - conc, dim=-1, keepdim=True).clamp_min(1e-12)
            mu_a, ok_a = _central_pixels(target, conc, ray, resolution)
            mu_0, ok_0 = _central_pixels(target, conc, ideal, resolution)
            d = mu_a - mu_0
            if full:  # the full cylinder's intercept is the axial band alone
                d[..., 0] = 0.0
            d = torch.where((ok_a & ok_0).unsqueeze(-1), d, torch.full_like(d, _MISS_PX))
            # a pose the controller cannot reach is the mount's limit, which a perfect heliostat shares: no loss
            d = torch.where(reach.unsqueeze(-1), d, torch.zeros_like(d))
            shifts.append(d)
            n_id = K.bisector_normal(sun_sh, conc, a)
            c = (n_act * sun_sh).sum(-1).clamp_min(0.0) / (n_id * sun_sh).sum(-1).clamp_min(1e-12)
            cos_ratio.append(torch.where(reach, c, torch.ones_like(c)))
        shifts = torch.stack(shifts)  # [V, S, h, 2]
        cos_ratio = torch.stack(cos_ratio)  # [V, S, h]
        pos = plant.field.kinematics.position[rows].to(torch.float64)
        for s in range(s_n):
            sun = suns[s].to(torch.float64)
            # the perfect heliostat's image: normal bisecting sun and aim at the field model's mirror centre
            normal = K.bisector_normal(sun.expand(h, 3), pos, a[s])
            images = _sample_images(plant, normal, sun, rows, resolution, samples)
            zero = _shifted_intercept(images, torch.zeros(1, h, 2, dtype=torch.float64), target, resolution)[0]
            moved = _shifted_intercept(images, shifts[:, s], target, resolution)
            ratio = torch.where(zero > 0, moved / zero.clamp_min(1e-30), torch.ones_like(moved))
            out[:, :, s] = (cos_ratio[:, s] * ratio).clamp(0.0, 1.5)
            if progress is not None:
                progress()
    return out


def ideal_mirror_plant(plant: Plant) -> Plant:
    """The plant with every heliostat's ideal facets (flat or canted) on the plant's control net."""
    sf = plant.field.surfaces
    cp = sf.control_points
    ideal = facet_ops.ideal_surfaces(plant.field.facets, (cp.shape[2], cp.shape[3]), (sf.degree_u, sf.degree_v))
    ideal = replace(ideal, control_points=ideal.control_points.to(cp))
    return replace(plant, field=replace(plant.field, surfaces=ideal))


def surface_tables(plant: Plant, suns: torch.Tensor, aims, rows: torch.Tensor, *,
                   atmosphere: Atmosphere | None = None, settings: FieldSettings | None = None,
                   progress=None) -> torch.Tensor:
    """Efficiency [h, S] of heliostats ``rows`` with ideal facets instead of their learned mirrors (the rest of
    the field as it is), per node; :func:`heliostat_tables` of the plant's own mirrors is the other side."""
    if rows.numel() == 0:
        return torch.zeros(0, suns.shape[0], dtype=torch.float64)
    return heliostat_tables(ideal_mirror_plant(plant), suns, aims, atmosphere=atmosphere, settings=settings,
                            rows=rows, progress=progress)["efficiency"]
