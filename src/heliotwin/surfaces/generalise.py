"""The surface learner: learning that carries over to unseen images, every setting chosen inside the training images.

It is the one surface learner of the library (:func:`reconstruct_generalising` is its study entry: fit, then
evaluate on test images, one report-row shape). Its settings are one class
(:class:`~heliotwin.surfaces.fit.SurfaceSettings`); each of its fits (leave-one-out and final) is one
:func:`~heliotwin.surfaces.fit.fit_surface`, run in calibration's fit loop; without a plant prior the
leave-one-out fits of one blur mode run as one batch (:func:`~heliotwin.surfaces.fitbatch.fit_surfaces`, the
same fits up to float rounding, one checkpoint key).

Steps (:func:`fit_generalising`), each a stated rule:

1. **Optics before surface** (:func:`choose_optics`). The ideal surface's spot must be a fair start before
   the surface is asked to absorb anything. Candidates: flat canted facets, or facets curved to a focal
   length that is a multiple of the one the heliostat's *canting* implies (:func:`canting_focal_length`:
   the facets' tilt towards the centre, ``f = r / (2 tilt)``, median over facets and axes), times slope
   errors of ``SurfaceSettings.slope_grid``; each with every training image's best blur of
   ``blur_grid_px`` and the camera model (:mod:`heliotwin.surfaces.nuisance`). The combination with the
   lowest mean training L1 of the ideal surface is kept; the ideal baseline uses it too.
2. **Image nuisance**: per image the camera cut and saturation (estimated from that measured image) and one
   blur ``sigma`` [px], learned with the surface. An unseen image gets the median blur of the training
   images on the same target (each target has its own camera), else of all training images.
3. **Loss**: L1 of unit-sum images (the judged metric), after the camera model.
4. **Selection by cross-validation** (:func:`loo_select`): for each slope-penalty weight of
   ``slope_weight_grid`` and each fold, fit on the other images and record each held-out image's L1 every
   ``eval_every`` steps; the (weight, step count) with the lowest mean held-out L1 over the images is kept (a
   cross-validated step budget: no single image decides when to stop). Folds: one image each (leave one
   out) by default; ``SurfaceSettings.folds`` K-fold (:func:`cv_folds`) with ``batch_images`` per fit and
   step, as ``reconstruct`` runs when every image trains (:data:`CV_FOLDS`, :data:`CV_BATCH_IMAGES`). Each
   image's held-out evaluation under the choice is kept: with every image training, those are the report's
   test rows (an honest error estimate from inside the images).
5. **Inconsistent images**: an image whose held-out L1 at the chosen setting is a robust-z outlier
   (two-sided, :func:`heliotwin.surfaces.acceptance.robust_outliers`) is dropped, and steps 1-4 are run
   again on the kept images (the odd image may have pulled the optics choice too).
6. **Final fit** on the kept images, then the **acceptance rule**
   (:func:`heliotwin.surfaces.acceptance.shrink_to_accept`) over *all* training images, dropped ones included.
7. **Facet edges**: the slope-deviation penalty with a hinge at 5 mrad (:mod:`heliotwin.surfaces.edges`).
8. **Plant prior** (optional ``prior``, :class:`heliotwin.surfaces.plantprior.SurfacePrior`): the prior
   mean's low-order facet shape joins the start candidates of step 1 (kept when its ideal fits the training
   images best), and the prior penalty (Mahalanobis distance of the facets' low-order shape from the plant
   mean) enters the loss with a weight chosen in step 4 jointly with the slope-penalty weight from
   :data:`~heliotwin.surfaces.plantprior.PRIOR_WEIGHT_GRID`, which includes 0: the prior is used only when
   held-out training images say it helps. With fewer than 3 images there is no leave-one-out, so no held-out
   evidence, and the penalty is not used (the grid's smallest weight, 0): the prior then acts through the
   start candidate only. (Tried and rejected: the grid's largest weight, as for the slope weight; in silico
   it lost to the start alone, see ``benchmarks/bench_surface_prior.py``.) Without a prior every step is as
   above.

Shapes: B images, R window pixels per side, F facets. Units: metres, radians; L1 of unit-sum images.
"""
from __future__ import annotations

