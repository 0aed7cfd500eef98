"""``lm``: Levenberg-Marquardt (scipy, MINPACK) on the 8-parameter Stone/Jülich error model.

The heliostats of a run are fitted together: their parameters are independent, so the joint minimum is every
heliostat's own minimum. The default solver (:data:`SOLVER`, :mod:`.batched`) advances all heliostats' problems
at once in tensors (per-heliostat normal equations, damping and convergence; cost linear in heliostats, any
device; a whole plant in one call). The reference solver is scipy's ``least_squares`` with an analytic
(autograd) Jacobian, :data:`LM_CHUNK` heliostats per problem: scipy treats the Jacobian as dense, so one
problem over a whole plant would cost the cube of its heliostats. Residuals per record are the three components of
(model normal - measured normal), whose norm is the pointing error to second order. A Gaussian prior
(Tikhonov) towards nominal adds ``delta / sigma`` residuals per parameter; with few records this is what
keeps the ill-conditioned directions (axis tilts versus offsets) from fitting noise.

:func:`fit_lm` is the solver (float64; batched on the inputs' device, or scipy on the CPU);
:func:`stone8_field_fit` the two-pass fit with the field prior that every method pre-aligns with;
:func:`fit_lm_method` the ``lm`` method (robust loss, bagging).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.distributed as dist
from scipy.optimize import least_squares

from ...devices import to_device
from ...field.plant import Kinematics
from ...io.checkpoint import resumable_range
from ...io.records import RecordTable
from .. import metrics, priors
from ..drift import Q_GRID, smooth, split_for_choice, whitener, with_offset
from ..inputs import FIT_FOCAL_SPOT, NOISE, fit_spots, trainable
from ..metrics import record_jacobian
from ..model import Calibrated
from ..params import STONE8, apply_deviations, check_names, kinds, units
from ..uncertainty import posterior, residual_variance
from . import batched

#: Most heliostats in one least-squares problem of :func:`fit_lm`. scipy's solvers factor the dense Jacobian
#: [3 R + H P, H P], so a joint problem costs ~H^3 (synthetic, 30 records each, 2 threads: 16 / 32 / 64 / 128
#: / 256 heliostats took 1.0 / 4.4 / 10 / 81 / 474 s; in chunks 1.4 / 3.7 / 12 / 26 / 49 s with the same RMS
#: deviation error to 3 digits).
#: Every folder of ``../shared`` (<= 30 heliostats) fits in one chunk, so its figures are those of one problem.
LM_CHUNK = 32

#: Default solver of :func:`fit_lm`: ``"batched"`` (:mod:`.batched`, all heliostats at once, any device) or
#: ``"scipy"`` (MINPACK / trf per chunk of :data:`LM_CHUNK`; kept as the reference the batched solver is tested
#: against). Synthetic plant, 100 records each, the ``lm`` method end to end: see
#: ``benchmarks/bench_plant_calibration.py``.
SOLVER = "batched"


def fit_lm(nominal: Kinematics, batch: RecordTable, *, names=STONE8, prior_sigma: dict | None = None,
           prior_mean: torch.Tensor | None = None, noise: float = NOISE, max_nfev: int = 200,
           loss: str = "linear", f_scale: float = 2e-3,
           prior_sigma_vector: torch.Tensor | None = None,
           prior_whitening: torch.Tensor | None = None,
           half_life_days: float | None = None, process_noise: float = 0.0,
           drift_basis: str = "axes", solver: str | None = None,
           start: torch.Tensor | None = None) -> tuple[torch.Tensor, dict]:
    """Fit deviations of every heliostat in ``batch`` by Levenberg-Marquardt.

    Parameters
    ----------
    nominal : Kinematics
        H heliostats (the batch's heliostat axis).
    batch : RecordTable
        Training records (every heliostat with at least one record is fitted).
    names : sequence of str
        Parameters to fit (default the Stone/Jülich 8).
    prior_sigma : dict, optional
        Prior standard deviation per kind in physical units ([rad] for angles and tilts, [m] for lengths, [1]
        for relative increments; default :data:`~heliotwin.calibrate.priors.STONE8_SIGMA`); ``{}`` or
        ``None`` values mean no prior (plain least squares).
    prior_mean : torch.Tensor, [H, P], optional
        Prior centre (default zero = nominal).
    noise : float
        Measurement noise per record [rad] that the prior is weighed against.
    prior_whitening : torch.Tensor, [P, P] or [H, P, P], optional
        A full-covariance Gaussian prior (e.g. :class:`~heliotwin.calibrate.priors.PlantPrior`): ``W`` with
        ``W^T W`` = the prior's inverse covariance; the prior term is ``|W (delta - mean)|^2``. Replaces
        ``prior_sigma`` / ``prior_sigma_vector`` when given.
    half_life_days : float, optional
        Drift tracking: a record ``a`` days older than its heliostat's latest training record weighs
        ``0.5 ** (a / half_life_days)`` (records without a time weigh 1), so the fit follows where a slowly
        drifting offset is *now* rather than its average over the training period.
    process_noise : float
        Random-walk offset of the two axis offsets [rad^2/day] (:mod:`heliotwin.calibrate.drift`): the residuals are
        fitted in generalised least squares, whitened by their covariance under that walk (0 = the static fit).
        Excludes ``half_life_days``. ``drift_basis``: which deviations drift (:data:`heliotwin.calibrate.drift.BASES`).
    solver : str, optional
        ``"batched"`` (default, :data:`SOLVER`): every heliostat's problem at once in tensors
        (:func:`~heliotwin.calibrate.methods.batched.solve`; any device, cost linear in heliostats);
        ``"scipy"``: scipy's ``least_squares`` on :data:`LM_CHUNK` heliostats at a time (CPU). Same minimum.
    start : torch.Tensor, [H, P], optional
        Batched solver: where to start (physical units) when a near solution is known, e.g. the fit of the
        same heliostats on other records (default: the prior mean). The minimum does not depend on it.

    Returns
    -------
    delta : torch.Tensor, [H, P]
        Deviations (zero for heliostats without records).
    info : dict
        ``nfev``, ``status``, ``message`` of the run, ``cost`` and ``method``.
    """
    solver = SOLVER if solver is None else solver
    if solver == "batched":
        return _fit_batched(nominal, batch, names=names, prior_sigma=prior_sigma, prior_mean=prior_mean, noise=noise,
                            max_nfev=max_nfev, loss=loss, f_scale=f_scale, prior_sigma_vector=prior_sigma_vector,
                            prior_whitening=prior_whitening, half_life_days=half_life_days,
                            process_noise=process_noise, drift_basis=drift_basis, start=start)
    if solver != "scipy":
        raise ValueError(f"solver must be 'batched' or 'scipy', got {solver!r}")
    if nominal.position.device.type != "cpu":  # scipy's LM runs on the CPU: fit CPU copies, deviations back
        cpu = lambda t: None if t is None else t.detach().cpu()  # noqa: E731
        delta, info = fit_lm(to_device(nominal, "cpu"), to_device(batch, "cpu"), names=names, prior_sigma=prior_sigma,
                             prior_mean=cpu(prior_mean), noise=noise, max_nfev=max_nfev, loss=loss, f_scale=f_scale,
                             prior_sigma_vector=cpu(prior_sigma_vector), prior_whitening=cpu(prior_whitening),
                             half_life_days=half_life_days, process_noise=process_noise, drift_basis=drift_basis,
                             solver="scipy")
        return delta.to(nominal.position.device), info
    names = check_names(names)
    h, p = nominal.num_heliostats, len(names)
    scale = units(names)  # optimise in natural units (mrad, mm, 0.1 %) for a well-scaled problem
    sig_vec = _sigma_vector(names, prior_sigma, prior_sigma_vector)
    mean = torch.zeros(h, p, dtype=torch.float64) if prior_mean is None else prior_mean.detach().double()
    # Heliostats without records keep zero deviations; exclude their parameters from the problem.
    active = (torch.bincount(batch.heliostat_index, minlength=h) > 0).nonzero().flatten()
    na = len(active)
    if na == 0 or len(batch) == 0:
        return torch.zeros(h, p, dtype=torch.float64), {"nfev": 0, "status": 0, "message": "no records", "cost": 0.0}
    if na > LM_CHUNK:  # independent problems: one per chunk of heliostats (see LM_CHUNK)
        return _fit_in_chunks(active, lambda chunk: fit_lm(
            nominal, chunk, names=names, prior_sigma=prior_sigma, prior_mean=prior_mean, noise=noise,
            max_nfev=max_nfev, loss=loss, f_scale=f_scale, prior_sigma_vector=prior_sigma_vector,
            prior_whitening=prior_whitening, half_life_days=half_life_days, process_noise=process_noise,
            drift_basis=drift_basis, solver="scipy"), batch, h, p)
    prior_cols = (torch.isfinite(sig_vec) & (sig_vec > 0)).nonzero().flatten()
    if prior_whitening is not None:
        w = prior_whitening.detach().double()
        sig_vec = w.expand(h, p, p).clone()  # per-heliostat whitening replaces the diagonal prior
        prior_cols = torch.arange(p)

    def unpack(x):
        full = torch.zeros(h, p, dtype=torch.float64)
        full[active] = torch.as_tensor(x, dtype=torch.float64).reshape(na, p) * scale
        return full

    weights, whiten = _drift_model(nominal, batch, half_life_days, process_noise, noise, drift_basis)
    fun, jac = _cached(_stacked_problem(nominal, batch, names, unpack, active, scale, mean, sig_vec, prior_cols,
                                        noise, weights, whiten))
    x0 = (mean[active] / scale).reshape(-1).numpy()
    # MINPACK's LM needs at least as many residuals as unknowns; with the prior this always holds,
    # without it a heliostat needs >= P/3 records (checked by the caller, padded here for safety).
    method = "trf" if len(batch) * 3 + na * len(prior_cols) < na * p else "lm"
    if loss != "linear":
        method = "trf"  # MINPACK LM has no robust loss
    sol = least_squares(fun, x0, jac=jac, method=method, max_nfev=max_nfev, x_scale=1.0, xtol=1e-12, ftol=1e-12,
                        loss=loss, f_scale=f_scale, gtol=1e-12)
    delta = unpack(sol.x)
    return delta, {"nfev": int(sol.nfev), "status": int(sol.status), "message": str(sol.message),
                   "cost": float(sol.cost), "method": method}


def _fit_in_chunks(active: torch.Tensor, fit_chunk, batch: RecordTable, h: int, p: int) -> tuple[torch.Tensor, dict]:
    """:func:`fit_lm` of the heliostats ``active`` [na], :data:`LM_CHUNK` at a time: ``fit_chunk(records)`` fits
    the records of one chunk (the others have none, so they stay out of its problem). Returns the deviations
    [H, P] and the runs' summed ``nfev`` / ``cost``, worst ``status``, and ``chunks``."""
    delta = torch.zeros(h, p, dtype=torch.float64)
    infos = []
    for chunk in active.split(LM_CHUNK):
        member = torch.zeros(h, dtype=torch.bool, device=batch.heliostat_index.device)
        member[chunk] = True
        d, info = fit_chunk(batch.subset(member[batch.heliostat_index]))
        delta[chunk] = d[chunk]
        infos.append(info)
    return delta, {"nfev": sum(i["nfev"] for i in infos), "status": min(i["status"] for i in infos),
                   "message": "; ".join(dict.fromkeys(i["message"] for i in infos)),
                   "cost": sum(i["cost"] for i in infos), "method": "/".join(dict.fromkeys(i["method"] for i in infos)),
                   "chunks": len(infos)}


@dataclass(frozen=True)
class _Rows:
    """What the residuals of :func:`~heliotwin.calibrate.metrics.record_jacobian` read of a record table: motor
    steps [n, 2], sun [n, 3] and measured spot [n, 3] (a cheap row subset of a :class:`RecordTable`)."""

    motor_steps: torch.Tensor
    sun: torch.Tensor
    spot: torch.Tensor

    def rows(self, idx: torch.Tensor | None) -> "_Rows":
        return self if idx is None else _Rows(self.motor_steps[idx], self.sun[idx], self.spot[idx])


def _fit_batched(nominal: Kinematics, batch: RecordTable, *, names, prior_sigma, prior_mean, noise, max_nfev, loss,
                 f_scale, prior_sigma_vector, prior_whitening, half_life_days, process_noise,
                 drift_basis, start=None) -> tuple[torch.Tensor, dict]:
    """:func:`fit_lm` by the batched solver (:func:`.batched.solve`): the same MAP problem per heliostat (record
    residuals, optionally recency-weighted or whitened, and the prior's residuals, all under ``loss``) in
    natural units, on the device of ``nominal``."""
    names = check_names(names)
    dev = nominal.position.device
    f64 = dict(dtype=torch.float64, device=dev)
    h, p = nominal.num_heliostats, len(names)
    scale = units(names, device=dev)
    sig_vec = _sigma_vector(names, prior_sigma, prior_sigma_vector).to(dev)
    mean = torch.zeros(h, p, **f64) if prior_mean is None else prior_mean.detach().to(**f64)
    hidx = batch.heliostat_index.to(dev)
    counts = torch.bincount(hidx, minlength=h)
    active = (counts > 0).nonzero().flatten()
    na = len(active)
    if na == 0 or len(batch) == 0:
        return torch.zeros(h, p, **f64), {"nfev": 0, "status": 0, "message": "no records", "cost": 0.0,
                                          "method": "batched"}
    group = batched.shard_group()
    if group is not None:  # this rank's shard of the heliostats; the others' deviations arrive by all_reduce
        mine = active[batched.contiguous_shard(na, dist.get_rank(group), dist.get_world_size(group)).to(dev)]
        member = torch.zeros(h, dtype=torch.bool, device=dev)
        member[mine] = True
        with batched.sharded(None):
            delta, info = _fit_batched(nominal, batch.subset(member[hidx]), names=names, prior_sigma=prior_sigma,
                                       prior_mean=prior_mean, noise=noise, max_nfev=max_nfev, loss=loss,
                                       f_scale=f_scale, prior_sigma_vector=prior_sigma_vector,
                                       prior_whitening=prior_whitening, half_life_days=half_life_days,
                                       process_noise=process_noise, drift_basis=drift_basis, start=start)
        dist.all_reduce(delta, group=group)  # disjoint shards: a sum is a gather
        totals = torch.tensor([info.get("converged", 0), info["nfev"], info["cost"]], dtype=torch.float64,
                              device=dev)
        dist.all_reduce(totals, group=group)
        info = dict(info, cost=float(totals[2]), converged=int(totals[0]), status=int(int(totals[0]) == na),
                    message=f"{int(totals[0])} of {na} heliostats converged ({dist.get_world_size(group)} ranks)")
        return delta, info
    col_of = torch.full((h,), -1, dtype=torch.long, device=dev)
    col_of[active] = torch.arange(na, device=dev)
    centre = mean[active] / scale
    if prior_whitening is not None:  # full covariance: noise * W_h (delta_h - mean_h)
        w = prior_whitening.detach().to(**f64).expand(h, p, p)[active]
        prior_matrix = noise * w * scale
    else:
        cols = (torch.isfinite(sig_vec) & (sig_vec > 0)).nonzero().flatten()
        prior_matrix = torch.zeros(na, len(cols), p, **f64)
        if len(cols):
            prior_matrix[:, torch.arange(len(cols), device=dev), cols] = (noise / sig_vec[cols]) * scale[cols]
    weights, whiten = _drift_model(nominal, batch, half_life_days, process_noise, noise, drift_basis)
    sw = None if weights is None else weights.to(**f64).sqrt()
    kin_rec = nominal.index(hidx)
    table = _Rows(batch.motor_steps, batch.sun, batch.spot)

    def evaluate(x_rows, rows):
        kin = kin_rec if rows is None else kin_rec.index(rows)
        res, jac = record_jacobian(kin, table.rows(rows), x_rows * scale, names)
        if sw is not None:
            w_rows = sw if rows is None else sw[rows]
            res, jac = res * w_rows[:, None], jac * w_rows[:, None, None]
        if whiten is not None:
            res, jac = whiten(res), whiten(jac)
        return res, jac * scale

    x0 = centre.clone() if start is None else start.detach().to(**f64)[active] / scale
    x, info = batched.solve(evaluate, x0, col_of[hidx], prior_matrix, centre, loss=loss, f_scale=f_scale,
                            max_iterations=max_nfev, subset_records=whiten is None, near=start is not None)
    delta = torch.zeros(h, p, **f64)
    delta[active] = x * scale
    status = 1 if info["converged"] == na else 0
    return delta, {"nfev": int(info["iterations"]), "status": status, "converged": info["converged"],
                   "message": f"{info['converged']} of {na} heliostats converged", "cost": info["cost"],
                   "method": "batched", "evaluations": info["evaluations"]}


def _drift_model(nominal: Kinematics, batch: RecordTable, half_life_days, process_noise, noise, drift_basis):
    """The fit's drift model, one of two (both solvers use this): per-record recency ``weights`` [R] (a half-life
    [days]) or the random walk's ``whiten`` (:func:`heliotwin.calibrate.drift.whitener`, q [rad^2/day]); (None,
    None) for a static fit. Both at once is a :class:`ValueError`."""
    weights = recency_weights(batch, half_life_days) if half_life_days else None
    whiten = None
    if process_noise and process_noise > 0:
        if weights is not None:
            raise ValueError("half_life_days and process_noise are two drift models: give one")
        whiten = whitener(nominal, batch, process_noise, noise, basis=drift_basis)
    return weights, whiten


def _sigma_vector(names, prior_sigma: dict | None, prior_sigma_vector: torch.Tensor | None) -> torch.Tensor:
    """Prior sigma per parameter [P] (inf = no prior): the per-parameter vector if given, else per kind."""
    if prior_sigma_vector is not None:  # per-parameter sigma (e.g. a field prior), overrides the kinds
        return prior_sigma_vector.detach().double().clone()
    sig = priors.STONE8_SIGMA if prior_sigma is None else prior_sigma
    return torch.tensor([sig.get(k, float("inf")) if sig.get(k) is not None else float("inf") for k in kinds(names)],
                        dtype=torch.float64)


def recency_weights(batch: RecordTable, half_life_days: float) -> torch.Tensor:
    """Weight per record [R]: ``0.5 ** (age / half_life)``, age [days] behind the heliostat's latest record."""
    dev = batch.heliostat_index.device
    t = batch.time.double() if batch.time is not None else torch.full((len(batch),), float("nan"),
                                                                       dtype=torch.float64, device=dev)
    known = torch.isfinite(t)
    latest = torch.full((batch.num_heliostats,), -float("inf"), dtype=torch.float64, device=dev)
    latest = latest.scatter_reduce(0, batch.heliostat_index[known], t[known], reduce="amax")
    age = ((latest[batch.heliostat_index] - t) / 86400.0).clamp_min(0.0)
    return torch.where(known, 0.5 ** (age / float(half_life_days)), torch.ones_like(t))


def _stacked_problem(nominal, batch, names, unpack, active, scale, mean, sig_vec, prior_cols, noise, weights=None,
                     whiten=None):
    """``fun_and_jac(x) -> (residuals, Jacobian)`` (numpy) of the joint MAP problem of every active heliostat.

    MAP: |r|^2 / noise^2 + |delta / sigma|^2, written as residuals (r, noise * delta / sigma) so that the
    prior is weighed against the measurement noise (~1 mrad per record), not against 1 rad. ``x`` holds the
    active heliostats' parameters in natural units, [na * P].
    """
    h, p, na = len(mean), len(names), len(active)
    hidx = batch.heliostat_index
    kin_rec = nominal.index(hidx)
    r_rows = len(batch)
    rows_idx = torch.arange(r_rows)
    col_of = torch.full((h,), -1, dtype=torch.long)
    col_of[active] = torch.arange(na)
    inv_sig = (noise / sig_vec) * scale if sig_vec.dim() == 1 else None  # prior residual per natural unit

    def fun_and_jac(x):
        delta = unpack(x)
        res, jac = record_jacobian(kin_rec, batch, delta[hidx], names)
        if weights is not None:  # weighted least squares: sqrt(w) on each record's residual rows
            sw = weights.sqrt()
            res, jac = res * sw[:, None], jac * sw[:, None, None]
        if whiten is not None:  # generalised least squares under the random-walk offset (drift.py)
            res, jac = whiten(res), whiten(jac)
        # Jacobian w.r.t. natural units, scattered into the block of each record's heliostat.
        jac = jac * scale
        J = torch.zeros(r_rows, 3, na, p, dtype=torch.float64)
        J[rows_idx, :, col_of[hidx], :] = jac
        J = J.reshape(r_rows * 3, na * p)
        res = res.reshape(-1)
        if sig_vec.dim() == 3:  # full covariance: noise * W_h (delta_h - mean_h), block diagonal Jacobian
            w = sig_vec[active]  # [na, P, P]
            z = noise * torch.einsum("hij,hj->hi", w, delta[active] - mean[active])
            Jp = torch.zeros(na, p, na, p, dtype=torch.float64)
            ar = torch.arange(na)
            Jp[ar, :, ar, :] = noise * w * scale
            res = torch.cat([res, z.reshape(-1)])
            J = torch.cat([J, Jp.reshape(na * p, na * p)])
        elif len(prior_cols):
            z = noise * (delta[active] - mean[active]) / sig_vec  # [na, P]
            pr = z[:, prior_cols].reshape(-1)
            Jp = torch.zeros(na, len(prior_cols), na, p, dtype=torch.float64)
            ar = torch.arange(na)
            for j, col in enumerate(prior_cols.tolist()):
                Jp[ar, j, ar, col] = inv_sig[col]
            res = torch.cat([res, pr])
            J = torch.cat([J, Jp.reshape(na * len(prior_cols), na * p)])
        return res.numpy(), J.numpy()

    return fun_and_jac


def _cached(fun_and_jac):
    """``(fun, jac)`` for scipy from one function that computes both (each point evaluated once)."""
    cache = {}

    def get(x):
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = fun_and_jac(x)
        return cache[key]

    return (lambda x: get(x)[0]), (lambda x: get(x)[1])


#: Robust loss of the Stone/Jülich LM fits (scipy ``least_squares`` loss, scale [rad] per residual).
LM_LOSS, LM_F_SCALE = "soft_l1", 1e-3

#: Bootstrap bags averaged by ``lm`` (0 = one fit on all records). Validation on later records that no run
#: trains or tests on (between the chronological train and test blocks): median of the per-heliostat mean
#: error 1.80 -> 1.34 mrad at N=10 and 1.15 -> 1.14 at N=30 with 10 bags (subsampling 80 %: 1.36 / 1.13).
LM_BAGS = 10


def stone8_field_fit(nominal: Kinematics, batch: RecordTable, usable: torch.Tensor, *, field_prior: bool = True,
                     loss: str = LM_LOSS, f_scale: float = LM_F_SCALE, half_life_days: float | None = None,
                     process_noise: float = 0.0, drift_basis: str = "axes", starts: dict | None = None):
    """LM on the Stone/Jülich 8 with the field prior (nominal prior when the run is too small for one).

    The first (loose) pass is plain least squares; the final fit uses the robust ``loss`` (one bad centroid
    in 10-30 records otherwise tilts the whole fit: AC33's pseudo-validation error halves with it).
    ``starts`` (optional, a dict): where the two passes start (``"first"``, ``"final"`` [H, 8]) when it holds
    them, else it receives this fit's (the bootstrap bags start from the full-data fit: fewer iterations,
    the same minima).

    Returns
    -------
    delta : torch.Tensor, [H, 8]
    prior : (mean [8], sigma [8]) or None
    """
    given = dict(starts) if starts else {}
    first, _ = fit_lm(nominal, batch, names=STONE8, prior_sigma=priors.LOOSE_SIGMA, start=given.get("first"))
    fp = priors.field_prior(first, usable, STONE8) if field_prior else None
    # the final pass starts from the loose pass (near its minimum) unless a nearer start is given
    final_start = given.get("final", first)
    if fp is None:
        delta, _ = fit_lm(nominal, batch, names=STONE8, prior_sigma=priors.STONE8_SIGMA, loss=loss, f_scale=f_scale,
                          half_life_days=half_life_days, process_noise=process_noise, drift_basis=drift_basis,
                          start=final_start)
    else:
        delta, _ = fit_lm(nominal, batch, names=STONE8, prior_sigma=priors.LOOSE_SIGMA,
                          prior_mean=fp[0].expand_as(first).clone(), prior_sigma_vector=fp[1], loss=loss,
                          f_scale=f_scale, half_life_days=half_life_days, process_noise=process_noise,
                          drift_basis=drift_basis, start=final_start)
    if starts is not None and not given:
        starts.update(first=first, final=delta)
    return delta, fp


def stone8_plant_fit(nominal: Kinematics, batch: RecordTable, prior: priors.PlantPrior, *, loss: str = LM_LOSS,
                     f_scale: float = LM_F_SCALE, half_life_days: float | None = None,
                     process_noise: float = 0.0, drift_basis: str = "axes", starts: dict | None = None
                     ) -> torch.Tensor:
    """LM on the Stone/Jülich 8 with a plant prior (mean + covariance learned from other heliostats), [H, 8].

    One pass: the prior does not depend on the run's records, so there is no loose first pass to make.
    ``starts``: as in :func:`stone8_field_fit` (``"final"`` only).
    """
    dev = nominal.position.device
    mean = prior.mean.to(dtype=torch.float64, device=dev).expand(nominal.num_heliostats, len(STONE8)).clone()
    given = dict(starts) if starts else {}
    delta, _ = fit_lm(nominal, batch, names=STONE8, prior_mean=mean, prior_whitening=prior.whitening().to(dev),
                      loss=loss, f_scale=f_scale, half_life_days=half_life_days, process_noise=process_noise,
                      drift_basis=drift_basis, start=given.get("final"))
    if starts is not None and not given:
        starts.update(final=delta)
    return delta


def bagged(fit_one, batch: RecordTable, bags: int, seed: int, *, carry: dict | None = None):
    """Average of ``fit_one(resampled batch)`` [H, P] over bootstrap resamples of every heliostat's records.

    Returns (mean delta, the first return value's extras of the full-data fit). Under an active checkpoint
    (:mod:`heliotwin.io.checkpoint`) the state is saved after every fit (full data, then each bag) and a
    resumed run goes on after the last finished one. ``carry`` (a dict of tensors that ``fit_one`` fills
    on the full-data fit and the bags read, e.g. where their solves start) is saved and restored with that
    state, so a resumed bag starts where the uninterrupted one did.
    """
    g = torch.Generator().manual_seed(int(seed))
    dev = batch.heliostat_index.device
    st: dict = {}
    carry = {} if carry is None else carry

    def dump():
        return {"full": st["full"].clone(), "extra": st["extra"], "acc": st["acc"].clone(), "gen": g.get_state(),
                "carry": {k: v.detach().clone() for k, v in carry.items()}}

    def load(saved):
        g.set_state(saved["gen"])
        st.update(full=saved["full"].to(dev), acc=saved["acc"].to(dev), extra=_to(saved["extra"], dev))
        carry.update({k: v.to(dev) for k, v in saved.get("carry", {}).items()})

    total = 1 if bags <= 0 or len(batch) == 0 else bags + 1
    # every heliostat's rows in ascending order (one stable sort, not one search of the table per heliostat)
    order = torch.sort(batch.heliostat_index, stable=True).indices
    per_heliostat = [rows for rows in order.split(batch.counts().tolist()) if len(rows)]
    for i in resumable_range("bags", total, dump, load):
        if i == 0:
            st["full"], st["extra"] = fit_one(batch)
            st["acc"] = torch.zeros_like(st["full"])
            continue
        # one draw per heliostat from the same generator, in heliostat order (the bags of earlier versions)
        idx = [rows[torch.randint(len(rows), (len(rows),), generator=g).to(rows.device)] for rows in per_heliostat]
        d, _ = fit_one(batch.subset(torch.cat(idx)))
        st["acc"] += d
    if total == 1:
        return st["full"], st["extra"]
    return st["acc"] / bags, st["extra"]


def _to(obj, device):
    """A field prior (tuple of tensors) or None on ``device``."""
    return None if obj is None else tuple(t.to(device) for t in obj)


def field_prior_extras(fp) -> dict | None:
    """The field prior (mean, sigma) [P] as JSON-ready lists (None without one)."""
    return None if fp is None else {"mean": fp[0].tolist(), "sigma": fp[1].tolist()}


def _prior_precision(plant_prior, fp) -> torch.Tensor:
    """Prior precision [P, P] of the final lm fit (plant prior, field prior or the nominal Stone/Jülich prior)."""
    if plant_prior is not None:
        w = plant_prior.whitening()
        return w.T @ w
    sigma = fp[1] if fp is not None else priors.sigma_vector(STONE8, priors.STONE8_SIGMA)
    return torch.diag(1.0 / sigma.double() ** 2)


def laplace(nominal: Kinematics, batch: RecordTable, delta: torch.Tensor, prior_precision: torch.Tensor,
            drift: float = 0.0) -> dict:
    """Laplace posterior of the Stone/Jülich 8 around ``delta`` [H, 8] on the fit's records
    (:mod:`heliotwin.calibrate.uncertainty`).

    Returns ``{"covariance": [H, 8, 8], "noise_rad": [H], "drift_rad": float}``.
    """
    h = nominal.num_heliostats
    hidx = batch.heliostat_index
    if len(batch) == 0:
        eye = torch.eye(len(STONE8), dtype=torch.float64, device=delta.device)
        return {"covariance": eye.expand(h, -1, -1).clone(),
                "noise_rad": torch.ones(h, dtype=torch.float64, device=delta.device),
                "drift_rad": float(drift)}
    res, jac = record_jacobian(nominal.index(hidx), batch, delta.detach()[hidx], STONE8)
    cov, noise = posterior(res, jac, hidx, prior_precision, h, len(STONE8))
    return {"covariance": cov, "noise_rad": noise, "drift_rad": float(drift)}


def walk_record_noise(nominal: Kinematics, batch: RecordTable, delta: torch.Tensor, q: float,
                      drift_basis: str = "axes") -> torch.Tensor:
    """The record noise per component [H] [rad] of the random-walk model at the static fit ``delta`` [H, 8]:
    the residuals whitened by the walk's covariance (:func:`~heliotwin.calibrate.drift.whitener` at ``q``
    [rad^2/day] and :data:`~heliotwin.calibrate.inputs.NOISE`) over the fit's degrees of freedom, the
    maximum-likelihood scale of the model given its ratio ``q / noise^2`` (the prediction-error decomposition,
    Durbin & Koopman ch. 7): the record noise an update's filter needs. The static residuals' noise
    (:func:`laplace`) counts the offset's wandering and every earlier step as noise (2-3x the records' own on a
    simulated plant): what a predictive interval at a new sun must cover, but as a filter's record noise it
    normalised an update's innovations ~6x too wide and hid 1-2 mrad steps from the alarm."""
    hidx = batch.heliostat_index
    res, _ = record_jacobian(nominal.index(hidx), batch, delta.detach()[hidx], STONE8)
    white = whitener(nominal, batch, q, NOISE, basis=drift_basis)
    return residual_variance(white(res), hidx, nominal.num_heliostats, len(STONE8)).sqrt()


def walk_noise(noise: torch.Tensor, ok: torch.Tensor) -> float:
    """The plant's noise per component [rad] of the random-walk model: the median of the heliostats' ``noise``
    [H] (:func:`walk_record_noise`) over the fitted ones ``ok`` [H] (a few heliostats with a step the walk
    cannot follow must not set it); :data:`~heliotwin.calibrate.inputs.NOISE` without any."""
    vals = noise[ok] if bool(ok.any()) else noise.new_zeros(0)
    return float(vals.median()) if len(vals) else NOISE


@dataclass(frozen=True)
class LMSettings:
    """Settings of the ``lm`` method (:func:`fit_lm_method`; each field is also one of its keywords).

    Attributes
    ----------
    field_prior : bool
        Without a plant prior: the field prior of the run's own training records (two-pass fit,
        :func:`stone8_field_fit`); False: the nominal Stone/Jülich prior.
    fit_focal_spot : str or None
        Centroids the fit trains on (:func:`~heliotwin.calibrate.inputs.fit_spots`; None: the records' own).
    loss, f_scale :
        The robust loss of scipy's ``least_squares`` and its scale [rad] per residual.
    bags : int
        Bootstrap bags averaged (0: one fit on all records).
    drift : float
        Predictive interval: offset drift per component [rad] added to the Laplace posterior's noise.
    walk_scale : float
        Predictive interval: scale of the random-walk offset's covariance (``drift_model="kalman"``).
    half_life_days : float or None
        Drift tracking by recency weights [days] (:func:`fit_lm`).
    drift_model : str
        ``"none"`` (static rigid body) or ``"kalman"`` (rigid body + a random-walk offset).
    process_noise : float or str
        The walk's process noise [mrad^2/day] per component, or ``"auto"`` (:func:`choose_process_noise`).
    drift_basis : str
        Which deviations drift (:data:`heliotwin.calibrate.drift.BASES`).
    """

    field_prior: bool = True
    fit_focal_spot: str | None = FIT_FOCAL_SPOT
    loss: str = LM_LOSS
    f_scale: float = LM_F_SCALE
    bags: int = LM_BAGS
    drift: float = 0.0
    walk_scale: float = 1.0
    half_life_days: float | None = None
    drift_model: str = "none"
    process_noise: float | str = 0.0
    drift_basis: str = "axes"


def fit_lm_method(nominal: Kinematics, train: RecordTable, validation: RecordTable | None, *, seed: int = 0,
                  progress: bool = False, plant_prior: priors.PlantPrior | None = None,
                  settings: LMSettings | None = None, **options) -> Calibrated:
    """``lm``: the Stone/Jülich 8 by Levenberg-Marquardt on every record it may see (train + validation).

    LM has no iteration count to stop early, so the validation records are used for fitting too (they
    still count towards ``--train``; their error is reported as validation error = in-sample). Fitted on
    :data:`~heliotwin.calibrate.inputs.FIT_FOCAL_SPOT` centroids with the robust :data:`LM_LOSS`, averaged
    over :data:`LM_BAGS` bootstrap resamples (bagging: with 10 records one outlier or one unlucky sun
    position otherwise decides the extrapolation).

    Parameters
    ----------
    nominal : Kinematics
        The run's H heliostats.
    train, validation : RecordTable
        Records over the same heliostat axis (validation may be None or empty).
    seed : int
        Seed of the bootstrap bags.
    progress : bool
        Unused (LM shows no loop); the methods' common signature.
    plant_prior : PlantPrior, optional
        Learned from *other* heliostats (:class:`~heliotwin.calibrate.priors.PlantPrior`, see
        :mod:`heliotwin.calibrate.protocol.archive`): replaces the field prior of the run's own records.
    settings : LMSettings, optional
        Default: :class:`LMSettings`'s defaults.
    **options
        Any field of :class:`LMSettings` by keyword, replacing ``settings``'s (e.g. ``bags=0``).

    Returns
    -------
    Calibrated
        ``delta`` [H, 8] over :data:`~heliotwin.calibrate.params.STONE8`; ``extras["posterior"]``: the
        Laplace posterior of every heliostat's deviations around the fit (:mod:`heliotwin.calibrate.uncertainty`;
        covariance [H, 8, 8], noise [H] [rad], the interval's ``drift`` [rad] and ``walk_scale``).

    Notes
    -----
    ``drift_model="kalman"``: the rigid body + a random-walk offset of the two axis offsets with
    ``process_noise`` [mrad^2/day] (:mod:`heliotwin.calibrate.drift`; ``"auto"``: chosen by chronological
    validation inside the training records, :func:`choose_process_noise`). The static part is fitted in
    generalised least squares, the offset smoothed over the training records; the returned ``delta`` is the
    static part + the offset at the latest training time (what aims the heliostat *now*),
    ``extras["drift_state"]`` holds that offset, its covariance, time and ``q``. ``walk_scale`` scales the
    walk's covariance in the predictive interval (chosen with ``drift`` by cross-validated coverage: a real
    offset does not wander without bound as a random walk would over the months of a chrono test block).
    """
    s = replace(settings or LMSettings(), **options)
    if s.drift_model not in ("none", "kalman"):
        raise ValueError(f"drift_model must be 'none' or 'kalman', got {s.drift_model!r}")
    seen = RecordTable.concatenate([train, validation]) if validation is not None and len(validation) else train
    ok = trainable(seen)
    fit_on = fit_spots(seen.subset(ok[seen.heliostat_index]), s.fit_focal_spot)
    process_noise, q_choice = s.process_noise, None
    if s.drift_model == "kalman" and process_noise == "auto":
        process_noise, q_choice = choose_process_noise(nominal, fit_on, ok, s, plant_prior=plant_prior)
    q = 1e-6 * float(process_noise) if s.drift_model == "kalman" else 0.0  # mrad^2/day -> rad^2/day
    delta, fp = _static_fit(nominal, fit_on, ok, s, plant_prior=plant_prior, q=q, seed=seed)
    post = laplace(nominal, fit_on, delta, _prior_precision(plant_prior, fp), s.drift)
    extras = {"field_prior": field_prior_extras(fp), "posterior": dict(post, walk_scale=float(s.walk_scale)),
              "summary": {"bags": s.bags, "fit_focal_spot": s.fit_focal_spot, "loss": s.loss,
                          "half_life_days": s.half_life_days, "drift_model": s.drift_model,
                          "prior": "plant" if plant_prior is not None else ("field" if fp is not None else "nominal")}}
    if s.drift_model == "kalman":
        state = smooth(nominal, fit_on, delta, q, NOISE, basis=s.drift_basis)
        # what an update's filter needs on top: the walk's own record noise per heliostat (the whitened residuals'
        # scale), and the factor that turns the offset's covariance and q from the 1 mrad the fit assumed into
        # the records' units (the same smoothing: q / noise^2 kept). The predictive interval keeps the static
        # residuals' noise: it must cover what the model misses at a new sun and time, which the walk absorbs
        # in-sample (with the walk's noise in the interval too, a --split chrono --drift kalman run on the
        # shared heliostats covered 0.66 of its test records instead of 0.89).
        state["record_noise"] = walk_record_noise(nominal, fit_on, delta, q, s.drift_basis)
        state["filter_scale"] = (walk_noise(state["record_noise"], ok) / NOISE) ** 2
        state["offset"][~ok] = 0.0
        state.pop("smoothed")
        state["static_deviations"] = delta
        extras["drift_state"] = state
        extras["summary"]["process_noise_mrad2_per_day"] = float(process_noise)
        if q_choice is not None:
            extras["summary"]["process_noise_choice"] = q_choice
        extras["summary"]["drift_basis"] = s.drift_basis
        delta = with_offset(delta, state["offset"], s.drift_basis)
    if plant_prior is not None:
        extras["plant_prior"] = plant_prior
        extras["summary"]["prior_heliostats"] = list(plant_prior.heliostats)
        extras["summary"]["prior_settings"] = dict(plant_prior.settings)
    return Calibrated("lm", list(train.heliostat_ids), nominal, STONE8, delta, ok, extras=extras)


def _static_fit(nominal, fit_on, ok, s: LMSettings, *, plant_prior, q: float, seed: int):
    """Bagged static (or GLS under a random-walk offset with ``q`` [rad^2/day]) fit of ``s``, [H, 8] and field
    prior."""
    fit = dict(loss=s.loss, f_scale=s.f_scale, half_life_days=s.half_life_days, process_noise=q,
               drift_basis=s.drift_basis)
    starts: dict = {}  # the full-data fit's solutions: where the bags' fits start (same minima, fewer steps)
    if plant_prior is not None:
        delta, fp = bagged(lambda b: (stone8_plant_fit(nominal, b, plant_prior, starts=starts, **fit), None), fit_on,
                           s.bags, seed, carry=starts)
    else:
        delta, fp = bagged(lambda b: stone8_field_fit(nominal, b, ok, field_prior=s.field_prior, starts=starts,
                                                      **fit), fit_on, s.bags, seed, carry=starts)
    delta[~ok] = 0.0
    return delta, fp


def choose_process_noise(nominal, fit_on: RecordTable, ok, settings: LMSettings | None = None, *, plant_prior=None,
                         grid=None) -> tuple[float, dict]:
    """``process_noise="auto"``: the q [mrad^2/day] of :data:`~heliotwin.calibrate.drift.Q_GRID` whose fit on
    each heliostat's earlier training records best predicts its latest quarter (median over heliostats of
    the mean error; ties: the smaller q). Validation stays inside the records the method may see. The fits
    are ``settings``'s (prior, loss, drift basis), unbagged and without recency weights.

    Returns (q, {q: median validation error [mrad]}).
    """
    s = replace(settings or LMSettings(), bags=0, half_life_days=None)
    grid = Q_GRID if grid is None else grid
    fit_rows, val_rows = split_for_choice(fit_on)
    early, late = fit_on.subset(fit_rows), fit_on.subset(val_rows)
    if len(late) == 0:
        return 0.0, {}
    scores = {}
    for qm in grid:
        q = 1e-6 * float(qm)
        d, _ = _static_fit(nominal, early, ok, s, plant_prior=plant_prior, q=q, seed=0)
        if q > 0:
            d = with_offset(d, smooth(nominal, early, d, q, NOISE, basis=s.drift_basis)["offset"], s.drift_basis)
        err = metrics.pointing_error(apply_deviations(nominal, d, STONE8), late)
        per_h = metrics.per_heliostat_mean(err.detach(), late.heliostat_index, late.num_heliostats)
        scores[float(qm)] = float(1e3 * per_h[torch.isfinite(per_h)].median())
    best = min(grid, key=lambda x: (scores[float(x)], x))
    return float(best), scores
