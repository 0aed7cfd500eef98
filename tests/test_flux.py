"""Tests of heliotwin.raytrace.flux: FluxImage conventions, crops, PNG IO and image metrics."""
import math
import os

import pytest
import torch

from heliotwin.errors import InputFileError
from heliotwin.field.targets import CylinderTarget, PlanarTarget
from heliotwin.io.images import read_png, to_png
from heliotwin.raytrace.flux import (
    FluxImage,
    centered_crop,
    cross_correlation,
    normalized_l1,
    pixel_centers,
    target_extent,
)

D64 = torch.float64


def _target():
    return PlanarTarget.from_center_normal("t", [1.0, 2.0, 50.0], [0.0, 1.0, 0.0], 8.0, 6.0)


def _gaussian_image(target, rows, cols, cx, cy, sigma):
    ext = target_extent(target, 1)
    x, y = pixel_centers(ext, rows, cols)
    return torch.exp(-((x[0].view(1, -1) - cx) ** 2 + (y[0].view(-1, 1) - cy) ** 2) / (2 * sigma ** 2)).unsqueeze(0)


def test_pixel_convention_and_centroid():
    tgt = _target()
    rows, cols = 6, 8  # 1 m pixels
    b = torch.zeros(1, rows, cols)
    b[0, 0, 0] = 5.0  # top-left pixel
    f = FluxImage(b, tgt, target_extent(tgt, 1))
    assert torch.allclose(f.centroid_local(), torch.tensor([[-3.5, 2.5]]))
    assert float(f.pixel_area[0]) == pytest.approx(1.0)
    assert float(f.total_power()[0]) == pytest.approx(5.0)
    # local x is along `right` (west for a north-facing target): the top-left pixel is east and up
    enu = f.centroid_enu()[0]
    assert enu.dtype == D64
    assert torch.allclose(enu, torch.tensor([1.0 + 3.5, 2.0, 52.5], dtype=D64))
    empty = FluxImage(torch.zeros(1, rows, cols), tgt, target_extent(tgt, 1))
    assert torch.allclose(empty.centroid_local(), torch.zeros(1, 2))


def test_centroid_on_cylinder_maps_back_to_surface():
    cyl = CylinderTarget("c", torch.tensor([0.0, 0.0, 60.0], dtype=D64), torch.tensor([0.0, 1.0, 0.0], dtype=D64),
                         torch.tensor([-1.0, 0.0, 0.0], dtype=D64), torch.tensor([0.0, 0.0, 1.0], dtype=D64),
                         4.0, 10.0, math.pi)
    b = torch.zeros(1, 10, 20)
    b[0, 4:6, 14:16] = 1.0
    f = FluxImage(b, cyl, target_extent(cyl, 1))
    xy = f.centroid_local()
    p = f.centroid_enu()[0]
    assert abs(float(torch.linalg.norm(p[:2] - cyl.axis_point[:2])) - 4.0) < 1e-9
    assert torch.allclose(cyl.to_local(p.unsqueeze(0)), xy.to(D64), atol=1e-5)


def test_centered_crop_identity_and_shift():
    tgt = _target()
    img = _gaussian_image(tgt, 60, 80, 1.0, -0.5, 0.4)
    crop = centered_crop(img, tgt, torch.tensor([[1.0, -0.5]], dtype=D64), size_m=2.0, resolution=64)
    assert crop.shape == (1, 64, 64) and crop.dtype == img.dtype
    f = FluxImage(crop, tgt, torch.tensor([[0.0, 2.0, -1.0, 1.0]], dtype=D64))
    c = f.centroid_local()[0].to(D64)
    assert torch.allclose(c, torch.tensor([1.0, 0.0], dtype=D64), atol=0.02)  # blob in the middle of the crop
    assert float(crop.max()) == pytest.approx(float(img.max()), rel=0.05)
    off = centered_crop(img, tgt, torch.tensor([-2.5, 2.0]), size_m=2.0, resolution=64)
    assert float(off.sum()) < 1e-3 * float(crop.sum())  # the blob is outside this window
    # a crop over the full extent at the same pixel grid is an identity resampling
    sq = PlanarTarget.from_center_normal("s", [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 8.0, 8.0)
    img2 = _gaussian_image(sq, 40, 40, 0.5, 1.0, 1.0)
    ident = centered_crop(img2, sq, torch.zeros(2), size_m=8.0, resolution=40)
    assert torch.allclose(ident, img2, atol=1e-6)
    assert torch.allclose(centered_crop(img2[0], sq, torch.zeros(2), size_m=8.0, resolution=40), img2[0], atol=1e-6)
    # gradients flow to the bitmap and the centre
    im = img2.clone().requires_grad_(True)
    cen = torch.tensor([[0.3, 0.2]], requires_grad=True)
    crop = centered_crop(FluxImage(im, sq, target_extent(sq, 1)), None, cen, size_m=4.0, resolution=16)
    crop.square().sum().backward()
    assert torch.isfinite(im.grad).all() and torch.isfinite(cen.grad).all() and float(cen.grad.abs().sum()) > 0


def test_png_roundtrip_and_atomic(tmp_path):
    b = torch.rand(20, 30) * 700.0
    b[3, 4] = 1000.0
    path = tmp_path / "flux.png"
    to_png(b, path)
    assert sorted(os.listdir(tmp_path)) == ["flux.png"]  # no temp file left behind
    back = read_png(path)
    assert back.shape == (20, 30) and back.dtype == torch.float32
    assert float(back.max()) == 1.0
    assert torch.allclose(back, b / 1000.0, atol=0.5 / 255 + 1e-6)
    to_png(torch.zeros(4, 4), tmp_path / "zero.png")
    assert float(read_png(tmp_path / "zero.png").max()) == 0.0


def test_read_png_errors(tmp_path):
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not a png at all")
    with pytest.raises(InputFileError) as e:
        read_png(bad)
    assert "bad.png" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(InputFileError, match="not found"):
        read_png(tmp_path / "missing.png")


def test_read_png_colour_and_16_bit(tmp_path):
    import numpy as np
    from PIL import Image

    rgb = np.zeros((5, 6, 3), dtype=np.uint8)
    rgb[..., 0] = rgb[..., 1] = rgb[..., 2] = 255
    Image.fromarray(rgb).save(tmp_path / "rgb.png")
    assert torch.allclose(read_png(tmp_path / "rgb.png"), torch.ones(5, 6))
    a16 = (np.arange(30, dtype=np.uint16).reshape(5, 6) * 2000)
    Image.fromarray(a16).save(tmp_path / "g16.png")
    got = read_png(tmp_path / "g16.png")
    assert torch.allclose(got, torch.from_numpy(a16.astype(np.float32) / 65535.0), atol=1e-6)


def test_metrics():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(2, 10, 12, generator=g)
    assert torch.allclose(normalized_l1(a, 3.0 * a), torch.zeros(2), atol=1e-6)
    x = torch.zeros(1, 4, 4)
    y = torch.zeros(1, 4, 4)
    x[0, 0, 0] = 1.0
    y[0, 3, 3] = 5.0
    assert float(normalized_l1(x, y)) == pytest.approx(2.0)
    assert torch.allclose(cross_correlation(a, 2.0 * a + 1.0), torch.ones(2), atol=1e-6)
    assert torch.allclose(cross_correlation(a, -a), -torch.ones(2), atol=1e-6)
    assert float(cross_correlation(a[:1], torch.ones(1, 10, 12))) == 0.0
    b = torch.rand(2, 10, 12, generator=g)
    cc = cross_correlation(a, b)
    assert (cc.abs() < 0.5).all()
