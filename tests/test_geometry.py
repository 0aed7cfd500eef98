"""Tests of heliotwin.geometry: identities, degenerate cases and gradients."""
import math

import pytest
import torch

from heliotwin.geometry import (
    angle_between,
    orthonormal_frame,
    ray_cylinder,
    ray_plane,
    reflect,
    rotation_e,
    rotation_n,
    rotation_u,
    safe_normalize,
)

D = torch.float64


def _rand_unit(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(n, 3, generator=g, dtype=D)
    return v / v.norm(dim=-1, keepdim=True)


def test_dot_term_by_term_equals_the_reduction_bit_for_bit():
    """``geometry._dot`` sums the three products term by term where nothing is recorded (faster on a CPU): the
    reduction's numbers to the bit, in both precisions and with broadcasting; with a gradient recorded it is the
    reduction itself (and its gradient the reduction's)."""
    from heliotwin.geometry import _dot

    g = torch.Generator().manual_seed(5)
    for dt in (torch.float32, torch.float64):
        for sa, sb in (((1000, 3), (1000, 3)), ((1000, 3), (3,)), ((50, 20, 3), (50, 1, 3))):
            a, b = torch.randn(*sa, generator=g, dtype=dt), torch.randn(*sb, generator=g, dtype=dt)
            assert torch.equal(_dot(a, b), (a * b).sum(-1))
    a = torch.randn(10, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.randn(10, 3, generator=g, dtype=torch.float64)
    grad, = torch.autograd.grad(_dot(a, b).sum(), a)
    assert torch.equal(grad, b)


def test_reflect_identities():
    d = _rand_unit(100, 1)
    n = _rand_unit(100, 2)
    r = reflect(d, n)
    assert torch.allclose(r.norm(dim=-1), torch.ones(100, dtype=D))
    assert torch.allclose(reflect(r, n), d)
    # normal component flips, tangential component stays
    assert torch.allclose((r * n).sum(-1), -(d * n).sum(-1))
    assert torch.allclose(reflect(d, -n), r)
    down = torch.tensor([0.0, 0.0, -1.0], dtype=D)
    assert torch.allclose(reflect(down, torch.tensor([0.0, 0.0, 1.0], dtype=D)), -down)


def test_safe_normalize_zero_vector_has_finite_grad():
    v = torch.tensor([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]], dtype=D, requires_grad=True)
    u = safe_normalize(v)
    assert torch.allclose(u[0], torch.tensor([0.6, 0.8, 0.0], dtype=D))
    assert torch.equal(u[1], torch.zeros(3, dtype=D))
    u.sum().backward()
    assert torch.isfinite(v.grad).all()


@pytest.mark.parametrize("special", [[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 1.0, 0], [1e-9, 0, -1.0],
                                     [0.6, 0.8, 0.0], [0.6, 0.8, -0.0]])
def test_orthonormal_frame_special_directions(special):
    d = torch.tensor(special, dtype=D)
    d = d / d.norm()
    u, v = orthonormal_frame(d)
    for a in (u, v):
        assert abs(float(a.norm()) - 1) < 1e-12
        assert abs(float(a @ d)) < 1e-12
    assert abs(float(u @ v)) < 1e-12
    assert torch.allclose(torch.linalg.cross(u, v), d, atol=1e-12)  # right-handed


def test_orthonormal_frame_batch_and_grad():
    d = _rand_unit(500, 3)
    u, v = orthonormal_frame(d)
    eye = torch.stack((u, v, d), -1)
    assert torch.allclose(eye.transpose(-1, -2) @ eye, torch.eye(3, dtype=D).expand(500, 3, 3), atol=1e-12)
    dd = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.3, -0.2, 0.0]], dtype=D, requires_grad=True)
    uu, vv = orthonormal_frame(dd)
    (uu.sum() + vv.square().sum()).backward()
    assert torch.isfinite(dd.grad).all()
    x = _rand_unit(4, 4).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: torch.cat(orthonormal_frame(t), -1), (x,))


def test_rotations():
    e, n, u = torch.eye(3, dtype=D)
    h = math.pi / 2
    assert torch.allclose(rotation_e(torch.tensor(h, dtype=D)) @ u, -n)  # conventions: R_E(pi/2) e_z = (0,-1,0)
    assert torch.allclose(rotation_e(torch.tensor(h, dtype=D)) @ n, u)
    assert torch.allclose(rotation_n(torch.tensor(h, dtype=D)) @ u, e)
    assert torch.allclose(rotation_u(torch.tensor(h, dtype=D)) @ e, n)
    ang = torch.linspace(-3, 3, 7, dtype=D)
    for rot in (rotation_e, rotation_n, rotation_u):
        r = rot(ang)
        assert r.shape == (7, 3, 3)
        assert torch.allclose(r @ r.transpose(-1, -2), torch.eye(3, dtype=D).expand(7, 3, 3), atol=1e-12)
        assert torch.allclose(torch.linalg.det(r), torch.ones(7, dtype=D))
        assert torch.autograd.gradcheck(rot, (ang.clone().requires_grad_(True),))
    assert rotation_u(torch.zeros(2, 5)).shape == (2, 5, 3, 3)


