"""The one surface fit: its settings (:class:`SurfaceSettings`) and :func:`fit_surface`, run in calibration's loop.

Every surface fit of the library is one call of :func:`fit_surface`: the leave-one-out fits and the final fit of
the learner (:mod:`heliotwin.surfaces.generalise`), and the in-silico study's fits
(:mod:`heliotwin.surfaces.insilico`). Its steps run in :func:`heliotwin.calibrate.fitloop.early_stopping_fit`
(one "heliostat"), which checkpoints and resumes them.

Pipeline per step::

    displacements --LearnableSurface (gauge fixed)--> NURBS facets --surface_points--> heliostat-frame samples
    --pose per image--> world samples --conv integrator (6 m window on the predicted centroid)--> images
    [--camera model (cut, saturation, per-image blur)] --image loss--> + regularisers --optimiser step

Two optimisers (:attr:`SurfaceSettings.optimizer`):

* ``"adam"`` (the learner's): ``steps`` Adam steps with exponential learning-rate decay (the per-image log-blur
  of the camera model at its own rate ``blur_lr``); with held-out images the held-out L1 is recorded every
  ``eval_every`` steps (the curve the cross-validation reads; the final state is kept). Every image, training
  or held out, is rendered with its footprint kernel made once from the start surface (the kernel depends on
  the surface only to second order).
* ``"lbfgs"`` (the in-silico study's): full-batch L-BFGS (strong-Wolfe line search) in rounds, each a fresh
  optimiser (history reset): first one round of ``continuation_iters`` iterations per entry of
  ``continuation`` with both images blurred by a Gaussian of that many pixels (a smoother loss landscape
  first: the flat start is otherwise caught in a local minimum), then sharp rounds of ``lbfgs_round``
  iterations. It ends (the loop's :class:`~heliotwin.calibrate.fitloop.EarlyEnd`) when a sharp round improves
  the loss by less than ``tolerance`` (relative) or after ``steps`` loss evaluations.

Shapes: B images; R window pixels per side; F facets. Units: metres, radians; displacements in the
regularisers in mm; L1 of unit-sum images.
"""
from __future__ import annotations

import dataclasses
import math
import statistics
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from ..calibrate.fitloop import EarlyEnd, State, early_stopping_fit
from ..errors import HeliotwinError
from ..field.plant import Facets, SunSettings
from . import losses
from .edges import slope_penalty
from .imaging import predict_images
from .learning import LearnableSurface, normal_heights
from .nuisance import CameraModel, apply_camera
from .observations import Observations
from .plantprior import prior_penalty

__all__ = ["SurfaceSettings", "SurfaceFit", "fit_surface", "adam_step", "blur_images", "blur_for",
           "evaluate_with_camera", "minibatch_rows", "kernel_view", "step_images", "keep_spectra", "OPTIMIZERS"]

#: The optimisers :func:`fit_surface` runs.
OPTIMIZERS = ("adam", "lbfgs")


