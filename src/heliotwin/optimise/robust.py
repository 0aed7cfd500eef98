"""Aim points that hold the peak limit with a stated probability under the twin's own pointing uncertainty.

The calibration stores each heliostat's Laplace posterior (``/learned/calibration/posterior``: covariance of the
kinematic deviations [P, P], residual noise and drift per component [rad];
:mod:`heliotwin.calibrate.uncertainty`). At one sun and aim point its mirror-normal error is Gaussian,

    dn = J L xi + sd (I - n n^T) eta,   xi ~ N(0, I_P), eta ~ N(0, I_3),   sd^2 = s^2 + tau^2,

(``J`` [3, P] the normal's derivative w.r.t. the deviations at the motor steps that aim it, ``L`` the
covariance's Cholesky factor): the predictive distribution whose 90 % intervals the calibration validates on
held-out records. A heliostat whose normal is off by ``dn`` reflects along ``r' = reflect(-s, n + dn)``; aiming
it at ``a' = p + |a - p| r'`` gives exactly that normal, so one draw of the plant is the exact field model at
displaced aim points (:func:`perturbed_aim`).

**Check** (:func:`exceedance`): ``draws`` seeded draws of every heliostat's error; per draw the receiver map's
peak; the probability of exceeding the limit is the share of draws over it (its binomial standard error
reported beside it). ``mc="exact"``: the exact model (:func:`heliotwin.optimise.aimpoints.evaluate`) per draw;
``mc="model"``: the image model corrected to the exact map at the aim points, ``F(a) + S(a + d) - S(a)``, with
each heliostat's spot displaced by the linearised map of its normal error onto the receiver surface
(:func:`spot_jacobian`): a thousand draws in about a second at 2,000 heliostats.

**Robust aim points** (:func:`robust_aimpoints`): constraint tightening ("back-off", as in chance-constrained
model-predictive control): the deterministic optimiser (:func:`~heliotwin.optimise.aimpoints.optimise_aimpoints`)
against an internal limit ``L' < L``, with ``L'`` lowered by the ratio of the limit to the draws' ``confidence``
quantile of the peak until the share of draws over ``L`` is at most ``1 - confidence`` (the same draws every
time: common random numbers). The power it costs is the robust result's power against the deterministic one's.

Shapes: H heliostats, D draws, P kinematic parameters; aim points [H, 3] ENU [m]; normal errors [D, H, 3].
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from scipy.stats import beta as beta_dist

from ..calibrate.params import apply_deviations
from ..devices import to_device
from ..errors import HeliotwinError
from ..field import kinematics as K
from ..field.plant import Kinematics, Plant
from ..geometry import reflect
from ..raytrace.field import tracking_normals
from .aimpoints import (
    AimResult,
    AimSettings,
    ImageModel,
    _local,
    evaluate,
    optimise_aimpoints,
)

__all__ = ["PointingPosterior", "require_posterior", "walked_covariance", "exceedance_bound", "pointing_posterior",
           "draw_normal_errors", "perturbed_aim",
           "spot_jacobian", "exceedance", "robust_aimpoints"]


@dataclass
class PointingPosterior:
    """Each heliostat's normal-error distribution at one sun and set of aim points.

    Attributes
    ----------
    jacobian_chol : torch.Tensor, [H, 3, P]
        ``J L``: the normal's derivative w.r.t. the deviations times the posterior covariance's Cholesky factor
        [1 per unit deviation]; zero rows for heliostats without a posterior.
    plane_sd : torch.Tensor, [H]
        Standard deviation per component of the in-plane error (residual noise and drift) [rad].
    normal : torch.Tensor, [H, 3]
        The tracking normals the errors are about.
    calibrated : int
        Heliostats with their own posterior (the others get the calibrated ones' median in-plane spread).
    """

    jacobian_chol: torch.Tensor
    plane_sd: torch.Tensor
    normal: torch.Tensor
    calibrated: int

    def sd_mrad(self) -> torch.Tensor:
        """Root-mean-square normal error per in-plane axis [H] [mrad]."""
        var = (self.jacobian_chol ** 2).sum((-1, -2)) + 2.0 * self.plane_sd ** 2
        return 1e3 * (0.5 * var).sqrt()


def require_posterior(learned: dict, path: str = "") -> dict:
    """The scenario's ``/learned/calibration`` when it stores a pointing posterior, else a one-line
    :class:`~heliotwin.errors.HeliotwinError` naming the file (``learned``: the scenario's ``/learned``)."""
    cal = (learned or {}).get("calibration") or {}
    if not cal.get("posterior"):
        raise HeliotwinError(f"{path or 'scenario'} [/learned/calibration/posterior]: no pointing posterior stored, "
                             "which --confidence needs (calibrate the plant with --method lm first)")
    return cal


def walked_covariance(cal: dict, cov: torch.Tensor, names: list, time_s: float | None) -> torch.Tensor:
    """``cov`` [H, P, P] with the stored random walk of the axis offsets grown from the state's time
    (``/learned/calibration/drift/time`` [H]) to ``time_s`` [POSIX s] (``q`` [rad^2/day] x days, never
    negative); unchanged without a drift state or a time."""
    drift = cal.get("drift") or {}
    if time_s is None or not drift or "time" not in drift or "process_noise_rad2_per_day" not in drift:
        return cov
    cols = [names.index(n) for n in (drift.get("names") or ()) if n in names]
    t = torch.as_tensor(drift["time"], dtype=torch.float64).reshape(-1)
    q = float(torch.as_tensor(drift["process_noise_rad2_per_day"], dtype=torch.float64).reshape(-1)[0])
    if not cols or t.shape[0] != cov.shape[0]:
        return cov
    days = ((float(time_s) - t) / 86400.0).nan_to_num(0.0).clamp_min(0.0).to(cov)
    cov = cov.clone()
    idx = torch.tensor(cols, dtype=torch.long, device=cov.device)
    cov[:, idx, idx] += (q * days)[:, None]
    return cov


def _walk_days(cal: dict, time_s: float | None) -> float:
    """Median days [1] from the heliostats' state time to ``time_s`` [POSIX s] (0 without a drift state)."""
    t = (cal.get("drift") or {}).get("time")
    if t is None or time_s is None:
        return 0.0
    d = ((float(time_s) - torch.as_tensor(t, dtype=torch.float64).reshape(-1)) / 86400.0).nan_to_num(0.0)
    return float(d.clamp_min(0.0).median()) if len(d) else 0.0


def exceedance_bound(over: int, draws: int, level: float = 0.95) -> float:
    """Exact (Clopper-Pearson) one-sided ``level`` upper bound on a probability seen ``over`` times in
    ``draws`` independent draws: 0 of 50 bounds it only below 5.8 % at 95 %."""
    k, n = int(over), int(draws)
    if k >= n:
        return 1.0
    return float(beta_dist.ppf(float(level), k + 1, n - k))


def pointing_posterior(plant: Plant, learned: dict, sun: torch.Tensor, aim: torch.Tensor,
                       path: str = "", time_s: float | None = None) -> PointingPosterior:
    """The normal-error distribution [rad] of every heliostat aiming at ``aim`` [H, 3] ENU [m] under ``sun`` [3]
    (unit, ENU).

    ``learned`` is the scenario's ``/learned`` dict; its ``calibration`` must hold a ``posterior`` (``heliotwin
    calibrate --method lm``), else a one-line :class:`~heliotwin.errors.HeliotwinError`. The Jacobian is taken
    at the stored fit (nominal kinematics plus deviations) and the motor steps that aim each heliostat there.
    ``time_s`` [POSIX s]: when the aim points are used; the offsets' stored random walk is grown to then
    (:func:`walked_covariance`), so a spread far from the records' time is wider.
    """
    cal = require_posterior(learned, path)
    where = f"{path or 'scenario'} [/learned/calibration/posterior]"
    try:
        ids = [str(i) for i in cal["heliostats"]]
        names = [str(n) for n in cal["parameter_names"]]
        post = cal["posterior"]
        cov = torch.as_tensor(post["covariance"], dtype=torch.float64)
        noise = torch.as_tensor(post["noise_rad"], dtype=torch.float64).reshape(-1)
        drift = float(torch.as_tensor(post.get("drift_rad", 0.0), dtype=torch.float64).reshape(-1)[0])
        delta = torch.as_tensor(cal["deviations"], dtype=torch.float64)
        nominal = Kinematics(**{f.name: torch.as_tensor(cal["nominal"][f.name])
                                for f in dataclasses.fields(Kinematics)})
    except (KeyError, IndexError, TypeError, ValueError, RuntimeError):
        raise HeliotwinError(f"{where}: malformed calibration posterior") from None
    p = len(names)
    if cov.shape != (len(ids), p, p) or noise.shape != (len(ids),):
        raise HeliotwinError(f"{where}: covariance must be [{len(ids)}, {p}, {p}] and noise [{len(ids)}]")
    cov = walked_covariance(cal, cov, names, time_s)
    pos = plant.field.kinematics.position.to(torch.float64)
    dev = pos.device  # the stored posterior is on the host; the plant may be on a GPU
    cov, noise, delta, nominal = cov.to(dev), noise.to(dev), delta.to(dev), to_device(nominal, dev)
    aim = aim.to(pos)
    sun = torch.as_tensor(sun).to(pos)
    h = pos.shape[0]
    normal = tracking_normals(pos, aim, sun)
    index = {hid: k for k, hid in enumerate(plant.field.ids)}
    rows = [k for k, hid in enumerate(ids) if hid in index]
    at = torch.tensor([index[ids[k]] for k in rows], dtype=torch.long, device=dev)
    jl = torch.zeros(h, 3, p, dtype=torch.float64, device=dev)
    sd = torch.zeros(h, dtype=torch.float64, device=dev)
    if rows:
        kin = nominal.index(rows)
        d = delta[rows].clone()
        steps, ok = K.inverse(apply_deviations(kin, d, names), aim[at], sun.expand(len(rows), 3), strict=False)
        steps = torch.where(ok[:, None] & torch.isfinite(steps), steps, kin.min_steps.to(steps))
        d.requires_grad_(True)
        rot, _ = K.forward(apply_deviations(kin, d, names), steps.detach())
        n = K.mirror_normal(rot)
        jac = torch.stack([torch.autograd.grad(n[:, c].sum(), d, retain_graph=c < 2)[0] for c in range(3)], 1)
        chol = torch.linalg.cholesky(cov[rows] + 1e-18 * torch.eye(p, dtype=torch.float64, device=dev))
        jl[at] = jac.detach() @ chol
        sd[at] = (noise[rows] ** 2 + drift ** 2).sqrt()
    missing = torch.ones(h, dtype=torch.bool, device=dev)
    missing[at] = False
    if bool(missing.any()) and rows:
        # no posterior of their own: the calibrated heliostats' median spread, in their own mirror plane
        mean_var = 0.5 * ((jl[at] ** 2).sum((-1, -2)) + 2.0 * sd[at] ** 2)
        sd[missing] = float(mean_var.median().sqrt())
    return PointingPosterior(jl, sd, normal, len(rows))


def draw_normal_errors(posterior: PointingPosterior, draws: int, generator: torch.Generator) -> torch.Tensor:
    """``draws`` seeded draws of every heliostat's normal error ``dn`` [D, H, 3] [rad] (module docstring), on
    the posterior's device; drawn where ``generator`` lives, so a seed gives the same draws on every device."""
    h, _, p = posterior.jacobian_chol.shape
    n = posterior.normal
    xi = torch.randn(int(draws), h, p, generator=generator, dtype=torch.float64, device=generator.device).to(n)
    eta = torch.randn(int(draws), h, 3, generator=generator, dtype=torch.float64, device=generator.device).to(n)
    plane = eta - (eta * n).sum(-1, keepdim=True) * n  # (I - n n^T) eta
    return torch.einsum("hcp,dhp->dhc", posterior.jacobian_chol, xi) + posterior.plane_sd[None, :, None] * plane


def perturbed_aim(plant: Plant, sun: torch.Tensor, aim: torch.Tensor, dn: torch.Tensor) -> torch.Tensor:
    """Aim points [..., H, 3] ENU [m] that turn the tracking normals towards ``aim`` [H, 3] by ``dn`` [..., H, 3]
    [rad] (its part in the mirror plane): the point at the same slant range along the ray the erring mirror
    reflects."""
    pos = plant.field.kinematics.position.to(torch.float64)
    aim = aim.to(pos)
    sun = torch.as_tensor(sun).to(pos)
    slant = torch.linalg.vector_norm(aim - pos, dim=-1, keepdim=True)
    normal = tracking_normals(pos, aim, sun)
    dn = dn - (dn * normal).sum(-1, keepdim=True) * normal
    n = torch.nn.functional.normalize(normal + dn, dim=-1)
    r = reflect(-torch.as_tensor(sun).to(pos).expand_as(n), n)
    return pos + slant * r


def spot_jacobian(plant: Plant, sun: torch.Tensor, aim: torch.Tensor, step: float = 1e-3) -> torch.Tensor:
    """Derivative [H, 2, 3] of each spot's map coordinates ``(x, y)`` [m] w.r.t. its normal error [rad] when
    aiming at ``aim`` [H, 3] ENU [m].

    A normal error ``dn`` (in the mirror plane) turns the reflected ray by ``dr = -2 ((d.n) dn + n (d.dn))``
    (``d = -sun``); the ray from the pivot then meets the receiver surface ``(x, y)`` where ``T_x dx + T_y dy -
    r t = |a - p| dr`` (``T`` the surface's tangents at the aim point, by central differences of ``step`` [m]).
    """
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    aim = aim.to(pos)
    normal = tracking_normals(pos, aim, torch.as_tensor(sun).to(pos))
    x, y = _local(rec, aim)
    xy = torch.stack((x, y), -1)
    tangents = []
    for k in range(2):
        e = torch.zeros(2, dtype=pos.dtype, device=pos.device)
        e[k] = step
        tangents.append((rec.to_world(xy + e) - rec.to_world(xy - e)) / (2.0 * step))
    ray = aim - pos
    slant = torch.linalg.vector_norm(ray, dim=-1)
    r = ray / slant[:, None]
    g = torch.stack((tangents[0], tangents[1], -r), -1)  # [H, 3, 3]
    d = -torch.as_tensor(sun).to(pos).expand_as(normal)
    dn = (d * normal).sum(-1)[:, None, None]
    b = -2.0 * (dn * torch.eye(3, dtype=pos.dtype, device=pos.device) + normal[:, :, None] * d[:, None, :])  # dr = B dn
    return slant[:, None, None] * torch.linalg.solve(g, b)[:, :2, :]


def exceedance(plant: Plant, sun: torch.Tensor, result: AimResult, limit: float, dn: torch.Tensor, *,
               atmosphere=None, resolution=(20, 48), mc: str = "model",
               model: ImageModel | None = None) -> dict:
    """Probability that the receiver's peak exceeds ``limit`` [W/m^2] at ``result``'s aim points, over the
    draws ``dn`` [D, H, 3] of the normal errors.

    ``mc="exact"``: the exact model per draw; ``mc="model"``: ``model`` (calibrated for these heliostats)
    corrected to ``result.flux`` (module docstring). Returns ``probability`` [-], its binomial
    ``standard_error``, ``draws``, the peaks' ``quantiles`` (0.5, 0.9, 0.95, 0.99) [W/m^2] and ``peaks`` [D].
    """
    aim = result.aim.to(torch.float64)
    if mc == "exact":
        aims = perturbed_aim(plant, sun, aim, dn)
        peaks = torch.tensor([evaluate(plant, sun, a, atmosphere, resolution).peak_flux_w_m2 for a in aims],
                             dtype=torch.float64)
    elif mc == "model":
        if model is None:
            raise ValueError("mc='model' needs the calibrated image model")
        rec = plant.target("receiver")
        x, y = _local(rec, aim)
        shift = torch.einsum("hkc,dhc->dhk", spot_jacobian(plant, sun, aim), dn)  # [D, H, 2]
        m = dataclasses.replace(model, profile_dtype=torch.float32)
        with torch.no_grad():
            base = result.flux.to(torch.float64) - m.flux(x, y)[0]
            peaks = torch.stack([(base + m.flux(x + s[:, 0], y + s[:, 1])[0]).max() for s in shift])
    else:
        raise ValueError(f"unknown mc {mc!r}; expected 'model' or 'exact'")
    over = (peaks > float(limit)).double()
    prob = float(over.mean())
    qs = torch.quantile(peaks, torch.tensor([0.5, 0.9, 0.95, 0.99], dtype=torch.float64, device=peaks.device))
    return {"probability": prob, "standard_error": math.sqrt(max(prob * (1.0 - prob), 1e-12) / len(peaks)),
            "draws": len(peaks), "mc": mc, "quantiles_w_m2": {"0.5": float(qs[0]), "0.9": float(qs[1]),
                                                               "0.95": float(qs[2]), "0.99": float(qs[3])},
            "peaks": peaks}


def robust_aimpoints(plant: Plant, sun: torch.Tensor, limit: float, confidence: float, learned: dict,
                     settings: AimSettings = AimSettings(), *, atmosphere=None, equator=None, model=None,
                     deterministic: AimResult | None = None, draws: int = 200, seed: int = 0, mc: str = "model",
                     tries: int = 6, path: str = "", time_s: float | None = None) -> tuple[AimResult, dict]:
    """Aim points whose peak stays at or below ``limit`` [W/m^2] with probability ``confidence`` under the
    stored pointing posterior (module docstring), and the report comparing them with the deterministic ones.

    Parameters
    ----------
    plant, sun, limit, settings, atmosphere, equator, model
        As for :func:`~heliotwin.optimise.aimpoints.optimise_aimpoints` (``model``/``equator`` from
        :func:`~heliotwin.optimise.aimpoints.calibrate_images`; ``model`` is needed for ``mc="model"``).
    confidence : float
        In (0, 1).
    learned : dict
        The scenario's ``/learned`` (its calibration's posterior).
    deterministic : AimResult, optional
        The deterministic aim points at ``limit`` (computed when not given).
    draws, seed : int
        Monte-Carlo draws of the plant and the seed of their generator.
    mc : {"model", "exact"}
        How each draw's map is computed (:func:`exceedance`); the tightening always decides on the same draws.
    tries : int
        Tightened optimisations at most.

    Returns
    -------
    robust : AimResult
        The robust aim points and their exact (undisturbed) check.
    report : dict
        ``confidence``, ``draws``, ``mc``, ``seed``, ``pointing_sd_mrad`` (median, max), ``calibrated_heliostats``,
        ``deterministic`` and ``robust`` (``exceedance_probability`` and its standard error, peak quantiles,
        power, internal limit), ``power_cost`` (1 - robust / deterministic power), ``decision_probability``
        (the share of draws over the limit the tightening aims at or below: ``1 - confidence`` less 1.645 binomial
        standard errors, so that independent draws stay within ``1 - confidence``), ``exceedance_upper_95``
        (exact Clopper-Pearson bound of the robust result's share over the limit), ``draws_needed`` (the fewest
        draws whose bound can fall below ``1 - confidence``), ``met`` (reached *and* that bound below ``1 -
        confidence``; else ``met_reason``), ``walked_days`` (median days the offsets' walk grew to ``time_s``).
    """
    if not 0.0 < float(confidence) < 1.0:
        raise HeliotwinError(f"--confidence: expected a probability in (0, 1), got {confidence!r}")
    alpha = 1.0 - float(confidence)
    # decide on a one-sided 95 % bound, not the estimate: stopping as soon as the draws' share dips under alpha
    # fits the aim points to these draws (measured: 0.095 on them, 0.14 on independent ones at alpha 0.1)
    goal = max(alpha - 1.645 * math.sqrt(alpha * (1.0 - alpha) / int(draws)), 0.5 * alpha)
    kw = dict(atmosphere=atmosphere, equator=equator, model=model)
    det = deterministic or optimise_aimpoints(plant, sun, limit, settings, **kw)
    post = pointing_posterior(plant, learned, sun, det.aim, path, time_s=time_s)
    gen = torch.Generator().manual_seed(int(seed))
    dn = draw_normal_errors(post, draws, gen)
    check = dict(atmosphere=atmosphere, resolution=settings.resolution, mc=mc, model=model)
    ex_det = exceedance(plant, sun, det, limit, dn, **check)
    best, ex_best, internal = det, ex_det, float(limit)  # the latest tightening (each one is tighter)
    tried = []
    level = 1.0 - goal
    # can these draws show alpha at all? 0 over the limit must bound the probability below it
    for _ in range(int(tries)):
        if ex_best["probability"] <= goal:
            break
        q = float(torch.quantile(ex_best["peaks"], level))
        internal = internal * min(float(limit) / q, 1.0 - 1e-3)  # the quantile scaled onto the limit
        best = optimise_aimpoints(plant, sun, internal, settings, **kw)
        ex_best = exceedance(plant, sun, best, limit, dn, **check)
        tried.append({"internal_limit_w_m2": internal, "exceedance_probability": ex_best["probability"],
                      "power_w": best.power_w, "standby": int(best.standby)})
    sd = post.sd_mrad()

    def entry(r, ex, lim):
        return {"exceedance_probability": ex["probability"], "standard_error": ex["standard_error"],
                "peak_quantiles_w_m2": ex["quantiles_w_m2"], "power_w": r.power_w,
                "undisturbed_peak_w_m2": r.peak_flux_w_m2, "internal_limit_w_m2": lim, "standby": int(r.standby)}

    # honest about the draws: an exact upper bound on the exceedance probability, met only when it is below
    # 1 - confidence (0 of D draws bounds it at 1 - 0.05^(1/D), about 3 / D: fewer draws cannot show more)
    over = int(round(ex_best["probability"] * len(ex_best["peaks"])))
    bound = exceedance_bound(over, len(ex_best["peaks"]))
    needed = math.ceil(math.log(0.05) / math.log1p(-alpha))
    report = {"confidence": float(confidence), "draws": int(draws), "mc": mc, "seed": int(seed),
              "exceedance_upper_95": bound, "draws_needed": needed,
              "walked_days": _walk_days(require_posterior(learned, path), time_s),
              "calibrated_heliostats": post.calibrated,
              "pointing_sd_mrad": {"median": float(sd.median()), "max": float(sd.max())},
              "deterministic": entry(det, ex_det, float(limit)), "robust": entry(best, ex_best, internal),
              "power_cost": 1.0 - best.power_w / det.power_w if det.power_w > 0 else 0.0,
              "decision_probability": goal, "met": bound <= alpha,
              "tightenings": tried}
    if bound > alpha:
        report["met_reason"] = (f"{over} of {len(ex_best['peaks'])} draws over the limit bound the exceedance "
                                f"probability only below {bound:.3g} (exact, 95 %), not {alpha:.3g}: at least "
                                f"{needed} draws are needed")
    return best, report