import dataclasses
import statistics

import torch

from ..calibrate.choice import lowest
from ..errors import HeliotwinError
from ..field.plant import Facets, SunSettings
from ..progress import iterate
from . import losses
from .acceptance import robust_outliers, shrink_to_accept, wilson_interval
from .edges import edge_ridge_mrad
from .fit import SurfaceSettings, blur_for, evaluate_with_camera, fit_surface, render
from .fitbatch import FitProblem, fit_surfaces
from .learning import LearnableSurface, heights_to_displacement, learnable_surfaces
from .nuisance import CameraModel, apply_camera, estimate_camera
from .observations import Observations
from .plantprior import PRIOR_WEIGHT_GRID, check_facets, describe, prior_penalty

__all__ = ["SurfaceSettings", "reconstruct_generalising", "CV_FOLDS", "CV_BATCH_IMAGES", "CV_OPTICS_IMAGES",
           "spread_images", "summarise",
           "canting_focal_length", "focused_start", "choose_optics", "fit_generalising",
           "blur_for", "evaluate_with_camera", "loo_select", "cv_folds"]


#: Cross-validation folds when every centred image trains the surface (``reconstruct``'s default). Leave one
#: out costs about the square of the images (AA39's 10 would take ~160 s against a 30 s budget per heliostat);
#: three folds hold each image out once at a cost that no longer grows with them (with the batches below).
CV_FOLDS = 3

#: Images per fit and Adam step in that mode: two, what the leave-one-out over three images renders per fit and
#: step, so a heliostat with many images costs what one with three does. Three images are then still learned
#: exactly as before (two per fold: the full batch). Checked in silico against the three latest images' learner
#: (``benchmarks/bench_insilico.py --every-image``, 10 cases of 9 images: better median test L1 in 7, and the
#: cross-validated L1 within 0.003 of the test L1 on average). Full batches would be better still by up to 0.008,
#: at twice the time.
CV_BATCH_IMAGES = 2

#: Images that score the optics candidates in that mode (spread over the record; :func:`spread_images`): the
#: choice renders every candidate (4 focus x 8 slope errors) for each image, the one cost of the learner that
#: still grew with the images (AA39's 10: 1.2 s; 40 images: 4.1 s). Twelve leave every heliostat with up to
#: twelve images learned exactly as without the bound; in silico with 24 images the bound chose the same optics
#: in 6 of 8 cases and the same median test L1 on average (``bench_insilico.py --every-image --optics all,12``).
CV_OPTICS_IMAGES = 12


def canting_focal_length(facets: Facets) -> float | None:
    """Focal length [m] the canting implies: ``|r| / (2 tilt)`` per facet and axis, median (None if uncanted).

    ``tilt`` is the facet normal's angle towards the heliostat centre along east (north), from the
    ``canting_e`` (``canting_n``) span vectors' up component; ``r`` the facet centre's east (north) offset.
    """
    tr = facets.translation[0].to(torch.float64)
    ce = facets.canting_e[0].to(torch.float64)
    cn = facets.canting_n[0].to(torch.float64)
    out = []
    for r, span in ((tr[:, 0], ce), (tr[:, 1], cn)):
        tilt = span[:, 2] / span.norm(dim=-1)  # [rad], up component of the span direction
        ok = (r.abs() > 1e-3) & (tilt.abs() > 1e-5) & (torch.sign(r) == torch.sign(tilt))
        out += (r[ok].abs() / (2 * tilt[ok].abs())).tolist()
    return statistics.median(out) if out else None


