"""The legacy surface learner's study (``reconstruct --method legacy``): learn a heliostat's surface from its
training images with a chosen image loss and early stopping, evaluate on the test images, and report.
:func:`heliotwin.workflows.reconstruct.reconstruct` loads the observations and calls :func:`reconstruct_observed`.

Protocol. The records with ``-flux-centered.png`` images are split by time
(:func:`heliotwin.surfaces.observations.split_records`); the poses aim the heliostat at each record's measured
focal spot; the optics (Buie sun, CSR 0.05, plus a slope error chosen among :data:`SLOPE_ERROR_GRID` by the
*ideal* surface's mean L1 on the training images) are the same for the ideal baseline and the learned
surface, so ``IMP = L1(ideal) / L1(learned) - 1`` measures shape. Test images are compared in the conv
integrator (and, independently, the Monte-Carlo tracer) and with the peer's sharp Gaussian sun
(:data:`SHARP_SUN`) for reference.

Units: metres, radians; L1 of unit-sum images (0 identical, 2 disjoint).
"""
from __future__ import annotations

import dataclasses
import statistics
import time

import torch

from ..errors import HeliotwinError
from ..field.plant import Facets, SunSettings
from . import losses
from .deflectometry import compare_surfaces, deflectometry_surface
from .imaging import evaluate_images, trace_mc_centered
from .learning import LearnableSurface
from .observations import Observations
from .training import TrainSettings, train_with_early_stopping

__all__ = ["reconstruct_observed", "choose_slope_error", "SLOPE_ERROR_GRID", "SHARP_SUN"]

#: Slope errors [rad] tried when fitting the ideal baseline's optics to the training images.
SLOPE_ERROR_GRID = (0.5e-3, 1.0e-3, 1.5e-3, 2.0e-3, 2.5e-3, 3.0e-3)
#: The peer's (ARTIST tutorial) optics, reported for comparison: 2.1 mrad Gaussian sun, no slope error.
SHARP_SUN = SunSettings(sunshape="gaussian", sigma=2.1e-3, slope_error=0.0)


def choose_slope_error(facets: Facets, train: Observations, base: SunSettings, settings: TrainSettings,
                       grid=SLOPE_ERROR_GRID) -> tuple[float, dict]:
    """Slope error that makes the *ideal* surface fit the training images best (mean L1).

    This gives the baseline physically honest optics (real sunshape + fitted slope error) from training data
    only; the learned surface is then trained and evaluated with the same optics, so IMP measures shape.

    Returns
    -------
    slope_error : float
        [rad].
    scores : dict
        ``slope error [rad] -> mean training L1``.
    """
    ideal = LearnableSurface(facets, settings.control_points, settings.degree).surfaces()
    scores = {}
    for se in grid:
        sun = dataclasses.replace(base, slope_error=float(se))
        scores[float(se)] = float(torch.tensor(evaluate_images(ideal, train, sun, samples=settings.samples,
                                                               resolution=settings.resolution,
                                                               size_m=settings.size_m)["l1"]).mean())
    best = min(scores, key=scores.get)
    return best, scores


def _test_rows(test: Observations, e_ideal: dict, e_learn: dict, e_sharp: dict, mc: dict) -> list[dict]:
    rows = []
    for i, rid in enumerate(test.ids):
        row = {"record": int(rid), "target": test.targets[i].name,
               "l1_ideal": e_ideal["l1"][i], "l1_learned": e_learn["l1"][i],
               "cc_ideal": e_ideal["cc"][i], "cc_learned": e_learn["cc"][i],
               "imp": e_ideal["l1"][i] / max(e_learn["l1"][i], 1e-12) - 1.0,
               "l1_ideal_sharp_sun": e_sharp["l1"][i]}
        if mc:
            row["l1_ideal_mc"] = mc["ideal"][i]
            row["l1_learned_mc"] = mc["learned"][i]
        rows.append(row)
    return rows


