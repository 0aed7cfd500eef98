"""NURBS core: basis functions, evaluation, rational forms, fitting, refinement, gradients."""
import math

import pytest
import torch

from heliotwin import nurbs
from heliotwin.errors import HeliotwinError

F64 = torch.float64


# ---------------------------------------------------------------- knots and basis
@pytest.mark.parametrize("n,p", [(4, 2), (7, 3), (5, 1), (3, 2), (6, 0)])
def test_clamped_knots(n, p):
    t = nurbs.clamped_knots(n, p, dtype=F64)
    assert t.shape == (n + p + 1,)
    assert torch.all(t[: p + 1] == 0) and torch.all(t[-(p + 1):] == 1)
    assert torch.all(t[1:] >= t[:-1])
    interior = t[p:n + 1]
    assert torch.allclose(interior[1:] - interior[:-1], torch.full((n - p,), 1.0 / (n - p), dtype=F64))


def test_clamped_knots_rejects_too_few_points():
    with pytest.raises(HeliotwinError):
        nurbs.clamped_knots(2, 2)


@pytest.mark.parametrize("n,p", [(4, 2), (7, 3), (5, 1), (3, 2), (9, 4)])
def test_partition_of_unity_and_nonnegativity(n, p):
    u = torch.linspace(0, 1, 101, dtype=F64)
    n0, n1 = nurbs.basis_functions(u, nurbs.clamped_knots(n, p, dtype=F64), p, n)
    assert n0.shape == (101, n) and n1.shape == (101, n)
    assert torch.allclose(n0.sum(1), torch.ones(101, dtype=F64), atol=1e-14)
    assert torch.all(n0 >= -1e-15)
    # derivatives of a partition of unity sum to zero
    assert torch.allclose(n1.sum(1), torch.zeros(101, dtype=F64), atol=1e-11)


def test_u_equal_one_is_last_span():
    n, p = 6, 3
    t = nurbs.clamped_knots(n, p, dtype=F64)
    n0, n1 = nurbs.basis_functions(torch.tensor([0.0, 1.0], dtype=F64), t, p, n)
    assert torch.equal(n0[0], torch.eye(n, dtype=F64)[0])
    assert torch.equal(n0[1], torch.eye(n, dtype=F64)[-1])
    # end derivative of a clamped spline: p / (t_{n+p} - t_n-ish) = p * (n - p) on the last two functions
    assert n1[1, -1].item() == pytest.approx(p * (n - p))
    assert n1[1, -2].item() == pytest.approx(-p * (n - p))


@pytest.mark.parametrize("n,p", [(5, 2), (8, 3), (4, 1)])
def test_basis_derivative_matches_finite_differences(n, p):
    t = nurbs.clamped_knots(n, p, dtype=F64)
    # avoid knots (derivatives of low degree jump there)
    u = torch.linspace(0.013, 0.987, 37, dtype=F64)
    h = 1e-6
    _, d = nurbs.basis_functions(u, t, p, n)
    fp, _ = nurbs.basis_functions(u + h, t, p, n)
    fm, _ = nurbs.basis_functions(u - h, t, p, n)
    assert torch.allclose(d, (fp - fm) / (2 * h), atol=1e-6)


def test_greville_gives_linear_precision():
    for n, p in [(4, 2), (7, 3), (6, 2), (3, 1)]:
        xi = nurbs.greville_abscissae(n, p, dtype=F64)
        u = torch.linspace(0, 1, 23, dtype=F64)
        n0, n1 = nurbs.basis_functions(u, nurbs.clamped_knots(n, p, dtype=F64), p, n)
        assert torch.allclose(n0 @ xi, u, atol=1e-14)
        assert torch.allclose(n1 @ xi, torch.ones_like(u), atol=1e-12)


def test_uniform_control_points_are_not_linear_for_quadratic():
    # the reason flat facets use Greville abscissae: this must differ
    n, p = 4, 2
    u = torch.tensor([0.25], dtype=F64)
    n0, _ = nurbs.basis_functions(u, nurbs.clamped_knots(n, p, dtype=F64), p, n)
    uniform = torch.linspace(0, 1, n, dtype=F64)
    assert abs((n0 @ uniform).item() - 0.25) > 1e-3


# ---------------------------------------------------------------- evaluation
def _random_net(shape=(2, 5, 4), seed=0, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, 3, generator=g, dtype=dtype)