@dataclass
class SurfaceSettings:
    """Settings of the surface learner (:func:`heliotwin.surfaces.generalise.fit_generalising`) and of every fit
    it runs (:func:`fit_surface`); grids are searched by the learner's stated rules, nothing is tuned to a
    heliostat.

    Attributes
    ----------
    control_points, degree, samples : (int, int)
        NURBS net and degree per facet; mirror samples per facet and direction.
    resolution, size_m : int, float
        Window pixels per side and side [m].
    focus_grid : tuple of float or None
        Optics choice: facet focal lengths as multiples of the canting focal length; ``None`` = flat facets.
    slope_grid : tuple of float
        Optics choice: slope errors [rad].
    blur_grid_px : tuple of float
        Optics choice: per-image blur candidates [px] (then learned).
    slope_weight_grid : tuple of float
        Weights of the slope-deviation penalty (per mrad^2) tried by leave-one-out.
    steps : int
        Adam: the step budget (the leave-one-out choice picks a count up to it); L-BFGS: the most loss
        evaluations.
    lr, decay, eval_every : float, float, int
        Adam: learning rate [mm per step], decay per step, held-out cadence [steps].
    ridge, laplacian, miss : float
        Fixed regulariser weights (displacements in mm; miss penalty per m^2).
    blur_lr : float
        Adam learning rate of the per-image log-blur.
    blur_modes : tuple of str
        Per-image blur "none" and/or "per-image", each run through the choice (the better one kept).
    select : bool
        Leave-one-out choice of weight and steps (with >= 3 images); False: the grid's largest weight and
        ``steps``.
    folds : int, optional
        Cross-validation folds of that choice: with more training images than ``folds``, image ``i`` (in time
        order) is held out in fold ``i mod folds``; None (or at least as many folds as images): leave one out.
    batch_images : int, optional
        Adam: images per fit and step, drawn without replacement from a fixed seeded schedule
        (:func:`minibatch_rows`; cycling through one random order per pass); None or at least the fit's images:
        every image every step (the fit is then the full-batch one, unchanged).
    batch_seed : int
        Seed of that schedule (every fit with the same number of images takes the same batches).
    optics_images : int, optional
        The optics choice scores its candidates on at most this many training images, spread over them in time
        (:func:`heliotwin.surfaces.generalise.spread_images`); None: on every one.
    optimizer : {"adam", "lbfgs"}
        See the module docstring.
    loss : {"l1", "l2", "kl"}
        Image loss (of unit-sum images; after the camera model where there is one).
    continuation, continuation_iters, lbfgs_round, tolerance
        L-BFGS only: blur continuation [px] and its iterations per round, iterations per sharp round, and the
        relative loss change that ends the fit.
    """

    control_points: tuple = (7, 7)
    degree: tuple = (3, 3)
    samples: tuple = (24, 24)
    resolution: int = 64
    size_m: float = 6.0
    focus_grid: tuple = (None, 1.0, 2.0, 4.0)
    slope_grid: tuple = (0.5e-3, 1.0e-3, 1.5e-3, 2.0e-3, 2.5e-3, 3.0e-3, 4.0e-3, 5.0e-3)
    blur_grid_px: tuple = (0.0, 1.0, 2.0, 3.0, 4.0)
    slope_weight_grid: tuple = (1e-3, 1e-2, 1e-1)
    steps: int = 300
    lr: float = 0.8
    decay: float = 0.99
    eval_every: int = 30
    ridge: float = 1e-4
    laplacian: float = 1e-2
    miss: float = 1.0
    blur_lr: float = 0.05
    blur_modes: tuple = ("none", "per-image")
    select: bool = True
    optimizer: str = "adam"
    loss: str = "l1"
    continuation: tuple = (3.0, 1.5)
    continuation_iters: int = 60
    lbfgs_round: int = 200
    tolerance: float = 1e-3
    folds: int | None = None
    batch_images: int | None = None
    batch_seed: int = 0
    optics_images: int | None = None

    def __post_init__(self):
        if self.optimizer not in OPTIMIZERS:
            raise HeliotwinError(f"unknown optimizer {self.optimizer!r}; expected adam or lbfgs")
        if self.loss not in losses.IMAGE_LOSSES:
            raise HeliotwinError(f"unknown image loss {self.loss!r}; expected one of {', '.join(losses.IMAGE_LOSSES)}")

    def as_dict(self) -> dict:
        """The settings as plain JSON values (tuples as lists), keyed by field name, for reports and checkpoints."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}


@dataclass
class SurfaceFit:
    """What :func:`fit_surface` returns.

    Attributes
    ----------
    model : LearnableSurface
        The final state (``model.surfaces()`` the learned surface ``[1, F, nu, nv, 3]`` [m]).
    sigma : torch.Tensor, [B], optional
        Learned per-image blur [px] (with a camera model).
    curve : list of (int, float)
        Held-out L1 every ``eval_every`` steps, the mean over the held-out images (Adam with held-out images;
        else empty).
    log : list of dict
        L-BFGS: per round ``{"step" (loss evaluations so far), "train", "blur_px", "total"}``.
    evaluations : int
        Adam steps, or L-BFGS loss evaluations, run.
    heldout : dict
        Per checked step, each held-out image's evaluation there: ``{step: {"l1", "l1_raw", "sigma"}}`` (lists
        of length H [1, 1, px]) and ``"images"`` ``[H, R, R]`` (the predictions through the camera model).
    """

    model: LearnableSurface
    sigma: torch.Tensor | None = None
    curve: list = field(default_factory=list)
    log: list = field(default_factory=list)
    evaluations: int = 0
    heldout: dict = field(default_factory=dict)


def minibatch_rows(sizes, batch: int | None, steps: int, seed: int = 0, device=None) -> torch.Tensor | None:
    """The images each of K fits takes at each step, as rows of their concatenated images.

    Problem ``k`` owns rows ``[start_k, start_k + sizes[k])``. With ``batch`` below its size it takes ``batch``
    of them per step: its images in one random order, then the next (a generator seeded with ``seed`` and its
    size, so fits with as many images take the same batches and a resumed fit the same ones), consecutive
    chunks read across the orders. Otherwise it takes all of them every step.

    Returns
    -------
    torch.Tensor, [steps, sum_k min(batch, sizes[k])], long, or None
        Rows per step, problem by problem; None when every problem takes all its images (full batch).
    """
    sizes = [int(n) for n in sizes]
    if batch is None or all(n <= int(batch) for n in sizes):
        return None
    out, start = [], 0
    for n in sizes:
        b = min(int(batch), n)
        if b == n:
            out.append(torch.arange(start, start + n).expand(steps, n))
        else:
            g = torch.Generator().manual_seed(int(seed) * 1_000_003 + n)
            passes = -(-steps * b // n)
            order = torch.cat([torch.randperm(n, generator=g) for _ in range(passes)])
            out.append(start + order[:steps * b].reshape(steps, b))
        start += n
    return torch.cat(out, dim=1).to(device)


def kernel_view(kernels: dict, rows) -> dict:
    """The footprint-kernel cache of :func:`~heliotwin.surfaces.imaging.render_samples` for a batch: entry ``j``
    (and its spectrum, where the full cache has it) is the full cache's ``rows[j]``, which must hold every image's
    kernel. A checkpoint restores the kernels alone: the render makes the missing spectra, and
    :func:`keep_spectra` puts them back."""
    rows = [int(r) for r in rows]
    view = {j: kernels[r] for j, r in enumerate(rows)}
    view.update({("spectrum", j): kernels[("spectrum", r)] for j, r in enumerate(rows) if ("spectrum", r) in kernels})
    return view


def step_images(rows: torch.Tensor, step: int, obs: Observations, kernels: dict, camera, log_sigma: torch.Tensor,
                meas: torch.Tensor) -> tuple:
    """The images a mini-batch fit renders at ``step`` (``rows`` from :func:`minibatch_rows`; past its last row,
    the last again): ``(idx, obs, kernels, camera, log_sigma, meas)`` of those rows -- their row list, their
    observations, a :func:`kernel_view` of the cache, their camera model (None stays None), log blurs ``[b]``
    [log px] and measured images ``[b, R, R]`` [1]. After the render, :func:`keep_spectra` with ``idx``."""
    at = rows[min(int(step), len(rows) - 1)]
    idx = at.tolist()
    return (idx, obs.subset(idx), kernel_view(kernels, idx), None if camera is None else camera.subset(idx),
            log_sigma[at], meas[at])


def keep_spectra(kernels: dict, view: dict, rows) -> None:
    """The spectra a render made in a :func:`kernel_view`, kept in the full cache under their rows."""
    for j, r in enumerate(int(r) for r in rows):
        if ("spectrum", r) not in kernels and ("spectrum", j) in view:
            kernels[("spectrum", r)] = view[("spectrum", j)]


def blur_images(images: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Separable Gaussian blur of ``[B, R, C]`` images (zero padding), same shape out; identity for
    ``sigma_px <= 0``. ``sigma_px``: the kernel's standard deviation [px], one for all B images (cut at 3 sigma)."""
    if sigma_px <= 0:
        return images
    k = int(math.ceil(3.0 * sigma_px))
    x = torch.arange(-k, k + 1, dtype=images.dtype, device=images.device)
    g = torch.exp(-0.5 * (x / sigma_px) ** 2)
    g = g / g.sum()
    y = F.conv2d(images[:, None], g.reshape(1, 1, -1, 1), padding=(k, 0))
    return F.conv2d(y, g.reshape(1, 1, 1, -1), padding=(0, k))[:, 0]


