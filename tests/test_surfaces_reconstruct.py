"""Tiny in-silico reconstructions with the one surface fit (Adam and L-BFGS): the learned surface recovers a known
bump better than the ideal one."""
from __future__ import annotations

import torch
from helpers.surfaces import dome_scene, small_scene

from heliotwin.field.plant import SunSettings
from heliotwin.surfaces import losses
from heliotwin.surfaces.fit import SurfaceSettings, fit_surface
from heliotwin.surfaces.imaging import predict_images
from heliotwin.surfaces.insilico import surface_metrics
from heliotwin.surfaces.learning import LearnableSurface, learnable_surfaces
from heliotwin.surfaces.observations import Observations


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
    settings = SurfaceSettings(control_points=net, degree=deg, samples=(12, 12), resolution=32, steps=50, lr=0.3,
                               decay=0.99, laplacian=1e-3, loss="l1")
    fit = fit_surface(facets, train, sun, settings)
    model = fit.model
    assert fit.evaluations == 50 and fit.sigma is None and fit.curve == []  # no camera model, no held-out image
    ideal = LearnableSurface(facets, net, deg).surfaces()
    with torch.no_grad():
        li = float(losses.l1(predict_images(ideal, test, sun, samples=(16, 16), resolution=32)[0], test.images).mean())
        ll = float(losses.l1(predict_images(model.surfaces(), test, sun, samples=(16, 16), resolution=32)[0],
                             test.images).mean())
    m_learned = surface_metrics(facets, model.surfaces(), truth)
    m_ideal = surface_metrics(facets, ideal, truth)
    assert ll < 0.7 * li, (li, ll)
    assert m_learned["normal_deviation_mrad"] < 0.7 * m_ideal["normal_deviation_mrad"], (m_learned, m_ideal)


def test_lbfgs_with_a_leave_one_out_weight_choice_ends_by_its_rules():
    from heliotwin.surfaces.insilico import choose_laplacian

    facets, obs, sun, truth = dome_scene(samples=(12, 12))
    s = SurfaceSettings(control_points=(5, 5), degree=(2, 2), samples=(10, 10), resolution=32, loss="l1",
                        optimizer="lbfgs", continuation=(1.5,), continuation_iters=5, lbfgs_round=10, steps=30)
    s, chosen = choose_laplacian(facets, obs, sun, s, (1e-3, 1e-2), cv="loo")
    assert chosen["laplacian_cv"] == "loo" and len(chosen["holdout"]) == 3
    assert set(chosen["laplacian_scores"]) == {1e-3, 1e-2}
    assert s.laplacian == min(chosen["laplacian_scores"], key=chosen["laplacian_scores"].get)
    fit = fit_surface(facets, obs, sun, s)
    model, log = fit.model, fit.log
    # The blur continuation first, then sharp rounds until the evaluation budget or the tolerance ends the fit.
    assert log[0]["blur_px"] == 1.5 and all(e["blur_px"] == 0.0 for e in log[1:])
    assert log[-1]["step"] == fit.evaluations
    sharp = [e["total"] for e in log[1:]]
    assert fit.evaluations >= 30 or sharp[-2] - sharp[-1] <= s.tolerance * abs(sharp[-1])
    ideal = LearnableSurface(facets, (5, 5), (2, 2)).surfaces()
    assert surface_metrics(facets, model.surfaces(), truth)["normal_deviation_mrad"] < \
        surface_metrics(facets, ideal, truth)["normal_deviation_mrad"]


def test_common_tilt_is_learned_in_fixed_windows_and_invisible_in_centred_ones():
    """A 1 mrad tilt of the whole mirror only moves the spot: centred windows cannot see it (and the gauge
    keeps it out of the learned surface); windows fixed on the aim point (known kinematics) can."""
    from heliotwin.surfaces.learning import gauge_basis

    facets, obs, target = small_scene(distance=20.0, n=3)
    sun = SunSettings(sunshape="buie", slope_error=0.5e-3)
    net, deg = (4, 4), (2, 2)
    tilt = gauge_basis(facets, net, deg, pistons=False)[:, 0]  # unit-norm common east-west tilt mode
    # Scale to a 1 mrad slope: the mode is a * s * |canting_e| with s in [-1, 1] spanning 2 |canting_e|.
    slope = (tilt.reshape(4, *net)[0, -1, 0] - tilt.reshape(4, *net)[0, 0, 0]) / (2 * 0.39)
    d_true = (1e-3 * tilt / slope).reshape(1, 4, *net)
    base = LearnableSurface(facets, net, deg).base
    truth = learnable_surfaces(facets, base, d_true, deg)
    ideal = LearnableSurface(facets, net, deg).surfaces()
    m_ideal = surface_metrics(facets, ideal, truth)["normal_deviation_mrad"]
    assert abs(m_ideal - 1.0) < 0.05, m_ideal
    kw = dict(samples=(12, 12), resolution=32)
    fixed = Observations(obs.sun, obs.rotation, obs.concentrator, obs.targets, None, obs.ids,
                         target.to_local(target.center.expand(3, 3)))
    with torch.no_grad():
        obs.images, c_truth, _ = predict_images(truth, obs, sun, **kw)
        fixed.images, _, _ = predict_images(truth, fixed, sun, **kw)
        centred_ideal, c_ideal, _ = predict_images(ideal, obs, sun, **kw)
        fixed_ideal, _, _ = predict_images(ideal, fixed, sun, **kw)
    # The spot moves by ~2 * 1 mrad * 20 m = 4 cm; centred images barely differ, fixed ones do.
    shift = float((c_truth - c_ideal).norm(dim=-1).mean())
    assert 0.03 < shift < 0.05, shift
    l1_centred = float(losses.l1(centred_ideal, obs.images).mean())
    l1_fixed = float(losses.l1(fixed_ideal, fixed.images).mean())
    assert l1_fixed > 5 * l1_centred, (l1_centred, l1_fixed)
    s = SurfaceSettings(control_points=net, degree=deg, samples=(12, 12), resolution=32, loss="l1", optimizer="lbfgs",
                        continuation=(), lbfgs_round=40, steps=80, laplacian=1e-3)
    learned_fixed = fit_surface(facets, fixed, sun, s).model
    learned_centred = fit_surface(facets, obs, sun, s).model
    assert not learned_fixed.gauge_tilt and learned_centred.gauge_tilt
    assert surface_metrics(facets, learned_fixed.surfaces(), truth)["normal_deviation_mrad"] < 0.2
    assert surface_metrics(facets, learned_centred.surfaces(), truth)["normal_deviation_mrad"] > 0.9