def test_evaluate_grid_order_and_batch():
    cp = _random_net((3, 5, 4))
    u = torch.tensor([0.1, 0.5, 0.9], dtype=F64)
    v = torch.tensor([0.2, 0.7], dtype=F64)
    pts, du, dv = nurbs.evaluate(cp, 2, 3, u, v)
    assert pts.shape == (3, 6, 3) and du.shape == (3, 6, 3) and dv.shape == (3, 6, 3)
    # u-major index i * Pv + j against scattered evaluation; batch elements independent
    uv = torch.stack(torch.meshgrid(u, v, indexing="ij"), -1).reshape(-1, 2)
    p2, du2, dv2 = nurbs.evaluate_points(cp, 2, 3, uv)
    assert torch.allclose(pts, p2) and torch.allclose(du, du2) and torch.allclose(dv, dv2)
    single, _, _ = nurbs.evaluate(cp[1], 2, 3, u, v)
    assert torch.allclose(single, pts[1])


def test_evaluate_derivatives_match_finite_differences():
    cp = _random_net((5, 6))
    w = 0.5 + torch.rand(5, 6, generator=torch.Generator().manual_seed(3), dtype=F64)
    uv = torch.tensor([[0.3, 0.4], [0.77, 0.12]], dtype=F64)
    h = 1e-6
    for weights in (None, w):
        _, du, dv = nurbs.evaluate_points(cp, 3, 2, uv, weights)
        at = lambda x: nurbs.evaluate_points(cp, 3, 2, x, weights)[0]  # noqa: E731
        ex = torch.tensor([h, 0.0], dtype=F64)
        ey = torch.tensor([0.0, h], dtype=F64)
        fd_u = (at(uv + ex) - at(uv - ex)) / (2 * h)
        fd_v = (at(uv + ey) - at(uv - ey)) / (2 * h)
        assert torch.allclose(du, fd_u, atol=1e-6)
        assert torch.allclose(dv, fd_v, atol=1e-6)


def test_endpoint_interpolation():
    cp = _random_net((5, 4))
    pts, _, _ = nurbs.evaluate(cp, 2, 2, torch.tensor([0.0, 1.0]), torch.tensor([0.0, 1.0]))
    corners = torch.stack((cp[0, 0], cp[0, -1], cp[-1, 0], cp[-1, -1]))
    assert torch.allclose(pts, corners, atol=1e-14)


def test_rational_equal_weights_equal_bspline():
    cp = _random_net((2, 5, 4))
    u = torch.linspace(0, 1, 7, dtype=F64)
    v = torch.linspace(0, 1, 5, dtype=F64)
    plain = nurbs.evaluate(cp, 2, 2, u, v)
    rational = nurbs.evaluate(cp, 2, 2, u, v, weights=torch.full((2, 5, 4), 3.7, dtype=F64))
    for a, b in zip(plain, rational):
        assert torch.allclose(a, b, atol=1e-13)


def test_rational_cylinder_is_exact():
    # Quarter cylinder of radius R: rational quadratic arc in u (weights 1, 1/sqrt2, 1), line in v.
    r = 2.5
    arc = torch.tensor([[r, 0.0], [r, r], [0.0, r]], dtype=F64)
    cp = torch.stack([torch.cat((arc, torch.full((3, 1), z, dtype=F64)), 1) for z in (0.0, 1.0)], dim=1)
    w = torch.tensor([1.0, 1 / math.sqrt(2), 1.0], dtype=F64)[:, None].expand(3, 2)
    u = torch.linspace(0, 1, 17, dtype=F64)
    v = torch.tensor([0.0, 0.4, 1.0], dtype=F64)
    pts, du, dv = nurbs.evaluate(cp, 2, 1, u, v, weights=w)
    radius = pts[:, :2].norm(dim=1)
    assert torch.allclose(radius, torch.full_like(radius, r), atol=1e-13)
    # tangent along u is perpendicular to the radius (quotient rule correct)
    assert torch.allclose((du[:, :2] * pts[:, :2]).sum(1), torch.zeros(len(pts), dtype=F64), atol=1e-12)
    # the non-rational net is not a circle
    pts_poly, _, _ = nurbs.evaluate(cp, 2, 1, u, v)
    assert (pts_poly[:, :2].norm(dim=1) - r).abs().max() > 1e-2


def test_follows_dtype():
    cp = _random_net((4, 4), dtype=torch.float32)
    pts, normals, areas = nurbs.surface_samples(cp, 2, 2, 3, 3)
    assert pts.dtype == normals.dtype == areas.dtype == torch.float32


