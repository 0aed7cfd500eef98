"""The aim-point solver: rounds of augmented-Lagrangian steps on the image model, each corrected by the exact model.

Surrogate-based optimisation with defect correction (first-order model management as in Alexandrov et al.,
Structural Optimization 15 (1998) 16), per round ``k``:

1. the exact model at the current aim points ``a_k`` gives the map ``F_k``, the power per heliostat (with its
   shading, blocking, cosine, attenuation) and its intercept;
2. the image model (:mod:`heliotwin.optimise.images`) is refreshed there (powers, spreads);
3. the corrected model ``S(a) + (F_k - S(a_k))`` equals the exact map at ``a_k``; the augmented Lagrangian
   (:func:`heliotwin.optimise.alm.alm_round`) solves the problem on it against the internal limit map
   ``(1 - m) L`` (every cell its own limit);
4. the exact model re-checks the new aim points; the margin ``m`` grows by the observed excess (the largest
   ``F_c / L_c - 1``) when the check fails. Rounds stop when the check passes and the power settles.

The options are one :class:`AimSettings`; a warm start is one :class:`~heliotwin.optimise.problem.WarmStart`. The
answer is the best aim points whose exact check held every cell under its limit; when none did, the fewest
heliostats on standby that make the least violating aim points hold it (:func:`_standby`).
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from types import SimpleNamespace

import torch

from ..errors import HeliotwinError
from ..field.targets import CylinderTarget
from ..raytrace.field import FieldSettings, equator_aim_points, field_optics, reuse_mirror_samples, tracking_normals
from .alm import Frame, RoundStart, Steps, alm_round
from .images import ImageModel, _image_model_at, _local, _world, calibrate_images, image_moments
from .problem import AimProblem, AimResult, FluxLimit, WarmStart, _Group, check_settings, target_mismatch

__all__ = ["AimSettings", "Calibration", "VISIBLE_HALF_ANGLE", "solve"]

#: Largest angle [rad] about a cylinder's axis between an aim point and the heliostat's own side of it.
VISIBLE_HALF_ANGLE = math.radians(70.0)
#: Exact checks at most when bisecting the standby count down (to half a per cent of the field).
STANDBY_BISECTIONS = 6


@dataclass(frozen=True)
class AimSettings:
    """The aim-point optimiser's knobs (:func:`optimise_aimpoints`; the ``aimpoints`` command's defaults).

    Attributes
    ----------
    resolution : (int, int)
        Reporting map (rows, cols) on which the limit is enforced and checked.
    iterations : int
        Adam steps on the image model per round.
    rounds : int
        Exact checks (one per round) at most.
    inner : int
        Multiplier update every ``inner`` steps.
    lr : float
        Adam step size [m] (decays to a tenth within each round).
    rho : float
        Augmented-Lagrangian weight on the relative excess ``F_c / limit - 1`` [-].
    margin : float
        Starting internal margin ``m`` [-].
    tolerance : float
        Relative change of the power (or mismatch) below which the rounds stop [-].
    slack : float
        Maximising power, the rounds also stop at a feasible round, the best so far, whose peak is within this
        fraction below the limit (with a warm start, the start's own check too) [-].
    field_gradient : bool
        Make the power model first-order exact at every round's start (see :func:`optimise_aimpoints`).
    softness : float
        Occlusion width [m] of the smooth field model used by ``field_gradient``.
    restore_steps : int
        After each round's Adam steps, at most this many steps on the corrected model's excess over the internal
        limit alone (at a tenth of the step size; they stop once no cell exceeds it): where the limit binds hard
        the multipliers lag and the model's peak still stood 2-4 % over, so the exact checks failed and the margin
        grew a round at a time. Chosen by ``benchmarks/bench_aimpoints.py --testbed --candidates`` (its
        ``choose_candidate`` rule) on the generated plants at 150 and 1,000 heliostats: every limit met
        either way, mean power +0.09 / +0.08 %, exact checks 599 -> 590 and 249 -> 240. They run with Adam
        moments of their own (chosen the same way over reusing the objective's: every limit met, mean power
        -0.05 % on both beds, exact checks 581 -> 571 and 243 -> 221, Adam steps -13 % and -23 %).
    warm_iterations, warm_lr, warm_tolerance : int, float, float
        With a warm start (``start_aim``): Adam steps per round, step size [m] and the predicted relative gain
        [-] below which the rounds stop (the start is near an optimum already: smaller, fewer steps; an exact
        check is worth making only for a gain above ``warm_tolerance``).
    """

    resolution: tuple[int, int] = (20, 48)
    iterations: int = 300
    rounds: int = 8
    inner: int = 10
    lr: float = 0.03
    rho: float = 1.0
    margin: float = 0.005
    tolerance: float = 1e-3
    field_gradient: bool = False
    softness: float = 0.05
    slack: float = 0.01
    warm_iterations: int = 50
    warm_lr: float = 0.01
    warm_tolerance: float = 2e-3
    restore_steps: int = 100




@dataclass(frozen=True)
class Calibration:
    """An image model and the exact equator result it was calibrated on (:func:`~heliotwin.optimise.images.
    calibrate_images`), when the caller has them already (both None: made here as needed)."""

    model: ImageModel | None = None
    equator: object = None


def _visible_arc(receiver, position: torch.Tensor):
    """Lateral bounds ``(lo, hi)`` [h] [m] of each heliostat's aim points on a cylinder: within
    :data:`VISIBLE_HALF_ANGLE` of the generator line facing it (an aim point on the far side is hidden behind
    the near side, where the exact model puts the light); None for a plane (any lateral aim point is seen)."""
    if not isinstance(receiver, CylinderTarget):
        return None
    d = position - receiver.axis_point.to(position)
    face = float(receiver.radius) * torch.atan2(d @ receiver.right.to(position), d @ receiver.normal.to(position))
    room = float(receiver.radius) * VISIBLE_HALF_ANGLE
    return face - room, face + room


def _field_power_gradient(problem: AimProblem, xy_all, rows, resolution, softness, dtype=torch.float32):
    """d(receiver power)/d(x, y) [h], [h] of this rank's heliostats ``rows`` through the smooth field model
    (shading, blocking, cosine, attenuation and intercept all move with the aim points) [W/m], at the aim points
    ``xy_all = (x, y)`` [H] each [m] of all heliostats."""
    grp, rec = _Group(problem.group), problem.plant.target("receiver")
    xa, ya = xy_all[0].clone().requires_grad_(), xy_all[1].clone().requires_grad_()
    settings = FieldSettings(resolution=tuple(int(r) for r in resolution), softness=float(softness), flux_samples=4,
                             flux_mode="window", dtype=dtype)
    r = field_optics(problem.plant, problem.sun, atmosphere=problem.atmosphere, aim=_world(rec, xa, ya),
                     settings=settings, heliostats=None if grp.group is None else rows)
    gx, gy = torch.autograd.grad(r.power_w.sum(), (xa, ya))  # a shard's power also moves with its occluders
    return grp.sum(gx.detach())[rows], grp.sum(gy.detach())[rows]


def _predicted_start(problem: AimProblem, start, start_field, resolution, rows, xy):
    """Image model at this sun and the predicted exact result at the aim points ``start`` [H, 3] (this rank's
    map coordinates ``xy``) from the exact result ``start_field`` of the same aim points at an earlier sun
    (``start_field.sun``), without evaluating the exact model: powers before spillage scaled by each heliostat's
    cosine ratio, spreads at this sun, and the earlier exact map plus the image model's change,
    ``F_prev + S_now(start) - S_prev(start)`` [rows, cols]."""
    plant, sun, grp = problem.plant, problem.sun, _Group(problem.group)
    x, y = xy
    pos = plant.field.kinematics.position.to(torch.float64)
    old_sun = torch.as_tensor(start_field.sun).to(pos)
    cos_old = (tracking_normals(pos, start, old_sun) * old_sun).sum(-1).clamp_min(1e-6)
    cos_new = (tracking_normals(pos, start, sun) * sun).sum(-1).clamp_min(0.0)
    old = _image_model_at(plant, old_sun, start, start_field, resolution, rows)
    now = dataclasses.replace(_image_model_at(plant, sun, start, start_field, resolution, rows),
                              power=old.power * (cos_new / cos_old)[rows])
    with torch.no_grad():
        f_new, p_new = now.flux(x, y)
        f_old, p_old = old.flux(x, y)
        flux = start_field.flux.to(pos) + grp.sum(f_new) - grp.sum(f_old)
        power = float(start_field.power_w.sum()) + float(grp.sum(p_new.sum())) - float(grp.sum(p_old.sum()))
    return now, SimpleNamespace(flux=flux, power_w=torch.tensor([power], dtype=torch.float64), predicted=True)


def _start(problem: AimProblem, resolution, rows, bounds, calibration: Calibration, warm: WarmStart | None):
    """Where :func:`solve`'s rounds start: ``(x, y, kick, first, model, p_eq, spreads_at_start)``.

    ``bounds = (x0, x_bounds)``: equator aiming's lateral coordinates [H] [m] and each heliostat's lateral range.
    Cold (``warm`` None): equator aiming (heights 0) with a small alternating ``kick`` [h] [m] for the first steps;
    ``first`` the exact equator result (``calibration.equator``, or made with the image model by
    :func:`calibrate_images`). Warm: ``warm.aim`` [H, 3] ENU [m] projected onto the receiver's height and each
    heliostat's visible arc, no kick, ``first`` its exact check; without ``calibration.model`` the image model is
    calibrated on that check (``spreads_at_start``). ``p_eq`` is equator aiming's power [W]: exact with an equator
    result, else the image model's corrected to the start's exact power. With ``warm.field`` (the start's exact
    result at an earlier sun) ``first`` is predicted, not evaluated (:func:`_predicted_start`; its ``predicted``
    is True) and the image model is made at this sun.
    """
    plant, sun, atmosphere, grp = problem.plant, problem.sun, problem.atmosphere, _Group(problem.group)
    x0, x_bounds = bounds
    model, equator = calibration.model, calibration.equator
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    h, half = pos.shape[0], 0.5 * float(rec.height)
    spreads_at_start = False
    if warm is not None:
        start = torch.as_tensor(warm.aim).to(pos)
        if start.shape != pos.shape:
            raise HeliotwinError(f"start aim points: expected shape {tuple(pos.shape)}, got {tuple(start.shape)}")
        xs, ys = _local(rec, start)
        x, y = xs[rows].clone(), ys[rows].clamp(-half, half)
        if x_bounds is not None:
            x = torch.minimum(torch.maximum(x, x_bounds[0]), x_bounds[1])
        start = _world(rec, grp.gather(x, h), grp.gather(y, h))
        if warm.field is not None:
            model, first = _predicted_start(problem, start, warm.field, resolution, rows, (x, y))
            spreads_at_start = True
        else:
            first = grp.field(plant, sun, atmosphere, start, check_settings(resolution))  # round 0's exact check
        if model is None:
            model, spreads_at_start = _image_model_at(plant, sun, start, first, resolution, rows), True
        kick = torch.zeros_like(x)  # no symmetric point to leave
    else:
        if model is None or equator is None:
            model, equator = calibrate_images(plant, sun, atmosphere, resolution, group=grp.group, equator=equator)
        first = equator  # round 0 is equator aiming, whose exact check the image model was calibrated on
        x, y = x0[rows].clone(), torch.zeros_like(x0[rows])
        # the first steps start from a small alternating spread: equator aiming is a symmetric point of the problem
        kick = 0.05 * (1 - 2 * (rows % 2)).to(pos)
    model = dataclasses.replace(model)  # its power is refreshed every round: leave the caller's alone
    if equator is not None:
        p_eq = float(equator.power_w.sum())
    else:  # equator aiming's power on the image model corrected to the start's exact power
        with torch.no_grad():
            p_e, p_s = model.flux(x0[rows], torch.zeros_like(x))[1], model.flux(x, y)[1]
            p_eq = float(grp.sum(p_e.sum())) + float(first.power_w.sum()) - float(grp.sum(p_s.sum()))
    return x, y, kick, first, model, p_eq, spreads_at_start


@reuse_mirror_samples()  # the rounds' exact checks move the heliostats, never their surfaces
def solve(problem: AimProblem, options: AimSettings = AimSettings(), warm: WarmStart | None = None, *,
          calibration: Calibration = Calibration(), progress=None) -> AimResult:
    """Aim points that maximise intercepted power (or match ``problem.target``) with every map cell at or below
    its own limit (``problem.limit``) on the exact model.

    Parameters
    ----------
    problem : AimProblem
        Plant, sun, flux limit (a :class:`~heliotwin.optimise.problem.FluxLimit`, or a float [W/m^2] for one
        peak limit), atmosphere, target, process group.
    options : AimSettings
        The optimiser's knobs (default: the ``aimpoints`` command's). With ``field_gradient`` the power model
        is also made first-order exact at every round's start: the difference between the smooth
        differentiable field model's power gradient (shading, blocking, cosine, attenuation, intercept;
        occlusion width ``softness`` [m]) and the image model's is added (one field-model backward per round).
    warm : WarmStart, optional
        Start from the previous instant's aim points (multipliers, margin, and its exact field for a predicted
        round 0) instead of equator aiming. Round 0 is then the exact check of them at this sun (or its
        prediction); without ``calibration.model`` the image model is calibrated on that check and without
        ``calibration.equator`` no equator check is made: the power the objective is relative to
        (:attr:`AimResult.reference_power_w`) is the corrected image model's estimate of equator aiming's.
    calibration : Calibration
        The exact equator result and a calibrated image model, when the caller has them.
    progress : callable, optional
        Called with a one-line string after each round.

    Returns
    -------
    AimResult
        All aim points [H, 3] and the exact check of them; ``history`` has per round the exact peak, power,
        margin and whether the check passed; ``iterations`` the Adam steps done; ``exact_checks`` the exact
        evaluations made (not counting the equator's); ``multipliers`` and ``parameter`` (the final margin) are
        the next instant's warm start.
    """
    t0 = time.perf_counter()
    resolution, iterations, lr, tolerance = options.resolution, options.iterations, options.lr, options.tolerance
    margin = float(options.margin)
    plant = problem.plant
    grp = _Group(problem.group)
    rec = plant.target("receiver")
    pos = plant.field.kinematics.position.to(torch.float64)
    limit = FluxLimit.of(problem.limit, resolution)
    problem = dataclasses.replace(problem, sun=torch.as_tensor(problem.sun).to(pos), limit=limit,
                                  target=None if problem.target is None else problem.target.to(pos))
    cells = limit.on(pos)
    h = pos.shape[0]
    rows = grp.rows(h, pos.device)
    x0, _ = _local(rec, equator_aim_points(rec, pos))
    x_bounds = _visible_arc(rec, pos[rows])
    if warm is not None:
        iterations, lr, tolerance = options.warm_iterations, options.warm_lr, options.warm_tolerance
    x, y, kick, first, model, p_eq, spreads_at_start = _start(problem, resolution, rows, (x0, x_bounds),
                                                             calibration, warm)
    predicted = getattr(first, "predicted", False)  # round 0 a prediction, not an exact check
    checks = int(warm is not None and not predicted)
    lam = torch.zeros(tuple(int(r) for r in resolution), dtype=torch.float64, device=pos.device)
    if warm is not None and warm.multipliers is not None:
        lam = warm.multipliers.detach().to(lam).clone()
    tgt = problem.target
    m = margin if warm is None or warm.margin is None else max(margin, float(warm.margin))
    frame = Frame(grp, 0.5 * float(rec.height), x_bounds, p_eq, float(h), tgt)
    steps_of = Steps(iterations, lr, options.rho, options.inner, options.restore_steps)
    best, best_key, least, least_key, history, steps = None, None, None, None, [], 0
    previous = None
    for k in range(int(options.rounds)):
        aim = _world(rec, grp.gather(x, h), grp.gather(y, h))
        if k == 0:
            ex = first  # equator aiming's check (cold) or the start's (warm), made above
        else:
            ex, checks = grp.field(plant, problem.sun, problem.atmosphere, aim, check_settings(resolution)), checks + 1
        peak, power, ratio = float(ex.flux.max()), float(ex.power_w.sum()), limit.ratio(ex.flux)
        guess = predicted and k == 0
        ok = limit.held(ex.flux) and not guess  # a prediction is never a result
        key = power / p_eq if tgt is None else -target_mismatch(ex.flux, tgt)
        history.append({"round": k, "peak_flux_w_m2": peak, "power_w": power, "margin": m, "feasible": ok,
                        "objective": key})
        if not limit.is_uniform:
            history[-1]["max_utilisation"] = ratio
        if guess:
            history[-1]["predicted"] = True
        if progress is not None:
            progress(f"round {k}: peak {ratio:.4f} of the limit, power {power / p_eq:.4f} of equator")
        res = AimResult(aim.detach(), power, peak, ex.flux, exact=None if guess else ex)
        if ok and (best is None or key > best_key):
            best, best_key = res, key
        if not guess and (least is None or limit.key(ex.flux) < least_key):
            least, least_key = res, limit.key(ex.flux)
        if ok and previous is not None and abs(key - previous) < tolerance:
            break
        near = bool((ex.flux >= (1.0 - float(options.slack)) * cells.to(ex.flux)).any())
        if ok and (k > 0 or warm is not None) and tgt is None and best is res and near:
            break  # the limit binds within the slack at the best power so far: more rounds only trade noise
        previous = key if ok else None
        if not ok and k > 0:
            m += ratio - 1.0 + 0.5 * margin
        elif ok and 1.0 - ratio > 2.0 * margin:
            # slack left on the table: give half of it back (the best feasible result is kept anyway)
            m = max(margin, m - 0.5 * (1.0 - ratio - margin))
        if k == int(options.rounds) - 1:
            break
        # refresh the per-heliostat power (shading, blocking and cosine move with the aim points) and the image
        # spreads (the incidence on the receiver moves with them)
        if not guess:
            model.power = (ex.power_w.to(pos) / ex.intercept.to(pos).clamp_min(1e-6))[rows]
        if k > 0 or (warm is not None and not spreads_at_start):  # else the calibration's own spreads here
            _, sd, box = image_moments(plant, problem.sun, aim, resolution, rows)
            model.sx, model.sy, model.bx, model.by = sd[:, 0], sd[:, 1], box[:, 0], box[:, 1]
        with torch.no_grad():
            f_s, p_s = model.flux(x, y)
            f_s, p_s = grp.sum(f_s), grp.sum(p_s.sum())
        linear = None
        if options.field_gradient:
            # first-order model management: the corrected model's power gradient at a_k becomes the field model's
            xs, ys = x.clone().requires_grad_(), y.clone().requires_grad_()
            gsx, gsy = torch.autograd.grad(model.flux(xs, ys)[1].sum(), (xs, ys))
            gfx, gfy = _field_power_gradient(problem, (grp.gather(x, h), grp.gather(y, h)), rows, resolution,
                                             options.softness)
            linear = (gfx - gsx, gfy - gsy)
        rnd = RoundStart(x, y + kick if k == 0 else y, ex.flux.to(pos) - f_s, power - float(p_s), cells * (1.0 - m),
                         lam, linear)
        x_new, y_new, predicted, done = alm_round(model, rnd, steps_of, frame)
        steps += done
        if ok and best is res and predicted - key < tolerance:
            # the corrected model equals the exact one here and sees no gain worth an exact check from here: the
            # next check would only confirm this result (or lose to it)
            history[-1]["stopped"] = "no predicted gain"
            break
        x, y = x_new, y_new
    out = best if best is not None else least
    if best is None:  # no aim point on the receiver held the limit: take the fewest heliostats off it that do
        out = _standby(problem, model, least, rows, resolution)
        checks += out.exact_checks
    out.seconds, out.iterations, out.history, out.parameter = time.perf_counter() - t0, steps, history, m
    out.multipliers, out.reference_power_w, out.exact_checks = lam.detach().clone(), p_eq, checks
    return out


def _standby(problem: AimProblem, model: ImageModel, least: AimResult, rows, resolution) -> AimResult:
    """The least-violating aim points with the fewest heliostats sent to standby that hold the limit exactly.

    A heliostat on standby aims ``5 sy`` above the receiver's top edge, on the side facing it (its image
    passes above the receiver; it still shades and blocks as it tracks). The heliostats are ranked by their
    image-model flux in the cells over their limit (most first); the count is first predicted on the image
    model corrected to the exact map, grown by half until the exact check passes (all of them at most), then
    bisected down (:data:`STANDBY_BISECTIONS` exact checks at most, to half a per cent of the field) to keep as
    many on the receiver as hold it. Returns ``least`` unchanged (limit still violated) when even every heliostat
    on standby does not hold it; else the result with ``standby`` set.
    """
    plant, limit, grp = problem.plant, problem.limit, _Group(problem.group)
    rec = plant.target("receiver")
    h = least.aim.shape[0]
    aim = least.aim.to(torch.float64)
    x_all, y_all = _local(rec, aim)
    x, y = x_all[rows], y_all[rows]
    with torch.no_grad():
        cells = limit.on(x).flip(0)  # [rows, cols], ascending y like the marginals
        gx, gy = model.marginals(x, y)
        over = (least.flux.to(x).flip(0) > cells).to(x)
        own = model.power * torch.einsum("hr,rc,hc->h", gy, over, gx) / model.cell_area  # [h] [W/m^2 x cells]
        mass = grp.gather(own, h)
        order = torch.argsort(mass, descending=True, stable=True)
        # the image model's prediction of how many must go: cumulative removal from the exact map
        img = (model.power[:, None, None] * gy[:, :, None] * gx[:, None, :]) / model.cell_area  # [h, rows, cols]
        local_rank = torch.empty_like(order)
        local_rank[order] = torch.arange(h, device=order.device)
        ranked = torch.zeros((h,) + tuple(img.shape[1:]), dtype=img.dtype, device=img.device)
        ranked[local_rank[rows]] = img
        ranked = grp.sum(ranked)
        remaining = least.flux.to(x).flip(0)[None] - torch.cumsum(ranked, 0)
        fits = (remaining <= cells[None]).flatten(1).all(1).nonzero()
        k = int(fits[0]) + 1 if fits.numel() else h
    sy_all = grp.gather(model.sy, h)
    x_eq, _ = _local(rec, equator_aim_points(rec, plant.field.kinematics.position.to(aim)))
    half = 0.5 * float(rec.height)

    def check(count):
        off = torch.zeros(h, dtype=torch.bool, device=aim.device)
        off[order[:count]] = True
        x_new = torch.where(off, x_eq, x_all)  # facing the heliostat: its beam passes above the receiver
        y_new = torch.where(off, half + 5.0 * sy_all.to(y_all), y_all)
        trial = _world(rec, x_new, y_new)
        ex = grp.field(plant, problem.sun, problem.atmosphere, trial, check_settings(resolution))
        out = AimResult(trial.detach(), float(ex.power_w.sum()), float(ex.flux.max()), ex.flux)
        out.standby = count
        return out

    fail, ok, calls = 0, None, 0
    while ok is None:  # grow from the prediction until the exact check passes
        r, calls = check(k), calls + 1
        if limit.held(r.flux):
            ok = r
        elif k >= h:
            least.exact_checks = calls
            return least
        else:
            fail, k = k, min(h, k + max(1, k // 2))
    for _ in range(STANDBY_BISECTIONS):  # then fewer on standby while it still passes
        if ok.standby - fail <= max(1, h // 200):
            break
        r, calls = check((fail + ok.standby) // 2), calls + 1
        if limit.held(r.flux):
            ok = r
        else:
            fail = r.standby
    ok.exact_checks = calls
    return ok
