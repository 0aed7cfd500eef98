"""Batched, differentiable NURBS surfaces (functional core).

A surface is a control net ``control_points`` [..., nu, nv, 3] (any leading batch shape, e.g. [H, F])
with degrees ``(p, q)``, uniform clamped knot vectors on [0, 1] in both directions and optional rational
weights [..., nu, nv]. Everything is built from two small dense basis matrices (one per parameter
direction) and ``einsum``, so the cost is linear in the batch size and autograd flows to control points
and weights.

Index convention: the first net index (u) runs along the facet's ``canting_e``, the second (v) along
``canting_n`` (see :mod:`heliotwin.field.facets`). Evaluated grids are u-major: ``index = i * Pv + j``.

Units: parameters are dimensionless in [0, 1]; points in metres; ``du = dS/du`` and ``dv = dS/dv`` in
metres per unit parameter; areas in m².
"""
from __future__ import annotations

from functools import lru_cache

import torch

from .errors import HeliotwinError

#: Norm floor used when normalising ``du x dv``: a degenerate (zero-area) control net then gives a zero
#: normal with finite gradients instead of NaN.
NORM_EPS = 1e-12


# --------------------------------------------------------------------------------------------------
# Knots and basis functions
# --------------------------------------------------------------------------------------------------
def _check_degree(num_control_points: int, degree: int) -> None:
    if degree < 0:
        raise HeliotwinError(f"NURBS degree must be >= 0, got {degree}")
    if num_control_points < degree + 1:
        raise HeliotwinError(
            f"a degree-{degree} B-spline needs at least {degree + 1} control points, got {num_control_points}")


def clamped_knots(num_control_points: int, degree: int, dtype=None, device=None) -> torch.Tensor:
    """Uniform clamped (open) knot vector on [0, 1].

    Parameters
    ----------
    num_control_points : int
        Number of control points n along this direction (n >= degree + 1).
    degree : int
        Polynomial degree p.
    dtype, device : optional
        Of the returned tensor (default dtype / CPU).

    Returns
    -------
    torch.Tensor, [n + p + 1]
        ``p + 1`` zeros, ``n - p - 1`` uniformly spaced interior knots, ``p + 1`` ones.

    Examples
    --------
    >>> clamped_knots(5, 2, dtype=torch.float64).tolist()
    [0.0, 0.0, 0.0, 0.3333333333333333, 0.6666666666666666, 1.0, 1.0, 1.0]
    """
    n, p = int(num_control_points), int(degree)
    _check_degree(n, p)
    interior = torch.arange(1, n - p, dtype=torch.float64) / (n - p)
    knots = torch.cat((torch.zeros(p + 1, dtype=torch.float64), interior, torch.ones(p + 1, dtype=torch.float64)))
    return knots.to(dtype=dtype or torch.get_default_dtype(), device=device)


def greville_abscissae(num_control_points: int, degree: int, dtype=None, device=None) -> torch.Tensor:
    """Greville abscissae of the uniform clamped knot vector.

    Control points placed at ``a + (b - a) * xi`` reproduce the *linear* function ``a + (b - a) u``
    exactly (linear precision). Uniformly spaced control points do not (for p >= 2 and n > p + 1 the
    end spans are compressed), which matters for areas and for "point at (0.5, 0.5) is the centre".

    Parameters
    ----------
    num_control_points : int
    degree : int
    dtype, device : optional

    Returns
    -------
    torch.Tensor, [n]
        ``xi_i = (t_{i+1} + ... + t_{i+p}) / p`` in [0, 1]; uniform ``i / (n - 1)`` for p = 0.
    """
    n, p = int(num_control_points), int(degree)
    _check_degree(n, p)
    if p == 0:
        xi = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    else:
        t = clamped_knots(n, p, dtype=torch.float64)
        # Window sums t[i+1] + ... + t[i+p] for i = 0..n-1 via a cumulative sum.
        c = torch.cat((torch.zeros(1, dtype=torch.float64), torch.cumsum(t, 0)))
        xi = (c[p + 1:p + 1 + n] - c[1:1 + n]) / p
    return xi.to(dtype=dtype or torch.get_default_dtype(), device=device)