def _optics_report(optics: SunSettings, scores: dict) -> dict:
    return {"sunshape": optics.sunshape, "csr": optics.csr, "slope_error_rad": optics.slope_error,
            "slope_error_selection": "min mean L1 of the ideal surface on the training images",
            "slope_error_scores": scores, "peer_sharp_sun": {"sunshape": "gaussian", "sigma_rad": 2.1e-3,
                                                              "slope_error_rad": 0.0}}


def _comparison_report(s: TrainSettings, alignment: str, background: float) -> dict:
    return {"window_m": s.size_m, "resolution": s.resolution,
            "normalisation": "each image divided by its sum; L1 = sum |a - b|",
            "centering": "measured: PAINT centred PNG; predicted: window centred on predicted centroid",
            "alignment": alignment, "background_subtraction_fraction_of_max": background,
            "downsampling": "256x256 PNGs box-averaged to 64x64"}


def _evaluate(ideal, learned, train, test, optics, s, evaluate_mc) -> dict:
    """Per-image L1/CC of the ideal and learned surfaces (conv; optionally MC) on test and training images."""
    kw = dict(samples=s.samples, resolution=s.resolution, size_m=s.size_m)
    out = {"ideal": evaluate_images(ideal, test, optics, **kw), "learned": evaluate_images(learned, test, optics, **kw),
           "sharp": evaluate_images(ideal, test, SHARP_SUN, **kw),
           "train_ideal": evaluate_images(ideal, train, optics, **kw),
           "train_learned": evaluate_images(learned, train, optics, **kw), "mc": {}}
    if evaluate_mc:
        meas = test.images
        for name, surf in (("ideal", ideal), ("learned", learned)):
            img = trace_mc_centered(surf, test, optics, rays_per_point=64, **kw)
            out["mc"][name] = losses.l1(img, meas.to(img)).tolist()
    return out


def _deflectometry_report(path, fit, defl, facets, ideal, learned, test, optics, s, rows, started_from) -> dict:
    e_defl = evaluate_images(defl, test, optics, samples=s.samples, resolution=s.resolution, size_m=s.size_m)
    for row, v in zip(rows, e_defl["l1"]):
        row["l1_deflectometry"] = v
    return {"file": str(path), "fit": fit, "started_from": bool(started_from),
            "learned_vs_deflectometry": compare_surfaces(facets, learned, defl),
            "ideal_vs_deflectometry": compare_surfaces(facets, ideal, defl),
            "median_l1_deflectometry": statistics.median(e_defl["l1"])}


def _report(train, test, ev, optics, scores, s, info, model, alignment, background):
    rows = _test_rows(test, ev["ideal"], ev["learned"], ev["sharp"], ev["mc"])
    d_mm = model.displacement.detach() * 1e3
    return {
        "train": [{"record": int(r), "l1_ideal": a, "l1_learned": b}
                  for r, a, b in zip(train.ids, ev["train_ideal"]["l1"], ev["train_learned"]["l1"])],
        "test": rows,
        "median_l1_ideal": statistics.median(ev["ideal"]["l1"]),
        "median_l1_learned": statistics.median(ev["learned"]["l1"]),
        "median_l1_ideal_sharp_sun": statistics.median(ev["sharp"]["l1"]),
        "median_imp": statistics.median(r["imp"] for r in rows),
        "median_imp_vs_sharp_sun": statistics.median(r["l1_ideal_sharp_sun"] / max(r["l1_learned"], 1e-12) - 1.0
                                                     for r in rows),
        "learned_below_ideal_on_all": all(r["l1_learned"] < r["l1_ideal"] for r in rows),
        "torch_threads": torch.get_num_threads(),
        "optics": _optics_report(optics, scores),
        "comparison": _comparison_report(s, alignment, background),
        "early_stopping": info.selection,
        "settings": s.as_dict(),
        "displacement_mm": {"max_abs": float(d_mm.abs().max()), "rms": float(d_mm.pow(2).mean().sqrt())},
    }


