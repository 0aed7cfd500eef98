"""The surface-learning integrator (splat * exact sun-cone kernel) agrees with raytrace.trace_analytic."""
from __future__ import annotations


from heliotwin.field import facets as facet_ops
from heliotwin.field.plant import SunSettings
from heliotwin.raytrace.analytic import trace_analytic
from heliotwin.surfaces import losses
from heliotwin.surfaces.learning import LearnableSurface
from heliotwin.surfaces.render import render_centered

from test_surfaces_losses import small_scene


def _world_samples(facets, obs, i, samples=(24, 24)):
    surf = LearnableSurface(facets, (5, 5), (2, 2)).surfaces()
    pts, nrm, area = facet_ops.surface_points(surf, samples)
    rot = obs.rotation[i]
    pw = obs.concentrator[i] + pts[0] @ rot.T
    return pw.float()[None], (nrm[0] @ rot.T).float()[None], area.float()


def test_render_matches_trace_analytic_for_gaussian_sun():
    facets, obs, target = small_scene(distance=30.0, n=2)
    for sun in (SunSettings(sunshape="gaussian", sigma=2.5e-3, slope_error=0.0),
                SunSettings(sunshape="gaussian", sigma=2.0e-3, slope_error=1.0e-3)):
        for i in range(2):
            pw, nw, area = _world_samples(facets, obs, i)
            sund = obs.sun[i:i + 1].float()
            res = render_centered(pw, nw, area, sund, target, sun, size_m=4.0, resolution=32)
            c = res.center[0].detach().double()
            window = (float(c[0]) - 2.0, float(c[1]) - 2.0, 4.0, 4.0)
            ref = trace_analytic(pw, nw, area, sund, target, resolution=(32, 32), sun=sun, window=window,
                                 clip_to_target=False).bitmap
            l1 = float(losses.l1(res.image, ref.to(res.image)).max())
            print(f"L1(render, trace_analytic) = {l1:.4f}")
            assert l1 < 0.03, (sun, i, l1)
            # Same absolute flux scale (power conserved in the window by both).
            ratio = float(res.image.sum() / ref.sum())
            assert abs(ratio - 1.0) < 0.02, ratio
