"""Physics tests of the ray tracers (Monte-Carlo, Gaussian-footprint, convolution), the dispatcher and the splatting."""
import math

import pytest
import torch

from heliotwin.errors import HeliotwinError
from heliotwin.field import facets as facet_ops
from heliotwin.field.plant import SunSettings
from heliotwin.field.targets import CylinderTarget, PlanarTarget
from heliotwin.raytrace import (
    FootprintSettings,
    RaySampling,
    normalized_l1,
    projective_splat,
    splat_bilinear,
    trace_gaussian,
    trace_mc,
)
from heliotwin.raytrace.conv import (
    fft_size,
    kernel_spectrum,
    mean_footprint_kernel,
    reflect_to_plane,
    render_centered,
)
from heliotwin.raytrace.flux import target_extent
from heliotwin.raytrace.montecarlo import _rotated_frames, planar_coefficients, prepare_mirror
from heliotwin.scene import INTEGRATORS, trace
from heliotwin.surfaces import losses
from heliotwin.surfaces.learning import LearnableSurface

D64 = torch.float64
DNI, RHO = 900.0, 0.94


def gen(seed=0):
    return torch.Generator().manual_seed(seed)


def square_mirror(center, e1, e2, side, m, normal):
    """m x m points on a flat square mirror of the given side, spanned by unit e1, e2."""
    c = torch.as_tensor(center, dtype=D64)
    e1, e2 = torch.as_tensor(e1, dtype=D64), torch.as_tensor(e2, dtype=D64)
    g = (torch.arange(m, dtype=D64) + 0.5) / m * side - side / 2
    a, b = torch.meshgrid(g, g, indexing="ij")
    pts = c + a.reshape(-1, 1) * e1 + b.reshape(-1, 1) * e2
    nrm = torch.as_tensor(normal, dtype=D64).expand_as(pts).clone()
    areas = torch.full((m * m,), (side / m) ** 2, dtype=D64)
    return pts, nrm, areas


def facing_setup(dist=100.0, side=2.0, m=20, offset=(0.0, 0.0)):
    """North-facing target at the origin (centre z = 10); flat mirror ``dist`` north of it facing south;
    sun due south on the horizon so the reflected rays hit the target perpendicularly.
    ``offset`` = (east, up) shift of the mirror [m]."""
    tgt = PlanarTarget.from_center_normal("t", [0.0, 0.0, 10.0], [0.0, 1.0, 0.0], 8.0, 8.0)
    pts, nrm, areas = square_mirror([offset[0], dist, 10.0 + offset[1]], [1, 0, 0], [0, 0, 1], side, m, [0, -1, 0])
    sun = torch.tensor([0.0, -1.0, 0.0], dtype=D64)
    return pts, nrm, areas, sun, tgt


def oblique_setup(dist=100.0, side=2.0, m=20, el_deg=35.0, az_deg=160.0):
    """A heliostat north-east of a north-facing target, aimed at the target centre (general geometry)."""
    tgt = PlanarTarget.from_center_normal("t", [0.0, 0.0, 50.0], [0.0, 1.0, 0.0], 8.0, 8.0)
    pos = torch.tensor([30.0, dist, 2.0], dtype=D64)
    to_t = (tgt.center - pos) / (tgt.center - pos).norm()
    az, el = math.radians(az_deg), math.radians(el_deg)
    s = torch.tensor([math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)], dtype=D64)
    n = (to_t + s) / (to_t + s).norm()
    e1 = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=D64), n)
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(n, e1)
    pts, nrm, areas = square_mirror(pos, e1, e2, side, m, n)
    return pts, nrm, areas, s, tgt


def spot_moments(flux):
    """Centroid and per-axis variance [m, m^2] of a FluxImage's first bitmap in local coordinates."""
    from heliotwin.raytrace.flux import pixel_centers

    b = flux.bitmap[0].double()
    x, y = pixel_centers(flux.extent[:1], *flux.shape)
    w = b / b.sum()
    cx = float((w.sum(0) * x[0]).sum())
    cy = float((w.sum(1) * y[0]).sum())
    vx = float((w.sum(0) * (x[0] - cx) ** 2).sum())
    vy = float((w.sum(1) * (y[0] - cy) ** 2).sum())
    return cx, cy, vx, vy


# ----------------------------------------------------------------------------------------------------
# radiometry
# ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("method", ["mc", "gaussian"])
def test_power_balance_large_target(method):
    pts, nrm, areas, sun, _ = facing_setup(dist=100.0)
    big = PlanarTarget.from_center_normal("big", [0.0, 0.0, 10.0], [0.0, 1.0, 0.0], 30.0, 30.0)
    optics = SunSettings(sunshape="buie", csr=0.1, slope_error=2e-3, dni=DNI, reflectivity=RHO)
    if method == "mc":
        f = trace_mc(pts, nrm, areas, sun, big, resolution=128, sun=optics, sampling=RaySampling(200), generator=gen())
    else:
        f = trace_gaussian(pts, nrm, areas, sun, big, resolution=128, sun=optics)
    expected = DNI * RHO * float(areas.sum())
    assert float(f.total_power_w[0]) == pytest.approx(expected, rel=1e-6)
    got = float(f.bitmap.double().sum() * f.pixel_area[0])
    assert got == pytest.approx(expected, rel=1e-3)
    assert float(f.intercepted_power_w[0]) == pytest.approx(expected, rel=1e-3)
    assert float(f.total_power()[0]) == pytest.approx(expected, rel=1e-3)


