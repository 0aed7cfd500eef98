"""``images``: calibration through the ray tracer from flux images (stub until the ray tracer lands).

Planned (issue 3): for records with flux images, render each record's spot with the differentiable ray
tracer (:mod:`heliotwin.raytrace`) from the calibrated kinematics and learn the deviations with the
published loss (pixel term + alignment term + miss term), so that rotations invisible to a centroid (e.g.
the mirror's rotation about its own normal, ``concentrator_tilt_n``) are learned too.
"""
from __future__ import annotations

from ..errors import HeliotwinError


def fit_images_method(nominal, train, validation, *, seed=0, progress=False, **options):
    """Not available yet: needs the ray tracer (heliotwin.raytrace)."""
    raise NotImplementedError("method 'images' needs the ray tracer (heliotwin.raytrace), which has not landed yet; "
                              "use --method lm|gradient|hybrid|mlp")


__all__ = ["fit_images_method", "HeliotwinError"]
