"""Losses, regularisers and the gradient of the rendered loss w.r.t. control points."""
from __future__ import annotations

import torch
from helpers.surfaces import small_scene

from heliotwin.field.plant import SunSettings
from heliotwin.surfaces import losses
from heliotwin.surfaces.imaging import predict_images
from heliotwin.surfaces.learning import LearnableSurface


def test_losses_scale_invariant_and_zero_at_match():
    g = torch.Generator().manual_seed(1)
    a = torch.rand(2, 16, 16, generator=g)
    b = torch.rand(2, 16, 16, generator=g)
    for fn in (losses.l1, losses.l2, losses.kl):
        assert torch.allclose(fn(a, b), fn(3.0 * a, 0.5 * b), atol=1e-5)
        assert float(fn(a, a).abs().max()) < 1e-5
        assert float(fn(a, b).min()) > 1e-3


def test_regularisers_have_gradients_that_do_not_cancel():
    g = torch.Generator().manual_seed(0)
    d = torch.randn(1, 4, 7, 7, generator=g, dtype=torch.float64, requires_grad=True)
    for fn in (losses.ridge, losses.lasso, losses.laplacian):
        (grad,) = torch.autograd.grad(fn(d), d)
        assert float(grad.abs().sum()) > 0, fn.__name__
    # Added with a fixed weight, the regulariser's gradient survives in the total (no normalisation by data).
    (g1,) = torch.autograd.grad((d.sum() - 1.0) ** 2 + 0.1 * losses.laplacian(d), d)
    (g0,) = torch.autograd.grad((d.sum() - 1.0) ** 2, d)
    assert float((g1 - g0).abs().max()) > 1e-6
    # Smoothness: a plane is free, a bump is not.
    u = torch.linspace(-1, 1, 7, dtype=torch.float64)
    plane = (u[:, None] + 0.5 * u[None, :]).reshape(1, 1, 7, 7)
    assert float(losses.laplacian(plane)) < 1e-20
    assert float(losses.laplacian(torch.exp(-4 * (u[:, None] ** 2 + u[None, :] ** 2)).reshape(1, 1, 7, 7))) > 1e-3


def test_loss_finite_difference_wrt_control_points():
    facets, obs, _ = small_scene()
    sun = SunSettings(sunshape="buie", slope_error=1e-3)
    model = LearnableSurface(facets, (4, 4), (2, 2))
    with torch.no_grad():
        g = torch.Generator().manual_seed(3)
        model.displacement_mm.copy_(torch.randn(model.displacement_mm.shape, generator=g, dtype=torch.float64))
        meas, _, _ = predict_images(model.surfaces(), obs, sun, samples=(16, 16), resolution=32)
        model.displacement_mm.zero_()
    kernels: dict = {}

    def loss():
        img, _, _ = predict_images(model.surfaces(), obs, sun, samples=(16, 16), resolution=32, kernels=kernels)
        return losses.image_loss("l2", img.double(), meas.double())

    value = loss()
    (grad,) = torch.autograd.grad(value, model.displacement_mm)
    eps = 0.05  # mm
    checked = 0
    for idx in [(0, 0, 1, 1), (0, 1, 2, 1), (0, 3, 0, 3)]:
        with torch.no_grad():
            model.displacement_mm[idx] += eps
            up = float(loss())
            model.displacement_mm[idx] -= 2 * eps
            down = float(loss())
            model.displacement_mm[idx] += eps
        fd = (up - down) / (2 * eps)
        assert abs(float(grad[idx])) > 1e-6
        assert abs(fd - float(grad[idx])) <= 0.1 * abs(fd) + 1e-6, (idx, fd, float(grad[idx]))
        checked += 1
    assert checked == 3