def test_incidence_cosine_scales_power():
    """Tilting the sun by theta about the mirror scales the reflected/intercepted power by cos(theta)."""
    pts, nrm, areas, _, _ = facing_setup(dist=20.0, side=1.0, m=10)
    big = PlanarTarget.from_center_normal("big", [0.0, 0.0, 10.0], [0.0, 1.0, 0.0], 40.0, 40.0)
    optics = SunSettings(sunshape="pillbox", slope_error=0.0, dni=DNI, reflectivity=RHO)
    powers = []
    for theta in (0.0, 0.3, 0.6):
        s = torch.tensor([0.0, -math.cos(theta), math.sin(theta)], dtype=D64)
        f = trace_mc(pts, nrm, areas, s, big, resolution=64, sun=optics, sampling=RaySampling(50), generator=gen())
        powers.append(float(f.intercepted_power_w[0]))
        assert float(f.total_power_w[0]) == pytest.approx(DNI * RHO * float(areas.sum()) * math.cos(theta), rel=1e-6)
    assert powers[1] / powers[0] == pytest.approx(math.cos(0.3), rel=1e-3)
    assert powers[2] / powers[0] == pytest.approx(math.cos(0.6), rel=1e-3)


def test_shaded_points_contribute_nothing_without_nan():
    pts, nrm, areas, sun, tgt = facing_setup(side=1.0, m=6)
    nrm = nrm.clone()
    nrm[:18] = -nrm[:18]  # half of the points face away from the sun
    nrm.requires_grad_(True)
    f = trace_mc(pts, nrm, areas, sun, tgt, resolution=64, sampling=RaySampling(20), generator=gen(),
                 sun=SunSettings(dni=DNI, reflectivity=RHO))
    assert float(f.total_power_w[0].detach()) == pytest.approx(DNI * RHO * float(areas[18:].sum()))
    f.bitmap.sum().backward()
    assert torch.isfinite(nrm.grad).all()
    assert torch.all(nrm.grad[:18] == 0)


# ----------------------------------------------------------------------------------------------------
# optics: sunshape in the ray frame, pillbox spot size
# ----------------------------------------------------------------------------------------------------

def test_pillbox_spot_size_perpendicular_incidence():
    """Uniform solar disc of radius D tan(4.65 mrad) convolved with the mirror square."""
    dist, side, R = 100.0, 0.2, 4.65e-3
    pts, nrm, areas, sun, _ = facing_setup(dist=dist, side=side, m=10)
    tgt = PlanarTarget.from_center_normal("t", [0.0, 0.0, 10.0], [0.0, 1.0, 0.0], 2.0, 2.0)
    optics = SunSettings(sunshape="pillbox", radius=R, slope_error=0.0, dni=DNI, reflectivity=RHO)
    f = trace_mc(pts, nrm, areas, sun, tgt, resolution=200, sun=optics, sampling=RaySampling(20000, stratified=True),
                 generator=gen(1))
    rho = dist * math.tan(R)
    px = 2.0 / 200
    cx, cy, vx, vy = spot_moments(f)
    expected = rho ** 2 / 4 + side ** 2 / 12 + px ** 2 / 6  # disc + mirror square + bilinear tent
    assert abs(cx) < 1e-3 and abs(cy) < 1e-3
    assert vx == pytest.approx(expected, rel=0.01)  # both axes: the scatter is in the ray's own frame
    assert vy == pytest.approx(expected, rel=0.01)
    # hard edge: nothing beyond rho + half-diagonal of the mirror (+ 1 px of splat)
    from heliotwin.raytrace.flux import pixel_centers

    x, y = pixel_centers(f.extent, 200, 200)
    r = torch.sqrt(x[0].view(1, -1) ** 2 + y[0].view(-1, 1) ** 2)
    b = f.bitmap[0].double()
    assert float(b[r > rho + side / math.sqrt(2) + 1.5 * px].sum()) == 0.0
    # plateau: inside rho - half-diagonal the flux is the disc's uniform flux density
    inner = r < rho - side / math.sqrt(2) - 2 * px
    plateau = DNI * RHO * float(areas.sum()) / (math.pi * rho ** 2)
    assert float(b[inner].mean()) == pytest.approx(plateau, rel=0.01)
    # and the flux at r = rho + 2 px beyond a would-be world-axis bug... drops to ~half at the rim
    rim = (r > rho - px) & (r < rho + px)
    assert 0.3 < float(b[rim].mean()) / plateau < 0.7


