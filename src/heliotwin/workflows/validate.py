"""The ``validate`` workflow: a plant's predicted focal spots and images against PAINT's measured ones.

:func:`validate` runs :func:`heliotwin.validate.validate_dataset` on the records of a PAINT folder (on the
nominal plant or a scenario's) and completes its report with the settings and what the plant is, so that
the command line, the API and the benchmarks report the same thing.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass

from ..errors import HeliotwinError
from ..validate import validate_dataset
from .trace import describe_plant

__all__ = ["ValidateSettings", "validate"]


@dataclass
class ValidateSettings:
    """How :func:`validate` traces (``heliotwin validate``'s defaults).

    Attributes
    ----------
    resolution : int
        Whole-target bitmap rows = columns for the centroids [pixels].
    samples : int
        Mirror samples per facet and direction.
    with_images : bool
        Compare the ``flux-centered`` images too.
    progress : bool
    device : str
        Where to trace (``"auto"``: CUDA when present).
    """

    resolution: int = 128
    samples: int = 16
    with_images: bool = True
    progress: bool = True
    device: str = "cpu"


def validate(dataset, scenario=None, settings: ValidateSettings | None = None, *, paint_dir=None) -> dict:
    """Predicted vs measured focal spots (and images) of every usable record.

    Parameters
    ----------
    dataset : heliotwin.io.paint.PaintDataset
        Records on the plant to check (:func:`heliotwin.io.scenario.load_records`).
    scenario : Scenario, optional
        Where the plant came from (None: the folder's nominal plant); only described in the report.
    settings : ValidateSettings, optional
    paint_dir : path, optional
        The PAINT folder, named in the report and in errors.

    Returns
    -------
    dict
        :func:`heliotwin.validate.validate_dataset`'s report (pointing errors [mrad], distances [m], per
        record, per heliostat, overall) with ``overall.seconds`` [s] and ``settings``.

    Raises
    ------
    HeliotwinError
        No usable record (names the first skipped record's reason).
    """
    settings = settings or ValidateSettings()
    t0 = time.perf_counter()
    report = validate_dataset(dataset, resolution=settings.resolution, samples=(settings.samples, settings.samples),
                              with_images=settings.with_images, progress=settings.progress, device=settings.device)
    if not report["overall"].get("records"):
        skipped = report.get("skipped_records") or dataset.skipped
        why = f"; first: {skipped[0].get('reason')}" if skipped else ""
        raise HeliotwinError(f"{paint_dir}: no usable record to validate ({len(skipped)} skipped{why})")
    report["overall"]["seconds"] = time.perf_counter() - t0
    report["settings"] = {"paint": os.path.abspath(paint_dir) if paint_dir is not None else None,
                          **describe_plant(scenario), "integrator": "gaussian", "resolution": settings.resolution,
                          "device": settings.device, "samples_per_facet": settings.samples ** 2,
                          "sunshape": dataset.plant.sun.sunshape,
                          "slope_error_mrad": dataset.plant.sun.slope_error * 1e3}
    return report
