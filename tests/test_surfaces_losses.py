"""Losses, regularisers and the gradient of the rendered loss w.r.t. control points."""
from __future__ import annotations

import torch

from heliotwin.field.plant import Facets, SunSettings
from heliotwin.field.targets import PlanarTarget
from heliotwin.surfaces import losses
from heliotwin.surfaces.learning import LearnableSurface
from heliotwin.surfaces.reconstruct import Observations, predict_images
from heliotwin.surfaces.render import aimed_pose
from heliotwin.field.plant import Kinematics


def _facets():
    t = torch.tensor([[[-0.4, 0.3, 0.0], [0.4, 0.3, 0.0], [-0.4, -0.3, 0.0], [0.4, -0.3, 0.0]]], dtype=torch.float64)
    ce = torch.tensor([0.39, 0.0, 0.0], dtype=torch.float64).expand(1, 4, 3).clone()
    cn = torch.tensor([0.0, 0.29, 0.0], dtype=torch.float64).expand(1, 4, 3).clone()
    return Facets(t, ce, cn)


def _kinematics(position):
    z = lambda *s: torch.zeros(*s, dtype=torch.float64)  # noqa: E731
    o = lambda *s: torch.ones(*s, dtype=torch.float64)  # noqa: E731
    return Kinematics(position=torch.tensor([position], dtype=torch.float64), joint_translation=z(1, 2, 3),
                      concentrator_translation=z(1, 3), joint_tilt=z(1, 2, 3), concentrator_tilt=z(1, 3),
                      increment=o(1, 2), offset=o(1, 2), pivot_radius=o(1, 2), initial_angle=z(1, 2),
                      initial_stroke_length=o(1, 2), clockwise=torch.zeros(1, 2, dtype=torch.bool),
                      linear=torch.zeros(1, 2, dtype=torch.bool), min_steps=-1e9 * o(1, 2), max_steps=1e9 * o(1, 2),
                      min_angle=z(1, 2), max_angle=z(1, 2))


def small_scene(distance=20.0, n=2):
    """A 1.6 m x 1.2 m, 4-facet heliostat ``distance`` m north of a 6 m target, n sun positions."""
    target = PlanarTarget.from_center_normal("t", [0.0, 0.0, 15.0], [0.0, 1.0, 0.0], 6.0, 6.0)
    kin = _kinematics([0.0, distance, 1.0])
    sun = torch.tensor([[0.3, -0.6, 0.74], [-0.4, -0.5, 0.77], [0.1, -0.3, 0.95], [0.5, -0.2, 0.84]],
                       dtype=torch.float64)[:n]
    sun = sun / sun.norm(dim=-1, keepdim=True)
    rot, conc = aimed_pose(kin, target.center.expand(n, 3), sun)
    return _facets(), Observations(sun, rot, conc, [target] * n, None, [str(i) for i in range(n)]), target


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