def test_symmetric_setup_gives_symmetric_bitmap():
    pts, nrm, areas, sun, tgt = facing_setup(dist=50.0, side=2.0, m=20)
    optics = SunSettings(sunshape="gaussian", sigma=3e-3, slope_error=1e-3)
    fa = trace_gaussian(pts, nrm, areas, sun, tgt, resolution=64, sun=optics)
    b = fa.bitmap[0]
    assert torch.allclose(b, b.flip(-1), rtol=1e-4, atol=1e-3 * float(b.max()))
    assert torch.allclose(b, b.flip(-2), rtol=1e-4, atol=1e-3 * float(b.max()))
    fm = trace_mc(pts, nrm, areas, sun, tgt, resolution=64, sun=optics, sampling=RaySampling(4000), generator=gen())
    bm = fm.bitmap[0]
    assert float(normalized_l1(bm, bm.flip(-1))) < 0.03
    assert float(normalized_l1(bm, bm.flip(-2))) < 0.03


def test_image_left_is_east_and_top_is_up():
    optics = SunSettings(sunshape="gaussian", sigma=2e-3, slope_error=0.0)
    pts, nrm, areas, sun, tgt = facing_setup(dist=50.0, side=1.0, m=8, offset=(2.0, 0.0))  # mirror 2 m east
    f = trace_mc(pts, nrm, areas, sun, tgt, resolution=64, sun=optics, sampling=RaySampling(200), generator=gen())
    b = f.bitmap[0]
    assert float(b[:, :32].sum()) > 0.99 * float(b.sum())  # left half = east
    assert float(f.centroid_local()[0, 0]) == pytest.approx(-2.0, abs=0.02)  # local x along right = west
    assert float(f.centroid_enu()[0, 0]) == pytest.approx(2.0, abs=0.02)  # east in ENU
    pts, nrm, areas, sun, tgt = facing_setup(dist=50.0, side=1.0, m=8, offset=(0.0, 2.0))  # mirror 2 m up
    f = trace_mc(pts, nrm, areas, sun, tgt, resolution=64, sun=optics, sampling=RaySampling(200), generator=gen())
    assert float(f.bitmap[0, :32].sum()) > 0.99 * float(f.bitmap.sum())  # top rows = up


# ----------------------------------------------------------------------------------------------------
# integrators agree
# ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("mode", ["window", "convolve"])
def test_gaussian_matches_converged_mc_gaussian(mode):
    pts, nrm, areas, sun, tgt = oblique_setup(dist=100.0, side=2.0, m=16)
    optics = SunSettings(sunshape="gaussian", sigma=2.51e-3, slope_error=1e-3)
    fa = trace_gaussian(pts, nrm, areas, sun, tgt, resolution=128, sun=optics, footprint=FootprintSettings(mode=mode))
    ref = torch.zeros(1, 128, 128)
    for seed in range(4):
        ref += trace_mc(pts, nrm, areas, sun, tgt, resolution=128, sun=optics,
                        sampling=RaySampling(8000, stratified=True),
                        generator=gen(seed)).bitmap
    l1 = float(normalized_l1(fa.bitmap, ref))
    assert l1 <= 0.02
    # sanity: the comparison can fail (a 20 % wider sun is clearly detected)
    wide = trace_gaussian(pts, nrm, areas, sun, tgt, resolution=128, footprint=FootprintSettings(mode=mode),
                          sun=SunSettings(sunshape="gaussian", sigma=3.0e-3, slope_error=1e-3))
    assert float(normalized_l1(wide.bitmap, ref)) > 2 * l1


def test_gaussian_modes_agree_and_auto_choice():
    """One heliostat: the shared-covariance convolution equals the per-point windows (second-order error)."""
    pts, nrm, areas, sun, tgt = oblique_setup(dist=60.0, side=3.0, m=12)
    optics = SunSettings(sunshape="gaussian", sigma=2.51e-3, slope_error=1e-3)
    w = trace_gaussian(pts, nrm, areas, sun, tgt, resolution=96, sun=optics, footprint=FootprintSettings(mode="window"))
    c = trace_gaussian(pts, nrm, areas, sun, tgt, resolution=96, sun=optics,
                       footprint=FootprintSettings(mode="convolve"))
    a = trace_gaussian(pts, nrm, areas, sun, tgt, resolution=96, sun=optics)
    assert float(normalized_l1(w.bitmap, c.bitmap)) < 0.01
    assert torch.equal(a.bitmap, c.bitmap)
    assert float(c.intercepted_power_w[0]) == pytest.approx(float(w.intercepted_power_w[0]), rel=1e-4)
    # two very different heliostats in one sample: auto falls back to per-point windows
    far = torch.cat((pts, pts * torch.tensor([1.0, 4.0, 1.0], dtype=D64)))
    nn = torch.cat((nrm, nrm))
    aa = torch.cat((areas, areas))
    a2 = trace_gaussian(far, nn, aa, sun, tgt, resolution=96, sun=optics)
    w2 = trace_gaussian(far, nn, aa, sun, tgt, resolution=96, sun=optics, footprint=FootprintSettings(mode="window"))
    assert torch.equal(a2.bitmap, w2.bitmap)


def test_projective_and_generic_paths_agree():
    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=10)
    optics = SunSettings(sunshape="buie")
    a = trace_mc(pts, nrm, areas, sun, tgt, resolution=96, sun=optics, sampling=RaySampling(300), generator=gen(3))
    b = trace_mc(pts, nrm, areas, sun, tgt, resolution=96, sun=optics, sampling=RaySampling(300, method="generic"),
                 generator=gen(3))
    assert torch.allclose(a.bitmap, b.bitmap, rtol=1e-3, atol=1e-4 * float(a.bitmap.max()))