# ---------------------------------------------------------------- samples, normals, areas
def test_flat_square_samples():
    # control points on a Greville grid -> linear map of [0,1]^2 onto a 2 x 3 m rectangle
    xi_u = nurbs.greville_abscissae(5, 3, dtype=F64)
    xi_v = nurbs.greville_abscissae(4, 2, dtype=F64)
    cp = torch.stack(torch.meshgrid(2.0 * xi_u, 3.0 * xi_v, indexing="ij") + (torch.zeros(5, 4, dtype=F64),), -1)
    pts, normals, areas = nurbs.surface_samples(cp, 3, 2, 8, 6)
    assert areas.sum().item() == pytest.approx(6.0, rel=1e-12)
    assert torch.allclose(areas, torch.full_like(areas, 6.0 / 48))
    assert torch.allclose(normals, torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand_as(normals))
    assert torch.allclose(pts[0], torch.tensor([2.0 / 16, 3.0 / 12, 0.0], dtype=F64))  # first cell midpoint


def test_sphere_cap_area_converges():
    # Fit a spherical cap z = sqrt(R^2 - x^2 - y^2) over a square; area by quadrature of the exact
    # height field vs the NURBS sample areas.
    rad, half = 3.0, 0.5
    g = torch.linspace(-half, half, 41, dtype=F64)
    x, y = torch.meshgrid(g, g, indexing="ij")
    z = torch.sqrt(rad ** 2 - x ** 2 - y ** 2)
    pts = torch.stack((x, y, z), -1).reshape(-1, 3)
    uv = ((torch.stack((x, y), -1).reshape(-1, 2)) + half) / (2 * half)
    cp = nurbs.fit(pts, uv, (10, 10), (3, 3))
    _, normals, areas = nurbs.surface_samples(cp, 3, 3, 64, 64)
    # exact: integral of R / sqrt(R^2 - x^2 - y^2) over the square, by a fine midpoint rule
    m = (torch.arange(2000, dtype=F64) + 0.5) / 2000 * 2 * half - half
    xx, yy = torch.meshgrid(m, m, indexing="ij")
    exact = (rad / torch.sqrt(rad ** 2 - xx ** 2 - yy ** 2)).mean() * (2 * half) ** 2
    # midpoint rule (64 x 64) and fit error, both O(1e-6); a flat-facet area would be off by 0.9 %
    assert areas.sum().item() == pytest.approx(exact.item(), rel=1e-5)
    assert torch.all(normals[..., 2] > 0.9)


# ---------------------------------------------------------------- fitting
def _angle(a, b):
    """Angle between vectors [rad] (atan2 form: accurate for small angles)."""
    return torch.atan2(torch.linalg.cross(a, b, dim=-1).norm(dim=-1), (a * b).sum(-1))


def test_fit_paraboloid_heights_and_normals():
    foc = 5.0
    hx, hy = 0.8, 0.64
    nx, ny = 60, 50
    gx = torch.linspace(-hx, hx, nx, dtype=F64)
    gy = torch.linspace(-hy, hy, ny, dtype=F64)
    x, y = torch.meshgrid(gx, gy, indexing="ij")
    z = (x ** 2 + y ** 2) / (4 * foc)
    pts = torch.stack((x, y, z), -1).reshape(-1, 3)
    uv = torch.stack(((x + hx) / (2 * hx), (y + hy) / (2 * hy)), -1).reshape(-1, 2)
    cp = nurbs.fit(pts, uv, (6, 6), (3, 3))
    # check at points that were not fitted
    tu = torch.rand(333, generator=torch.Generator().manual_seed(1), dtype=F64)
    tv = torch.rand(333, generator=torch.Generator().manual_seed(2), dtype=F64)
    s, su, sv = nurbs.evaluate_points(cp, 3, 3, torch.stack((tu, tv), -1))
    xs, ys = -hx + 2 * hx * tu, -hy + 2 * hy * tv
    assert torch.allclose(s[:, 0], xs, atol=1e-9) and torch.allclose(s[:, 1], ys, atol=1e-9)
    assert (s[:, 2] - (xs ** 2 + ys ** 2) / (4 * foc)).abs().max() < 1e-8
    normal = torch.nn.functional.normalize(torch.linalg.cross(su, sv, dim=-1), dim=-1)
    analytic = torch.stack((-xs / (2 * foc), -ys / (2 * foc), torch.ones_like(xs)), -1)
    assert _angle(normal, analytic).max() < 1e-4