def blur_for(train_targets: list, train_sigma: torch.Tensor, targets: list) -> torch.Tensor:
    """Blur [px] for images on ``targets``: median of the training images' blur on the same target, else all.

    ``train_sigma`` ``(N,)`` [px] belongs to the N ``train_targets``; the result is ``(M,)`` [px], one per entry
    of ``targets`` (float32, on ``train_sigma``'s device)."""
    names = [t.name for t in train_targets]
    out = []
    for t in targets:
        same = [float(s) for n, s in zip(names, train_sigma) if n == t.name]
        out.append(statistics.median(same or [float(s) for s in train_sigma]))
    return torch.tensor(out, dtype=torch.float32, device=train_sigma.device)


def render(surf, obs: Observations, sun: SunSettings, s: SurfaceSettings, kernels=None):
    """Model images ``[B, R, R]`` [W/m^2] of ``surf`` for ``obs`` (conv integrator, ``s``'s window and samples) and
    the miss penalty [m^2] (scalar); ``kernels``: the footprint-kernel cache of
    :func:`~heliotwin.surfaces.imaging.predict_images`."""
    pred, _, miss = predict_images(surf, obs, sun, samples=s.samples, resolution=s.resolution, size_m=s.size_m,
                                   kernels=kernels)
    return pred, miss