def test_determinism():
    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=10)
    a = trace_mc(pts, nrm, areas, sun, tgt, resolution=64, sampling=RaySampling(100), generator=gen(11))
    b = trace_mc(pts, nrm, areas, sun, tgt, resolution=64, sampling=RaySampling(100), generator=gen(11))
    c = trace_mc(pts, nrm, areas, sun, tgt, resolution=64, sampling=RaySampling(100), generator=gen(12))
    assert torch.equal(a.bitmap, b.bitmap)
    assert not torch.equal(a.bitmap, c.bitmap)


def test_chunking_and_batches():
    """Chunks spanning several samples give the same bitmaps as one chunk; B can be large."""
    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=6)
    pts = torch.stack([pts + torch.tensor([0.0, 0.0, 0.05 * i], dtype=D64) for i in range(7)])
    kw = dict(resolution=(40, 48))
    a = trace_mc(pts, nrm, areas, sun, tgt, generator=gen(2), sampling=RaySampling(30, max_rays_per_chunk=10 ** 7),
                 **kw)
    b = trace_mc(pts, nrm, areas, sun, tgt, generator=gen(2), sampling=RaySampling(30, max_rays_per_chunk=500), **kw)
    c = trace_mc(pts, nrm, areas, sun, tgt, generator=gen(2),
                 sampling=RaySampling(30, max_rays_per_chunk=500, workers=2), **kw)
    assert a.bitmap.shape == (7, 40, 48)
    assert torch.allclose(a.bitmap, b.bitmap, rtol=1e-5, atol=1e-5 * float(a.bitmap.max()))
    assert torch.allclose(a.bitmap, c.bitmap, rtol=1e-5, atol=1e-5 * float(a.bitmap.max()))
    many = pts[:1].expand(300, -1, -1)
    f = trace_mc(many, nrm, areas, sun.expand(300, 3), tgt, generator=gen(),
                 sampling=RaySampling(30, max_rays_per_chunk=4096), **kw)
    assert f.bitmap.shape == (300, 40, 48)
    assert torch.allclose(f.intercepted_power_w, f.intercepted_power_w[0].expand(300), rtol=0.05)


def test_batched_planar_target():
    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=8)
    tgt2 = PlanarTarget.from_center_normal("u", [0.5, 0.0, 50.5], [0.1, 1.0, 0.0], 6.0, 7.0)
    both = PlanarTarget("b", torch.stack((tgt.center, tgt2.center)), torch.stack((tgt.normal, tgt2.normal)),
                        torch.stack((tgt.right, tgt2.right)), torch.stack((tgt.up, tgt2.up)),
                        torch.tensor([8.0, 6.0], dtype=D64), torch.tensor([8.0, 7.0], dtype=D64))
    p2 = pts.expand(2, -1, -1)
    fb = trace_gaussian(p2, nrm, areas, sun, both, resolution=48)
    for i, t in enumerate((tgt, tgt2)):
        fi = trace_gaussian(pts, nrm, areas, sun, t, resolution=48)
        assert torch.allclose(fb.bitmap[i], fi.bitmap[0], rtol=1e-4, atol=1e-4 * float(fi.bitmap.max()))
        assert torch.allclose(fb.centroid_enu()[i], fi.centroid_enu()[0], atol=1e-4)
    fm = trace_mc(p2, nrm, areas, sun, both, resolution=48, sampling=RaySampling(500), generator=gen())
    assert torch.allclose(fm.centroid_local(), fb.centroid_local(), atol=0.02)


def test_window_matches_full_image():
    """Tracing into a pixel-aligned window reproduces the full image's pixels there (same rays)."""
    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=8)
    full = trace_mc(pts, nrm, areas, sun, tgt, resolution=80, sampling=RaySampling(200), generator=gen(4))
    px = 8.0 / 80
    win = (-4.0 + 20 * px, 4.0 - 60 * px, 40 * px, 40 * px)  # columns 20..59, rows 20..59
    part = trace_mc(pts, nrm, areas, sun, tgt, resolution=40, sampling=RaySampling(200), generator=gen(4), window=win)
    assert torch.allclose(part.extent[0], torch.tensor([-2.0, 2.0, -2.0, 2.0], dtype=D64))
    inner_full = full.bitmap[0, 21:59, 21:59]
    inner_part = part.bitmap[0, 1:39, 1:39]
    assert torch.allclose(inner_part, inner_full, rtol=1e-3, atol=1e-3 * float(full.bitmap.max()))
    # a window larger than the target: flux only on the target
    big = trace_mc(pts, nrm, areas, sun, tgt, resolution=120, sampling=RaySampling(200), generator=gen(4),
                   window=(-6.0, -6.0, 12.0, 12.0))
    assert float(big.bitmap[0, :, :19].sum()) == 0.0 and float(big.bitmap[0, :19].sum()) == 0.0
    assert float(big.intercepted_power_w[0]) == pytest.approx(float(full.intercepted_power_w[0]), rel=1e-3)
    gauss = SunSettings(sunshape="gaussian", sigma=2.5e-3)
    an = trace_gaussian(pts, nrm, areas, sun, tgt, resolution=40, window=win, sun=gauss)
    mc = trace_mc(pts, nrm, areas, sun, tgt, resolution=40, sampling=RaySampling(5000, stratified=True),
                  generator=gen(4), window=win, sun=gauss)
    assert float(normalized_l1(an.bitmap, mc.bitmap)) < 0.03


