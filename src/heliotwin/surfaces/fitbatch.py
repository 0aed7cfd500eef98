"""K surface fits run as one (:func:`fit_surfaces`): the learner's leave-one-out fits in one batched Adam run.

Why it equals K serial :func:`~heliotwin.surfaces.fit.fit_surface` calls. The K problems share nothing but the
settings: each has its own displacements (one row of a ``[K, F, nu, nv]`` parameter), per-image log-blurs,
training images, camera model, slope-penalty weight and held-out image. The objective is the sum of the K
problems' objectives, so the gradient of a problem's row is the gradient of its own objective (no other term
depends on it), and Adam (elementwise moments, one learning-rate schedule) takes the serial fit's step. Only the
float rounding of batched sums differs (``tests/test_surfaces_generalise.py`` compares curves and surfaces with
the serial fits).

Why it is faster. One step of one fit is a few thousand small tensor operations whose cost is mostly the
per-operation overhead; one batched step over K problems has about as many operations as one serial step.

Mini-batches (``SurfaceSettings.batch_images``): each problem renders its own batch of images per step
(:func:`~heliotwin.surfaces.fit.minibatch_rows`), as its serial fit does, so a step's cost no longer grows with
the images.

Scope. Adam with a camera model and held-out images per problem, no plant prior (the leave-one-out fits of
:func:`~heliotwin.surfaces.generalise.loo_select`), one heliostat's facets and start for all problems. The
problem axis is the heliostat axis of :class:`~heliotwin.field.plant.Surfaces` ``[H, F, ...]`` and the render
takes each image's own mirror samples, so problems of different heliostats need per-problem facets and starts
(their facet counts equal, or padded), not a new forward model.

Shapes: K problems; B_k training images of problem k, B = sum of B_k; F facets; R window pixels per side.
Units as :mod:`heliotwin.surfaces.fit`.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import torch

from ..calibrate.fitloop import early_stopping_fit
from ..errors import HeliotwinError
from ..field import facets as facet_ops
from ..field.plant import Facets, SunSettings
from ..scene import to_world
from . import losses
from .edges import slope_penalties
from .fit import (
    SurfaceFit,
    SurfaceSettings,
    _loop_state,
    adam_step,
    blur_for,
    keep_spectra,
    minibatch_rows,
    step_images,
)
from .imaging import render_samples
from .learning import MM, LearnableSurface, gauge_basis, learnable_surfaces, normal_heights
from .nuisance import CameraModel, apply_camera
from .observations import Observations

__all__ = ["FitProblem", "fit_surfaces", "concat_observations"]


@dataclass
class FitProblem:
    """One of the K problems of :func:`fit_surfaces` (the arguments of one serial ``fit_surface`` call).

    Attributes
    ----------
    obs : Observations
        Training images ``[B_k, R, R]`` with poses.
    camera : CameraModel
        Their camera model (``B_k`` entries).
    sigma0 : torch.Tensor, [B_k]
        Starting per-image blur [px].
    slope_weight : float
        Weight of the slope-deviation penalty (0: none).
    heldout : (Observations, CameraModel)
        Its held-out images (one or more: a fold) and their camera model.
    """

    obs: Observations
    camera: CameraModel
    sigma0: torch.Tensor
    slope_weight: float
    heldout: tuple


def concat_observations(parts: list) -> Observations:
    """The observations of ``parts`` (a list of :class:`Observations`) one after the other (B = sum of their B)."""
    def cat(xs):
        if all(x is None for x in xs):
            return None
        if any(x is None for x in xs):
            raise HeliotwinError("observations to join must all have images (and centres), or none")
        return torch.cat(xs)

    return Observations(torch.cat([o.sun for o in parts]), torch.cat([o.rotation for o in parts]),
                        torch.cat([o.concentrator for o in parts]), [t for o in parts for t in o.targets],
                        cat([o.images for o in parts]), [i for o in parts for i in o.ids],
                        cat([o.centers for o in parts]))


def _concat_cameras(parts: list) -> CameraModel:
    return CameraModel(torch.cat([c.threshold for c in parts]), torch.cat([c.n_saturated for c in parts]))


def _per_problem_mean(values: torch.Tensor, owner: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    # [B] per-image values -> [K] means over each problem's images.
    return torch.zeros(len(counts), dtype=values.dtype, device=values.device).index_add(0, owner, values) / counts


class _BatchLive:
    """The live state of a batched fit (what its checkpoint saves), like :class:`heliotwin.surfaces.fit._Live`."""

    def __init__(self, displacement_mm: torch.Tensor, log_sigma: torch.Tensor, k: int):
        self.displacement_mm, self.log_sigma, self.kernels = displacement_mm, log_sigma, {}
        self.curves, self.steps = [[] for _ in range(k)], 0
        self.heldout = [{} for _ in range(k)]

    def dump(self) -> dict:
        return {"steps": self.steps, "displacement_mm": self.displacement_mm.detach().clone(),
                "log_sigma": self.log_sigma.detach().clone(),
                "kernels": {k: v for k, v in self.kernels.items() if not isinstance(k, tuple)},
                "curves": [[[a, b] for a, b in c] for c in self.curves],
                "heldout": [{int(s): dict(v) for s, v in h.items()} for h in self.heldout]}

    def load(self, data: dict) -> None:
        with torch.no_grad():
            self.displacement_mm.copy_(data["displacement_mm"])
            self.log_sigma.copy_(data["log_sigma"])
        self.kernels.clear()
        self.kernels.update(data["kernels"])
        self.curves[:] = [[(int(a), float(b)) for a, b in c] for c in data["curves"]]
        self.heldout[:] = [{int(s): dict(v) for s, v in h.items()} for h in data["heldout"]]
        self.steps = int(data["steps"])


def fit_surfaces(facets: Facets, problems: list, sun: SunSettings, s: SurfaceSettings, *,
                 start: torch.Tensor | None = None, steps: int | None = None) -> list:
    """Run the K serial fits ``fit_surface(facets, p.obs, sun, s, start=start, camera=p.camera, sigma0=p.sigma0,
    slope_weight=p.slope_weight, heldout=p.heldout, steps=steps)`` of ``problems`` as one batched Adam run.

    Parameters
    ----------
    facets : Facets
        One heliostat, ``[1, F, 3]`` [m] (shared by all problems).
    problems : list of FitProblem
        K >= 1 problems (all with or all without fixed window centres).
    sun : SunSettings
    s : SurfaceSettings
        ``optimizer="adam"``.
    start : torch.Tensor, [1, F, nu, nv, 3], optional
        Starting control net (default: flat canted facets), shared.
    steps : int, optional
        Overrides ``s.steps``.

    Under an active checkpoint the batch claims one ``fit`` key. Follows the device of facets and observations.

    Returns
    -------
    list of SurfaceFit
        One per problem, in order: final state (``model``), learned blur ``sigma`` ``[B_k]`` [px], held-out
        ``curve`` and steps run.
    """
    if s.optimizer != "adam":
        raise HeliotwinError("fit_surfaces runs the Adam fit only")
    if not problems:
        raise HeliotwinError("fit_surfaces needs at least one problem")
    k = len(problems)
    steps = int(s.steps if steps is None else steps)
    tilt = problems[0].obs.centers is None
    if any((p.obs.centers is None) != tilt for p in problems):
        raise HeliotwinError("fit_surfaces: problems must all have fixed window centres, or none")
    proto = LearnableSurface(facets, s.control_points, s.degree, initial=start, fix_gauge=True, gauge_tilt=tilt)
    start_mm = proto.start_mm  # [1, F, nu, nv]
    q = gauge_basis(proto.facets, proto.num_control_points, proto.degree, common_tilt=tilt).to(start_mm)
    weights = torch.tensor([float(p.slope_weight) for p in problems], dtype=torch.float64)
    ref = None
    if bool((weights != 0).any()):
        ref = normal_heights(facets, proto.surfaces().control_points.detach(), s.degree, (16, 16))[1].detach()
    obs = concat_observations([p.obs for p in problems])
    dev = obs.images.device
    sizes = [len(p.obs) for p in problems]
    owner = torch.repeat_interleave(torch.arange(k, device=dev), torch.tensor(sizes, device=dev))
    camera = _concat_cameras([p.camera for p in problems])
    meas = obs.images.to(torch.float32)
    rows = minibatch_rows(sizes, s.batch_images, steps, s.batch_seed, device=dev)
    taken = sizes if rows is None else [min(int(s.batch_images), n) for n in sizes]  # images per step
    step_owner = torch.repeat_interleave(torch.arange(k, device=dev), torch.tensor(taken, device=dev))
    counts = torch.tensor(taken, dtype=torch.float32, device=dev)
    hobs = concat_observations([p.heldout[0] for p in problems])
    hcam = _concat_cameras([p.heldout[1] for p in problems])
    hsizes = [len(p.heldout[0]) for p in problems]
    howner = torch.repeat_interleave(torch.arange(k, device=dev), torch.tensor(hsizes, device=dev))
    hbounds = [sum(hsizes[:i]) for i in range(k + 1)]
    sig0 = torch.cat([p.sigma0.to(device=dev, dtype=torch.float32) for p in problems])
    log_sigma = torch.log(sig0.clamp_min(0.1)).clone().requires_grad_(True)
    disp = proto.displacement_mm.detach().expand(k, *start_mm.shape[1:]).clone().requires_grad_(True)
    live = _BatchLive(disp, log_sigma, k)
    bounds = [sum(sizes[:i]) for i in range(k + 1)]

    def displacement() -> torch.Tensor:
        # LearnableSurface.displacement per row: the gauge modes projected out of the change from the start [m].
        change = (disp - start_mm).reshape(k, -1)
        return (start_mm + (change - (change @ q) @ q.T).reshape(disp.shape)) * MM

    def world(d_m: torch.Tensor, images: Observations, rows: torch.Tensor):
        surf = learnable_surfaces(proto.facets, proto.base, d_m, s.degree)
        pts, nrm, area = facet_ops.surface_points(surf, s.samples)  # [K, N, 3]
        pw, nw = to_world(images.rotation.to(pts), images.concentrator.to(pts), pts[rows], nrm[rows], torch.float32)
        return surf, pw, nw, area.to(torch.float32)[rows], images.sun.to(pw)

    def start_kernels(images: Observations, rows: torch.Tensor, cache: dict) -> None:
        # Every image's kernel from the start surface (what the first full step would make), each distinct pose
        # once: the problems share the start, and an image sits in several problems (folds x weights).
        if all(("spectrum", i) in cache for i in range(len(images))):
            return
        keys = [(id(t), *images.sun[i].tolist(), *images.rotation[i].flatten().tolist(),
                 *images.concentrator[i].tolist()) for i, t in enumerate(images.targets)]
        first, unique = {}, []  # key -> its position among the distinct poses; their first rows
        for i, key in enumerate(keys):
            if key not in first:
                first[key] = len(unique)
                unique.append(i)
        sub, made = images.subset(unique), {}
        with torch.no_grad():
            _, pw, nw, ar, sund = world(displacement(), sub, rows[unique])
            render_samples(pw, nw, ar, sund, sub, sun, resolution=s.resolution, size_m=s.size_m, kernels=made)
        for i, key in enumerate(keys):
            cache[i], cache[("spectrum", i)] = made[first[key]], made[("spectrum", first[key])]

    start_kernels(obs, owner, live.kernels)

    def objective() -> tuple[torch.Tensor, torch.Tensor]:
        d_m = displacement()
        if rows is None:
            seen, kern, cam, sig, meas_t = obs, live.kernels, camera, log_sigma, meas
        else:  # this step's images (the loop has taken live.steps steps)
            idx, seen, kern, cam, sig, meas_t = step_images(rows, live.steps, obs, live.kernels, camera, log_sigma,
                                                            meas)
        surf, pw, nw, ar, sund = world(d_m, seen, step_owner)
        pred, _, miss, _ = render_samples(pw, nw, ar, sund, seen, sun, resolution=s.resolution, size_m=s.size_m,
                                          kernels=kern)
        if rows is not None:
            keep_spectra(live.kernels, kern, idx)
        per_image = losses.IMAGE_LOSSES[s.loss](apply_camera(pred, cam, sig.exp()), meas_t.to(pred))
        data = _per_problem_mean(per_image, step_owner, counts)
        d = d_m / 1e-3
        reg = s.ridge * d.pow(2).flatten(1).mean(-1) + s.laplacian * losses.laplacian_per_row(d)
        total = data.to(reg) + reg + s.miss * _per_problem_mean(miss, step_owner, counts).to(reg)
        if ref is not None:
            total = total + slope_penalties(surf, ref, weights.to(reg))
        return total.sum(), data.sum()

    opt = torch.optim.Adam([{"params": [disp], "lr": s.lr}, {"params": [log_sigma], "lr": s.blur_lr}])
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=s.decay)

    step = adam_step(opt, sched, objective, live)

    hkernels: dict = {}  # the held-out images' kernels from the start surface, as the training images' are made
    start_kernels(hobs, howner, hkernels)

    def heldout_l1() -> torch.Tensor:
        at = live.steps
        if at == 0 or at % s.eval_every != 0:
            return torch.full((k,), float("inf"))
        blur = live.log_sigma.detach().exp()
        sig = torch.cat([blur_for(p.obs.targets, blur[bounds[i]:bounds[i + 1]], p.heldout[0].targets)
                         for i, p in enumerate(problems)])
        with torch.no_grad():
            _, pw, nw, ar, sund = world(displacement(), hobs, howner)
            pred, _, _, _ = render_samples(pw, nw, ar, sund, hobs, sun, resolution=s.resolution, size_m=s.size_m,
                                           kernels=hkernels)
            meas_h = hobs.images.to(pred)
            cam = apply_camera(pred, hcam, sig)
            l1, l1_raw = losses.l1(cam, meas_h).tolist(), losses.l1(pred, meas_h).tolist()
        means = []
        for i in range(k):
            a, b = hbounds[i], hbounds[i + 1]
            live.heldout[i][at] = {"l1": l1[a:b], "l1_raw": l1_raw[a:b], "sigma": sig[a:b].tolist(),
                                   "images": cam[a:b].clone()}
            means.append(sum(l1[a:b]) / (b - a))
            live.curves[i].append((at, means[-1]))
        return torch.tensor(means, dtype=torch.float64)

    early_stopping_fit(step, heldout_l1, _loop_state(live), steps, validated=torch.zeros(k, dtype=torch.bool),
                       check_every=s.eval_every)
    out = []
    for i in range(k):
        model = copy.deepcopy(proto)
        with torch.no_grad():
            model.displacement_mm.copy_(disp[i:i + 1])
        out.append(SurfaceFit(model, log_sigma.detach()[bounds[i]:bounds[i + 1]].exp(), list(live.curves[i]), [],
                              live.steps, dict(live.heldout[i])))
    return out