def _inverse_or_zero(d: torch.Tensor) -> torch.Tensor:
    # Cox-de Boor convention 0/0 = 0 for repeated knots; where() keeps gradients finite.
    safe = torch.where(d > 0, d, torch.ones_like(d))
    return torch.where(d > 0, 1.0 / safe, torch.zeros_like(d))


def basis_functions(u: torch.Tensor, knots: torch.Tensor, degree: int,
                    num_control_points: int) -> tuple[torch.Tensor, torch.Tensor]:
    """B-spline basis functions and their first derivatives (Cox-de Boor), vectorised over u.

    Parameters
    ----------
    u : torch.Tensor, [N]
        Parameters, nominally in [t_p, t_n] = [0, 1] for clamped knots. ``u == 1`` belongs to the last
        non-empty span (so the last basis function is 1 there). Values outside the range are evaluated
        with the polynomial piece of the nearest end span (smooth extrapolation).
    knots : torch.Tensor, [n + p + 1]
        Non-decreasing knot vector.
    degree : int
        Degree p.
    num_control_points : int
        Number of basis functions n.

    Returns
    -------
    N0 : torch.Tensor, [N, n]
        Basis values (non-negative inside the range; rows sum to 1).
    N1 : torch.Tensor, [N, n]
        Derivatives dN/du.

    Notes
    -----
    Dtype/device follow ``u``. Differentiable w.r.t. ``u`` (knots are treated as constants).
    """
    n, p = int(num_control_points), int(degree)
    _check_degree(n, p)
    u = torch.as_tensor(u)
    if not u.is_floating_point():
        u = u.to(torch.get_default_dtype())
    if u.dim() != 1:
        raise HeliotwinError(f"basis_functions expects u of shape [N], got {tuple(u.shape)}")
    t = torch.as_tensor(knots).to(dtype=u.dtype, device=u.device)
    if t.shape != (n + p + 1,):
        raise HeliotwinError(f"knot vector must have n + p + 1 = {n + p + 1} entries, got {tuple(t.shape)}")
    num_spans = n + p
    # Span k with t_k <= u < t_{k+1}; clamping to [p, n-1] puts u == t_n (= 1) in the last real span and
    # makes out-of-range u use the end polynomials.
    span = torch.searchsorted(t, u.detach().contiguous(), right=True) - 1
    span = span.clamp(p, n - 1)
    basis = torch.nn.functional.one_hot(span, num_spans).to(u.dtype)  # degree 0, [N, n + p]
    uu = u[:, None]
    prev = basis
    for d in range(1, p + 1):  # loop over the (small) degree only
        m = num_spans - d  # number of degree-d functions on this knot vector
        i = torch.arange(m, device=u.device)
        inv_left = _inverse_or_zero(t[i + d] - t[i])
        inv_right = _inverse_or_zero(t[i + d + 1] - t[i + 1])
        prev, basis = basis, (uu - t[i]) * inv_left * basis[:, :m] + (t[i + d + 1] - uu) * inv_right * basis[:, 1:m + 1]
    if p == 0:
        return basis, torch.zeros_like(basis)
    i = torch.arange(n, device=u.device)
    # dN_{i,p}/du = p [N_{i,p-1} / (t_{i+p} - t_i) - N_{i+1,p-1} / (t_{i+p+1} - t_{i+1})]
    deriv = p * (_inverse_or_zero(t[i + p] - t[i]) * prev[:, :n]
                 - _inverse_or_zero(t[i + p + 1] - t[i + 1]) * prev[:, 1:n + 1])
    return basis, deriv


