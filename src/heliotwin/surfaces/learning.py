"""Learnable NURBS mirror surfaces: control-point displacements along each facet's normal.

Parametrisation
---------------
Per facet, the control net is ``base + d * n_facet`` (:func:`heliotwin.field.facets.displace_along_normal`)
with ``base`` the ideal flat canted net (or a loaded surface refitted to the chosen net size) and ``d`` the
learned displacement [m]. In-plane control-point motion only re-parametrises a nearly flat facet, so the
normal offset is the physically meaningful degree of freedom. Optional rational weights are learned as
``exp(log_w)`` (positive, 1 at start). :meth:`LearnableSurface.refine` moves to a finer net during training
(exact knot insertion where the knot vectors nest) and keeps the represented surface.

The optimiser sees ``d`` in millimetres (``scale``): Adam's step is then a displacement in mm, which makes
one learning rate work across heliostat sizes.

Shapes: F facets, (nu, nv) control points per facet, P samples per facet.
"""
from __future__ import annotations

import torch
from torch import nn

from .. import nurbs
from ..errors import HeliotwinError
from ..field import facets as facet_ops
from ..field.plant import Facets, Surfaces

__all__ = ["learnable_surfaces", "LearnableSurface", "gauge_basis", "parse_grid", "normal_heights",
           "heights_to_displacement"]

#: Metres per optimiser unit of displacement (the parameters are in mm).
MM = 1e-3


def parse_grid(text: str) -> tuple[int, int]:
    """``"7x7"`` -> ``(7, 7)``; ``"9"`` -> ``(9, 9)``; raises :class:`HeliotwinError` otherwise."""
    parts = str(text).lower().replace("×", "x").split("x")
    try:
        vals = tuple(int(p) for p in parts)
    except ValueError:
        raise HeliotwinError(f"bad control-point grid {text!r}; expected e.g. 7x7") from None
    if len(vals) == 1:
        vals = vals * 2
    if len(vals) != 2 or min(vals) < 2:
        raise HeliotwinError(f"bad control-point grid {text!r}; expected e.g. 7x7 with >= 2 per side")
    return vals  # type: ignore[return-value]


def learnable_surfaces(facets: Facets, base: torch.Tensor, displacement: torch.Tensor, degree: tuple[int, int],
                       log_weights: torch.Tensor | None = None) -> Surfaces:
    """Functional core: the surfaces for given displacements.

    Parameters
    ----------
    facets : Facets
        One heliostat's placement, ``[1, F, 3]`` tensors.
    base : torch.Tensor, [1, F, nu, nv, 3]
        Base control net [m] (heliostat frame).
    displacement : torch.Tensor, [1, F, nu, nv]
        Offsets along the facet normals [m].
    degree : (int, int)
    log_weights : torch.Tensor, [1, F, nu, nv], optional
        Log of the rational weights (None: a B-spline).

    Returns
    -------
    Surfaces
        Differentiable w.r.t. ``displacement`` and ``log_weights``.
    """
    cp = facet_ops.displace_along_normal(base, displacement, facets)
    weights = None if log_weights is None else torch.exp(log_weights)
    return Surfaces(control_points=cp, degree_u=int(degree[0]), degree_v=int(degree[1]), weights=weights)