def focused_start(facets: Facets, focal_length: float | None, num_control_points, degree) -> torch.Tensor | None:
    """Control net ``[1, F, nu, nv, 3]`` of facets curved to a paraboloid of ``focal_length`` [m] (None: flat)."""
    if focal_length is None:
        return None
    # A tiny least-squares fit: on the CPU (heights_to_displacement builds its bases there), then to the net.
    le = facets.canting_e[0].detach().cpu().to(torch.float64).norm(dim=-1)
    ln = facets.canting_n[0].detach().cpu().to(torch.float64).norm(dim=-1)
    su = sv = 32
    u = (torch.arange(su, dtype=torch.float64) + 0.5) / su * 2 - 1
    v = (torch.arange(sv, dtype=torch.float64) + 0.5) / sv * 2 - 1
    x = u[None, :, None] * le[:, None, None]
    y = v[None, None, :] * ln[:, None, None]
    h = (x ** 2 + y ** 2) / (4 * float(focal_length))  # [F, su, sv] [m]; degree >= 2 holds it exactly
    d = heights_to_displacement(h, num_control_points, degree)
    base = LearnableSurface(facets, num_control_points, degree).base
    return learnable_surfaces(facets, base, d.to(base), degree).control_points.detach()


def choose_optics(facets: Facets, train: Observations, base_sun: SunSettings, camera: CameraModel,
                  s: SurfaceSettings, prior=None, renders: dict | None = None) -> dict:
    """Step 1 (module docstring): facet focus x slope error (x per-image blur) by the ideal's training L1.

    With a ``prior`` (:class:`~heliotwin.surfaces.plantprior.SurfacePrior`) its mean shape is one more
    start candidate (``focus_multiple`` ``"prior"``). ``renders``: a cache ``(focus, slope error) -> ideal
    images [B, R, R]`` of these ``train`` images and window settings, shared by calls that differ only in
    the blur grid (the blur modes), so each ideal is rendered once.
    """
    f_cant = canting_focal_length(facets)
    focus = [None] + [m for m in s.focus_grid if m is not None and f_cant is not None]
    if prior is not None:
        focus.append("prior")
    every, every_camera = train, camera
    pick = spread_images(len(train), s.optics_images)
    if pick is not None:  # the candidates are scored on images spread over the record, the blurs found for all
        train, camera = train.subset(pick), camera.subset(pick)
    def ideal_images(key, ideal, images, sun):  # rendered once per key for the calls sharing ``renders``
        if renders is not None and key in renders:
            return renders[key]
        pred, _ = render(ideal, images, sun, s)
        if renders is not None:
            renders[key] = pred
        return pred

    def best_blur(pred, images, cam):  # per image: the lowest L1 over the blur grid [B] and its grid index [B]
        meas = images.images.to(torch.float32).to(pred)
        per_blur = torch.stack([losses.l1(apply_camera(pred, cam, torch.full((len(images),), float(b),
                                                                             device=pred.device)), meas)
                                for b in s.blur_grid_px])  # [G, B]
        return per_blur.min(0)

    scores, best = [], None
    for m in focus:
        if m == "prior":
            start = prior.start(facets, s.control_points, s.degree)
        else:
            start = focused_start(facets, None if m is None else m * f_cant, s.control_points, s.degree)
        ideal = LearnableSurface(facets, s.control_points, s.degree, initial=start).surfaces()
        for se in s.slope_grid:
            sun = dataclasses.replace(base_sun, slope_error=float(se))
            with torch.no_grad():
                l1, ib = best_blur(ideal_images((m, float(se)), ideal, train, sun), train, camera)
            row = {"focus_multiple": m, "focal_length_m": None if m in (None, "prior") else m * f_cant,
                   "slope_error_rad": float(se), "mean_l1": float(l1.mean()),
                   "blur_px": [float(s.blur_grid_px[i]) for i in ib.tolist()]}
            scores.append(row)
            if best is None or row["mean_l1"] < best["mean_l1"]:
                best = dict(row, start=start, ideal=ideal, sun=sun)
    if pick is not None:  # the chosen ideal's best blur for every training image
        with torch.no_grad():
            key = ("every", best["focus_multiple"], best["slope_error_rad"])
            _, ib = best_blur(ideal_images(key, best["ideal"], every, best["sun"]), every, every_camera)
        best["blur_px"] = [float(s.blur_grid_px[i]) for i in ib.tolist()]
    out = {"canting_focal_length_m": f_cant, "chosen": {k: v for k, v in best.items()
                                                        if k not in ("start", "ideal", "sun")},
           "start": best["start"], "scores": scores,
           "rule": "min mean training L1 of the ideal surface (camera model, best blur per image)"}
    if pick is not None:
        out["scored_on"] = {"records": list(train.ids), "rule": f"{len(pick)} of the {len(every)} training images, "
                            f"spread evenly over them in time; the chosen ideal's blur then found for every image"}
    return out


