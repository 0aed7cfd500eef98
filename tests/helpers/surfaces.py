"""Shared scenes for the surface-learning and conv-integrator tests (import as ``helpers.surfaces``)."""
from __future__ import annotations

import torch

from heliotwin.field.kinematics import aimed_pose
from heliotwin.field.plant import Facets, Kinematics, SunSettings
from heliotwin.field.targets import PlanarTarget
from heliotwin.surfaces.imaging import predict_images
from heliotwin.surfaces.learning import LearnableSurface, learnable_surfaces
from heliotwin.surfaces.observations import Observations

__all__ = ["facets4", "kinematics_at", "small_scene"]


def facets4() -> Facets:
    """Four 0.78 m x 0.58 m flat facets of one heliostat, ``[1, 4, 3]`` float64, heliostat frame [m]."""
    t = torch.tensor([[[-0.4, 0.3, 0.0], [0.4, 0.3, 0.0], [-0.4, -0.3, 0.0], [0.4, -0.3, 0.0]]], dtype=torch.float64)
    ce = torch.tensor([0.39, 0.0, 0.0], dtype=torch.float64).expand(1, 4, 3).clone()
    cn = torch.tensor([0.0, 0.29, 0.0], dtype=torch.float64).expand(1, 4, 3).clone()
    return Facets(t, ce, cn)


def kinematics_at(position) -> Kinematics:
    """One ideal heliostat (no tilts or offsets, unlimited motor range) at ``position`` (ENU [m])."""
    z = lambda *s: torch.zeros(*s, dtype=torch.float64)  # noqa: E731
    o = lambda *s: torch.ones(*s, dtype=torch.float64)  # noqa: E731
    return Kinematics(position=torch.tensor([position], dtype=torch.float64), joint_translation=z(1, 2, 3),
                      concentrator_translation=z(1, 3), joint_tilt=z(1, 2, 3), concentrator_tilt=z(1, 3),
                      increment=o(1, 2), offset=o(1, 2), pivot_radius=o(1, 2), initial_angle=z(1, 2),
                      initial_stroke_length=o(1, 2), clockwise=torch.zeros(1, 2, dtype=torch.bool),
                      linear=torch.zeros(1, 2, dtype=torch.bool), min_steps=-1e9 * o(1, 2), max_steps=1e9 * o(1, 2),
                      min_angle=z(1, 2), max_angle=z(1, 2))


def small_scene(distance=20.0, n=2):
    """A 1.6 m x 1.2 m, 4-facet heliostat ``distance`` m north of a 6 m target, n <= 4 sun positions.

    Returns
    -------
    facets : Facets
    obs : Observations
        Poses aimed at the target centre, no images.
    target : PlanarTarget
    """
    target = PlanarTarget.from_center_normal("t", [0.0, 0.0, 15.0], [0.0, 1.0, 0.0], 6.0, 6.0)
    kin = kinematics_at([0.0, distance, 1.0])
    sun = torch.tensor([[0.3, -0.6, 0.74], [-0.4, -0.5, 0.77], [0.1, -0.3, 0.95], [0.5, -0.2, 0.84]],
                       dtype=torch.float64)[:n]
    sun = sun / sun.norm(dim=-1, keepdim=True)
    rot, conc = aimed_pose(kin, target.center.expand(n, 3), sun)
    return facets4(), Observations(sun, rot, conc, [target] * n, None, [str(i) for i in range(n)]), target


def dome_scene(samples=(10, 10), distance=20.0, n=3):
    """:func:`small_scene` with images of a known dome-shaped surface (1.5 mm bulge per facet, 5 x 5 net).

    Returns
    -------
    facets : Facets
    obs : Observations
        With ``images`` [n, 32, 32] rendered from the dome (``samples`` mirror samples per facet).
    sun : SunSettings
        Buie sunshape, 0.5 mrad slope error.
    truth : Surfaces
        The dome.
    """
    facets, obs, _ = small_scene(distance=distance, n=n)
    sun = SunSettings(sunshape="buie", slope_error=0.5e-3)
    u = torch.linspace(-1, 1, 5, dtype=torch.float64)
    d_true = (1.5e-3 * (1 - u[:, None] ** 2) * (1 - u[None, :] ** 2)).expand(1, 4, 5, 5).clone()
    truth = learnable_surfaces(facets, LearnableSurface(facets, (5, 5), (2, 2)).base, d_true, (2, 2))
    with torch.no_grad():
        obs.images, _, _ = predict_images(truth, obs, sun, samples=samples, resolution=32)
    return facets, obs, sun, truth