def test_hard_splat_conserves_power():
    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=10)
    a = trace_mc(pts, nrm, areas, sun, tgt, resolution=64, sampling=RaySampling(300), generator=gen(5))
    h = trace_mc(pts, nrm, areas, sun, tgt, resolution=64, sampling=RaySampling(300, splat="hard"), generator=gen(5))
    assert float(h.intercepted_power_w[0]) == pytest.approx(float(a.intercepted_power_w[0]), rel=1e-4)
    assert torch.allclose(h.centroid_local(), a.centroid_local(), atol=2e-3)
    assert not h.bitmap.requires_grad


# ----------------------------------------------------------------------------------------------------
# cylinder receiver
# ----------------------------------------------------------------------------------------------------

def _cylinder():
    return CylinderTarget("rcv", torch.tensor([0.0, 0.0, 60.0], dtype=D64), torch.tensor([0.0, 1.0, 0.0], dtype=D64),
                          torch.tensor([-1.0, 0.0, 0.0], dtype=D64), torch.tensor([0.0, 0.0, 1.0], dtype=D64),
                          4.0, 12.0, math.pi)


def test_cylinder_power_and_centroid():
    cyl = _cylinder()
    pts, nrm, areas, sun, _ = oblique_setup(side=2.0, m=10)
    # re-aim the mirror at the apex
    pos = pts.mean(0)
    to_t = (cyl.center - pos) / (cyl.center - pos).norm()
    n = (to_t + sun) / (to_t + sun).norm()
    nrm = n.expand_as(pts)
    optics = SunSettings(sunshape="gaussian", sigma=2.5e-3, slope_error=1e-3, dni=DNI, reflectivity=RHO)
    f = trace_mc(pts, nrm, areas, sun, cyl, resolution=(96, 64), sun=optics,
                 sampling=RaySampling(2000, stratified=True), generator=gen())
    expected = DNI * RHO * float(areas.sum()) * float(nrm[0] @ sun)
    assert float(f.intercepted_power_w[0]) == pytest.approx(expected, rel=1e-3)
    assert float((f.centroid_enu()[0] - cyl.center).norm()) < 0.05
    fa = trace_gaussian(pts, nrm, areas, sun, cyl, resolution=(96, 64), sun=optics)
    assert float(fa.intercepted_power_w[0]) == pytest.approx(expected, rel=1e-3)
    assert float(normalized_l1(fa.bitmap, f.bitmap)) < 0.04


# ----------------------------------------------------------------------------------------------------
# gradients
# ----------------------------------------------------------------------------------------------------

def test_gradcheck_splat_bilinear():
    g = gen(6)
    px = (torch.rand(2, 15, generator=g, dtype=D64) * 8.0 - 1.0).requires_grad_(True)  # some off the bitmap
    py = (torch.rand(2, 15, generator=g, dtype=D64) * 7.0 - 1.0).requires_grad_(True)
    w = torch.rand(2, 15, generator=g, dtype=D64).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b, c: splat_bilinear(a, b, c, 6, 7), (px, py, w))
    out = splat_bilinear(px, py, w, 6, 7)
    inside = (px >= -0.5) & (px <= 6.5) & (py >= -0.5) & (py <= 5.5)
    assert torch.allclose(out.sum((-2, -1)), (w * inside).sum(-1))


def test_gradcheck_projective_splat():
    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=3)
    sun_s = SunSettings()
    mirror = prepare_mirror(pts, nrm, areas, sun, sun_s, D64)
    u, v = _rotated_frames(mirror.reflected, gen(1))
    coef, _ = planar_coefficients(mirror.points, mirror.reflected, u, v, tgt, target_extent(tgt, 1), 12, 10)
    coef = coef.reshape(9, 3, 3).detach().clone().requires_grad_(True)
    g = gen(2)
    pattern = torch.cat((torch.ones(1, 6, dtype=D64), torch.randn(2, 6, generator=g, dtype=D64) * 0.01))
    w = torch.rand(9, generator=g, dtype=D64).requires_grad_(True)
    for workers in (1, 2):
        assert torch.autograd.gradcheck(
            lambda c, ww: projective_splat(c, ww, pattern, 12, 10, 1, 9, max_rays_per_chunk=20, workers=workers),
            (coef, w))