def spread_images(n: int, most: int | None) -> list | None:
    """``most`` indices spread evenly over ``n`` time-ordered images (the first and the last included), or None
    when there are no more than ``most`` (or no bound): which images score the optics candidates."""
    if most is None or n <= int(most):
        return None
    m = max(2, int(most))
    return sorted({round(i * (n - 1) / (m - 1)) for i in range(m)})


def cv_folds(n: int, folds: int | None) -> list:
    """The held-out images of each fold: with ``folds`` below ``n``, image ``i`` (the training images are in time
    order) is held out in fold ``i mod folds``, so every fold spans the record's years; otherwise one image per
    fold (leave one out). Returns a list of lists of indices into the ``n`` images."""
    kf = n if folds is None else max(1, min(n, int(folds)))
    return [[i for i in range(n) if i % kf == f] for f in range(kf)]


def loo_select(facets, train, camera, sigma0, sun, start, s, progress=False, prior=None,
               prior_grid=PRIOR_WEIGHT_GRID) -> dict:
    """Step 4-5: cross-validated choice of the slope-penalty weight and step count; outliers.

    Leave one training image out, or with ``s.folds`` below the images K folds (:func:`cv_folds`); every image is
    held out once, and a setting's score is the mean held-out L1 over the images. With a ``prior`` the
    prior-penalty weight (``prior_grid``, which should include 0) is chosen jointly: the (slope weight, prior
    weight, step count) with the lowest mean held-out L1; ties go to the earlier grid entry (0 first: a prior
    that does not help on held-out images is not used).

    ``train``: the B training images; ``camera`` their camera model; ``sigma0`` ``[B]`` [px] their starting
    blurs; ``start`` the starting net ``[1, F, nu, nv, 3]`` [m] (None: flat canted facets); ``sun`` the
    chosen optics. Returns the chosen ``slope_weight`` (and ``prior_weight``), ``steps``, the B held-out
    L1s [1] under that choice, their robust z-scores, the indices to ``drop``, the whole ``table``, the
    ``folds`` and, in memory (``heldout_rows``, not JSON), each image's held-out evaluation under the choice
    (``l1``, ``l1_raw``, ``sigma`` [px] and the predicted ``image`` ``[R, R]`` through the camera model).
    """
    n = len(train)
    folds = cv_folds(n, s.folds)
    fits: dict = {}
    pgrid = (None,) if prior is None else tuple(float(p) for p in prior_grid)
    jobs = [(w, p, f) for w in s.slope_weight_grid for p in pgrid for f in range(len(folds))]

    def keep_of(f):
        return [i for i in range(n) if i not in folds[f]]

    label = "heliotwin reconstruct: " + ("leave-one-out" if len(folds) == n else "cross-validation")
    if prior is None and s.optimizer == "adam":
        # The same fits as the loop below, run as one batch (fitbatch: equal up to float rounding, ~K x fewer
        # tensor operations).
        problems = [FitProblem(train.subset(keep_of(f)), camera.subset(keep_of(f)), sigma0[keep_of(f)], w,
                               (train.subset(folds[f]), camera.subset(folds[f]))) for w, _, f in jobs]
        for _ in iterate([jobs], label, unit="run", enabled=progress, every=25):
            batch = fit_surfaces(facets, problems, sun, s, start=start)
        fits = dict(zip(jobs, batch))
    else:
        for w, p, f in iterate(jobs, label, unit="fit", enabled=progress, every=25):
            keep = keep_of(f)
            fits[(w, p, f)] = fit_surface(facets, train.subset(keep), sun, s, start=start,
                                          camera=camera.subset(keep), sigma0=sigma0[keep], slope_weight=w,
                                          prior=prior, prior_weight=p or 0.0,
                                          heldout=(train.subset(folds[f]), camera.subset(folds[f])))

    def per_image(w, p, st) -> list:
        # every image's held-out evaluation at step st, in image order
        out = [None] * n
        for f, held in enumerate(folds):
            ev = fits[(w, p, f)].heldout[st]
            for j, i in enumerate(held):
                out[i] = {"l1": ev["l1"][j], "l1_raw": ev["l1_raw"][j], "sigma": ev["sigma"][j],
                          "image": ev["images"][j]}
        return out

    table = {}
    for w in s.slope_weight_grid:
        for p in pgrid:
            for st, _ in fits[(w, p, 0)].curve:
                table[(w, p, st)] = statistics.mean(r["l1"] for r in per_image(w, p, st))
    (w_best, p_best, st_best) = lowest(table)
    rows = per_image(w_best, p_best, st_best)
    held = [r["l1"] for r in rows]
    drop, z = robust_outliers(held)
    out = {"slope_weight": w_best, "steps": st_best, "heldout_l1": held, "robust_z": z, "drop": drop,
           "folds": len(folds), "heldout_rows": rows}
    if prior is None:
        out["table"] = [{"slope_weight": w, "steps": st, "mean_heldout_l1": v} for (w, _, st), v in table.items()]
        return out
    out["prior_weight"] = p_best
    out["table"] = [{"slope_weight": w, "prior_weight": p, "steps": st, "mean_heldout_l1": v}
                    for (w, p, st), v in table.items()]
    return out


