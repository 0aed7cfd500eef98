"""Learn one heliostat's mirror surface from flux images (functional core + a thin training loop).

Pipeline per optimiser step::

    displacements --LearnableSurface--> NURBS facets --surface_points--> heliostat-frame samples
    --pose (R, concentrator) per image [x small learned correction]--> world samples
    --render_centered (splat * sun-cone kernel, 6 m window on the predicted centroid)--> images
    --normalise--> image loss + fixed-weight regularisers (+ miss penalty) --Adam + exponential decay-->

Alignment. Real records carry the *measured* focal spot: the pose used for an image is the one that aims
the (ideal) heliostat's central ray at it (:func:`~heliotwin.surfaces.render.aimed_pose`), so the tens of
mrad of nominal-kinematics error never enter. The comparison is in the 6 m window centred on each image's own
centroid (measured: by PAINT; predicted: by us), so residual aiming error is not read as shape either.
Optionally a small per-image orientation correction (2 angles, ridge-penalised) is learned jointly.

Early stopping. Every ``eval_every`` steps the image loss on held-out (validation) images is evaluated; the
best parameters are restored at the end and training stops after ``patience`` evaluations without gain.

Shapes: B images; R window pixels per side; F facets. Units: metres, radians.
"""
from __future__ import annotations

import copy
import math
import time
from dataclasses import asdict, dataclass, field

import torch

from ..errors import HeliotwinError, InputFileError
from ..field import facets as facet_ops
from ..field.plant import Facets, SunSettings, Surfaces
from ..field.targets import PlanarTarget
from ..raytrace.flux import cross_correlation
from . import losses
from .learning import LearnableSurface
from .render import correction_rotation, footprint_kernel, reflect_to_plane, render_centered

__all__ = ["Observations", "TrainSettings", "predict_images", "fit_surface", "evaluate_images", "trace_mc_centered"]


@dataclass
class Observations:
    """B images of one heliostat with their poses.

    Attributes
    ----------
    sun : torch.Tensor, [B, 3], float64
        Unit vectors towards the sun.
    rotation : torch.Tensor, [B, 3, 3], float64
        ``R_world_heliostat`` per image.
    concentrator : torch.Tensor, [B, 3], float64
        ENU [m].
    targets : list of PlanarTarget, length B
    images : torch.Tensor, [B, R, R], optional
        Measured centred images (any scale; they are normalised to unit sum where compared).
    ids : list of str
        Names (record ids) for reports.
    centers : torch.Tensor, [B, 2], optional
        Fixed window centres (target-local [m]) for images taken with *known* kinematics, e.g. the aim
        point: the spot's position in the window then carries information (a common tilt of all facets
        becomes observable). None (PAINT's ``flux-centered`` images): each window is centred on its own
        spot centroid.
    """

    sun: torch.Tensor
    rotation: torch.Tensor
    concentrator: torch.Tensor
    targets: list
    images: torch.Tensor | None = None
    ids: list = field(default_factory=list)
    centers: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.sun.shape[0])

    def subset(self, idx) -> "Observations":
        idx = list(idx)
        return Observations(self.sun[idx], self.rotation[idx], self.concentrator[idx], [self.targets[i] for i in idx],
                            None if self.images is None else self.images[idx], [self.ids[i] for i in idx],
                            None if self.centers is None else self.centers[idx])


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
    integrator : {"analytic", "mc"}
        Training integrator (``rays_per_point`` and ``seed`` for MC: one fresh draw per step).
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
    integrator: str = "analytic"
    rays_per_point: int = 32
    seed: int = 0
    eval_every: int = 10
    patience: int = 8
    resolution: int = 64
    size_m: float = 6.0
    optimizer: str = "adam"
    fix_gauge: bool = False
    continuation: tuple = (3.0, 1.5)
    continuation_iters: int = 60
    lbfgs_round: int = 200
    tolerance: float = 1e-3
    laplacian_grid: tuple = ()
    laplacian_cv: str = "last"

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


def _groups(targets: list) -> list[tuple[PlanarTarget, list[int]]]:
    out: dict[int, tuple] = {}
    for i, t in enumerate(targets):
        out.setdefault(id(t), (t, []))[1].append(i)
    return list(out.values())