def test_splat_scratch_reuse_keeps_calls_apart():
    """The splats keep their CPU buffers between calls (speed must not hang on the allocator's state): two
    forwards alive at once, then one backward, give each call's own image and gradients, as fresh calls do
    after :func:`release_scratch`."""
    from heliotwin.raytrace.splat import release_scratch

    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=3)
    mirror = prepare_mirror(pts, nrm, areas, sun, SunSettings(), D64)
    u, v = _rotated_frames(mirror.reflected, gen(1))
    coef0, _ = planar_coefficients(mirror.points, mirror.reflected, u, v, tgt, target_extent(tgt, 1), 12, 10)
    g = gen(3)
    pattern = torch.cat((torch.ones(1, 40, dtype=D64), torch.randn(2, 40, generator=g, dtype=D64) * 0.02))
    weights = (torch.rand(9, generator=g, dtype=D64), torch.rand(9, generator=g, dtype=D64))
    coefs = (coef0.reshape(9, 3, 3), coef0.reshape(9, 3, 3) * (1 + 0.05 * torch.rand(9, 3, 3, generator=g)))
    probe = torch.rand(12, 10, generator=g, dtype=D64)

    def leaf(t):
        return t.detach().clone().requires_grad_(True)

    alone = []
    for c, w in zip(coefs, weights):
        release_scratch()
        c, w = leaf(c), leaf(w)
        img = projective_splat(c, w, pattern, 12, 10, 1, 9, max_rays_per_chunk=64)
        (img * probe).sum().backward()
        alone.append((img.detach(), c.grad, w.grad))
    leaves = [(leaf(c), leaf(w)) for c, w in zip(coefs, weights)]
    imgs = [projective_splat(c, w, pattern, 12, 10, 1, 9, max_rays_per_chunk=64) for c, w in leaves]
    sum((img * probe).sum() for img in imgs).backward()
    for img, (c, w), (img0, gc0, gw0) in zip(imgs, leaves, alone):
        assert torch.equal(img.detach(), img0)
        assert torch.allclose(c.grad, gc0, rtol=1e-12, atol=1e-12)
        assert torch.allclose(w.grad, gw0, rtol=1e-12, atol=1e-12)
    assert not torch.equal(alone[0][0], alone[1][0])  # the two calls really differ


def test_gradcheck_trace_mc_end_to_end():
    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=2)
    p = pts.clone().requires_grad_(True)
    n = nrm.clone().requires_grad_(True)

    def fn(pp, nn):
        return trace_mc(pp, nn, areas, sun, tgt, resolution=(10, 12), sampling=RaySampling(5), generator=gen(3),
                        dtype=D64).bitmap

    assert torch.autograd.gradcheck(fn, (p, n), atol=1e-5)


@pytest.mark.parametrize("mode", ["window", "convolve"])
def test_gradcheck_gaussian(mode):
    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=2, dist=30.0)
    p = pts.clone().requires_grad_(True)
    n = nrm.clone().requires_grad_(True)
    s = sun.clone().requires_grad_(True)

    def fn(pp, nn, ss):
        return trace_gaussian(pp, nn, areas, ss, tgt, resolution=(12, 10), dtype=D64,
                              footprint=FootprintSettings(mode=mode),
                              sun=SunSettings(sunshape="gaussian", sigma=4e-3)).bitmap

    assert torch.autograd.gradcheck(fn, (p, n, s), atol=1e-5, fast_mode=(mode == "convolve"))


def test_no_nan_gradients_in_degenerate_cases():
    tgt = PlanarTarget.from_center_normal("t", [0.0, 0.0, 10.0], [0.0, 1.0, 0.0], 8.0, 8.0)
    pts = torch.tensor([[0.0, 50.0, 10.0],    # normal incidence, straight at the target
                        [0.0, 50.0, 10.0],    # normal exactly +z, sun at zenith: ray goes straight up (parallel)
                        [0.0, 50.0, 10.0],    # normal exactly -z: shaded
                        [0.0, 50.0, 10.0],    # grazing: reflected ray parallel to the target plane
                        [40.0, 50.0, 10.0],   # off the target
                        [0.0, -5.0, 10.0]],   # behind the target
                       dtype=D64, requires_grad=True)
    sun = torch.tensor([0.0, 0.0, 1.0], dtype=D64)
    s2 = math.sqrt(0.5)
    nrm = torch.tensor([[0.0, -s2, s2], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [s2, 0.0, s2], [0.0, -s2, s2],
                        [0.0, s2, s2]], dtype=D64, requires_grad=True)
    areas = torch.ones(6, dtype=D64)
    for fn in (lambda: trace_mc(pts, nrm, areas, sun, tgt, resolution=32, sampling=RaySampling(50), generator=gen()),
               lambda: trace_mc(pts, nrm, areas, sun, tgt, resolution=32, sampling=RaySampling(50, method="generic"),
                                generator=gen()),
               lambda: trace_gaussian(pts, nrm, areas, sun, tgt, resolution=32,
                                      footprint=FootprintSettings(mode="window")),
               lambda: trace_gaussian(pts, nrm, areas, sun, tgt, resolution=32,
                                      footprint=FootprintSettings(mode="convolve"))):
        pts.grad = nrm.grad = None
        f = fn()
        assert torch.isfinite(f.bitmap).all()
        (f.bitmap * torch.linspace(0, 1, 32)).sum().backward()
        assert torch.isfinite(pts.grad).all() and torch.isfinite(nrm.grad).all()
        assert float(nrm.grad[0].abs().sum()) > 0  # the valid point does get a gradient


# ----------------------------------------------------------------------------------------------------
# conv integrator (exact-sunshape convolution) and the dispatcher
# ----------------------------------------------------------------------------------------------------