def _mode_settings(s: SurfaceSettings, mode: str) -> SurfaceSettings:
    # "none": no per-image blur (the surface and the global slope error explain the spot); "per-image": learned.
    return s if mode == "per-image" else dataclasses.replace(s, blur_grid_px=(0.0,), blur_lr=0.0)


def _candidates(facets, train, base_sun, camera, s, progress, prior=None, prior_grid=PRIOR_WEIGHT_GRID) -> list:
    """Per blur mode: the optics choice and (with >= 3 images) the leave-one-out table."""
    out, renders = [], {}  # the modes differ in the blur only: their ideal images are the same
    for mode in s.blur_modes:
        sm = _mode_settings(s, mode)
        opt = choose_optics(facets, train, base_sun, camera, sm, prior, renders)
        sun = dataclasses.replace(base_sun, slope_error=opt["chosen"]["slope_error_rad"])
        sigma0 = torch.tensor(opt["chosen"]["blur_px"], dtype=torch.float32, device=train.images.device)
        rows = None
        if len(train) >= 3 and s.select:
            sel = loo_select(facets, train, camera, sigma0, sun, opt["start"], sm, progress, prior, prior_grid)
            rows = sel.pop("heldout_rows")  # tensors: kept beside the JSON-ready selection
            score = min(r["mean_heldout_l1"] for r in sel["table"])
        else:
            sel = {"slope_weight": s.slope_weight_grid[-1], "steps": s.steps, "drop": [],
                   "note": "no leave-one-out (fewer than 3 images or select=False)"}
            if prior is not None:  # no held-out evidence that the penalty helps: its smallest weight (0)
                sel["prior_weight"] = float(min(prior_grid))
            score = opt["chosen"]["mean_l1"]
        out.append({"mode": mode, "settings": sm, "optics": opt, "sun": sun, "sigma0": sigma0, "selection": sel,
                    "score": score, "heldout_rows": rows})
    return out