def predict_images(surfaces: Surfaces, obs: Observations, sun: SunSettings, *, samples=(24, 24), resolution: int = 64,
                   size_m: float = 6.0, delta: torch.Tensor | None = None, kernels: dict | None = None,
                   integrator: str = "analytic", generator: torch.Generator | None = None, rays_per_point: int = 32,
                   kernel_supersample: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Centred-window images of one heliostat for B poses (differentiable w.r.t. the surface and ``delta``).

    Parameters
    ----------
    surfaces : Surfaces
        One heliostat (``[1, F, nu, nv, 3]``).
    obs : Observations
    sun : SunSettings
    samples : (int, int)
    resolution, size_m
    delta : torch.Tensor, [B, 2], optional
        Orientation corrections [rad].
    kernels : dict, optional
        Cache ``image index -> footprint kernel``, filled on first use (the kernel is a second-order
        function of the surface; reusing it keeps the optimisation cheap and deterministic).
    integrator : {"analytic", "mc"}
        ``analytic``: splat * sun-cone kernel (:mod:`heliotwin.surfaces.render`, noise-free);
        ``mc``: :func:`heliotwin.raytrace.trace_mc` in the same window (needs ``generator``; the window
        centre is then held fixed within a step).

    Returns
    -------
    images : torch.Tensor, [B, R, R]
        Flux [W/m^2].
    centers : torch.Tensor, [B, 2]
        Window centres (local target coordinates [m]).
    miss : torch.Tensor, []
        Soft miss penalty [m^2].
    """
    pts, nrm, area = facet_ops.surface_points(surfaces, samples)  # [1, N, 3]
    b = len(obs)
    rot = obs.rotation.to(pts.dtype)
    if delta is not None:
        rot = rot @ correction_rotation(delta.to(pts.dtype))
    pw = obs.concentrator.to(pts.dtype)[:, None, :] + pts @ rot.transpose(-1, -2)  # [B, N, 3]
    nw = nrm @ rot.transpose(-1, -2)
    pw, nw = pw.to(torch.float32), nw.to(torch.float32)
    ar = area.to(torch.float32).expand(b, -1)
    sund = obs.sun.to(torch.float32)
    images = [None] * b
    centers = [None] * b
    misses = []
    for target, idx in _groups(obs.targets):
        kern = None
        if kernels is not None:
            if not all(i in kernels for i in idx):  # computed once, then reused (also by render_centered now)
                kern_new = _kernels_for(pw[idx], nw[idx], ar[idx], sund[idx], target, sun, size_m / resolution,
                                        2 * resolution, kernel_supersample)
                for j, i in enumerate(idx):
                    kernels[i] = kern_new[j]
            kern = torch.stack([kernels[i] for i in idx])
        fixed = None if obs.centers is None else obs.centers[idx].to(pw)
        res = render_centered(pw[idx], nw[idx], ar[idx], sund[idx], target, sun, size_m=size_m,
                              resolution=resolution, kernel=kern, center=fixed)
        img = res.image
        if integrator == "mc":
            from ..raytrace.montecarlo import trace_mc

            c = res.center.detach().to(torch.float64)
            win = torch.stack((c[:, 0] - size_m / 2, c[:, 1] - size_m / 2, torch.full_like(c[:, 0], size_m),
                               torch.full_like(c[:, 0], size_m)), -1)
            img = trace_mc(pw[idx], nw[idx], ar[idx], sund[idx], target, resolution=(resolution, resolution), sun=sun,
                           rays_per_point=rays_per_point, generator=generator or torch.Generator().manual_seed(0),
                           window=win, clip_to_target=False).bitmap
        elif integrator != "analytic":
            raise HeliotwinError(f"unknown integrator {integrator!r}; expected analytic or mc")
        for j, i in enumerate(idx):
            images[i] = img[j]
            centers[i] = res.center[j]
        misses.append(res.miss * len(idx))
    return torch.stack(images), torch.stack(centers), sum(misses) / b


@torch.no_grad()
def _kernels_for(pw, nw, ar, sund, target, sun, pixel, size, supersample=4):
    _, refl, dist = reflect_to_plane(pw, nw, sund, target)
    w = ar * (nw * sund.unsqueeze(1)).sum(-1).clamp_min(0.0)
    ws = w.sum(-1).clamp_min(1e-12)
    ray = (w.unsqueeze(-1) * refl).sum(1) / ws.unsqueeze(-1)
    ray = ray / ray.norm(dim=-1, keepdim=True)
    return footprint_kernel(sun, ray, (w * dist).sum(1) / ws, target, pixel, size, supersample)


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


def evaluate_images(surfaces: Surfaces, obs: Observations, sun: SunSettings, *, samples=(24, 24),
                    resolution: int = 64, size_m: float = 6.0) -> dict:
    """Per-image L1 (unit-sum images) and cross-correlation against ``obs.images``.

    Returns
    -------
    dict with ``l1`` [B], ``cc`` [B] (lists of float) and ``images`` [B, R, R] (predicted, detached).
    """
    with torch.no_grad():
        pred, centers, _ = predict_images(surfaces, obs, sun, samples=samples, resolution=resolution, size_m=size_m)
        meas = obs.images.to(pred)
        return {"l1": losses.l1(pred, meas).tolist(),
                "cc": cross_correlation(losses.normalize(pred), losses.normalize(meas)).tolist(),
                "images": pred, "centers": centers}


def trace_mc_centered(surfaces: Surfaces, obs: Observations, sun: SunSettings, *, samples=(24, 24),
                      resolution: int = 64, size_m: float = 6.0, rays_per_point: int = 64, seed: int = 0
                      ) -> torch.Tensor:
    """Monte-Carlo images (:func:`heliotwin.raytrace.trace_mc`) in the same centred windows.

    The window centre is the one the analytic images use (the predicted centroid of the central-ray hits,
    or ``obs.centers`` when fixed), so both integrators are compared on identical windows.

    Returns
    -------
    torch.Tensor, [B, R, R]
        Flux [W/m^2].
    """
    from ..raytrace.montecarlo import trace_mc

    gen = torch.Generator().manual_seed(int(seed))
    with torch.no_grad():
        pts, nrm, area = facet_ops.surface_points(surfaces, samples)
        _, centers, _ = predict_images(surfaces, obs, sun, samples=samples, resolution=resolution, size_m=size_m)
        out = []
        for i in range(len(obs)):
            rot = obs.rotation[i].to(pts.dtype)
            pw = obs.concentrator[i].to(pts.dtype) + pts[0] @ rot.T
            nw = nrm[0] @ rot.T
            c = centers[i].to(torch.float64)
            window = (float(c[0]) - size_m / 2, float(c[1]) - size_m / 2, size_m, size_m)
            img = trace_mc(pw.float(), nw.float(), area[0].float(), obs.sun[i].float(), obs.targets[i],
                           resolution=(resolution, resolution), sun=sun, rays_per_point=rays_per_point,
                           generator=gen, window=window, clip_to_target=False)
            out.append(img.bitmap[0])
        return torch.stack(out)


def fit_surface(facets: Facets, train: Observations, sun: SunSettings, settings: TrainSettings | None = None, *,
                validation: Observations | None = None, initial: torch.Tensor | None = None,
                initial_degree=None, progress: bool = True, log: list | None = None) -> LearnableSurface:
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
        Held-out images for early stopping (default: none; the full step budget runs).
    initial : torch.Tensor, [1, F, nu0, nv0, 3], optional
        Starting surface (e.g. a deflectometry fit); default flat canted.
    progress : bool
        tqdm bar.
    log : list, optional
        Appended with ``{"step", "train", "val"}`` dicts.

    Returns
    -------
    LearnableSurface
        With the best (lowest validation loss, or last) parameters loaded.
    """
    from tqdm.auto import tqdm

    s = settings or TrainSettings()
    if train.images is None or len(train) == 0:
        raise HeliotwinError("fit_surface needs at least one training image")
    # With fixed windows (known kinematics) the common tilt is seen; only the facet pistons stay invisible.
    gauge_tilt = train.centers is None
    model = LearnableSurface(facets, s.control_points, s.degree, s.learn_weights, initial, initial_degree,
                             fix_gauge=s.fix_gauge, gauge_tilt=gauge_tilt)
    if s.optimizer == "lbfgs":
        return _fit_lbfgs(model, train, sun, s, log)
    if s.optimizer != "adam":
        raise HeliotwinError(f"unknown optimizer {s.optimizer!r}; expected adam or lbfgs")
    meas = losses.normalize(train.images.to(torch.float32))
    val_meas = None if validation is None or len(validation) == 0 else losses.normalize(validation.images.float())
    delta = torch.zeros(len(train), 2, dtype=torch.float64, requires_grad=True) if s.learn_orientation else None
    kernels: dict = {}
    val_kernels: dict = {}

    def make_opt():
        params = [p for p in model.parameters() if p.requires_grad]
        groups = [{"params": params, "lr": s.lr}]
        if delta is not None:
            groups.append({"params": [delta], "lr": s.lr * 1e-3})  # mm-scale lr -> ~0.1 mrad steps
        opt = torch.optim.Adam(groups)
        return opt, torch.optim.lr_scheduler.ExponentialLR(opt, gamma=s.decay)

    opt, sched = make_opt()
    gen = torch.Generator().manual_seed(int(s.seed))
    best = (math.inf, copy.deepcopy(model.state_dict()), model.num_control_points)
    bad = 0
    bar = tqdm(range(s.steps), desc="surface", disable=not progress, leave=False)
    for step in bar:
        if s.refine_to is not None and step == s.refine_at and step > 0:
            model.refine(s.refine_to)
            lr_now = sched.get_last_lr()[0]
            opt, sched = make_opt()
            for g in opt.param_groups:
                g["lr"] = lr_now * (g["lr"] / s.lr)
            best = (math.inf, best[1], best[2])  # a new parameter space: restart the bookkeeping
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
        if val_meas is not None and (step % s.eval_every == s.eval_every - 1 or step == s.steps - 1):
            with torch.no_grad():
                vp, _, _ = predict_images(model.surfaces(), validation, sun, samples=s.samples,
                                          resolution=s.resolution, size_m=s.size_m, kernels=val_kernels)
                vloss = float(losses.l1(vp, val_meas).mean())
            if log is not None:
                log.append({"step": step + 1, "train": float(data.detach()), "val": vloss})
            if vloss < best[0] - 1e-5:
                best = (vloss, copy.deepcopy(model.state_dict()), model.num_control_points)
                bad = 0
            else:
                bad += 1
                if bad >= s.patience:
                    break
            bar.set_postfix(train=f"{float(data.detach()):.4f}", val=f"{vloss:.4f}")
        elif log is not None and step % s.eval_every == 0:
            log.append({"step": step + 1, "train": float(data.detach())})
    if val_meas is not None and best[0] < math.inf:
        if best[2] != model.num_control_points:
            # The best state was on the coarse net: rebuild it, then load.
            model = LearnableSurface(facets, best[2], s.degree, s.learn_weights, fix_gauge=s.fix_gauge,
                                     gauge_tilt=gauge_tilt)
        model.load_state_dict(best[1])
    model.orientation_delta = None if delta is None else delta.detach()
    model.steps_run = step + 1
    model.best_step = None
    if val_meas is not None and log is not None:
        vals = [e for e in log if "val" in e]
        if vals:
            model.best_step = min(vals, key=lambda e: e["val"])["step"]
    return model


def blur_images(images: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Separable Gaussian blur of ``[B, R, C]`` images (zero padding); identity for ``sigma_px <= 0``."""
    import torch.nn.functional as F

    if sigma_px <= 0:
        return images
    k = int(math.ceil(3.0 * sigma_px))
    x = torch.arange(-k, k + 1, dtype=images.dtype)
    g = torch.exp(-0.5 * (x / sigma_px) ** 2)
    g = g / g.sum()
    y = F.conv2d(images[:, None], g.reshape(1, 1, -1, 1), padding=(k, 0))
    return F.conv2d(y, g.reshape(1, 1, 1, -1), padding=(0, k))[:, 0]


def _fit_lbfgs(model: LearnableSurface, train: Observations, sun: SunSettings, s: TrainSettings,
               log: list | None) -> LearnableSurface:
    """L-BFGS with blur continuation (see :class:`TrainSettings`); deterministic (analytic integrator)."""
    if s.integrator != "analytic":
        raise HeliotwinError("optimizer lbfgs needs the analytic integrator (noise-free loss)")
    meas = losses.normalize(train.images.to(torch.float32))
    kernels: dict = {}
    evals = 0

    def objective(blur):
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

    cont = [(float(b), int(s.continuation_iters)) for b in s.continuation]
    rounds = cont + [(0.0, int(s.lbfgs_round))] * 1000
    if s.refine_to is not None and tuple(s.refine_to) != tuple(model.num_control_points):
        # Coarse-to-fine: the blur continuation and one sharp round on the coarse net, then refine (the
        # represented surface is kept) and run the whole schedule again on the fine net.
        rounds = cont + [(0.0, int(s.continuation_iters)), ("refine", 0)] + rounds
    previous = math.inf
    for blur, iters in rounds:
        if blur == "refine":
            model.refine(tuple(s.refine_to))
            continue
        budget = int(s.steps) - evals
        if budget <= 0:
            break
        params = [p for p in model.parameters() if p.requires_grad]
        opt = torch.optim.LBFGS(params, lr=1.0, max_iter=min(iters, budget), history_size=20,
                                line_search_fn="strong_wolfe", tolerance_grad=1e-10, tolerance_change=1e-14)
        closure = objective(blur)
        value = float(opt.step(closure).detach())
        if log is not None:
            log.append({"step": evals, "train": getattr(closure, "data", value), "blur_px": blur, "total": value})
        if blur == 0.0 and (s.refine_to is None or tuple(model.num_control_points) == tuple(s.refine_to)):
            if previous - value <= s.tolerance * abs(value):
                break
            previous = value
    model.orientation_delta = None
    model.steps_run = evals
    model.best_step = None
    return model


# ----------------------------------------------------------------------------------------------------
# Real PAINT data
# ----------------------------------------------------------------------------------------------------
#: Slope errors [rad] tried when fitting the ideal baseline's optics to the training images.
SLOPE_ERROR_GRID = (0.5e-3, 1.0e-3, 1.5e-3, 2.0e-3, 2.5e-3, 3.0e-3)
#: The peer's (ARTIST tutorial) optics, reported for comparison: 2.1 mrad Gaussian sun, no slope error.
SHARP_SUN = SunSettings(sunshape="gaussian", sigma=2.1e-3, slope_error=0.0)


def load_centered_image(path, resolution: int = 64, background: float = 0.0) -> torch.Tensor:
    """A PAINT ``-flux-centered.png`` as ``[R, R]`` float32 at the comparison resolution.

    256x256 images (newer releases) are box-averaged to 64x64 so that every image is compared on the
    same 9.4 cm pixels; other sizes are area-resampled. ``background`` (fraction of the max) is subtracted
    and clipped at 0 (see :func:`heliotwin.surfaces.losses.threshold_background`).
    """
    import torch.nn.functional as F

    from ..raytrace.flux import read_png

    img = read_png(path)
    if img.shape[0] != img.shape[1]:
        raise InputFileError(path, f"expected a square centred image, got {list(img.shape)}")
    if img.shape[0] != resolution:
        img = F.interpolate(img[None, None], size=(resolution, resolution), mode="area")[0, 0]
    if background > 0:
        img = losses.threshold_background(img, background)
    if float(img.sum()) <= 0:
        raise InputFileError(path, "image is empty (all zero)")
    return img


def _record_time_key(record):
    return (0, str(record.datetime), record.record_id) if record.datetime else (1, "", record.record_id)


def split_records(records: list, train_records=None, train_first: int | None = None) -> tuple[list, list]:
    """Train/test split of the records that have centred images.

    ``train_first=K``: the K earliest by DateTime (records without one come after, by id); the rest are test.
    ``train_records``: explicit ids (each must have a centred image); the rest are test.
    """
    with_img = [r for r in records if r.flux_centered_png]
    if not with_img:
        raise HeliotwinError("no records with a '-flux-centered.png' image for this heliostat")
    if train_records:
        ids = {int(x) for x in train_records}
        known = {r.record_id for r in with_img}
        missing = sorted(ids - known)
        if missing:
            raise HeliotwinError(f"train record(s) {', '.join(map(str, missing))} have no centred image or do not "
                                 f"exist; records with images: {', '.join(str(r.record_id) for r in with_img)}")
        train = [r for r in with_img if r.record_id in ids]
    else:
        k = 3 if train_first is None else int(train_first)
        if k < 1:
            raise HeliotwinError(f"--train-first must be >= 1, got {k}")
        ordered = sorted(with_img, key=_record_time_key)
        train = ordered[:k]
    test = [r for r in with_img if r not in train]
    if not test:
        raise HeliotwinError(f"no test images left: {len(with_img)} records have centred images, all used for training")
    train.sort(key=_record_time_key)
    return train, test


def observations_from_records(plant, heliostat_index: int, records: list, resolution: int = 64,
                              background: float = 0.0, alignment: str = "focal-spot") -> Observations:
    """Poses and measured images of PAINT records.

    ``alignment="focal-spot"`` aims the heliostat at each record's measured focal spot (HeliOS, else UTIS);
    ``"motor"`` uses the nominal kinematics at the recorded motor steps.
    """
    from ..field import kinematics as kin_ops
    from ..sun import direction_from_paint_angles
    from .render import aimed_pose

    kin = plant.field.kinematics.index(heliostat_index)
    sun = direction_from_paint_angles(torch.tensor([r.sun_azimuth for r in records], dtype=torch.float64),
                                      torch.tensor([r.sun_elevation for r in records], dtype=torch.float64))
    if alignment == "focal-spot":
        rot, conc = aimed_pose(kin, torch.stack([r.spot() for r in records]), sun)
    elif alignment == "motor":
        steps = torch.tensor([r.motor_steps for r in records], dtype=torch.float64).reshape(-1, 1, 2)
        rot, conc = kin_ops.forward(kin, steps)
        rot, conc = rot[:, 0], conc[:, 0]
    else:
        raise HeliotwinError(f"unknown alignment {alignment!r}; expected focal-spot or motor")
    targets = []
    for r in records:
        t = plant.target(r.target)
        if not isinstance(t, PlanarTarget):
            raise HeliotwinError(f"record {r.record_id}: target {r.target!r} is not planar")
        targets.append(t)
    images = torch.stack([load_centered_image(r.flux_centered_png, resolution, background) for r in records])
    return Observations(sun, rot, conc, targets, images, [str(r.record_id) for r in records])


def choose_slope_error(facets: Facets, train: Observations, base: SunSettings, settings: TrainSettings,
                       grid=SLOPE_ERROR_GRID) -> tuple[float, dict]:
    """Slope error that makes the *ideal* surface fit the training images best (mean L1).

    This gives the baseline physically honest optics (real sunshape + fitted slope error) from training data
    only; the learned surface is then trained and evaluated with the same optics, so IMP measures shape.
    """
    ideal = LearnableSurface(facets, settings.control_points, settings.degree).surfaces()
    scores = {}
    for se in grid:
        sun = dataclasses_replace(base, slope_error=float(se))
        scores[float(se)] = float(torch.tensor(evaluate_images(ideal, train, sun, samples=settings.samples,
                                                               resolution=settings.resolution,
                                                               size_m=settings.size_m)["l1"]).mean())
    best = min(scores, key=scores.get)
    return best, scores


def dataclasses_replace(obj, **changes):
    import dataclasses

    return dataclasses.replace(obj, **changes)


def train_with_early_stopping(facets: Facets, train: Observations, sun: SunSettings, settings: TrainSettings,
                              progress: bool = True, initial=None, initial_degree=None) -> tuple[LearnableSurface, dict]:
    """Early stopping on held-out *training* images, then a refit on all of them.

    With >= 3 training images the latest one is held out: phase 1 trains on the others and records the
    step with the lowest held-out L1; phase 2 trains on all images for that many steps. With fewer images
    the full step budget runs on all of them.
    """
    info: dict = {"holdout": None, "best_step": settings.steps}
    if settings.optimizer == "lbfgs":
        # L-BFGS runs to convergence; what is chosen on the held-out latest image is the smoothness weight.
        if settings.laplacian_grid and len(train) >= 2:
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
                    m1 = fit_surface(facets, head, sun, dataclasses_replace(settings, laplacian=float(w)),
                                     progress=False, initial=initial, initial_degree=initial_degree)
                    fold_l1.append(float(torch.tensor(evaluate_images(
                        m1.surfaces(), held, sun, samples=settings.samples, resolution=settings.resolution,
                        size_m=settings.size_m)["l1"]).mean()))
                scores[float(w)] = sum(fold_l1) / len(fold_l1)
            best = min(scores, key=scores.get)
            settings = dataclasses_replace(settings, laplacian=best)
            info.update(holdout=[train.ids[k] for k in folds] if len(folds) > 1 else train.ids[-1],
                        laplacian_scores=scores, laplacian_cv=settings.laplacian_cv)
        info["laplacian"] = settings.laplacian
        model = fit_surface(facets, train, sun, settings, progress=progress, initial=initial, initial_degree=initial_degree)
        info["best_step"] = model.steps_run
        return model, info
    if len(train) >= 3:
        log: list = []
        m1 = fit_surface(facets, train.subset(range(len(train) - 1)), sun, settings,
                         validation=train.subset([len(train) - 1]), progress=progress, log=log,
                         initial=initial, initial_degree=initial_degree)
        info["holdout"] = train.ids[-1]
        info["best_step"] = int(m1.best_step or settings.steps)
        info["holdout_curve"] = [(e["step"], round(e["val"], 5)) for e in log if "val" in e]
    s2 = dataclasses_replace(settings, steps=max(int(info["best_step"]), settings.eval_every))
    model = fit_surface(facets, train, sun, s2, progress=progress, initial=initial, initial_degree=initial_degree)
    return model, info


def reconstruct_paint(paint_dir, heliostat_id: str, *, train_records=None, train_first: int | None = None,
                      settings: TrainSettings | None = None, sun: SunSettings | None = None,
                      slope_error: float | None = None, background: float = 0.0, alignment: str = "focal-spot",
                      evaluate_mc: bool = True, progress: bool = True, deflectometry=None,
                      start_from_deflectometry: bool = False) -> tuple[dict, LearnableSurface, object, dict]:
    """Learn a heliostat's surface from its earliest centred images; evaluate on the others.

    ``deflectometry`` (a PAINT deflectometry HDF5 path): its NURBS fit is traced on the test images like the
    ideal and learned surfaces, and the learned surface is compared with it in mm and mrad (report key
    ``deflectometry``); with ``start_from_deflectometry`` the learning starts from it instead of flat.

    Returns
    -------
    report : dict
        JSON-ready (per test record L1 / cross-correlation for ideal and learned, median IMP, seconds, settings).
    model : LearnableSurface
    dataset : PaintDataset
    extras : dict
        ``train``/``test`` Observations and predicted test images (for plots).
    """
    import statistics

    from ..io.paint import load_paint

    t0 = time.perf_counter()
    s = settings or TrainSettings()
    ds = load_paint(paint_dir, heliostats=[heliostat_id])
    plant = ds.plant
    records = ds.records_of(heliostat_id)
    train_recs, test_recs = split_records(records, train_records, train_first)
    train = observations_from_records(plant, 0, train_recs, s.resolution, background, alignment)
    test = observations_from_records(plant, 0, test_recs, s.resolution, background, alignment)
    facets = Facets(*(getattr(plant.field.facets, a)[:1] for a in ("translation", "canting_e", "canting_n")))
    defl = defl_fit = None
    if deflectometry is not None:
        from .deflectometry import deflectometry_surface

        defl, defl_fit = deflectometry_surface(deflectometry, Facets(*(t.to(torch.float64) for t in facets)))
    elif start_from_deflectometry:
        raise HeliotwinError("start_from_deflectometry needs a deflectometry file")
    base_sun = sun or SunSettings(sunshape="buie", csr=0.05)
    if slope_error is None:
        chosen, scores = choose_slope_error(facets, train, base_sun, s)
    else:
        chosen, scores = float(slope_error), {}
    optics = dataclasses_replace(base_sun, slope_error=chosen)
    t_fit = time.perf_counter()
    init = dict(initial=defl.control_points, initial_degree=(defl.degree_u, defl.degree_v)) \
        if start_from_deflectometry else {}
    model, info = train_with_early_stopping(facets, train, optics, s, progress, **init)
    fit_seconds = time.perf_counter() - t_fit
    ideal = LearnableSurface(facets, s.control_points, s.degree).surfaces()
    learned = model.surfaces()
    kw = dict(samples=s.samples, resolution=s.resolution, size_m=s.size_m)
    e_ideal = evaluate_images(ideal, test, optics, **kw)
    e_learn = evaluate_images(learned, test, optics, **kw)
    e_sharp = evaluate_images(ideal, test, SHARP_SUN, **kw)
    e_train_i = evaluate_images(ideal, train, optics, **kw)
    e_train_l = evaluate_images(learned, train, optics, **kw)
    mc = {}
    if evaluate_mc:
        meas = test.images
        for name, surf in (("ideal", ideal), ("learned", learned)):
            img = trace_mc_centered(surf, test, optics, rays_per_point=64, **kw)
            mc[name] = losses.l1(img, meas.to(img)).tolist()
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
    d_mm = model.displacement.detach() * 1e3
    report = {
        "heliostat": heliostat_id,
        "paint": str(paint_dir),
        "train": [{"record": int(r), "l1_ideal": a, "l1_learned": b}
                  for r, a, b in zip(train.ids, e_train_i["l1"], e_train_l["l1"])],
        "test": rows,
        "median_l1_ideal": statistics.median(e_ideal["l1"]),
        "median_l1_learned": statistics.median(e_learn["l1"]),
        "median_l1_ideal_sharp_sun": statistics.median(e_sharp["l1"]),
        "median_imp": statistics.median(r["imp"] for r in rows),
        "median_imp_vs_sharp_sun": statistics.median(r["l1_ideal_sharp_sun"] / max(r["l1_learned"], 1e-12) - 1.0
                                                     for r in rows),
        "learned_below_ideal_on_all": all(r["l1_learned"] < r["l1_ideal"] for r in rows),
        "seconds": time.perf_counter() - t0,
        "fit_seconds": fit_seconds,
        "torch_threads": torch.get_num_threads(),
        "optics": {"sunshape": optics.sunshape, "csr": optics.csr, "slope_error_rad": optics.slope_error,
                   "slope_error_selection": "min mean L1 of the ideal surface on the training images",
                   "slope_error_scores": scores, "peer_sharp_sun": {"sunshape": "gaussian", "sigma_rad": 2.1e-3,
                                                                     "slope_error_rad": 0.0}},
        "comparison": {"window_m": s.size_m, "resolution": s.resolution,
                       "normalisation": "each image divided by its sum; L1 = sum |a - b|",
                       "centering": "measured: PAINT centred PNG; predicted: window centred on predicted centroid",
                       "alignment": alignment, "background_subtraction_fraction_of_max": background,
                       "downsampling": "256x256 PNGs box-averaged to 64x64"},
        "early_stopping": info,
        "settings": s.as_dict(),
        "displacement_mm": {"max_abs": float(d_mm.abs().max()), "rms": float(d_mm.pow(2).mean().sqrt())},
    }
    if defl is not None:
        from .deflectometry import compare_surfaces

        e_defl = evaluate_images(defl, test, optics, **kw)
        for row, v in zip(rows, e_defl["l1"]):
            row["l1_deflectometry"] = v
        report["deflectometry"] = {
            "file": str(deflectometry), "fit": defl_fit, "started_from": bool(start_from_deflectometry),
            "learned_vs_deflectometry": compare_surfaces(facets, learned, defl),
            "ideal_vs_deflectometry": compare_surfaces(facets, ideal, defl),
            "median_l1_deflectometry": statistics.median(e_defl["l1"])}
    extras = {"train": train, "test": test, "ideal_images": e_ideal["images"], "learned_images": e_learn["images"],
              "optics": optics, "facets": facets, "ideal": ideal}
    return report, model, ds, extras