def _conv_world_samples(facets, obs, i, samples=(24, 24)):
    surf = LearnableSurface(facets, (5, 5), (2, 2)).surfaces()
    pts, nrm, area = facet_ops.surface_points(surf, samples)
    rot = obs.rotation[i]
    pw = obs.concentrator[i] + pts[0] @ rot.T
    # Fixed mirror samples (no autograd graph back to the surface's parameters).
    return pw.detach().float()[None], (nrm[0] @ rot.T).detach().float()[None], area.detach().float()


def test_conv_matches_trace_gaussian_for_gaussian_sun():
    from helpers.surfaces import small_scene

    facets, obs, target = small_scene(distance=30.0, n=2)
    for sun in (SunSettings(sunshape="gaussian", sigma=2.5e-3, slope_error=0.0),
                SunSettings(sunshape="gaussian", sigma=2.0e-3, slope_error=1.0e-3)):
        for i in range(2):
            pw, nw, area = _conv_world_samples(facets, obs, i)
            sund = obs.sun[i:i + 1].float()
            res = render_centered(pw, nw, area, sund, target, sun, size_m=4.0, resolution=32)
            c = res.center[0].detach().double()
            window = (float(c[0]) - 2.0, float(c[1]) - 2.0, 4.0, 4.0)
            ref = trace_gaussian(pw, nw, area, sund, target, resolution=(32, 32), sun=sun, window=window,
                                 clip_to_target=False).bitmap
            l1 = float(losses.l1(res.image, ref.to(res.image)).max())
            print(f"L1(conv, trace_gaussian) = {l1:.4f}")
            assert l1 < 0.03, (sun, i, l1)
            # Same absolute flux scale (power conserved in the window by both).
            ratio = float(res.image.sum() / ref.sum())
            assert abs(ratio - 1.0) < 0.02, ratio


def test_gradcheck_conv():
    """render_centered w.r.t. mirror points, normals and areas (float64; kernel held fixed as in training)."""
    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=3, dist=30.0)
    optics = SunSettings(sunshape="buie", csr=0.05, slope_error=1e-3)
    p, n, a = pts[None].clone(), nrm[None].clone(), areas[None].clone()
    s = sun[None]
    kern = mean_footprint_kernel(p, n, a, s, tgt, optics, 1.0 / 8, 16)
    center = render_centered(p, n, a, s, tgt, optics, size_m=1.0, resolution=8, kernel=kern).center.detach()

    def fn(pp, nn, aa):
        return render_centered(pp, nn, aa, s, tgt, optics, size_m=1.0, resolution=8, kernel=kern, center=center).image

    inputs = tuple(t.requires_grad_(True) for t in (p, n, a))
    assert torch.autograd.gradcheck(fn, inputs, atol=1e-5, fast_mode=True)
    # ... and with the window following the predicted centroid (the PAINT-style default).
    assert torch.autograd.gradcheck(
        lambda pp: render_centered(pp, n.detach(), a.detach(), s, tgt, optics, size_m=1.0, resolution=8,
                                   kernel=kern).image, (p,), atol=1e-5, fast_mode=True)


