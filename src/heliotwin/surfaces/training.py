"""Learn one heliostat's mirror surface from flux images: settings, the two optimisers, early stopping.

Pipeline per optimiser step::

    displacements --LearnableSurface--> NURBS facets --surface_points--> heliostat-frame samples
    --pose (R, concentrator) per image [x small learned correction]--> world samples
    --conv integrator (splat * sun-cone kernel, 6 m window on the predicted centroid)--> images
    --normalise--> image loss + fixed-weight regularisers (+ miss penalty) --Adam + exponential decay-->

(or full-batch L-BFGS with a blur continuation, ``optimizer="lbfgs"``). The forward model is
:func:`heliotwin.surfaces.imaging.predict_images`; the observations (poses aimed at the measured spots) come
from :mod:`heliotwin.surfaces.observations`.

Early stopping. Every ``eval_every`` steps the image loss on held-out (validation) images is evaluated; the
best parameters are restored at the end and training stops after ``patience`` evaluations without gain.

Fits return ``(model, FitInfo)``: the learned :class:`~heliotwin.surfaces.learning.LearnableSurface` and what
the fit did (steps, best step, orientation corrections, log, choices made on held-out images). The learner
follows the device of the facets and observations.

Checkpoints. Under an active :mod:`heliotwin.io.checkpoint` (``reconstruct --resume``) every fit claims a
key (``surface/0``, ``surface/1``, ... in the deterministic order of :func:`train_with_early_stopping`) and
saves its full state: the surface (and its net, after a refinement), the orientation corrections, Adam's
and the learning-rate schedule's states, the generator (MC integrator), the early-stopping bookkeeping and
the log; every few Adam steps, and after every L-BFGS round. A resumed fit continues after its last saved
step (a finished fit is restored, not rerun) and reaches the uninterrupted fit's result.

Shapes: B images; R window pixels per side; F facets. Units: metres, radians.
"""
from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import asdict, dataclass, field

import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from ..errors import HeliotwinError
from ..field.plant import Facets, SunSettings
from ..io import checkpoint as _checkpoint
from ..io.images import CENTERED_WINDOW_M
from . import losses
from .imaging import check_learning_integrator, evaluate_images, predict_images
from .learning import LearnableSurface
from .observations import Observations

__all__ = ["TrainSettings", "FitInfo", "fit_surface", "train_with_early_stopping", "blur_images"]