def normal_heights(facets: Facets, control_points: torch.Tensor, degree: tuple[int, int],
                   samples: tuple[int, int] = (32, 32), weights=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Height along the facet normal and unit normals of a surface, sampled on the facet's parameter grid.

    Parameters
    ----------
    facets : Facets
        ``[1, F, 3]`` placement [m] (translations) of the heliostat's F facets.
    control_points : torch.Tensor, [1, F, nu, nv, 3]
        The surface's NURBS control net [m], heliostat frame.
    degree : (int, int)
        NURBS degree (p, q) in u and v.
    samples : (int, int)
        (su, sv) midpoint samples per facet and direction.
    weights : torch.Tensor, [1, F, nu, nv], optional
        Rational weights [1]; default all ones.

    Returns
    -------
    heights : torch.Tensor, [F, su, sv]
        ``(S(u, v) - translation) . n_facet`` [m].
    normals : torch.Tensor, [F, su, sv, 3]
        Unit surface normals (heliostat frame).
    """
    su, sv = samples
    surf = Surfaces(control_points, int(degree[0]), int(degree[1]), weights)
    pts, nrm, _ = facet_ops.surface_points(surf, samples)
    nf = control_points.shape[1]
    pts = pts.reshape(nf, su, sv, 3)
    nrm = nrm.reshape(nf, su, sv, 3)
    fn = facet_ops.facet_normals(facets.canting_e, facets.canting_n)[0].to(pts)  # [F, 3]
    tr = facets.translation[0].to(pts)
    h = ((pts - tr[:, None, None, :]) * fn[:, None, None, :]).sum(-1)
    return h, nrm


def heights_to_displacement(heights: torch.Tensor, num_control_points, degree) -> torch.Tensor:
    """Least-squares normal displacements whose surface has the given heights at cell midpoints.

    Parameters
    ----------
    heights : torch.Tensor, [F, su, sv]
        Heights along the facet normal [m] at ``u = (i + 0.5) / su``, ``v = (j + 0.5) / sv``.
    num_control_points, degree : (int, int)

    Returns
    -------
    torch.Tensor, [1, F, nu, nv]
        [m]. The flat base has height 0 everywhere (linear precision), so heights are linear in the
        displacements, ``h = B_u d B_v^T``, solved with pseudo-inverses.
    """
    h = heights
    su, sv = h.shape[-2], h.shape[-1]
    nu, nv = (int(x) for x in num_control_points)
    p, q = (int(x) for x in degree)
    f = dict(dtype=h.dtype, device=h.device)  # the bases live where the heights do
    u = (torch.arange(su, **f) + 0.5) / su
    v = (torch.arange(sv, **f) + 0.5) / sv
    bu, _ = nurbs.basis_functions(u, nurbs.clamped_knots(nu, p, **f), p, nu)
    bv, _ = nurbs.basis_functions(v, nurbs.clamped_knots(nv, q, **f), q, nv)
    d = torch.einsum("ai,fij,bj->fab", torch.linalg.pinv(bu), h, torch.linalg.pinv(bv))
    return d.reshape(1, h.shape[0], nu, nv)


def gauge_basis(facets: Facets, num_control_points, degree, pistons: bool = True, common_tilt: bool = True
                ) -> torch.Tensor:
    """Orthonormal basis of the displacement modes invisible in centred-window images.

    A flat facet's control points sit at the Greville abscissae, so ``d_ij = a s_i |canting_e| +
    b t_j |canting_n|`` (``s, t`` in [-1, 1]) is an exact planar tilt of slope ``(a, b)`` [mm/m]; the same
    ``(a, b)`` on every facet is a rigid tilt of the whole mirror, which only translates the spot (removed
    by centring the window). A facet piston (constant ``d``) does not change any normal.

    ``common_tilt=False`` leaves the rigid tilt out (images in fixed windows with known kinematics see it).

    Returns
    -------
    torch.Tensor, [F nu nv, K], float64
        ``K = 2`` (with ``common_tilt``) + F (with ``pistons``) orthonormal columns.
    """
    nu, nv = (int(x) for x in num_control_points)
    p, q = (int(x) for x in degree)
    nf = facets.translation.shape[1]
    f = dict(dtype=torch.float64, device=facets.translation.device)
    s = 2.0 * nurbs.greville_abscissae(nu, p, **f) - 1.0
    t = 2.0 * nurbs.greville_abscissae(nv, q, **f) - 1.0
    le = facets.canting_e[0].to(torch.float64).norm(dim=-1)
    ln = facets.canting_n[0].to(torch.float64).norm(dim=-1)
    modes = []
    if common_tilt:
        modes += [(le[:, None, None] * s[None, :, None]).expand(nf, nu, nv).reshape(-1),
                  (ln[:, None, None] * t[None, None, :]).expand(nf, nu, nv).reshape(-1)]
    if pistons:
        eye = torch.eye(nf, **f)
        modes += [eye[k][:, None, None].expand(nf, nu, nv).reshape(-1) for k in range(nf)]
    basis, _ = torch.linalg.qr(torch.stack(modes, 1))
    return basis


class LearnableSurface(nn.Module):
    """One heliostat's learnable facets (thin stateful wrapper around :func:`learnable_surfaces`).

    Parameters
    ----------
    facets : Facets
        ``[1, F, 3]`` placement (float64).
    num_control_points : (int, int)
        (nu, nv), e.g. (7, 7).
    degree : (int, int)
        (p, q), e.g. (3, 3).
    learn_weights : bool
        Also learn rational weights.
    initial : torch.Tensor, [1, F, nu0, nv0, 3], optional
        A loaded surface's control net (degree ``initial_degree``) to start from; it is refitted to the
        chosen net and the residual normal offset becomes the initial displacement. Default: flat canted.
    initial_degree : (int, int), optional
    dtype : torch.dtype
        Of the surface computations (float64 keeps the finite-difference checks clean).
    fix_gauge : bool
        Project out the displacement modes that centred-window images cannot see (see
        :func:`gauge_basis`): a common tilt of all facets (it only moves the whole spot, and the window
        follows the spot) and each facet's piston. The represented surface then keeps the ideal mean
        orientation and each facet's mean height; all other shapes are unaffected.
    gauge_tilt : bool
        Include the common tilt in that projection (default). False for images in fixed windows taken with
        known kinematics, where the spot's position in the window shows the common tilt.
    """

    def __init__(self, facets: Facets, num_control_points=(7, 7), degree=(3, 3), learn_weights: bool = False,
                 initial: torch.Tensor | None = None, initial_degree=None, dtype=torch.float64,
                 fix_gauge: bool = False, gauge_tilt: bool = True):
        super().__init__()
        self.fix_gauge = bool(fix_gauge)
        self.gauge_tilt = bool(gauge_tilt)
        self.facets = Facets(*(t.to(dtype) for t in (facets.translation, facets.canting_e, facets.canting_n)))
        if self.facets.translation.dim() != 3 or self.facets.translation.shape[0] != 1:
            raise HeliotwinError("LearnableSurface holds exactly one heliostat ([1, F, 3] facets)")
        self.num_control_points = tuple(int(x) for x in num_control_points)
        self.degree = tuple(int(x) for x in degree)
        for n, p in zip(self.num_control_points, self.degree):
            if n < p + 1:
                raise HeliotwinError(f"{n} control points cannot carry degree {p} (need >= {p + 1})")
        base = facet_ops.flat_control_points(self.facets, self.num_control_points, self.degree)
        self.register_buffer("base", base)
        nf = base.shape[1]
        disp = torch.zeros(1, nf, *self.num_control_points, dtype=dtype, device=base.device)
        if initial is not None:
            disp = self._displacement_of(initial.to(dtype), tuple(initial_degree or self.degree))
        self.displacement_mm = nn.Parameter(disp / MM)
        # Gauge projection acts on the change from the start, so a loaded surface is kept as it is.
        self.register_buffer("start_mm", (disp / MM).clone())
        self.log_weights = nn.Parameter(torch.zeros_like(disp)) if learn_weights else None
        self._gauge: dict = {}  # gauge_basis per (net, device): fixed by the facets, not recomputed every step

    def _apply(self, fn, *args, **kwargs):
        # .cpu() / .to(device) move the facets too: they are a plain dataclass, not a registered buffer
        super()._apply(fn, *args, **kwargs)
        self.facets = Facets(*(fn(t) for t in (self.facets.translation, self.facets.canting_e, self.facets.canting_n)))
        self._gauge = {}
        return self

    def _gauge_basis(self, like: torch.Tensor) -> torch.Tensor:
        key = (self.num_control_points, self.gauge_tilt, like.device, like.dtype)
        if key not in self._gauge:
            self._gauge[key] = gauge_basis(self.facets, self.num_control_points, self.degree,
                                           common_tilt=self.gauge_tilt).to(like)
        return self._gauge[key]

    def _displacement_of(self, control_points: torch.Tensor, degree) -> torch.Tensor:
        # Least-squares normal offsets on this net reproducing the given surface's normal heights.
        h, _ = normal_heights(self.facets, control_points, degree, (24, 24))
        return heights_to_displacement(h, self.num_control_points, self.degree)

    @property
    def displacement(self) -> torch.Tensor:
        """Displacements along the facet normals [m], ``[1, F, nu, nv]`` (gauge-projected if ``fix_gauge``)."""
        d = self.displacement_mm
        if self.fix_gauge:
            q = self._gauge_basis(d)
            change = (d - self.start_mm).reshape(-1)
            d = self.start_mm + (change - q @ (q.T @ change)).reshape(d.shape)
        return d * MM

    def surfaces(self) -> Surfaces:
        """Current surfaces (differentiable)."""
        return learnable_surfaces(self.facets, self.base, self.displacement, self.degree, self.log_weights)

    def forward(self) -> Surfaces:
        """The same as :meth:`surfaces` (so the module can be called): control points ``[1, F, nu, nv, 3]`` [m]."""
        return self.surfaces()

    @torch.no_grad()
    def refine(self, new_num: tuple[int, int]) -> None:
        """Switch to a finer net representing the same surface (new parameters: rebuild the optimiser)."""
        new_num = tuple(int(x) for x in new_num)
        if self.log_weights is not None:
            raise HeliotwinError("refinement of rational (weighted) surfaces is not supported")
        # Displacements are a scalar B-spline field; refine them with the same linear transfer as points.
        def up(d):
            d3 = torch.stack((d, torch.zeros_like(d), torch.zeros_like(d)), -1)
            return nurbs.refine(d3, self.degree[0], self.degree[1], new_num)[..., 0].contiguous()

        d_new, s_new = up((self.displacement / MM).detach()), up(self.start_mm)
        self.num_control_points = new_num
        self.base = facet_ops.flat_control_points(self.facets, new_num, self.degree)
        self.start_mm = s_new
        self.displacement_mm = nn.Parameter(d_new)
