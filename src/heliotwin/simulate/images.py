"""Flux-centred images of a few simulated heliostats, rendered from true (defective) surfaces.

Off by default (``SimulationSettings.images = 0``). For ``images`` heliostats (drawn with the seed) the truth
gets a defective surface -- per facet a screw dome and a waviness, the in-silico study's ground truth
(:func:`heliotwin.surfaces.insilico.ground_truth_heights`, ~2 mm) on its finer NURBS net -- and up to
``images_per_heliostat`` of their records get a ``<id>-flux-centered.png``: the spot of the true heliostat at
the record's pose (true kinematics at the recorded motor steps) in PAINT's 6 m window, rendered by the
surface learner's own image model (:func:`heliotwin.surfaces.imaging.predict_images`), then what the camera
does to it (:mod:`heliotwin.surfaces.nuisance`): saturation (the image scaled by :data:`SATURATION_GAIN` and
clipped at the max), centroid-free pixel noise (:data:`PIXEL_NOISE`) and the background cut (everything below
:data:`BACKGROUND_CUT` of the max set to 0).
"""
from __future__ import annotations

import numpy as np
import torch

from ..field import kinematics as K
from ..field.facets import flat_control_points
from ..field.plant import Facets, Surfaces
from ..surfaces.imaging import predict_images
from ..surfaces.insilico import TRUTH_DEGREE, TRUTH_NET, ground_truth_heights
from ..surfaces.learning import heights_to_displacement, learnable_surfaces
from ..surfaces.observations import Observations

#: Camera gain before clipping at the max: the top ~15 % of the spot saturates (flat plateau).
SATURATION_GAIN = 1.15
#: Pixel noise, fraction of the max.
PIXEL_NOISE = 0.005
#: Background cut, fraction of the max (the image processing's threshold).
BACKGROUND_CUT = 0.03
#: Pixels per side of a flux-centred image (PAINT's older releases).
RESOLUTION = 64


def true_surfaces(facets: Facets, chosen: list, generator: torch.Generator) -> Surfaces:
    """Surfaces [H, F, 15, 15, 3] (degree 3): ideal for every heliostat except ``chosen`` (indices), which get
    the in-silico study's defects."""
    base = flat_control_points(facets, TRUTH_NET, TRUTH_DEGREE)
    cp = base.clone()
    for h in chosen:  # a few heliostats (the images option), not the field
        one = Facets(*(getattr(facets, a)[h:h + 1] for a in ("translation", "canting_e", "canting_n")))
        heights = ground_truth_heights(facets.translation.shape[1], generator)
        d = heights_to_displacement(heights, TRUTH_NET, TRUTH_DEGREE)
        cp[h] = learnable_surfaces(one, base[h:h + 1], d, TRUTH_DEGREE).control_points[0].detach()
    return Surfaces(cp, TRUTH_DEGREE[0], TRUTH_DEGREE[1], None)


def camera(images: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
    """What the camera and image processing make of flux images [B, R, R]: scaled to max 1, saturated, noisy,
    background cut (module docstring)."""
    x = images / images.amax((-2, -1), keepdim=True).clamp_min(1e-300)
    x = (x * SATURATION_GAIN).clamp(max=1.0)
    x = x + torch.from_numpy(rng.normal(0.0, PIXEL_NOISE, tuple(x.shape))).to(x)
    return torch.where(x < BACKGROUND_CUT, torch.zeros_like(x), x.clamp(max=1.0))


def render(surfaces: Surfaces, kin, steps: torch.Tensor, sun: torch.Tensor, targets: list, sun_settings,
           rng: np.random.Generator, samples=(32, 32)) -> torch.Tensor:
    """Camera images [B, R, R] of one heliostat (``surfaces`` [1, ...], ``kin`` [B] per record) at motor steps
    [B, 2] with the sun [B, 3] on planar ``targets`` (B)."""
    rot, conc = K.forward(kin, steps)
    obs = Observations(sun, rot, conc, list(targets), None, [str(i) for i in range(len(targets))])
    with torch.no_grad():
        img, _, _ = predict_images(surfaces, obs, sun_settings, samples=samples, resolution=RESOLUTION)
    return camera(img.double(), rng)