def evaluate_with_camera(surf, obs: Observations, sun: SunSettings, camera: CameraModel, sigma: torch.Tensor,
                         s: SurfaceSettings, kernels: dict | None = None) -> dict:
    """Per-image L1 with the camera model (``l1``) and of the raw model image (``l1_raw``), lists of length B;
    predicted images through the camera model (``images``, ``[B, R, R]``). ``sigma``: per-image blur ``[B]`` [px];
    ``kernels``: a footprint-kernel cache of these images (:func:`render`; default: made from ``surf``)."""
    with torch.no_grad():
        pred, _ = render(surf, obs, sun, s, kernels)
        meas = obs.images.to(pred)
        cam = apply_camera(pred, camera, sigma)
        return {"l1": losses.l1(cam, meas).tolist(), "l1_raw": losses.l1(pred, meas).tolist(), "images": cam}


class _Live:
    """The live state of one fit (what its checkpoint saves): surface, log-blur, the footprint-kernel cache
    (filled from the first step's surface, so a resumed fit renders as the uninterrupted one), the held-out
    curve, the steps (Adam) or rounds (L-BFGS) taken, the loss evaluations and the round log."""

    def __init__(self, model: LearnableSurface, log_sigma: torch.Tensor):
        self.model, self.log_sigma, self.kernels, self.curve, self.steps = model, log_sigma, {}, [], 0
        self.evals, self.log, self.heldout = 0, [], {}

    def dump(self) -> dict:
        return {"steps": self.steps, "model": {k: v.detach().clone() for k, v in self.model.state_dict().items()},
                "log_sigma": self.log_sigma.detach().clone(),
                # the kernels alone: their spectra are derived from them and rebuilt identically on resume
                "kernels": {k: v for k, v in self.kernels.items() if not isinstance(k, tuple)},
                "curve": [[a, b] for a, b in self.curve], "evals": self.evals, "log": [dict(e) for e in self.log],
                "heldout": {int(k): dict(v) for k, v in self.heldout.items()}}

    def load(self, data: dict) -> None:
        self.model.load_state_dict(data["model"])
        with torch.no_grad():
            self.log_sigma.copy_(data["log_sigma"])
        self.kernels.clear()
        self.kernels.update(data["kernels"])
        self.curve[:] = [(int(a), float(b)) for a, b in data["curve"]]
        self.steps, self.evals, self.log = int(data["steps"]), int(data["evals"]), [dict(e) for e in data["log"]]
        self.heldout = {int(k): dict(v) for k, v in data.get("heldout", {}).items()}


def _loop_state(live: _Live) -> State:
    """:class:`~heliotwin.calibrate.fitloop.State` of a surface fit: one "heliostat" whose kept state is the final
    one (the held-out curve is what the caller chooses from, not a best state)."""
    def keep(best, rows):
        if bool(rows.any()):
            best.update(live.dump())

    return State(snapshot=live.dump, keep=keep, live=live, dump=lambda obj: obj.dump() if obj is live else dict(obj),
                 load=lambda obj, data: obj.load(data) if obj is live else obj.update(data))


def _rounds(s: SurfaceSettings) -> list:
    """``(blur_px, iterations)`` per L-BFGS round: the continuation, then (at most 1000) sharp rounds."""
    return [(float(b), int(s.continuation_iters)) for b in s.continuation] + [(0.0, int(s.lbfgs_round))] * 1000