@pytest.mark.parametrize("resolution", [8, 14, 64])
def test_conv_window_fft_is_alias_free(resolution):
    """The window from the 5R/2 FFT (fft_size) equals the one of the full linear convolution (4R FFT): for
    render_centered (with its kernel or a precomputed spectrum), and for a splat and kernel filled to their far
    corners (the largest aliasing index), where the alias-free bound n >= 5R/2 is tight."""
    res, big = resolution, 2 * resolution
    n_small = fft_size(res)
    assert n_small == 5 * res // 2
    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=6, dist=30.0)
    optics = SunSettings(sunshape="buie", csr=0.05, slope_error=2e-3)
    size_m, pix = 2.0, 2.0 / res
    p, n, a, s = pts[None], nrm[None], areas[None], sun[None]
    kern = mean_footprint_kernel(p, n, a, s, tgt, optics, pix, big)
    out = render_centered(p, n, a, s, tgt, optics, size_m=size_m, resolution=res, kernel=kern)
    cached = render_centered(p, n, a, s, tgt, optics, size_m=size_m, resolution=res,
                             spectrum=kernel_spectrum(kern, res))
    assert torch.equal(out.image, cached.image)
    # The same splat (render_centered's grid: twice the window, on the predicted centroid), convolved at 4R.
    hits, _, _ = reflect_to_plane(p, n, s, tgt)
    w = a * (n * s.unsqueeze(1)).sum(-1).clamp_min(0.0)
    c = out.center.detach()
    img = splat_bilinear((hits[..., 0] - (c[:, :1] - size_m)) / pix - 0.5,
                         ((c[:, 1:] + size_m) - hits[..., 1]) / pix - 0.5, w, big, big)
    rows = torch.arange(big // 2 + res // 2, big // 2 + res // 2 + res)

    def conv(splat, kernel, size):
        # The window of the circular convolution on a size x size grid (index q mod size).
        out = torch.fft.irfft2(torch.fft.rfft2(splat, s=(size, size)) * torch.fft.rfft2(kernel, s=(size, size)),
                               s=(size, size))
        return out[:, rows % size][:, :, rows % size]

    ref = conv(img, kern, 2 * big).clamp_min(0.0) * (optics.dni * optics.reflectivity / pix ** 2)
    assert torch.allclose(out.image, ref, rtol=0, atol=1e-12 * float(ref.max()))
    # Power up to the far corners of splat and kernel: still exact at 5R/2, aliased one pixel below.
    full_img = img + torch.rand(img.shape, generator=gen(4), dtype=D64)
    full_kern = kern + torch.rand(kern.shape, generator=gen(3), dtype=D64)
    full = conv(full_img, full_kern, 2 * big)
    tol = 1e-12 * float(full.abs().max())
    assert torch.allclose(conv(full_img, full_kern, n_small), full, rtol=0, atol=tol)
    assert not torch.allclose(conv(full_img, full_kern, n_small - 1), full, rtol=0, atol=1e-6)


def test_angular_density_blur_equals_separable_conv2d():
    """The slope-error blur of the tabulated density (banded matmuls, bounded memory) is the zero-padded
    separable convolution it replaces (conv2d), to float64 precision."""
    import torch.nn.functional as F

    from heliotwin import sunshape as sunshape_ops
    from heliotwin.raytrace.conv import _ANG_STEP, angular_density

    sun = SunSettings(sunshape="pillbox", radius=4.65e-3, slope_error=1.5e-3)
    dens, half = angular_density(sun)
    n = int(round(half / _ANG_STEP))
    ax = torch.arange(-n, n + 1, dtype=D64) * _ANG_STEP
    a, b = torch.meshgrid(ax, ax, indexing="ij")
    sub = (torch.arange(3, dtype=D64) - 1.0) / 3.0 * _ANG_STEP
    raw = sum(sunshape_ops.radial_profile("pillbox", torch.sqrt((a + da) ** 2 + (b + db) ** 2), sigma=sun.sigma,
                                          radius=sun.radius, csr=sun.csr) for da in sub for db in sub)
    spread = 2.0 * sun.slope_error
    k = int(math.ceil(4.5 * spread / _ANG_STEP))
    g = torch.exp(-0.5 * ((torch.arange(-k, k + 1, dtype=D64) * _ANG_STEP) / spread) ** 2)
    g = g / g.sum()
    ref = F.conv2d(F.conv2d(raw[None, None], g.reshape(1, 1, -1, 1), padding=(k, 0)), g.reshape(1, 1, 1, -1),
                   padding=(0, k))[0, 0]
    ref = ref / (ref.sum() * _ANG_STEP ** 2)
    assert dens.shape == ref.shape
    assert torch.allclose(dens, ref, rtol=0, atol=1e-13 * float(ref.max()))


def test_dispatcher_names_and_errors():
    pts, nrm, areas, sun, tgt = oblique_setup(side=2.0, m=6, dist=50.0)
    optics = SunSettings(sunshape="gaussian", sigma=2.5e-3, slope_error=1e-3)
    win = (-3.0, -3.0, 6.0, 6.0)
    assert INTEGRATORS == ("mc", "gaussian", "conv")
    images = {}
    for name in INTEGRATORS:
        f = trace(pts, nrm, areas, sun, tgt, integrator=name, resolution=32, sun=optics, window=win,
                  generator=gen(), rays_per_point=400, clip_to_target=False) if name != "conv" else \
            trace(pts, nrm, areas, sun, tgt, integrator=name, resolution=32, sun=optics, window=win)
        assert f.method == name and f.bitmap.shape == (1, 32, 32)
        images[name] = f
    # Same reflected power (DNI rho sum A cos) from every integrator.
    for name in ("mc", "conv"):
        assert float(images[name].total_power_w[0]) == pytest.approx(float(images["gaussian"].total_power_w[0]),
                                                                     rel=1e-5)
    images = {k: f.bitmap for k, f in images.items()}
    # The three integrators estimate the same image (Gaussian sun; MC with its noise).
    assert float(normalized_l1(images["conv"], images["gaussian"])[0]) < 0.05
    assert float(normalized_l1(images["mc"], images["gaussian"])[0]) < 0.1
    for bad in ("analytic", "nope"):
        with pytest.raises(HeliotwinError) as exc:
            trace(pts, nrm, areas, sun, tgt, integrator=bad)
        assert len(str(exc.value).splitlines()) == 1 and "gaussian" in str(exc.value)
    with pytest.raises(HeliotwinError, match="square"):
        trace(pts, nrm, areas, sun, tgt, integrator="conv", resolution=(32, 16))


def test_settings_refuse_bad_options_at_construction():
    """A bad ray or footprint option is named when the settings are built, before any tracing."""
    for bad, match in ((dict(rays_per_point=0), "rays_per_point"), (dict(splat="nearest"), "splat"),
                       (dict(method="fast"), "method")):
        with pytest.raises(HeliotwinError, match=match):
            RaySampling(**bad)
    with pytest.raises(HeliotwinError, match="mode"):
        FootprintSettings(mode="exact")
    assert RaySampling().rays_per_point == 100 and FootprintSettings().smoothing == pytest.approx(1.0 / 6.0)