def fit_generalising(facets: Facets, train: Observations, base_sun: SunSettings, s: SurfaceSettings | None = None,
                     progress: bool = False, prior=None, prior_grid=PRIOR_WEIGHT_GRID) -> tuple[LearnableSurface, dict]:
    """Steps 1-8 of the module docstring on one heliostat's training images.

    The per-image blur is itself a choice: ``blur_modes`` ("none", "per-image") are each run through the
    optics choice and leave-one-out, and the mode with the lowest mean held-out L1 is kept.

    ``prior``: a plant prior (:class:`~heliotwin.surfaces.plantprior.SurfacePrior`, step 8) with the
    heliostat's facet count; ``prior_grid``: its penalty weights tried by leave-one-out (include 0).
    The report then has ``prior`` (sources, chosen weight, rule, Mahalanobis^2 of start and result).

    Returns
    -------
    model : LearnableSurface
        The accepted surface (shrunk toward the start if the acceptance rule required it).
    info : dict
        ``optics`` (SunSettings), ``start`` (control net or None), ``camera``, ``sigma`` (per training image
        [px]), ``ideal_kernels`` (the ideal's footprint-kernel cache on the training images: its evaluations
        there share it), a JSON-ready ``report`` of every choice and ``validation``: each training image's
        evaluation when it was held out, under the chosen setting (a dropped image's from the first pass; None
        without cross-validation), a list of dicts as :func:`loo_select`'s ``heldout_rows``.
    """
    s = s or SurfaceSettings()
    if prior is not None:
        check_facets(prior, facets)
    camera = estimate_camera(train.images.to(torch.float32))
    cands = _candidates(facets, train, base_sun, camera, s, progress, prior, prior_grid)
    best = min(cands, key=lambda c: c["score"])
    n = len(train)
    drop = list(best["selection"]["drop"])
    keep = [i for i in range(n) if i not in drop]
    first = None
    validation = best["heldout_rows"]  # each image's held-out evaluation (None without cross-validation)
    if drop:  # choose everything again without the inconsistent images (they pulled the optics too)
        first = {"blur_mode": best["mode"], "selection": best["selection"]}
        cands = _candidates(facets, train.subset(keep), base_sun, camera.subset(keep), s, progress, prior,
                            prior_grid)
        best = min(cands, key=lambda c: c["score"])
        if validation is not None and best["heldout_rows"] is not None:  # a dropped image: its first-pass row
            validation = [best["heldout_rows"][keep.index(i)] if i in keep else validation[i] for i in range(n)]
        # else (fewer than 3 kept: no second cross-validation) every row stays the first pass's
    sm, sun, start, sel = best["settings"], best["sun"], best["optics"]["start"], best["selection"]
    sigma0 = torch.zeros(n, dtype=torch.float32, device=train.images.device)
    sigma0[keep] = best["sigma0"]
    final = fit_surface(facets, train.subset(keep), sun, sm, start=start, camera=camera.subset(keep),
                        sigma0=sigma0[keep], slope_weight=sel["slope_weight"], prior=prior,
                        prior_weight=sel.get("prior_weight", 0.0), steps=sel["steps"])
    model, sigma_keep = final.model, final.sigma
    sigma = sigma0.clone()
    sigma[keep] = sigma_keep
    if drop:  # a dropped image's blur follows the rule for unseen images
        sigma[drop] = blur_for([train.targets[i] for i in keep], sigma_keep, [train.targets[i] for i in drop])
    ideal = LearnableSurface(facets, s.control_points, s.degree, initial=start).surfaces()
    ideal_kernels: dict = {}  # the ideal's footprint kernels on the training images, for every evaluation of it
    ideal_l1 = evaluate_with_camera(ideal, train, sun, camera, sigma, sm, ideal_kernels)["l1"]
    learned_mm = model.displacement_mm.detach().clone()
    start_mm = model.start_mm.detach().clone()

    def l1_at(alpha):
        with torch.no_grad():
            model.displacement_mm.copy_(start_mm + alpha * (learned_mm - start_mm))
        return evaluate_with_camera(model.surfaces(), train, sun, camera, sigma, sm)["l1"]

    alpha, tried = shrink_to_accept(l1_at, ideal_l1)
    l1_at(alpha)
    report = {"optics": {k: v for k, v in best["optics"].items() if k != "start"}, "selection": sel,
              "blur_mode": best["mode"],
              "blur_mode_scores": {c["mode"]: c["score"] for c in cands},
              "blur_mode_rule": "lowest mean held-out L1 (leave-one-training-image-out) over modes",
              "candidates": [{"mode": c["mode"], "optics_chosen": c["optics"]["chosen"],
                              "selection": c["selection"]} for c in cands],
              "dropped": [{"record": train.ids[i], "robust_z": (first or best)["selection"]["robust_z"][i],
                           "heldout_l1": (first or best)["selection"]["heldout_l1"][i],
                           "why": "held-out L1 under a fit to the other training images is a robust-z outlier "
                                  "(|z| > 3); optics, blur mode, weight and steps were then chosen again without it"}
                          for i in drop],
              "first_pass": first,
              "acceptance": {"alpha": alpha, "tried": tried, "shrunk": alpha < 1.0,
                             "rule": "no training image (dropped ones included) worse than the ideal surface; "
                                     "else shrink the deviation from the ideal (largest alpha that passes)"},
              "camera": camera.as_dict(train.ids), "blur_px": dict(zip(train.ids, sigma.tolist())),
              "settings": s.as_dict()}
    if prior is not None:
        with torch.no_grad():
            m2 = {k: float(prior_penalty(prior, surf, facets)) for k, surf in (("start", ideal),
                                                                             ("learned", model.surfaces()))}
        report["prior"] = {**describe(prior), "weight": sel["prior_weight"], "grid": [float(p) for p in prior_grid],
                           "start_is_prior_mean": best["optics"]["chosen"]["focus_multiple"] == "prior",
                           "mahalanobis2": m2,
                           "rule": "penalty weight: jointly with the slope weight and step count by the lowest mean "
                                   "held-out L1 (leave-one-training-image-out; ties to the earlier, 0 first); with "
                                   "fewer than 3 images (no held-out image) the smallest weight of the grid. Start: "
                                   "the prior mean's shape is one candidate of the optics choice (lowest training L1 "
                                   "of the ideal)"}
    return model, {"optics": sun, "start": start, "camera": camera, "sigma": sigma, "report": report,
                   "ideal": ideal, "ideal_kernels": ideal_kernels, "settings": sm, "validation": validation}