def test_fit_normals_reduce_slope_error_from_noisy_points():
    # Noisy heights (0.2 mm) but exact normals: weighting the normal constraints must improve slopes.
    foc = 8.0
    g = torch.linspace(-0.8, 0.8, 40, dtype=F64)
    x, y = torch.meshgrid(g, g, indexing="ij")
    gen = torch.Generator().manual_seed(7)
    z = (x ** 2 + y ** 2) / (4 * foc) + 2e-4 * torch.randn(x.shape, generator=gen, dtype=F64)
    pts = torch.stack((x, y, z), -1).reshape(-1, 3)
    uv = (torch.stack((x, y), -1).reshape(-1, 2) + 0.8) / 1.6
    n = torch.stack((-x / (2 * foc), -y / (2 * foc), torch.ones_like(x)), -1).reshape(-1, 3)
    n = torch.nn.functional.normalize(n, dim=-1)

    def slope_error(cp):
        _, su, sv = nurbs.evaluate_points(cp, 3, 3, uv)
        return _angle(torch.linalg.cross(su, sv, dim=-1), n).square().mean().sqrt()

    plain = slope_error(nurbs.fit(pts, uv, (12, 12), (3, 3)))
    with_normals = slope_error(nurbs.fit(pts, uv, (12, 12), (3, 3), normals=n, normal_weight=100.0))
    assert with_normals < 0.3 * plain


def test_fit_rejects_bad_shapes():
    with pytest.raises(HeliotwinError):
        nurbs.fit(torch.zeros(10, 2), torch.zeros(10, 2))
    with pytest.raises(HeliotwinError):
        nurbs.fit(torch.zeros(10, 3), torch.zeros(9, 2))
    with pytest.raises(HeliotwinError, match="without normals"):  # batches share uv, not normal terms
        nurbs.fit(torch.zeros(2, 10, 3), torch.zeros(10, 2), normals=torch.zeros(2, 10, 3), normal_weight=1.0)


def test_a_batch_of_fits_on_one_grid_equals_the_fits_one_by_one():
    """Leading axes of ``points`` are independent fits sharing ``uv`` (one system, many right-hand sides): each
    equals its own fit, with and without the ridge."""
    g = torch.Generator().manual_seed(3)
    pts = torch.randn(2, 3, 150, 3, generator=g, dtype=F64)
    uv = torch.rand(150, 2, generator=g, dtype=F64)
    for ridge in (0.0, 1e-6):
        batch = nurbs.fit(pts, uv, (5, 4), (2, 3), ridge=ridge)
        assert batch.shape == (2, 3, 5, 4, 3)
        for i in range(2):
            for j in range(3):
                one = nurbs.fit(pts[i, j], uv, (5, 4), (2, 3), ridge=ridge)
                assert torch.allclose(batch[i, j], one, rtol=0, atol=1e-12)


# ---------------------------------------------------------------- refinement
def test_refine_nested_is_exact():
    cp = _random_net((3, 4, 5))  # batch of 3, degree (2, 3)
    fine = nurbs.refine(cp, 2, 3, (6, 7))  # n - p: 2 -> 4 and 2 -> 4 (nested knot vectors)
    assert fine.shape == (3, 6, 7, 3)
    u = torch.linspace(0, 1, 29, dtype=F64)
    a, adu, _ = nurbs.evaluate(cp, 2, 3, u, u)
    b, bdu, _ = nurbs.evaluate(fine, 2, 3, u, u)
    assert (a - b).abs().max() < 1e-6
    assert (adu - bdu).abs().max() < 1e-5


def test_refine_non_nested_is_close_for_smooth_surface():
    # a paraboloid-like (quadratic) surface is in every degree-2 space: exact even when not nested
    xi = nurbs.greville_abscissae(4, 2, dtype=F64)
    x, y = torch.meshgrid(xi, xi, indexing="ij")
    cp = torch.stack((x, y, torch.zeros_like(x)), -1)
    cp[..., 2] = nurbs.fit(
        torch.stack((x, y, x ** 2 + y ** 2), -1).reshape(-1, 3), torch.stack((x, y), -1).reshape(-1, 2), (4, 4), (2, 2)
    )[..., 2]
    fine = nurbs.refine(cp, 2, 2, (7, 5))
    u = torch.linspace(0, 1, 31, dtype=F64)
    assert (nurbs.evaluate(cp, 2, 2, u, u)[0] - nurbs.evaluate(fine, 2, 2, u, u)[0]).abs().max() < 1e-6


