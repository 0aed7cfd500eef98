"""In silico under model mismatch: the truth is imaged with optics and a camera the learner does not assume.

Truth images (:func:`camera_truth`): the defective truth surface of :mod:`heliotwin.surfaces.insilico`
rendered with ``truth_sun`` (default a Gaussian sun, sigma 2.8 mrad, slope error 1.2 mrad -- not the model's
Buie sun), then a camera that saturates (``saturation``: the recorded image is ``min(I / (saturation max I), 1)``)
and cuts the background (``cut``: values below that fraction of the max set to 0). The learner
(:func:`heliotwin.surfaces.generalise.reconstruct_generalising`) models a Buie sun (CSR 0.05) with a slope
error it chooses, and estimates the cut and saturation from the images by its own rules.

Every random draw takes a ``torch.Generator`` seeded from ``seed``.
"""
from __future__ import annotations

import time

import torch

from ..field.plant import SunSettings
from .fit import blur_images
from .generalise import SurfaceSettings, reconstruct_generalising
from .insilico import make_scene, observe, random_suns, surface_metrics

__all__ = ["camera_truth", "add_halo", "run_mismatch_case", "TRUTH_SUN"]

#: Optics of the truth images (differs from the learner's Buie sun, CSR 0.05).
TRUTH_SUN = SunSettings(sunshape="gaussian", sigma=2.8e-3, slope_error=1.2e-3)


def camera_truth(images: torch.Tensor, saturation: float, cut: float) -> torch.Tensor:
    """Recorded images ``[B, R, C]`` (max 1): saturate at ``saturation`` x max, then cut below ``cut``."""
    x = images / images.amax((-2, -1), keepdim=True).clamp_min(1e-30)
    x = torch.clamp(x / saturation, max=1.0)
    return torch.where(x < cut, torch.zeros_like(x), x)


def add_halo(images: torch.Tensor, fraction: float = 0.5, sigma_px: float = 8.0) -> torch.Tensor:
    """``(1 - fraction) I + fraction blur(I)`` (same power): a broad diffuse halo on ``[B, R, C]`` images, same
    shape out. ``fraction`` [1] of each image's power goes into the halo, a Gaussian blur of ``sigma_px`` [px]
    (:func:`~heliotwin.surfaces.fit.blur_images`) rescaled to the image's own sum."""
    wide = blur_images(images, sigma_px)
    wide = wide * images.sum((-2, -1), keepdim=True) / wide.sum((-2, -1), keepdim=True).clamp_min(1e-30)
    return (1 - fraction) * images + fraction * wide


def run_mismatch_case(plant, distance: float = 50.0, num_train: int = 4, num_test: int = 10, seed: int = 0,
                      truth_sun: SunSettings = TRUTH_SUN, saturation: float = 0.8, cut: float = 0.05,
                      window: str = "centred", settings: SurfaceSettings | None = None,
                      progress: bool = False, halo: int | None = None, latest: int | None = None) -> dict:
    """One in-silico case under mismatch; the generalising report plus surface recovery metrics.

    ``distance``: the heliostat's horizontal offset from the target [m]
    (:func:`~heliotwin.surfaces.insilico.make_scene`); ``saturation`` and ``cut``: the truth camera's levels as
    fractions of each image's max [1] (:func:`camera_truth`); ``window``: "centred" (spot-centred windows,
    PAINT's) or "aim" (fixed on the aim point), both 6 m wide. ``halo``: index of a training image that gets a
    broad diffuse halo (:func:`add_halo`) -- an inconsistent image the outlier rule should drop. ``latest``: train on
    the last ``latest`` of the ``num_train`` images only (the same scene, suns and test images: the learner of a
    few latest images beside the one of every image).

    Returns
    -------
    dict
        The report of :func:`~heliotwin.surfaces.generalise.reconstruct_generalising`, plus ``seconds`` [s],
        ``recovery`` (learned and ideal normal deviation [mrad] and height RMS [mm] against the truth) and
        ``case`` (the inputs above, ``distance_m`` [m], the truth sun's ``sigma_rad`` and ``slope_error_rad``
        [rad]).
    """
    gen = torch.Generator().manual_seed(int(seed))
    scene = make_scene(plant, distance, gen, sun=truth_sun)
    suns = random_suns(plant.site, num_train + num_test, gen)
    train = observe(scene, suns[:num_train], window=window)
    test = observe(scene, suns[num_train:], window=window, ids=[str(i) for i in range(num_train, len(suns))])
    if halo is not None:
        train.images[halo] = add_halo(train.images[halo:halo + 1])[0]
    train.images = camera_truth(train.images, saturation, cut)
    test.images = camera_truth(test.images, saturation, cut)
    if latest is not None:
        train = train.subset(range(max(0, num_train - int(latest)), num_train))
    t0 = time.perf_counter()
    report, model, info = reconstruct_generalising(scene.facets, train, test, SunSettings(sunshape="buie", csr=0.05),
                                                   settings, progress)
    report["seconds"] = time.perf_counter() - t0
    report["recovery"] = {"learned": surface_metrics(scene.facets, model.surfaces(), scene.truth),
                          "ideal": surface_metrics(scene.facets, info["ideal"], scene.truth)}
    report["case"] = {"distance_m": distance, "train_images": len(train), "test_images": num_test, "seed": seed,
                      "window": window, "truth_sun": {"sunshape": truth_sun.sunshape, "sigma_rad": truth_sun.sigma,
                                                      "slope_error_rad": truth_sun.slope_error},
                      "truth_camera": {"saturation_fraction_of_max": saturation, "cut_fraction_of_max": cut},
                      "model_sun": {"sunshape": "buie", "csr": 0.05},
                      "halo_training_image": None if halo is None else train.ids[halo]}
    return report