def summarise(train_rows: list, test_rows: list) -> dict:
    """Headline figures: medians, training images worse than ideal, test images improved with a Wilson 95 % CI."""
    k = sum(r["l1_learned"] < r["l1_ideal"] for r in test_rows)
    n = len(test_rows)
    lo, hi = wilson_interval(k, n)
    return {"median_l1_ideal": statistics.median(r["l1_ideal"] for r in test_rows),
            "median_l1_learned": statistics.median(r["l1_learned"] for r in test_rows),
            "median_l1_ideal_raw": statistics.median(r["l1_ideal_raw"] for r in test_rows),
            "median_l1_learned_raw": statistics.median(r["l1_learned_raw"] for r in test_rows),
            "train_worse_than_ideal": sum(r["l1_learned"] > r["l1_ideal"] + 1e-6 for r in train_rows),
            "train_worse_than_ideal_raw": sum(r["l1_learned_raw"] > r["l1_ideal_raw"] + 1e-6 for r in train_rows),
            "test_improved": k, "test_images": n, "test_improved_wilson95": [lo, hi],
            "test_improved_raw": sum(r["l1_learned_raw"] < r["l1_ideal_raw"] for r in test_rows),
            # IMP = L1(ideal) / L1(learned) - 1 (docs/glossary.md)
            "median_imp": statistics.median(r["l1_ideal"] / max(r["l1_learned"], 1e-12) - 1.0 for r in test_rows)}


def _rows(obs, e_ideal, e_learn) -> list:
    return [{"record": rid, "target": t.name, "l1_ideal": a, "l1_learned": b, "l1_ideal_raw": c, "l1_learned_raw": d}
            for rid, t, a, b, c, d in zip(obs.ids, obs.targets, e_ideal["l1"], e_learn["l1"], e_ideal["l1_raw"],
                                          e_learn["l1_raw"])]


