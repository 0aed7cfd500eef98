"""A tiny in-silico reconstruction: the learned surface recovers a known bump better than the ideal one."""
from __future__ import annotations

import torch

from heliotwin.field.plant import SunSettings
from heliotwin.surfaces import losses
from heliotwin.surfaces.insilico import surface_metrics
from heliotwin.surfaces.learning import LearnableSurface, learnable_surfaces
from heliotwin.surfaces.reconstruct import TrainSettings, fit_surface, predict_images

from test_surfaces_losses import small_scene


def test_tiny_reconstruction_recovers_bump():
    facets, obs, _ = small_scene(distance=20.0, n=3)
    sun = SunSettings(sunshape="buie", slope_error=0.5e-3)
    net, deg = (5, 5), (2, 2)
    # Truth: a dome on every facet (centre +1.5 mm, edges 0) on the same net.
    u = torch.linspace(-1, 1, net[0], dtype=torch.float64)
    dome = 1.5e-3 * (1 - u[:, None] ** 2) * (1 - u[None, :] ** 2)
    d_true = dome.expand(1, 4, *net).clone()
    base = LearnableSurface(facets, net, deg).base
    truth = learnable_surfaces(facets, base, d_true, deg)
    with torch.no_grad():
        obs.images, _, _ = predict_images(truth, obs, sun, samples=(16, 16), resolution=32)
    train, test = obs.subset([0, 1]), obs.subset([2])
    settings = TrainSettings(control_points=net, degree=deg, samples=(12, 12), resolution=32, steps=50, lr=0.3,
                             decay=0.99, laplacian=1e-3, loss="l1")
    model = fit_surface(facets, train, sun, settings, progress=False)
    ideal = LearnableSurface(facets, net, deg).surfaces()
    with torch.no_grad():
        li = float(losses.l1(predict_images(ideal, test, sun, samples=(16, 16), resolution=32)[0], test.images).mean())
        ll = float(losses.l1(predict_images(model.surfaces(), test, sun, samples=(16, 16), resolution=32)[0],
                             test.images).mean())
    m_learned = surface_metrics(facets, model.surfaces(), truth)
    m_ideal = surface_metrics(facets, ideal, truth)
    assert ll < 0.7 * li, (li, ll)
    assert m_learned["normal_deviation_mrad"] < 0.7 * m_ideal["normal_deviation_mrad"], (m_learned, m_ideal)