def test_ray_plane():
    o = torch.tensor([[0.0, 10.0, 1.0], [0.0, 10.0, 1.0], [0.0, 10.0, 1.0]], dtype=D, requires_grad=True)
    d = torch.tensor([[0.0, -1.0, 0.1], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=D, requires_grad=True)
    c = torch.tensor([0.0, 0.0, 0.0], dtype=D)
    nrm = torch.tensor([0.0, 1.0, 0.0], dtype=D)
    t, hit = ray_plane(o, d, c, nrm)
    assert hit.tolist() == [True, False, False]  # parallel; behind
    assert abs(float(t[0].detach()) - 10.0) < 1e-12
    p = (o[0] + t[0] * d[0]).detach()
    assert torch.allclose(p, torch.tensor([0.0, 0.0, 2.0], dtype=D))
    t.sum().backward()
    assert torch.isfinite(o.grad).all() and torch.isfinite(d.grad).all()
    assert torch.autograd.gradcheck(lambda a, b: ray_plane(a, b, c, nrm)[0], (o[:1].detach().requires_grad_(True),
                                                                             d[:1].detach().requires_grad_(True)))


def test_ray_cylinder_cases():
    axis_point = torch.zeros(3, dtype=D)
    axis = torch.tensor([0.0, 0.0, 1.0], dtype=D)
    R = 2.0
    o = torch.tensor([[10.0, 0.0, 0.0],   # straight at the axis
                      [10.0, 0.0, 0.0],   # moving away
                      [10.0, 5.0, 0.0],   # misses
                      [10.0, 0.0, 0.0],   # parallel to the axis
                      [0.5, 0.0, 0.0],    # inside
                      [10.0, 2.0, 0.0],   # tangent
                      [10.0, 1.0, 3.0]],  # oblique hit
                     dtype=D, requires_grad=True)
    d = torch.tensor([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0],
                      [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [-1.0, 0.0, -0.2]], dtype=D, requires_grad=True)
    t, hit, valid = ray_cylinder(o, d, axis_point, axis, R)
    assert hit.tolist() == [True, False, False, False, False, False, True]
    assert valid.tolist()[:4] == [True, True, False, False]
    assert abs(float(t[0].detach()) - 8.0) < 1e-12
    p = (o[6] + t[6] * d[6]).detach()
    assert abs(float(p[:2].norm()) - R) < 1e-12
    assert float(t[6].detach()) == pytest.approx(10.0 - math.sqrt(3.0))
    (t.sum()).backward()
    assert torch.isfinite(o.grad).all() and torch.isfinite(d.grad).all()
    sel = [0, 6]
    assert torch.autograd.gradcheck(lambda a, b: ray_cylinder(a, b, axis_point, axis, R)[0],
                                    (o[sel].detach().requires_grad_(True), d[sel].detach().requires_grad_(True)))


def test_ray_cylinder_matches_brute_force():
    g = torch.Generator().manual_seed(5)
    o = torch.randn(200, 3, generator=g, dtype=D) * 5 + torch.tensor([20.0, 0.0, 0.0], dtype=D)
    target = torch.randn(200, 3, generator=g, dtype=D)
    d = target - o
    axis = torch.tensor([0.1, 0.2, 1.0], dtype=D)
    axis = axis / axis.norm()
    t, hit, _ = ray_cylinder(o, d, torch.zeros(3, dtype=D), axis, 3.0)
    p = o + t.unsqueeze(-1) * d
    radial = p - (p @ axis).unsqueeze(-1) * axis
    assert hit.sum() > 20
    assert torch.allclose(radial[hit].norm(dim=-1), torch.full((int(hit.sum()),), 3.0, dtype=D), atol=1e-9)
    # the hit is the first crossing: the midpoint between origin and hit is outside
    mid = o + 0.5 * t.unsqueeze(-1) * d
    mrad = (mid - (mid @ axis).unsqueeze(-1) * axis).norm(dim=-1)
    assert (mrad[hit] > 3.0).all()


def test_angle_between_accuracy_and_grads():
    a = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float32)
    tiny = 1e-6
    b = torch.tensor([math.cos(tiny), math.sin(tiny), 0.0], dtype=torch.float32)
    assert abs(float(angle_between(a, b)) - tiny) < 1e-9  # acos would give 0 or 4.9e-4 in float32
    b2 = torch.tensor([-math.cos(tiny), math.sin(tiny), 0.0], dtype=torch.float32)
    assert abs(float(angle_between(a, b2)) - (math.pi - tiny)) < 1e-6
    for other in ([2.0, 0.0, 0.0], [-3.0, 0.0, 0.0]):
        x = torch.tensor([1.0, 0.0, 0.0], dtype=D, requires_grad=True)
        y = torch.tensor(other, dtype=D, requires_grad=True)
        angle_between(x, y).backward()
        assert torch.isfinite(x.grad).all() and torch.isfinite(y.grad).all()
    x = _rand_unit(5, 7).requires_grad_(True)
    y = (_rand_unit(5, 8) * 3).requires_grad_(True)
    assert torch.autograd.gradcheck(angle_between, (x, y))
    ang = angle_between(_rand_unit(50, 9), _rand_unit(50, 10))
    ref = torch.acos((_rand_unit(50, 9) * _rand_unit(50, 10)).sum(-1))
    assert torch.allclose(ang, ref, atol=1e-10)