def reconstruct_generalising(facets: Facets, train: Observations, test: Observations, base_sun: SunSettings,
                             s: SurfaceSettings | None = None, progress: bool = False,
                             reference=None, prior=None, prior_grid=PRIOR_WEIGHT_GRID
                             ) -> tuple[dict, LearnableSurface, dict]:
    """Fit (:func:`fit_generalising`) and evaluate on test images; JSON-ready report.

    ``test`` None: every image trains the surface, and the test rows are each training image's evaluation when
    its cross-validation fold held it out, under the chosen setting (``info["validation"]``; the report's
    ``test_is`` says "cross-validation"; the ideal is evaluated with the same blur). Otherwise test images:
    camera model estimated from each measured test image (its cut and plateau: a property of
    that recording, like PAINT's centring), blur by :func:`blur_for` from the training blurs (never fitted
    to a test image). ``l1_*`` are with the camera model, ``l1_*_raw`` of the raw model images; the ideal
    uses the same optics, start and nuisance, so the difference measures shape. ``info`` (third result) gets
    ``train_images`` / ``test_images``: ``{"ideal", "learned"}`` predicted images ``[B, R, R]`` through the
    camera model, for plots; ``test_camera`` and ``test_sigma`` (``[B]`` [px]): the test images' camera model.
    ``reference``: the surface the edge ridge is measured against (default: the ideal start).
    ``prior``, ``prior_grid``: the plant prior, see :func:`fit_generalising`.
    """
    s = s or SurfaceSettings()
    model, info = fit_generalising(facets, train, base_sun, s, progress, prior, prior_grid)
    sun, ideal, learned = info["optics"], info["ideal"], model.surfaces()
    ev = {}
    if test is None:  # every image trained the surface: the test rows are the cross-validation's held-out ones
        rows = info["validation"]
        if rows is None:
            raise HeliotwinError(f"every one of the {len(train)} centred images trains the surface, and its error is "
                                 f"estimated by cross-validation over them: that needs at least 3 images")
        cam_te, sig_te = info["camera"], torch.tensor([r["sigma"] for r in rows], dtype=torch.float32,
                                                      device=train.images.device)
        e_ideal = evaluate_with_camera(ideal, train, sun, cam_te, sig_te, info["settings"], info["ideal_kernels"])
        e_learn = {"l1": [r["l1"] for r in rows], "l1_raw": [r["l1_raw"] for r in rows],
                   "images": torch.stack([r["image"] for r in rows])}
        ev["test"] = _rows(train, e_ideal, e_learn)
        info["test_images"] = {"ideal": e_ideal["images"], "learned": e_learn["images"]}
        test = train
    else:
        cam_te = estimate_camera(test.images.to(torch.float32))
        sig_te = blur_for(train.targets, info["sigma"], test.targets)
    for name, obs, cam, sig in (("train", train, info["camera"], info["sigma"]), ("test", test, cam_te, sig_te)):
        if name in ev:
            continue
        e_ideal = evaluate_with_camera(ideal, obs, sun, cam, sig, info["settings"],
                                       info["ideal_kernels"] if obs is train else None)
        e_learn = evaluate_with_camera(learned, obs, sun, cam, sig, info["settings"])
        ev[name] = _rows(obs, e_ideal, e_learn)
        info[f"{name}_images"] = {"ideal": e_ideal["images"], "learned": e_learn["images"]}  # with the camera model
    info["test_camera"], info["test_sigma"] = cam_te, sig_te
    report = {"train": ev["train"], "test": ev["test"], **summarise(ev["train"], ev["test"]),
              "edge_ridge": edge_ridge_mrad(learned, reference or ideal, facets),
              "test_camera": cam_te.as_dict(test.ids), "test_blur_px": dict(zip(test.ids, sig_te.tolist())),
              "optics_used": {"sunshape": sun.sunshape, "csr": sun.csr, "slope_error_rad": sun.slope_error},
              **info["report"]}
    report["test_is"] = "cross-validation" if test is train else "held-out images"
    return report, model, info