@dataclass
class TrainSettings:
    """Hyper-parameters of :func:`fit_surface` (defaults chosen by validation on training splits).

    Attributes
    ----------
    control_points, degree : (int, int)
        NURBS net and degree per facet.
    learn_weights : bool
        Learn rational weights too.
    refine_to : (int, int) or None
        Refine to this net at step ``refine_at`` (coarse-to-fine).
    samples : (int, int)
        Mirror samples per facet and direction.
    loss : {"l1", "l2", "kl"}
    steps, lr, decay
        Adam steps, initial learning rate [mm per step], per-step exponential decay factor.
    ridge, lasso, laplacian : float
        Fixed regulariser weights (displacements in mm).
    miss : float
        Weight of the miss penalty [1/m^2].
    learn_orientation : bool
        Learn a per-image 2-angle orientation correction (ridge ``orientation_ridge`` per mrad^2).
    eval_every, patience : int
        Early-stopping cadence (steps) and patience (evaluations).
    integrator : {"conv", "mc"}
        Training integrator (:data:`heliotwin.surfaces.imaging.LEARNING_INTEGRATORS`; ``rays_per_point`` and
        ``seed`` for MC: one fresh draw per step). Evaluation always uses ``conv``.
    resolution, size_m : int, float
        Window pixels and side [m].
    optimizer : {"adam", "lbfgs"}
        ``lbfgs``: full-batch L-BFGS (strong-Wolfe line search) in rounds of ``lbfgs_round`` iterations
        (history reset between rounds), preceded by a coarse-to-fine continuation: one round of
        ``continuation_iters`` iterations per entry of ``continuation`` with both images blurred by a
        Gaussian of that many pixels (a smoother loss landscape first: the flat start is otherwise caught
        in a local minimum). Stops when a round improves the loss by less than ``tolerance`` (relative) or
        after ``steps`` loss evaluations. ``adam``: ``steps`` Adam steps with exponential decay and early
        stopping on validation images.
    fix_gauge : bool
        Project out the common tilt and facet pistons (invisible in centred windows, see
        :func:`heliotwin.surfaces.learning.gauge_basis`).
    laplacian_grid : tuple of float
        If given (and >= 2 training images), :func:`train_with_early_stopping` chooses the Laplacian
        weight among these by the L1 on the held-out latest training image (lbfgs mode).
    laplacian_cv : {"last", "loo"}
        How that weight is validated: ``"last"`` holds out the latest training image only; ``"loo"``
        leave-one-out over all training images (each image held out once, mean held-out L1), a less
        noisy choice that does not hinge on one sun position.
    """

    control_points: tuple = (7, 7)
    degree: tuple = (3, 3)
    learn_weights: bool = False
    refine_to: tuple | None = None
    refine_at: int = 0
    samples: tuple = (24, 24)
    loss: str = "kl"
    steps: int = 200
    lr: float = 0.8
    decay: float = 0.99
    ridge: float = 1e-4
    lasso: float = 0.0
    laplacian: float = 1e-2
    miss: float = 1.0
    learn_orientation: bool = False
    orientation_ridge: float = 1e-4
    integrator: str = "conv"
    rays_per_point: int = 32
    seed: int = 0
    eval_every: int = 10
    patience: int = 8
    resolution: int = 64
    size_m: float = CENTERED_WINDOW_M
    optimizer: str = "adam"
    fix_gauge: bool = False
    continuation: tuple = (3.0, 1.5)
    continuation_iters: int = 60
    lbfgs_round: int = 200
    tolerance: float = 1e-3
    laplacian_grid: tuple = ()
    laplacian_cv: str = "last"

    def __post_init__(self):
        check_learning_integrator(self.integrator)

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


@dataclass
class FitInfo:
    """What a fit did (the second element of every fit's return value).

    Attributes
    ----------
    steps_run : int
        Adam steps, or L-BFGS loss evaluations, of the (final) fit.
    best_step : int or None
        Adam with validation images: the step with the lowest validation L1.
        :func:`train_with_early_stopping`: the step budget chosen on the held-out image (Adam) or the
        loss evaluations of the final fit (L-BFGS). None otherwise.
    orientation_delta : torch.Tensor, [B, 2], optional
        Learned per-image orientation corrections [rad] (``learn_orientation``), detached.
    log : list of dict
        ``{"step", "train"[, "val"]}`` (Adam) or ``{"step", "train", "blur_px", "total"}`` (L-BFGS rounds).
    selection : dict
        JSON-ready record of what :func:`train_with_early_stopping` chose on held-out training images
        (``holdout``, ``best_step``, ``holdout_curve`` or ``laplacian``/``laplacian_scores``); empty for a
        plain :func:`fit_surface`.
    """

    steps_run: int
    best_step: int | None = None
    orientation_delta: torch.Tensor | None = None
    log: list = field(default_factory=list)
    selection: dict = field(default_factory=dict)


def _regularisers(model: LearnableSurface, s: TrainSettings) -> torch.Tensor:
    d = model.displacement / 1e-3  # [mm], gauge-projected
    total = d.new_zeros(())
    if s.ridge:
        total = total + s.ridge * losses.ridge(d)
    if s.lasso:
        total = total + s.lasso * losses.lasso(d)
    if s.laplacian:
        total = total + s.laplacian * losses.laplacian(d)
    return total