# ---------------------------------------------------------------- gradients
def test_gradcheck_evaluate():
    cp = _random_net((4, 3)).requires_grad_(True)
    w = (0.5 + torch.rand(4, 3, generator=torch.Generator().manual_seed(5), dtype=F64)).requires_grad_(True)
    u = torch.tensor([0.0, 0.3, 1.0], dtype=F64)
    v = torch.tensor([0.25, 0.8], dtype=F64)
    assert torch.autograd.gradcheck(lambda c: nurbs.evaluate(c, 2, 1, u, v), (cp,))
    assert torch.autograd.gradcheck(lambda c, ww: nurbs.evaluate(c, 2, 1, u, v, ww), (cp, w))


def test_gradcheck_surface_samples():
    cp = (_random_net((3, 3)) * 0.1 + torch.stack(torch.meshgrid(
        torch.linspace(0, 1, 3, dtype=F64), torch.linspace(0, 1, 3, dtype=F64), indexing="ij")
        + (torch.zeros(3, 3, dtype=F64),), -1)).requires_grad_(True)
    w = (0.5 + torch.rand(3, 3, generator=torch.Generator().manual_seed(6), dtype=F64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda c, ww: nurbs.surface_samples(c, 2, 2, 2, 3, ww), (cp, w))


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_cached_midpoint_basis_equals_direct_evaluation(dtype):
    """The cached sample bases give the same basis matrices and surface samples as evaluating from scratch."""
    for n, p, s in ((7, 3, 24), (5, 2, 16), (4, 1, 3)):
        b0, b1 = nurbs.midpoint_basis(n, p, s, dtype, torch.device("cpu"))
        u = nurbs.midpoints(s, dtype=dtype)
        d0, d1 = nurbs.basis_functions(u, nurbs.clamped_knots(n, p, dtype=dtype), p, n)
        assert b0.dtype == dtype and torch.equal(b0, d0) and torch.equal(b1, d1)
        assert nurbs.midpoint_basis(n, p, s, dtype, torch.device("cpu"))[0] is b0  # computed once
    cp = (_random_net((2, 7, 5)) * 0.05).to(dtype)
    w = (0.5 + torch.rand(2, 7, 5, generator=torch.Generator().manual_seed(2), dtype=F64)).to(dtype)
    for weights in (None, w):
        pts, du, dv = nurbs.evaluate(cp, 3, 2, nurbs.midpoints(6, dtype=dtype), nurbs.midpoints(4, dtype=dtype),
                                     weights)
        cross = torch.linalg.cross(du, dv, dim=-1)
        p2, n2, a2 = nurbs.surface_samples(cp, 3, 2, 6, 4, weights)
        assert torch.equal(p2, pts)
        assert torch.equal(a2, cross.norm(dim=-1) / 24)
        assert torch.equal(n2, cross / cross.norm(dim=-1, keepdim=True))


def test_no_nan_gradient_for_degenerate_net():
    cp = torch.ones(4, 4, 3, dtype=F64, requires_grad=True)  # all control points coincide: du x dv = 0
    pts, normals, areas = nurbs.surface_samples(cp, 2, 2, 3, 3)
    assert torch.all(areas == 0) and torch.all(normals == 0)
    (pts.sum() + normals.sum() + areas.sum()).backward()
    assert torch.isfinite(cp.grad).all()
    # a collapsed row (u-edge degenerate, like a triangle) too
    cp2 = _random_net((4, 4)).clone()
    cp2[0] = cp2[0, :1]
    cp2.requires_grad_(True)
    _, n2, a2 = nurbs.surface_samples(cp2, 2, 2, 4, 4)
    (n2.sum() + a2.sum()).backward()
    assert torch.isfinite(cp2.grad).all()


def test_fit_is_differentiable():
    g = torch.linspace(0, 1, 6, dtype=F64)
    x, y = torch.meshgrid(g, g, indexing="ij")
    pts = torch.stack((x, y, 0.1 * x * y), -1).reshape(-1, 3).requires_grad_(True)
    uv = torch.stack((x, y), -1).reshape(-1, 2)
    cp = nurbs.fit(pts, uv, (4, 4), (2, 2))
    cp[..., 2].sum().backward()
    assert torch.isfinite(pts.grad).all() and pts.grad[:, 2].abs().sum() > 0
