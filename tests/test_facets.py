"""Facet placement, canting and ideal surfaces (PAINT AA39 layout)."""
import pytest
import torch

from heliotwin import nurbs
from heliotwin.errors import HeliotwinError, InputFileError
from heliotwin.field import facets as fc
from heliotwin.field.plant import Facets, Surfaces

F64 = torch.float64

AA39 = [
    {"translation_vector": [-0.8075, 0.6425, 0.0402], "canting_e": [0.80248, -0.0, -0.0049846],
     "canting_n": [1.957e-05, 0.63749, 0.0031505]},
    {"translation_vector": [0.8075, 0.6425, 0.0402], "canting_e": [0.80248, -0.0, 0.0049846],
     "canting_n": [-1.957e-05, 0.63749, 0.0031505]},
    {"translation_vector": [-0.8075, -0.6425, 0.0402], "canting_e": [0.80248, -0.0, -0.0049846],
     "canting_n": [-1.957e-05, 0.63749, -0.0031505]},
    {"translation_vector": [0.8075, -0.6425, 0.0402], "canting_e": [0.80248, -0.0, 0.0049846],
     "canting_n": [1.957e-05, 0.63749, -0.0031505]},
]


def aa39_facets(h=2) -> Facets:
    t, e, n = fc.facets_from_paint(AA39)
    # heliostat 2 gets a different canting to make the batch non-trivial
    e2 = e.clone()
    e2[:, 2] *= 3.0
    stack = lambda a, b: torch.stack([a, b][:h])  # noqa: E731
    return Facets(stack(t, t), stack(e, e2), stack(n, n))


def test_facets_from_paint():
    t, e, n = fc.facets_from_paint(AA39)
    assert t.shape == e.shape == n.shape == (4, 3) and t.dtype == F64
    assert t[1].tolist() == [0.8075, 0.6425, 0.0402]
    assert n[3].tolist() == [1.957e-05, 0.63749, -0.0031505]


def test_facets_from_paint_errors_name_field():
    bad = [dict(AA39[0]), dict(AA39[1])]
    del bad[1]["canting_n"]
    with pytest.raises(HeliotwinError, match=r"facets\[1\]\.canting_n"):
        fc.facets_from_paint(bad)
    bad = [dict(AA39[0], canting_e=[1.0, 2.0])]
    with pytest.raises(InputFileError, match=r"heliostat-properties\.json.*facets\[0\]\.canting_e"):
        fc.facets_from_paint(bad, path="heliostat-properties.json")
    with pytest.raises(HeliotwinError):
        fc.facets_from_paint([])


def test_facet_normals_point_up_and_are_perpendicular():
    f = aa39_facets()
    nrm = fc.facet_normals(f.canting_e, f.canting_n)
    assert nrm.shape == (2, 4, 3)
    assert torch.allclose(nrm.norm(dim=-1), torch.ones(2, 4, dtype=F64))
    assert torch.all(nrm[..., 2] > 0.99)
    assert torch.allclose((nrm * f.canting_e).sum(-1), torch.zeros(2, 4, dtype=F64), atol=1e-15)
    assert torch.allclose((nrm * f.canting_n).sum(-1), torch.zeros(2, 4, dtype=F64), atol=1e-15)
    # canting: facet 1 (west) tilts its normal towards east (+x), facet 2 (east) towards west
    assert nrm[0, 0, 0] > 0 and nrm[0, 1, 0] < 0