def fit_surface(facets: Facets, train: Observations, sun: SunSettings, settings: TrainSettings | None = None, *,
                validation: Observations | None = None, initial: torch.Tensor | None = None,
                initial_degree=None, progress: bool = True) -> tuple[LearnableSurface, FitInfo]:
    """Learn the facets' normal displacements from ``train.images``.

    Parameters
    ----------
    facets : Facets
        One heliostat, ``[1, F, 3]``.
    train : Observations
        Training images with poses.
    sun : SunSettings
        Optics (the same for the ideal baseline, so the improvement measures shape).
    settings : TrainSettings
    validation : Observations, optional
        Held-out images for early stopping (Adam; default: none, the full step budget runs).
    initial : torch.Tensor, [1, F, nu0, nv0, 3], optional
        Starting surface (e.g. a deflectometry fit); default flat canted.
    initial_degree : (int, int), optional
        Degree of ``initial`` (default the settings' degree).
    progress : bool
        tqdm bar.

    Returns
    -------
    model : LearnableSurface
        With the best (lowest validation loss, or last) parameters loaded.
    info : FitInfo
    """
    s = settings or TrainSettings()
    if train.images is None or len(train) == 0:
        raise HeliotwinError("fit_surface needs at least one training image")
    # With fixed windows (known kinematics) the common tilt is seen; only the facet pistons stay invisible.
    gauge_tilt = train.centers is None
    model = LearnableSurface(facets, s.control_points, s.degree, s.learn_weights, initial, initial_degree,
                             fix_gauge=s.fix_gauge, gauge_tilt=gauge_tilt)
    if s.optimizer == "lbfgs":
        return _fit_lbfgs(model, train, sun, s)
    if s.optimizer != "adam":
        raise HeliotwinError(f"unknown optimizer {s.optimizer!r}; expected adam or lbfgs")
    return _fit_adam(model, facets, train, validation, sun, s, progress)


def _adam(model: LearnableSurface, s: TrainSettings, delta: torch.Tensor | None, lr: float | None = None):
    """Adam + exponential decay over the model's (and ``delta``'s) parameters, starting at ``lr``."""
    params = [p for p in model.parameters() if p.requires_grad]
    groups = [{"params": params, "lr": s.lr}]
    if delta is not None:
        groups.append({"params": [delta], "lr": s.lr * 1e-3})  # mm-scale lr -> ~0.1 mrad steps
    opt = torch.optim.Adam(groups)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=s.decay)
    if lr is not None:
        for g in opt.param_groups:
            g["lr"] = lr * (g["lr"] / s.lr)
    return opt, sched


def _adam_step(model, train, sun, s, meas, delta, kernels, *, gen, opt, sched) -> float:
    """One Adam step on the training images; returns the data loss."""
    opt.zero_grad(set_to_none=True)
    pred, _, miss = predict_images(model.surfaces(), train, sun, samples=s.samples, resolution=s.resolution,
                                   size_m=s.size_m, delta=delta, kernels=kernels, integrator=s.integrator,
                                   generator=gen, rays_per_point=s.rays_per_point)
    data = losses.image_loss(s.loss, pred, meas)
    total = data + _regularisers(model, s) + s.miss * miss
    if delta is not None:
        total = total + s.orientation_ridge * (delta / 1e-3).pow(2).mean()
    total.backward()
    opt.step()
    sched.step()
    return float(data.detach())


@torch.no_grad()
def _validation_l1(model, validation, sun, s, val_meas, val_kernels) -> float:
    vp, _, _ = predict_images(model.surfaces(), validation, sun, samples=s.samples, resolution=s.resolution,
                              size_m=s.size_m, kernels=val_kernels)
    return float(losses.l1(vp, val_meas).mean())


def _state_copy(model: LearnableSurface) -> dict:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def _load_model(model: LearnableSurface, control_points, state: dict) -> None:
    """A saved surface into ``model`` (refined first when it was saved on the finer net)."""
    if tuple(control_points) != tuple(model.num_control_points):
        model.refine(tuple(int(c) for c in control_points))
    model.load_state_dict(state)


