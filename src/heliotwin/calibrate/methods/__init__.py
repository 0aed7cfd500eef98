"""The calibration methods behind ``--method``: a plain registry with one signature.

``METHODS[name](nominal, train, validation, *, seed, progress, **options) -> Calibrated``: ``nominal`` has
the run's H heliostats, ``train``/``validation`` are batches over the same heliostat axis (validation
carved out of the ``--train`` records). Heliostats without enough training records
(:data:`~heliotwin.calibrate.inputs.MIN_TRAIN`) come back with ``ok = False``.

Each method lives in its own module of this package; the pieces they share live below them, at
:mod:`heliotwin.calibrate`'s top level (:mod:`~heliotwin.calibrate.inputs`: usable heliostats and fit
centroids; :mod:`~heliotwin.calibrate.fitloop`: the early-stopping loop; :mod:`~heliotwin.calibrate.model`:
what they return) or in :mod:`.lm` (the Stone/Jülich pre-alignment every method starts from), so this
registry imports them all without a cycle.
"""
from __future__ import annotations

from ...errors import HeliotwinError
from .gradient import fit_gradient_method
from .hybrid import fit_hybrid_method
from .images import fit_images_method
from .lm import fit_lm_method
from .mlp import fit_mlp_method

METHODS = {
    "lm": fit_lm_method,
    "gradient": fit_gradient_method,
    "hybrid": fit_hybrid_method,
    "mlp": fit_mlp_method,
    "images": fit_images_method,
}


def get_method(name: str):
    """The fit function of a method (one-line error listing the known ones)."""
    if name not in METHODS:
        raise HeliotwinError(f"unknown calibration method {name!r}; known: {', '.join(METHODS)}")
    return METHODS[name]