def reconstruct_observed(facets: Facets, train: Observations, test: Observations,
                         settings: TrainSettings | None = None, *, sun: SunSettings | None = None,
                         slope_error: float | None = None, evaluate_mc: bool = True, progress: bool = True,
                         deflectometry=None, start_from_deflectometry: bool = False, alignment: str = "focal-spot",
                         background: float = 0.0) -> tuple[dict, LearnableSurface, dict]:
    """Learn a heliostat's surface from its training images (:func:`train_with_early_stopping`); evaluate on
    the test images.

    Parameters
    ----------
    facets : Facets
        One heliostat, ``[1, F, 3]`` [m].
    train, test : Observations
        Images ``[B, R, R]`` with poses (:func:`heliotwin.surfaces.observations.paint_observations`).
    settings : TrainSettings
    sun : SunSettings, optional
        Base optics (default Buie, CSR 0.05); the slope error is ``slope_error`` [rad] or, when None, chosen
        by the ideal surface's training L1 (:func:`choose_slope_error`).
    evaluate_mc : bool
        Also compare the test images traced by the Monte-Carlo tracer.
    deflectometry : path, optional
        A PAINT deflectometry HDF5 file: its NURBS fit is traced on the test images like the ideal and learned
        surfaces and the learned surface is compared with it in mm and mrad (report key ``deflectometry``);
        with ``start_from_deflectometry`` the learning starts from it instead of flat.
    alignment, background
        How the observations were made (reported).

    Under an active :mod:`heliotwin.io.checkpoint` every fit saves its state and a resumed checkpoint continues
    it (:mod:`heliotwin.surfaces.training`). The learner follows the device of ``facets`` and the observations.

    Returns
    -------
    report : dict
        JSON-ready (per test record L1 / cross-correlation for ideal and learned, median IMP, settings,
        ``fit_seconds``).
    model : LearnableSurface
    extras : dict
        ``train``/``test`` Observations, predicted ideal/learned test images ``[B, R, R]`` (for plots),
        ``optics``, ``facets``, ``ideal`` and ``fit_info`` (:class:`~heliotwin.surfaces.training.FitInfo`).
    """
    s = settings or TrainSettings()
    defl = defl_fit = None
    if deflectometry is not None:
        defl, defl_fit = deflectometry_surface(deflectometry, Facets(*(t.to(torch.float64) for t in facets)))
    elif start_from_deflectometry:
        raise HeliotwinError("start_from_deflectometry needs a deflectometry file")
    base_sun = sun or SunSettings(sunshape="buie", csr=0.05)
    if slope_error is None:
        chosen, scores = choose_slope_error(facets, train, base_sun, s)
    else:
        chosen, scores = float(slope_error), {}
    optics = dataclasses.replace(base_sun, slope_error=chosen)
    t_fit = time.perf_counter()
    init = dict(initial=defl.control_points, initial_degree=(defl.degree_u, defl.degree_v)) \
        if start_from_deflectometry else {}
    model, info = train_with_early_stopping(facets, train, optics, s, progress, **init)
    fit_seconds = time.perf_counter() - t_fit
    ideal = LearnableSurface(facets, s.control_points, s.degree).surfaces()
    learned = model.surfaces()
    ev = _evaluate(ideal, learned, train, test, optics, s, evaluate_mc)
    report = _report(train, test, ev, optics, scores, s, info, model, alignment, background)
    report.update(fit_seconds=fit_seconds)
    if defl is not None:
        report["deflectometry"] = _deflectometry_report(deflectometry, defl_fit, defl, facets, ideal, learned, test,
                                                        optics, s, report["test"], start_from_deflectometry)
    extras = {"train": train, "test": test, "ideal_images": ev["ideal"]["images"],
              "learned_images": ev["learned"]["images"], "optics": optics, "facets": facets, "ideal": ideal,
              "fit_info": info}
    return report, model, extras