class _AdamRun:
    """The mutable state of :func:`_fit_adam` (what a checkpoint saves and restores)."""

    def __init__(self, model, s, delta, gen):
        self.model, self.s, self.delta, self.gen = model, s, delta, gen
        self.opt, self.sched = _adam(model, s, delta)
        self.best = (math.inf, copy.deepcopy(model.state_dict()), model.num_control_points)
        self.bad, self.steps_run, self.log, self.next_step, self.finished = 0, 0, [], 0, False
        # The footprint-kernel caches are filled from the surface of the first step that needs them: part of
        # the state (a resumed fit recomputing them from a later surface would take other steps).
        self.kernels: dict = {}
        self.val_kernels: dict = {}

    def entry(self) -> dict:
        return {"step": self.next_step, "finished": self.finished,
                "control_points": list(self.model.num_control_points), "model": _state_copy(self.model),
                "delta": None if self.delta is None else self.delta.detach().clone(),
                "opt": copy.deepcopy(self.opt.state_dict()), "sched": self.sched.state_dict(),
                "gen": self.gen.get_state(), "best_val": float(self.best[0]), "best_state": self.best[1],
                "best_cp": list(self.best[2]), "bad": self.bad, "steps_run": self.steps_run, "log": list(self.log),
                "kernels": dict(self.kernels), "val_kernels": dict(self.val_kernels)}

    def restore(self, e: dict) -> None:
        if tuple(e["control_points"]) != tuple(self.model.num_control_points):
            self.model.refine(tuple(int(c) for c in e["control_points"]))
            self.opt, self.sched = _adam(self.model, self.s, self.delta)
        self.model.load_state_dict(e["model"])
        if self.delta is not None:
            with torch.no_grad():
                self.delta.copy_(e["delta"])
        self.opt.load_state_dict(e["opt"])
        self.sched.load_state_dict(e["sched"])
        self.gen.set_state(e["gen"])
        self.best = (float(e["best_val"]), e["best_state"], tuple(int(c) for c in e["best_cp"]))
        self.bad, self.steps_run, self.log = int(e["bad"]), int(e["steps_run"]), list(e["log"])
        self.next_step, self.finished = int(e["step"]), bool(e["finished"])
        self.kernels.update(e["kernels"])
        self.val_kernels.update(e["val_kernels"])


def _fit_adam(model, facets, train, validation, sun, s, progress) -> tuple[LearnableSurface, FitInfo]:
    """Adam with exponential decay and early stopping on ``validation`` (see :class:`TrainSettings`)."""
    meas = losses.normalize(train.images.to(torch.float32))
    val_meas = None if validation is None or len(validation) == 0 else losses.normalize(validation.images.float())
    delta = None
    if s.learn_orientation:
        delta = torch.zeros(len(train), 2, dtype=train.rotation.dtype, device=train.rotation.device,
                            requires_grad=True)
    run = _AdamRun(model, s, delta, torch.Generator(device=train.sun.device).manual_seed(int(s.seed)))
    ck = _checkpoint.current()
    key = ck.claim("surface") if ck is not None else None
    if key is not None and ck.get(key) is not None:
        run.restore(ck.get(key))
    steps = range(run.next_step, 0 if run.finished else s.steps)
    bar = tqdm(steps, desc="surface", disable=not progress, leave=False, initial=run.next_step, total=s.steps)
    for step in bar:
        if s.refine_to is not None and step == s.refine_at and step > 0:
            model.refine(s.refine_to)
            run.opt, run.sched = _adam(model, s, delta, lr=run.sched.get_last_lr()[0])
            run.best = (math.inf, run.best[1], run.best[2])  # a new parameter space: restart the bookkeeping
        data = _adam_step(model, train, sun, s, meas, delta, run.kernels, gen=run.gen, opt=run.opt, sched=run.sched)
        run.steps_run = step + 1
        if val_meas is not None and (step % s.eval_every == s.eval_every - 1 or step == s.steps - 1):
            vloss = _validation_l1(model, validation, sun, s, val_meas, run.val_kernels)
            run.log.append({"step": step + 1, "train": data, "val": vloss})
            bar.set_postfix(train=f"{data:.4f}", val=f"{vloss:.4f}")
            if vloss < run.best[0] - 1e-5:
                run.best = (vloss, copy.deepcopy(model.state_dict()), model.num_control_points)
                run.bad = 0
            else:
                run.bad += 1
                run.finished = run.bad >= s.patience
        elif step % s.eval_every == 0:
            run.log.append({"step": step + 1, "train": data})
        run.next_step = step + 1
        run.finished = run.finished or run.next_step == s.steps
        if key is not None:
            if run.finished or ck.due(run.next_step):
                ck.put(key, run.entry())
            ck.notify("step", key, run.next_step)
        if run.finished:
            break
    best, log = run.best, run.log
    if val_meas is not None and best[0] < math.inf:
        if best[2] != model.num_control_points:
            # The best state was on the coarse net: rebuild it, then load.
            model = LearnableSurface(facets, best[2], s.degree, s.learn_weights, fix_gauge=s.fix_gauge,
                                     gauge_tilt=train.centers is None)
        model.load_state_dict(best[1])
    vals = [e for e in log if "val" in e]
    best_step = min(vals, key=lambda e: e["val"])["step"] if vals else None
    return model, FitInfo(run.steps_run, best_step, None if delta is None else delta.detach(), log)