def fit_surface(facets: Facets, obs: Observations, sun: SunSettings, s: SurfaceSettings, *,
                start: torch.Tensor | None = None, camera: CameraModel | None = None,
                sigma0: torch.Tensor | None = None, slope_weight: float = 0.0, prior=None, prior_weight: float = 0.0,
                heldout: tuple | None = None, steps: int | None = None) -> SurfaceFit:
    """Learn the facets' normal displacements from ``obs.images`` (one heliostat).

    Parameters
    ----------
    facets : Facets
        One heliostat, ``[1, F, 3]`` [m].
    obs : Observations
        Training images ``[B, R, R]`` with poses.
    sun : SunSettings
        Optics (the same as the ideal baseline's, so an improvement measures shape).
    s : SurfaceSettings
    start : torch.Tensor, [1, F, nu, nv, 3], optional
        Starting control net on ``s.control_points`` (default: flat canted facets).
    camera : CameraModel, optional
        The images' camera model (cut, saturation; :mod:`heliotwin.surfaces.nuisance`): the loss is then on
        the model images through it, with a per-image blur learned from ``sigma0`` ``[B]`` [px] (Adam only).
    slope_weight : float
        Weight of the slope-deviation penalty against the start (:func:`heliotwin.surfaces.edges.slope_penalty`;
        0: not evaluated).
    prior, prior_weight
        A plant prior (:class:`~heliotwin.surfaces.plantprior.SurfacePrior`) and the weight of its penalty
        (0: not evaluated, so a fit without a prior is unchanged).
    heldout : (Observations, CameraModel), optional
        Held-out images (Adam with a camera model): their L1 every ``eval_every`` steps (the curve: their
        mean; each image's in ``SurfaceFit.heldout``), their blur by :func:`blur_for` from the current training
        blurs.
    steps : int, optional
        Overrides ``s.steps``.

    Under an active :mod:`heliotwin.io.checkpoint` every fit claims a key (``fit/0``, ``fit/1``, ... in the
    caller's deterministic order) and saves its state; a resumed fit goes on after its last saved step and a
    finished one is restored, not rerun. The fit follows the device of the facets and the observations.

    Returns
    -------
    SurfaceFit
    """
    if obs.images is None or len(obs) == 0:
        raise HeliotwinError("fit_surface needs at least one training image")
    steps = int(s.steps if steps is None else steps)
    # With fixed windows (known kinematics) the common tilt is seen; only the facet pistons stay invisible.
    model = LearnableSurface(facets, s.control_points, s.degree, initial=start, fix_gauge=True,
                             gauge_tilt=obs.centers is None)
    ref = None
    if slope_weight:
        ref = normal_heights(facets, model.surfaces().control_points.detach(), s.degree, (16, 16))[1].detach()
    dev = obs.images.device
    sig = torch.zeros(len(obs)) if sigma0 is None else sigma0
    log_sigma = torch.log(sig.to(device=dev, dtype=torch.float32).clamp_min(0.1)).clone().requires_grad_(True)
    meas = obs.images.to(torch.float32)
    live = _Live(model, log_sigma)
    rows = minibatch_rows([len(obs)], s.batch_images, steps, s.batch_seed) if s.optimizer == "adam" else None
    if rows is not None:  # every image's kernel from the start surface first: what the first full step would make
        with torch.no_grad():
            render(model.surfaces(), obs, sun, s, live.kernels)

    def objective(blur: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
        """(total, data) of the live surface: image loss + regularisers (+ penalties)."""
        surf = model.surfaces()
        if rows is None:
            pred, miss = render(surf, obs, sun, s, live.kernels)
            cam, sig, seen = camera, log_sigma, meas
        else:  # this step's images (the loop has taken live.steps steps)
            at, step_obs, view, cam, sig, seen = step_images(rows, live.steps, obs, live.kernels, camera, log_sigma,
                                                             meas)
            pred, miss = render(surf, step_obs, sun, s, view)
            keep_spectra(live.kernels, view, at)
        if camera is not None:
            data = losses.image_loss(s.loss, apply_camera(pred, cam, sig.exp()), seen.to(pred))
        else:
            target = blur_images(losses.normalize(seen.to(pred)), blur)
            data = losses.image_loss(s.loss, blur_images(losses.normalize(pred), blur), target)
        d = model.displacement / 1e-3
        reg = s.ridge * losses.ridge(d) + s.laplacian * losses.laplacian(d)
        total = data + reg + s.miss * miss
        if slope_weight:
            total = total + slope_penalty(surf, ref, facets, slope_weight)
        if prior is not None and prior_weight > 0:
            total = total + prior_weight * prior_penalty(prior, surf, facets)
        return total, data

    if s.optimizer == "lbfgs":
        if camera is not None or heldout is not None:
            raise HeliotwinError("the lbfgs optimizer fits without a camera model or held-out image")
        _lbfgs(model, live, objective, s, steps)
        return SurfaceFit(model, None, [], live.log, live.evals)
    _adam(model, live, objective, obs, sun, s, steps, heldout)
    return SurfaceFit(model, log_sigma.detach().exp() if camera is not None else None, live.curve, [], live.steps,
                      live.heldout)


def adam_step(opt: torch.optim.Optimizer, sched, objective, live):
    """One optimiser step of a surface fit as a closure for the fit loop (shared by the one-problem and the
    batched fit, :mod:`heliotwin.surfaces.fitbatch`).

    ``objective() -> (total, data)`` (scalar tensors: what is minimised, and the data term reported); ``live``
    counts the steps taken (``live.steps``). The closure returns the data term [unit-sum image L1] as a float.
    """
    def step() -> float:
        opt.zero_grad(set_to_none=True)
        total, data = objective()
        total.backward()
        opt.step()
        sched.step()
        live.steps += 1
        return float(data.detach())
    return step


def _adam(model, live: _Live, objective, obs, sun, s: SurfaceSettings, steps: int, heldout) -> None:
    """Adam with exponential decay; the held-out curve (module docstring)."""
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.Adam([{"params": params, "lr": s.lr}, {"params": [live.log_sigma], "lr": s.blur_lr}])
    # Chainable: a resumed fit's schedule goes on from the learning rate restored into the optimiser.
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=s.decay)

    step = adam_step(opt, sched, objective, live)
    hkernels: dict = {}  # the held-out images' kernels from the start surface, as the training images' are made
    if heldout is not None:
        with torch.no_grad():
            render(model.surfaces(), heldout[0], sun, s, hkernels)

    def heldout_l1() -> torch.Tensor:
        # Only on the eval_every grid (not at the start, nor at a last step off the grid): the curve's steps
        # are the step counts the leave-one-out choice compares.
        at = live.steps
        if heldout is None or at == 0 or at % s.eval_every != 0:
            return torch.full((1,), float("inf"))
        hobs, hcam = heldout
        sig = blur_for(obs.targets, live.log_sigma.detach().exp(), hobs.targets)
        ev = evaluate_with_camera(model.surfaces(), hobs, sun, hcam, sig, s, hkernels)
        live.heldout[at] = {"l1": ev["l1"], "l1_raw": ev["l1_raw"], "sigma": sig.tolist(), "images": ev["images"]}
        l1 = statistics.mean(ev["l1"])
        live.curve.append((at, l1))
        return torch.full((1,), float(l1))

    early_stopping_fit(step, heldout_l1, _loop_state(live), int(steps), validated=torch.zeros(1, dtype=torch.bool),
                       check_every=s.eval_every if heldout is not None else max(1, int(steps)))