def _basis(num: int, degree: int, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    knots = clamped_knots(num, degree, dtype=u.dtype, device=u.device)
    return basis_functions(u, knots, degree, num)


@lru_cache(maxsize=64)
def midpoint_basis(num_control_points: int, degree: int, samples: int, dtype=None, device=None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Basis functions at the cell midpoints :func:`midpoints`, cached: the one home of the fixed sample bases.

    A surface sampled on a fixed parameter grid (every optimiser step of a surface fit) is ``B_u C B_v^T``
    with constant ``B_u``, ``B_v``; computing them once instead of per evaluation is the same numbers.

    Parameters
    ----------
    num_control_points, degree : int
        n and p of the uniform clamped knot vector.
    samples : int
        Midpoints ``(i + 0.5) / samples``.
    dtype, device : optional

    Returns
    -------
    N0, N1 : torch.Tensor, [samples, n]
        As :func:`basis_functions` (no autograd graph; shared, so never modify them in place).
    """
    u = midpoints(samples, dtype=dtype, device=device)
    with torch.no_grad():
        b0, b1 = _basis(int(num_control_points), int(degree), u)
    return b0, b1


# --------------------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------------------
def _as_param(x, like: torch.Tensor) -> torch.Tensor:
    x = torch.as_tensor(x).to(dtype=like.dtype, device=like.device)
    return x.reshape(-1)


def _tensor_grid(net: torch.Tensor, bu0, bu1, bv0, bv1):
    # Contract v first, then u: cost O(batch * nu * nv * (Pu + Pv)) rather than O(batch * nu * nv * Pu * Pv).
    tv0 = torch.einsum("jb,...abk->...ajk", bv0, net)
    tv1 = torch.einsum("jb,...abk->...ajk", bv1, net)
    s = torch.einsum("ia,...ajk->...ijk", bu0, tv0)
    su = torch.einsum("ia,...ajk->...ijk", bu1, tv0)
    sv = torch.einsum("ia,...ajk->...ijk", bu0, tv1)
    flat = lambda x: x.reshape(*x.shape[:-3], x.shape[-3] * x.shape[-2], x.shape[-1])  # noqa: E731
    return flat(s), flat(su), flat(sv)


def evaluate(control_points: torch.Tensor, degree_u: int, degree_v: int, u: torch.Tensor, v: torch.Tensor,
             weights: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Evaluate a (batched) NURBS surface and its partial derivatives on the tensor grid u x v.

    Parameters
    ----------
    control_points : torch.Tensor, [..., nu, nv, 3]
        Control net [m].
    degree_u, degree_v : int
        Degrees p, q (uniform clamped knots on [0, 1]).
    u : torch.Tensor, [Pu]
        Parameters along the first net index.
    v : torch.Tensor, [Pv]
        Parameters along the second net index.
    weights : torch.Tensor, [..., nu, nv], optional
        Rational weights (> 0); None = non-rational B-spline. Broadcasts against the batch shape.

    Returns
    -------
    points : torch.Tensor, [..., Pu*Pv, 3]
        S(u_i, v_j) at index ``i * Pv + j`` [m].
    du, dv : torch.Tensor, [..., Pu*Pv, 3]
        Partial derivatives dS/du, dS/dv [m per unit parameter] (quotient rule when rational).

    Notes
    -----
    Dtype/device follow ``control_points``; differentiable w.r.t. control points and weights.
    """
    cp = control_points
    if cp.dim() < 3 or cp.shape[-1] != 3:
        raise HeliotwinError(f"control_points must have shape [..., nu, nv, 3], got {tuple(cp.shape)}")
    nu, nv = cp.shape[-3], cp.shape[-2]
    u, v = _as_param(u, cp), _as_param(v, cp)
    return _evaluate_bases(cp, _basis(nu, degree_u, u), _basis(nv, degree_v, v), weights)


def _evaluate_bases(cp, basis_u, basis_v, weights):
    # evaluate() on given basis matrices ([Pu, nu] and [Pv, nv], values and derivatives).
    nu, nv = cp.shape[-3], cp.shape[-2]
    (bu0, bu1), (bv0, bv1) = basis_u, basis_v
    if weights is None:
        return _tensor_grid(cp, bu0, bu1, bv0, bv1)
    w = weights.to(dtype=cp.dtype, device=cp.device)
    if w.shape[-2:] != (nu, nv):
        raise HeliotwinError(f"weights must have shape [..., {nu}, {nv}], got {tuple(w.shape)}")
    cp, w = torch.broadcast_tensors(cp, w[..., None])
    # Homogeneous coordinates (w P, w): a polynomial B-spline in 4-D, projected back by the quotient rule.
    a, au, av = _tensor_grid(torch.cat((cp * w, w[..., :1]), dim=-1), bu0, bu1, bv0, bv1)
    return _project_homogeneous(a, au, av)


def evaluate_points(control_points: torch.Tensor, degree_u: int, degree_v: int, uv: torch.Tensor,
                    weights: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Evaluate a (batched) NURBS surface and its partial derivatives at scattered parameters.

    Parameters
    ----------
    control_points : torch.Tensor, [..., nu, nv, 3]
        Control net [m].
    degree_u, degree_v : int
    uv : torch.Tensor, [N, 2]
        Parameter pairs (u, v), shared by the whole batch.
    weights : torch.Tensor, [..., nu, nv], optional
        Rational weights; None = non-rational.

    Returns
    -------
    points, du, dv : torch.Tensor, [..., N, 3]
        S(u_k, v_k) [m] and its partial derivatives [m per unit parameter].
    """
    cp = control_points
    if cp.dim() < 3 or cp.shape[-1] != 3:
        raise HeliotwinError(f"control_points must have shape [..., nu, nv, 3], got {tuple(cp.shape)}")
    uv = torch.as_tensor(uv).to(dtype=cp.dtype, device=cp.device)
    if uv.dim() != 2 or uv.shape[-1] != 2:
        raise HeliotwinError(f"uv must have shape [N, 2], got {tuple(uv.shape)}")
    nu, nv = cp.shape[-3], cp.shape[-2]
    bu0, bu1 = _basis(nu, degree_u, uv[:, 0])
    bv0, bv1 = _basis(nv, degree_v, uv[:, 1])

    def scattered(net):
        tv0 = torch.einsum("kb,...abc->...kac", bv0, net)
        tv1 = torch.einsum("kb,...abc->...kac", bv1, net)
        return (torch.einsum("ka,...kac->...kc", bu0, tv0), torch.einsum("ka,...kac->...kc", bu1, tv0),
                torch.einsum("ka,...kac->...kc", bu0, tv1))

    if weights is None:
        return scattered(cp)
    w = weights.to(dtype=cp.dtype, device=cp.device)
    if w.shape[-2:] != (nu, nv):
        raise HeliotwinError(f"weights must have shape [..., {nu}, {nv}], got {tuple(w.shape)}")
    cp, w = torch.broadcast_tensors(cp, w[..., None])
    a, au, av = scattered(torch.cat((cp * w, w[..., :1]), dim=-1))
    return _project_homogeneous(a, au, av)


def _project_homogeneous(a, au, av):
    # Quotient rule: S = A / W, S_u = (A_u - W_u S) / W.
    wsum = a[..., 3:]
    points = a[..., :3] / wsum
    return points, (au[..., :3] - au[..., 3:] * points) / wsum, (av[..., :3] - av[..., 3:] * points) / wsum


def midpoints(samples: int, dtype=None, device=None) -> torch.Tensor:
    """Cell-midpoint parameters ``(i + 0.5) / samples``, i = 0..samples-1 ([samples], dimensionless)."""
    if samples < 1:
        raise HeliotwinError(f"need at least one sample per direction, got {samples}")
    return (torch.arange(samples, dtype=torch.float64) + 0.5).div(samples).to(
        dtype=dtype or torch.get_default_dtype(), device=device)


def surface_samples(control_points: torch.Tensor, degree_u: int, degree_v: int, samples_u: int, samples_v: int,
                    weights: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sample a surface at parameter-cell midpoints with unit normals and area weights.

    The parameter square is cut into ``samples_u x samples_v`` equal cells; each sample sits at a cell
    midpoint ``((i + 0.5) / samples_u, (j + 0.5) / samples_v)``, so no boundary is counted twice and the
    areas are the midpoint rule for ``A = \\int\\int |S_u x S_v| du dv`` (exact for a flat facet with a
    linear parametrisation, e.g. :func:`heliotwin.field.facets.flat_control_points`).

    Parameters
    ----------
    control_points : torch.Tensor, [..., nu, nv, 3]
        Control net [m].
    degree_u, degree_v : int
    samples_u, samples_v : int
        Samples per direction; P = samples_u * samples_v.
    weights : torch.Tensor, [..., nu, nv], optional
        Rational weights.

    Returns
    -------
    points : torch.Tensor, [..., P, 3]
        Surface points [m], u-major.
    normals : torch.Tensor, [..., P, 3]
        Unit normals ``(S_u x S_v) / |S_u x S_v|``; the zero vector where the surface is degenerate
        (the norm is floored at :data:`NORM_EPS` so gradients stay finite).
    areas : torch.Tensor, [..., P]
        Surface area represented by each sample [m²]: ``|S_u x S_v| / (samples_u * samples_v)``.
    """
    cp = control_points
    if cp.dim() < 3 or cp.shape[-1] != 3:
        raise HeliotwinError(f"control_points must have shape [..., nu, nv, 3], got {tuple(cp.shape)}")
    nu, nv = cp.shape[-3], cp.shape[-2]
    points, du, dv = _evaluate_bases(cp, midpoint_basis(nu, degree_u, int(samples_u), cp.dtype, cp.device),
                                     midpoint_basis(nv, degree_v, int(samples_v), cp.dtype, cp.device), weights)
    cross = torch.linalg.cross(du, dv, dim=-1)
    # vector_norm's backward is zero at the zero vector; the clamp keeps the division finite there.
    length = torch.linalg.vector_norm(cross, dim=-1)
    normals = cross / length.clamp_min(NORM_EPS)[..., None]
    areas = length / (samples_u * samples_v)
    return points, normals, areas


# --------------------------------------------------------------------------------------------------
# Fitting and refinement
# --------------------------------------------------------------------------------------------------
def _row_products(bu: torch.Tensor, bv: torch.Tensor) -> torch.Tensor:
    # Tensor-product basis rows: [N, nu] x [N, nv] -> [N, nu * nv] (index a * nv + b, like the net).
    return (bu[:, :, None] * bv[:, None, :]).reshape(bu.shape[0], -1)


def fit(points: torch.Tensor, uv: torch.Tensor, num_control_points: tuple[int, int] = (8, 8),
        degree: tuple[int, int] = (3, 3), normals: torch.Tensor | None = None, normal_weight: float = 0.0,
        ridge: float = 1e-9, chunk_size: int = 16384) -> torch.Tensor:
    """Least-squares fit of a non-rational B-spline surface to scattered points with known parameters.

    Minimises, over the control net C (solved in float64 by the normal equations)::

        sum_k |S(u_k, v_k) - p_k|^2
        + normal_weight * sum_k [(S_u(u_k, v_k) . n_k)^2 + (S_v(u_k, v_k) . n_k)^2]
        + ridge * mean(diag(A^T A)) * |C - c|^2

    The normal terms say "the measured normal is perpendicular to both tangents": they are linear in C,
    so they add slope information (e.g. from deflectometry, where normals are the primary measurement
    and points are integrated from them). Their residual is in metres like the point residual
    (``|S_u| ~`` facet size, so a slope error eps costs about ``facet_size * eps``). The ridge pulls
    unconstrained control points (no data in their support) to the data centroid c; its relative size
    makes it independent of the number of points.

    Parameters
    ----------
    points : torch.Tensor, [..., N, 3]
        Measured points [m]; leading axes (without ``normals``) are independent fits that share ``uv`` (one
        system, many right-hand sides: e.g. every facet of a field resampled on one parameter grid).
    uv : torch.Tensor, [N, 2]
        Their surface parameters in [0, 1]^2.
    num_control_points : (int, int)
        (nu, nv).
    degree : (int, int)
        (p, q).
    normals : torch.Tensor, [N, 3], optional
        Measured unit normals (only the direction matters).
    normal_weight : float
        Weight of the normal terms (dimensionless; 0 ignores the normals).
    ridge : float
        Relative Tikhonov regularisation (>= 0).
    chunk_size : int
        Points per chunk when assembling the normal equations (bounds memory for large scans).

    Returns
    -------
    torch.Tensor, [..., nu, nv, 3]
        Control points [m], dtype/device of ``points``. Differentiable w.r.t. points and normals.
    """
    nu, nv = (int(x) for x in num_control_points)
    p, q = (int(x) for x in degree)
    use_normals = normals is not None and normal_weight > 0
    if points.dim() < 2 or points.shape[-1] != 3 or (use_normals and points.dim() != 2):
        raise HeliotwinError(f"fit: points must have shape [N, 3] (or [..., N, 3] without normals), got "
                             f"{tuple(points.shape)}")
    if uv.shape != (points.shape[-2], 2):
        raise HeliotwinError(f"fit: uv must have shape [{points.shape[-2]}, 2], got {tuple(uv.shape)}")
    if use_normals and normals.shape != points.shape:
        raise HeliotwinError(f"fit: normals must have shape {tuple(points.shape)}, got {tuple(normals.shape)}")
    if normal_weight < 0 or ridge < 0:
        raise HeliotwinError("fit: normal_weight and ridge must be >= 0")
    f64 = dict(dtype=torch.float64, device=points.device)
    pts = points.to(**f64)
    params = uv.to(**f64)
    nrm = normals.to(**f64) if use_normals else None
    centroid = pts.mean(dim=-2, keepdim=True)
    pts = pts - centroid  # the ridge then shrinks towards the centroid, not the frame origin
    m = nu * nv
    ku, kv = clamped_knots(nu, p, **f64), clamped_knots(nv, q, **f64)
    gram = torch.zeros(m, m, **f64)
    rhs = torch.zeros(*pts.shape[:-2], m, 3, **f64)
    slope = torch.zeros(3 * m, 3 * m, **f64) if use_normals else None
    for start in range(0, pts.shape[-2], chunk_size):  # chunks bound memory; not a per-point loop
        sl = slice(start, start + chunk_size)
        bu0, bu1 = basis_functions(params[sl, 0], ku, p, nu)
        bv0, bv1 = basis_functions(params[sl, 1], kv, q, nv)
        rows = _row_products(bu0, bv0)
        gram = gram + rows.T @ rows
        rhs = rhs + rows.T @ pts[..., sl, :]
        if use_normals:
            n = nrm[sl]
            for d in (_row_products(bu1, bv0), _row_products(bu0, bv1)):
                # Row of "S_u . n" over the unknowns C[a, i] (flattened a * 3 + i) is d[a] * n[i].
                w = (d[:, :, None] * n[:, None, :]).reshape(d.shape[0], 3 * m)
                slope = slope + w.T @ w
    scale = gram.diagonal().mean().clamp_min(torch.finfo(torch.float64).tiny)
    eye = torch.eye(m, **f64)
    if not use_normals:
        # one factorisation for every right-hand side: [..., m, 3] as [m, ... * 3]
        flat = rhs.movedim(-2, 0).reshape(m, -1)
        sol = torch.linalg.solve(gram + ridge * scale * eye, flat).reshape(m, *rhs.shape[:-2], 3).movedim(0, -2)
    else:
        eye3 = torch.eye(3, **f64)
        system = torch.kron(gram + ridge * scale * eye, eye3) + normal_weight * slope
        sol = torch.linalg.solve(system, rhs.reshape(3 * m)).reshape(m, 3)
    return (sol + centroid).reshape(*points.shape[:-2], nu, nv, 3).to(dtype=points.dtype)


def refine(control_points: torch.Tensor, degree_u: int, degree_v: int,
           new_num: tuple[int, int]) -> torch.Tensor:
    """A finer control net representing (a least-squares refit of) the same non-rational surface.

    The new net minimises the squared distance between old and new surface on a dense parameter grid
    (including the boundary). When ``new_n - p`` is a multiple of ``n - p`` in a direction, the new
    uniform knot vector contains the old one, the old surface lies in the new spline space and the
    result is exact (knot insertion) up to round-off; otherwise it is the best approximation.

    The map is linear and separable (``C' = T_u C T_v^T``), so it is batched and differentiable.

    Parameters
    ----------
    control_points : torch.Tensor, [..., nu, nv, 3]
        Control net [m].
    degree_u, degree_v : int
        Degrees (kept).
    new_num : (int, int)
        (nu2, nv2) new net size.

    Returns
    -------
    torch.Tensor, [..., nu2, nv2, 3]
        New control points, dtype/device of the input.
    """
    cp = control_points
    nu, nv = cp.shape[-3], cp.shape[-2]
    nu2, nv2 = (int(x) for x in new_num)

    def transfer(n_old: int, n_new: int, degree: int) -> torch.Tensor:
        # Least squares of new basis onto old basis samples: T = pinv(B_new) B_old, [n_new, n_old].
        g = torch.linspace(0.0, 1.0, 4 * max(n_old, n_new) + 1, dtype=torch.float64, device=cp.device)
        b_old, _ = _basis(n_old, degree, g)
        b_new, _ = _basis(n_new, degree, g)
        return torch.linalg.lstsq(b_new, b_old).solution.to(cp.dtype)

    tu, tv = transfer(nu, nu2, degree_u), transfer(nv, nv2, degree_v)
    return torch.einsum("ai,...ijk,bj->...abk", tu, cp, tv)