def blur_images(images: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Separable Gaussian blur of ``[B, R, C]`` images (zero padding); identity for ``sigma_px <= 0``."""
    if sigma_px <= 0:
        return images
    k = int(math.ceil(3.0 * sigma_px))
    x = torch.arange(-k, k + 1, dtype=images.dtype, device=images.device)
    g = torch.exp(-0.5 * (x / sigma_px) ** 2)
    g = g / g.sum()
    y = F.conv2d(images[:, None], g.reshape(1, 1, -1, 1), padding=(k, 0))
    return F.conv2d(y, g.reshape(1, 1, 1, -1), padding=(0, k))[:, 0]


def _lbfgs_rounds(s: TrainSettings, model: LearnableSurface) -> list:
    """``(blur_px, iterations)`` per L-BFGS round; ``("refine", 0)`` marks the switch to the fine net."""
    cont = [(float(b), int(s.continuation_iters)) for b in s.continuation]
    rounds = cont + [(0.0, int(s.lbfgs_round))] * 1000
    if s.refine_to is not None and tuple(s.refine_to) != tuple(model.num_control_points):
        # Coarse-to-fine: the blur continuation and one sharp round on the coarse net, then refine (the
        # represented surface is kept) and run the whole schedule again on the fine net.
        rounds = cont + [(0.0, int(s.continuation_iters)), ("refine", 0)] + rounds
    return rounds


def _fit_lbfgs(model: LearnableSurface, train: Observations, sun: SunSettings,
               s: TrainSettings) -> tuple[LearnableSurface, FitInfo]:
    """L-BFGS with blur continuation (see :class:`TrainSettings`); deterministic (conv integrator)."""
    if s.integrator != "conv":
        raise HeliotwinError("optimizer lbfgs needs the conv integrator (noise-free loss)")
    meas = losses.normalize(train.images.to(torch.float32))
    kernels: dict = {}
    evals = 0
    log: list = []

    def objective(blur, opt):
        target = blur_images(meas, blur)

        def closure():
            nonlocal evals
            opt.zero_grad(set_to_none=True)
            pred, _, miss = predict_images(model.surfaces(), train, sun, samples=s.samples, resolution=s.resolution,
                                           size_m=s.size_m, kernels=kernels)
            data = losses.image_loss(s.loss, blur_images(losses.normalize(pred), blur), target)
            total = data + _regularisers(model, s) + s.miss * miss
            total.backward()
            evals += 1
            closure.data = float(data.detach())
            return total
        return closure

    previous, first, finished = math.inf, 0, False
    rounds = _lbfgs_rounds(s, model)  # of the start's net, before a restored (refined) state is loaded
    ck = _checkpoint.current()
    key = ck.claim("surface") if ck is not None else None
    saved = ck.get(key) if key is not None else None
    if saved is not None:  # continue after the last finished round
        _load_model(model, saved["control_points"], saved["model"])
        evals, log, previous = int(saved["evals"]), list(saved["log"]), float(saved["previous"])
        first, finished = int(saved["step"]), bool(saved["finished"])
        kernels.update(saved["kernels"])  # filled from the start's surface (see _AdamRun)
    for r, (blur, iters) in enumerate(rounds):
        if finished:
            break
        if r < first:
            continue
        if blur == "refine":
            model.refine(tuple(s.refine_to))
            continue
        budget = int(s.steps) - evals
        if budget <= 0:
            break
        params = [p for p in model.parameters() if p.requires_grad]
        opt = torch.optim.LBFGS(params, lr=1.0, max_iter=min(iters, budget), history_size=20,
                                line_search_fn="strong_wolfe", tolerance_grad=1e-10, tolerance_change=1e-14)
        closure = objective(blur, opt)
        value = float(opt.step(closure).detach())
        log.append({"step": evals, "train": getattr(closure, "data", value), "blur_px": blur, "total": value})
        if blur == 0.0 and (s.refine_to is None or tuple(model.num_control_points) == tuple(s.refine_to)):
            finished = previous - value <= s.tolerance * abs(value)
            previous = value if not finished else previous
        if key is not None:  # a round is long: save after every one
            ck.put(key, {"step": r + 1, "finished": finished or evals >= int(s.steps),
                         "control_points": list(model.num_control_points), "model": _state_copy(model),
                         "evals": evals, "log": list(log), "previous": float(previous), "kernels": dict(kernels)})
            ck.notify("step", key, r + 1)
    return model, FitInfo(evals, None, None, log)


def _choose_laplacian(facets, train, sun, settings, init) -> tuple[TrainSettings, dict]:
    """The Laplacian weight of ``settings.laplacian_grid`` with the lowest held-out L1 (L-BFGS mode)."""
    n = len(train)
    if settings.laplacian_cv == "loo":
        folds = list(range(n))
    elif settings.laplacian_cv == "last":
        folds = [n - 1]
    else:
        raise HeliotwinError(f"unknown laplacian_cv {settings.laplacian_cv!r}; expected last or loo")
    scores = {}
    for w in settings.laplacian_grid:
        fold_l1 = []
        for k in folds:
            head, held = train.subset([i for i in range(n) if i != k]), train.subset([k])
            m1, _ = fit_surface(facets, head, sun, dataclasses.replace(settings, laplacian=float(w)), progress=False,
                                **init)
            fold_l1.append(float(torch.tensor(evaluate_images(
                m1.surfaces(), held, sun, samples=settings.samples, resolution=settings.resolution,
                size_m=settings.size_m)["l1"]).mean()))
        scores[float(w)] = sum(fold_l1) / len(fold_l1)
    best = min(scores, key=scores.get)
    info = dict(holdout=[train.ids[k] for k in folds] if len(folds) > 1 else train.ids[-1],
                laplacian_scores=scores, laplacian_cv=settings.laplacian_cv)
    return dataclasses.replace(settings, laplacian=best), info


def train_with_early_stopping(facets: Facets, train: Observations, sun: SunSettings, settings: TrainSettings,
                              progress: bool = True, initial=None,
                              initial_degree=None) -> tuple[LearnableSurface, FitInfo]:
    """Early stopping on held-out *training* images, then a refit on all of them.

    Adam: with >= 3 training images the latest one is held out: phase 1 trains on the others and records
    the step with the lowest held-out L1; phase 2 trains on all images for that many steps. With fewer
    images the full step budget runs on all of them. L-BFGS runs to convergence; what is chosen on held-out
    training images is the Laplacian weight (``laplacian_grid``, ``laplacian_cv``).

    Returns
    -------
    model : LearnableSurface
    info : FitInfo
        Of the final fit, with ``best_step`` and ``selection`` describing the choices.
    """
    init = dict(initial=initial, initial_degree=initial_degree)
    info: dict = {"holdout": None, "best_step": settings.steps}
    if settings.optimizer == "lbfgs":
        if settings.laplacian_grid and len(train) >= 2:
            settings, chosen = _choose_laplacian(facets, train, sun, settings, init)
            info.update(chosen)
        info["laplacian"] = settings.laplacian
        model, fit = fit_surface(facets, train, sun, settings, progress=progress, **init)
        info["best_step"] = fit.steps_run
        return model, dataclasses.replace(fit, best_step=info["best_step"], selection=info)
    if len(train) >= 3:
        _, first = fit_surface(facets, train.subset(range(len(train) - 1)), sun, settings,
                               validation=train.subset([len(train) - 1]), progress=progress, **init)
        info["holdout"] = train.ids[-1]
        info["best_step"] = int(first.best_step or settings.steps)
        info["holdout_curve"] = [(e["step"], round(e["val"], 5)) for e in first.log if "val" in e]
    s2 = dataclasses.replace(settings, steps=max(int(info["best_step"]), settings.eval_every))
    model, fit = fit_surface(facets, train, sun, s2, progress=progress, **init)
    return model, dataclasses.replace(fit, best_step=info["best_step"], selection=info)