def _lbfgs(model, live: _Live, objective, s: SurfaceSettings, steps: int) -> None:
    """L-BFGS rounds with blur continuation, ended by the loop's tolerance and evaluation-budget rules."""
    rounds = _rounds(s)

    def one_round() -> float:
        blur, iters = rounds[live.steps]
        params = [p for p in model.parameters() if p.requires_grad]
        opt = torch.optim.LBFGS(params, lr=1.0, max_iter=min(iters, steps - live.evals), history_size=20,
                                line_search_fn="strong_wolfe", tolerance_grad=1e-10, tolerance_change=1e-14)

        def closure():
            opt.zero_grad(set_to_none=True)
            total, data = objective(blur)
            total.backward()
            live.evals += 1
            closure.data = float(data.detach())
            return total

        value = float(opt.step(closure).detach())
        live.log.append({"step": live.evals, "train": getattr(closure, "data", value), "blur_px": blur,
                         "total": value})
        live.steps += 1
        return value

    ending = EarlyEnd(tolerance=s.tolerance, after=len(s.continuation) + 1, done=lambda: live.evals >= steps)
    early_stopping_fit(one_round, lambda: torch.full((1,), float("inf")), _loop_state(live), len(rounds),
                       validated=torch.zeros(1, dtype=torch.bool), check_every=len(rounds), early_end=ending,
                       optimiser_states=False)
