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
from .sizes import check_trace_sizes
from .trace import describe_plant

__all__ = ["ValidateSettings", "validate", "METRICS", "split_by_state"]

#: What each number of the report computes (also written into the report as ``metrics``). The centred L1 here
#: is not ``reconstruct``'s: see ``median_centered_l1``.
METRICS = {
    "pointing_error_mrad": "angle between the plant's mirror normal at the recorded motor steps and the measured "
                           "normal (bisector of the sun and concentrator -> measured spot) [mrad]; calibrate's "
                           "metric",
    "distance_m": "predicted flux centroid (gaussian integrator) to the measured spot, in the target plane [m]",
    "median_centered_l1": "L1 of unit-sum images, sum |p - m| in [0, 2], between the plant's predicted 6 m x 6 m "
                          "centred image (this plant's kinematics and surfaces, the folder's default sunshape and "
                          "slope error, no camera model) and PAINT's flux-centered PNG, over EVERY record with an "
                          "image (training and test). reconstruct's l1_learned differs in three ways: it is over "
                          "its test images only, the prediction passes through a camera model fitted per image "
                          "(background cut, saturation, blur) and uses the slope error/focus it chose; its "
                          "l1_learned_raw drops the camera model. On AA39 these give 0.137 (reconstruct, camera "
                          "model) against about 0.2 here for the same learned surface.",
    "median_centered_cross_correlation": "zero-mean normalised cross-correlation of the same two images [-1, 1]",
    "by_state": "medians over heliostats, kept apart for heliostats whose kinematics are calibrated in the "
                "scenario and those still on nominal kinematics (a mixed median hides both)",
}
_MEDIAN_KEYS = ("median_pointing_error_mrad", "median_distance_m", "median_centered_l1",
                "median_centered_cross_correlation")


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
        record, per heliostat, overall) with ``overall.seconds`` [s], ``settings``, each heliostat's
        ``kinematics`` (calibrated/nominal) and ``surface`` (learned/ideal), ``by_state`` (the medians of the
        calibrated and of the nominal heliostats apart, :func:`split_by_state`) and ``metrics`` (what each
        number computes, :data:`METRICS`).

    Raises
    ------
    HeliotwinError
        No usable record (names the first skipped record's reason).
    """
    settings = settings or ValidateSettings()
    check_trace_sizes(resolution=settings.resolution, samples=settings.samples,
                      facets=dataset.plant.field.facets.translation.shape[1])
    t0 = time.perf_counter()
    report = validate_dataset(dataset, resolution=settings.resolution, samples=(settings.samples, settings.samples),
                              with_images=settings.with_images, progress=settings.progress, device=settings.device)
    if not report["overall"].get("records"):
        skipped = report.get("skipped_records") or dataset.skipped
        why = f"; first: {skipped[0].get('reason')}" if skipped else ""
        raise HeliotwinError(f"{paint_dir}: no usable record to validate ({len(skipped)} skipped{why})")
    report["overall"]["seconds"] = time.perf_counter() - t0
    split_by_state(report, scenario)
    report["metrics"] = METRICS
    report["settings"] = {"paint": os.path.abspath(paint_dir) if paint_dir is not None else None,
                          **describe_plant(scenario), "integrator": "gaussian", "resolution": settings.resolution,
                          "device": settings.device, "samples_per_facet": settings.samples ** 2,
                          "sunshape": dataset.plant.sun.sunshape,
                          "slope_error_mrad": dataset.plant.sun.slope_error * 1e3}
    return report


def _median(values):
    vals = sorted(v for v in values if v is not None)
    if not vals:
        return None
    mid = len(vals) // 2
    return vals[mid] if len(vals) % 2 else 0.5 * (vals[mid - 1] + vals[mid])


def split_by_state(report: dict, scenario=None) -> dict:
    """Mark every heliostat of ``report`` as calibrated or nominal (kinematics) and learned or ideal (surface)
    from ``scenario``'s learned state, and add ``report["by_state"]``: per group the heliostats and the medians
    over them of the per-heliostat medians (:data:`_MEDIAN_KEYS`). Returns ``report`` (changed in place)."""
    learned = getattr(scenario, "learned", None) or {}
    calibrated = set((learned.get("calibration") or {}).get("heliostats", []))
    surfaces = set(learned.get("surfaces") or {})
    groups = {"calibrated": [], "nominal": []}
    for hid, h in report.get("heliostats", {}).items():
        h["kinematics"] = "calibrated" if hid in calibrated else "nominal"
        h["surface"] = "learned" if hid in surfaces else "ideal"
        groups[h["kinematics"]].append(hid)
    report["by_state"] = {
        name: {"heliostats": ids, **{k: _median([report["heliostats"][h].get(k) for h in ids]) for k in _MEDIAN_KEYS}}
        for name, ids in groups.items()}
    return report