@pytest.mark.parametrize("num,deg", [((4, 4), (2, 2)), ((7, 5), (3, 2)), ((2, 2), (1, 1)), ((6, 6), (3, 3))])
def test_flat_facet_area_normals_centre(num, deg):
    f = aa39_facets()
    surf = fc.ideal_surfaces(f, num, deg)
    assert isinstance(surf, Surfaces) and surf.control_points.shape == (2, 4, *num, 3) and surf.weights is None
    pts, nrm, areas = fc.surface_points(surf, (9, 7))
    assert pts.shape == (2, 4 * 63, 3) and nrm.shape == (2, 4 * 63, 3) and areas.shape == (2, 4 * 63)
    # area of a parallelogram = |2e x 2n|; AA39 facet ~ 1.605 x 1.275 m
    exact = 4.0 * torch.linalg.cross(f.canting_e, f.canting_n, dim=-1).norm(dim=-1)  # [H, F]
    per_facet = areas.reshape(2, 4, 63).sum(-1)
    assert torch.allclose(per_facet, exact, rtol=1e-9, atol=0)
    assert per_facet[0].sum().item() == pytest.approx(4 * 1.605 * 1.275, rel=1e-3)
    expected_n = fc.facet_normals(f.canting_e, f.canting_n)[:, :, None, :].expand(2, 4, 63, 3)
    assert torch.allclose(nrm.reshape(2, 4, 63, 3), expected_n, atol=1e-12)
    # S(0.5, 0.5) is the facet centre; S is linear: S(u, v) = t + (2u-1) e + (2v-1) n
    half = torch.tensor([0.5], dtype=F64)
    centre, _, _ = nurbs.evaluate(surf.control_points, *deg, half, half)
    assert torch.allclose(centre[..., 0, :], f.translation, atol=1e-14)
    uv = torch.tensor([[0.1, 0.9], [0.0, 1.0], [0.73, 0.21]], dtype=F64)
    s, _, _ = nurbs.evaluate_points(surf.control_points, *deg, uv)
    lin = (f.translation[..., None, :] + (2 * uv[:, :1] - 1) * f.canting_e[..., None, :]
           + (2 * uv[:, 1:] - 1) * f.canting_n[..., None, :])
    assert torch.allclose(s, lin, atol=1e-14)


def test_surface_points_order_is_facet_major():
    f = aa39_facets()
    surf = fc.ideal_surfaces(f)
    pts, _, _ = fc.surface_points(surf, (4, 4))
    per_facet = pts.reshape(2, 4, 16, 3)
    # mean of the (symmetric) midpoint samples of each facet is its centre
    assert torch.allclose(per_facet.mean(2), f.translation, atol=1e-14)
    # first sample of facet 0 is the cell next to the (-e, -n) corner
    expect = f.translation[0, 0] - 0.75 * f.canting_e[0, 0] - 0.75 * f.canting_n[0, 0]
    assert torch.allclose(per_facet[0, 0, 0], expect)


def test_displace_along_normal():
    f = aa39_facets()
    cp = fc.flat_control_points(f)
    d = torch.full(cp.shape[:-1], 2e-3, dtype=F64)
    moved = fc.displace_along_normal(cp, d, f)
    # a uniform displacement is a rigid shift of the facet along its normal
    pts0, n0, a0 = fc.surface_points(Surfaces(cp), (5, 5))
    pts1, n1, a1 = fc.surface_points(Surfaces(moved), (5, 5))
    assert torch.allclose(((pts1 - pts0) * n0).sum(-1), torch.full_like(a0, 2e-3), atol=1e-15)
    assert torch.allclose(n1, n0, atol=1e-14) and torch.allclose(a1, a0, rtol=1e-12)
    # a bump in the middle raises the centre, and tilts normals outward
    d = torch.zeros(cp.shape[:-1], dtype=F64)
    d[..., 1:3, 1:3] = 1e-3
    bumped = fc.displace_along_normal(cp, d, f)
    c0, _, _ = nurbs.evaluate(bumped, 2, 2, torch.tensor([0.5]), torch.tensor([0.5]))
    height = ((c0[..., 0, :] - f.translation) * fc.facet_normals(f.canting_e, f.canting_n)).sum(-1)
    assert torch.all(height > 0.5e-3)


def test_gradcheck_displace_along_normal():
    f = aa39_facets(1)
    cp = fc.flat_control_points(f, (3, 3), (2, 2)).requires_grad_(True)
    d = (1e-3 * torch.randn(cp.shape[:-1], generator=torch.Generator().manual_seed(0), dtype=F64)).requires_grad_(True)
    e = f.canting_e.clone().requires_grad_(True)
    n = f.canting_n.clone().requires_grad_(True)
    fn = lambda c, dd, ee, nn: fc.displace_along_normal(c, dd, Facets(f.translation, ee, nn))  # noqa: E731
    assert torch.autograd.gradcheck(fn, (cp, d, e, n))
    # the whole chain displacement -> sampled normals/areas
    chain = lambda dd: fc.surface_points(Surfaces(fc.displace_along_normal(cp.detach(), dd, f)), (2, 2))  # noqa: E731
    assert torch.autograd.gradcheck(chain, (d,))


def test_follows_dtype():
    f = aa39_facets()
    f32 = Facets(f.translation.float(), f.canting_e.float(), f.canting_n.float())
    surf = fc.ideal_surfaces(f32)
    assert surf.control_points.dtype == torch.float32
    pts, nrm, areas = fc.surface_points(surf, (3, 3))
    assert pts.dtype == nrm.dtype == areas.dtype == torch.float32
