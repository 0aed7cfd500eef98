"""A twin that stays current: new calibration records assimilated as a posterior update, not a refit.

The state of a calibrated heliostat is its Gaussian posterior over the Stone/Jülich deviations *now*,
``x ~ N(m, P)`` (``m`` [P], ``P`` [P, P]; rad, relative for increments): the Laplace posterior of the last
fit (:mod:`heliotwin.calibrate.uncertainty`) plus, with the drift model, the random-walk offset's covariance
(:mod:`heliotwin.calibrate.drift`). Between records the drifting deviations (the axis offsets) walk:

    P <- P + q dt E E^T,     dt [days] since the state's time, q [rad^2/day], E the drifting columns,

and a record is one (iterated) extended Kalman update (Sarkka, *Bayesian Filtering and Smoothing*, ch. 5 and
7; Bell & Cathey 1993 for the iterated form). The record's residual ``r(x) = n_model(x) - n_measured`` [3]
lies in the mirror's tangent plane; projected on an orthonormal tangent basis ``T`` [2, 3] of the model
normal it is a 2-d measurement

    z = -T r(m) = H (x - m) + e,     H = T dr/dx [2, P],   e ~ N(0, s^2 I_2),

with ``s`` the heliostat's residual noise per component. Innovation covariance ``S = H P H^T + s^2 I``, gain
``K = P H^T S^-1``, ``m <- m + K z``, ``P <- (I - K H) P (I - K H)^T + s^2 K K^T`` (Joseph form: stays
symmetric positive definite over thousands of updates). For a linear model, assimilating records one by one
gives exactly the batch least-squares posterior of all of them (tested).

Step alarms. Under the model the normalised innovation ``d^2 = z^T S^-1 z`` is chi-square with 2 degrees of
freedom; a record whose ``d^2`` exceeds :func:`alarm_threshold` raises an alarm for its heliostat, and the
state is *re-opened*: the drifting columns' variance grows by ``max(reopen^2, |z|^2)``. The alarming record
itself is not assimilated (one record cannot tell a step from an outlier of its centroid); the next records,
weighed against the open offset, move it to where it now is if the jump is real and leave it where it was if
not, so a jump is followed from the record after the alarm on instead of being averaged away over months.
The threshold comes from a target false-alarm rate per record and the normalised leave-one-out residuals of
records the calibration saw (:func:`leave_one_out_d2`): real residuals have heavier tails than the Gaussian,
and the threshold scales the chi-square quantile by how much wider their bulk is (never narrower).

A step smaller than the record noise shows in several records before one of them is far enough out: the
step tests of a record are the generalised likelihood ratios (Willsky & Jones 1976) of one constant jump ``b``
of the drifting columns over the latest k = 1..``window`` records, ``g^T F^-1 g`` with ``g = sum H_b^T S^-1
z`` and ``F = sum H_b^T S^-1 H_b`` (``H_b``: the drifting columns of ``H``); k = 1 is ``d^2``, each is
chi-square (2 dof) under the model, so the threshold is the quantile of the rate divided by the number of
tests. A jump that several records show is real: the offset is re-opened by ``max(reopen^2, |F^-1 g|^2)`` and
the record assimilated at full weight.

Open alarms. An alarm stays *open* (:class:`FilterState`'s ``alarms``) until the heliostat's next
:data:`CONFIRM_RECORDS` records settle it: their step test against the **pre-alarm** state (the mean and
covariance the alarming record was predicted with, the walk grown to each record; the same generalised
likelihood ratio ``g^T F^-1 g`` of one constant jump of the drifting columns, summed over those records only,
not the alarming ones) is chi-square (2 dof) if nothing happened. Above ``confirm_threshold`` (the
:data:`CONFIRM_LEVEL` quantile scaled by the threshold's ``kappa``) the step is *confirmed*, and the state the
filter has re-fitted on those records (against the re-opened offset) is the one applied; at or below it the
alarm is *cleared* ("not confirmed by 3 records": a one-off outlier, after which the filter is back where it
was). A new alarm of a heliostat with one open closes the old one as *superseded*. The detection itself is
unchanged: open alarms are bookkeeping over the filter, which runs as before.

Moderate outliers (``d^2`` above the chi-square's 95 % quantile, below the alarm) are down-weighted as a
Huber M-estimate does (their noise is inflated until ``d^2`` equals that quantile), as the batch fit's robust
loss does.

Every function works on all heliostats at once: the records of an update are processed in *rounds* (round k
= every heliostat's k-th new record, in time order), each round one batched linearisation and one batched
update over the heliostats; there is no loop over heliostats.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from ..field.plant import Kinematics
from ..io.records import RecordTable
from .drift import padded_index
from .metrics import model_normals, pointing_error_of_normals, record_jacobian
from .params import apply_deviations

_DAY = 86400.0

#: chi-square (2 dof) quantile above which a record is down-weighted (Huber): 95 %.
HUBER_D2 = -2.0 * math.log(0.05)

#: False-alarm rate per clean record of the step alarm when a plant's record rate is unknown.
FALSE_ALARM_RATE = 1e-3

#: False step alarms per heliostat-year the default threshold spends (:func:`false_alarm_rate_for`): an operator
#: budget is per heliostat and year, not per record -- a plant that calibrates daily would get 10x the alarms of
#: one that calibrates every ten days at the same per-record rate. Half of the 0.1 an operator accepts (issue
#: "A plant's day"), since real residuals' tails are heavier than the model's.
FALSE_ALARMS_PER_HELIOSTAT_YEAR = 0.05

#: Range of the per-record rate derived from that budget [1].
FALSE_ALARM_RATE_RANGE = (1e-4, 1e-2)

#: Smallest re-opening of the drifting columns at an alarm [rad] (per column, standard deviation).
REOPEN = 2e-3

#: Records of the step tests' longest window (:func:`assimilate`).
WINDOW = 3

#: Records after an alarm that settle it (:func:`assimilate`, module docstring: confirmed or cleared). Three: a step
#: detected on one record shows in the next three at about three times its alarm statistic, one detected over the
#: longest window (:data:`WINDOW`) at about its own, both far above :data:`CONFIRM_LEVEL`'s quantile; a one-off
#: outlier leaves three clean records, confirmed with probability :data:`CONFIRM_LEVEL` only
#: (tests/test_open_alarms.py measures both on the simulator's steps and on injected outliers).
CONFIRM_RECORDS = 3

#: Share of clean post-alarm windows that would (wrongly) confirm a step; its chi-square (2 dof) quantile times
#: the threshold's ``kappa`` is the confirmation threshold.
CONFIRM_LEVEL = 0.01

#: Outcomes of a closed alarm (``closed["outcome"]`` of :func:`assimilate`'s history).
ALARM_OUTCOMES = {1: "step confirmed, applied", 2: "not confirmed by {n} records", 3: "superseded by a later alarm"}


def confirm_threshold(kappa: float = 1.0, level: float = CONFIRM_LEVEL) -> float:
    """The statistic [1] above which the records after an alarm confirm its step: the chi-square (2 dof)
    quantile of ``1 - level``, scaled by the alarm threshold's ``kappa`` (real residuals' wider bulk)."""
    return max(1.0, float(kappa)) * -2.0 * math.log(float(level))


#: q [mrad^2/day] tried by :func:`choose_process_noise`: 0.001 to 0.1, log-spaced (7 values, a third of a decade
#: apart). 0.01 mrad^2/day is a 1 mrad standard deviation per component after 100 days.
PROCESS_NOISE_GRID = tuple(float(f"{10 ** (-3 + k / 3):.3g}") for k in range(7))

#: Relative margin of validation error within which :func:`choose_process_noise` counts q values as tied and
#: takes the largest (a walk too fast costs a little noise; one too slow absorbs steps and drift late).
PROCESS_NOISE_TIE = 0.005

#: Share of each heliostat's timed records (the latest) that :func:`choose_process_noise` validates on.
VALIDATION_SHARE = 0.25

#: Floor of the in-sample residual covariance (share of s^2) in :func:`leave_one_out_d2` (high leverage).
_LEVERAGE_FLOOR = 0.05


@dataclass
class FilterState:
    """The Gaussian state of H heliostats.

    Attributes
    ----------
    mean : torch.Tensor, [H, P]
        Deviations now (rad, m; relative for increments), ordered as ``names``.
    covariance : torch.Tensor, [H, P, P]
    time : torch.Tensor, [H]
        POSIX s of the state (NaN: unknown; the first record then adds no process noise).
    noise : torch.Tensor, [H]
        Residual noise per component of a record [rad].
    process_noise : float
        ``q`` [rad^2/day] of the drifting columns' random walk.
    drift_columns : tuple of int
        Columns of ``mean`` that walk (e.g. the two axis offsets).
    names : tuple of str
        The deviations' names (:mod:`heliotwin.calibrate.params`).
    window_g, window_f : torch.Tensor, [H, W - 1, B] and [H, W - 1, B, B], optional
        The step test's evidence of each heliostat's latest ``W - 1`` records (oldest first; B drifting
        columns): ``H_b^T S^-1 z`` and ``H_b^T S^-1 H_b`` (:func:`assimilate`); None: none yet.
    alarms : dict of tensors, optional
        The open alarms, one slot per heliostat (:func:`no_open_alarms`'s fields: ``open`` [H] bool,
        ``record_id`` [H], ``time`` [H] POSIX s when opened, ``statistic`` [H], ``window`` [H], the pre-alarm
        ``mean`` [H, P] and ``covariance`` [H, P, P], the settling evidence ``g`` [H, B], ``f`` [H, B, B] and
        ``records`` [H]); None: none open.
    """

    mean: torch.Tensor
    covariance: torch.Tensor
    time: torch.Tensor
    noise: torch.Tensor
    process_noise: float
    drift_columns: tuple
    names: tuple
    window_g: torch.Tensor | None = None
    window_f: torch.Tensor | None = None
    alarms: dict | None = None

    def drift_embedding(self) -> torch.Tensor:
        """``E E^T`` [P, P]: 1 on the diagonal of the drifting columns."""
        p = self.mean.shape[-1]
        e = torch.zeros(p, p, dtype=self.mean.dtype, device=self.mean.device)
        cols = torch.as_tensor(list(self.drift_columns), dtype=torch.long, device=self.mean.device)
        e[cols, cols] = 1.0
        return e


def no_open_alarms(h: int, p: int, b: int, device=None) -> dict:
    """The open-alarm slots of ``h`` heliostats with none open (``p`` deviations, ``b`` drifting columns)."""
    f64 = dict(dtype=torch.float64, device=device)
    return {"open": torch.zeros(h, dtype=torch.bool, device=device),
            "record_id": torch.full((h,), -1, dtype=torch.long, device=device),
            "time": torch.full((h,), float("nan"), **f64), "statistic": torch.zeros(h, **f64),
            "window": torch.zeros(h, dtype=torch.long, device=device), "mean": torch.zeros(h, p, **f64),
            "covariance": torch.zeros(h, p, p, **f64), "g": torch.zeros(h, b, **f64), "f": torch.zeros(h, b, b, **f64),
            "records": torch.zeros(h, dtype=torch.long, device=device)}


def tangent_basis(normal: torch.Tensor) -> torch.Tensor:
    """Orthonormal basis of the plane normal to each unit vector, [R, 2, 3] (``normal`` [R, 3], ENU).

    The first vector is horizontal (east-north plane) unless the normal is near vertical; continuous and
    well conditioned for every normal a heliostat takes."""
    n = normal / normal.norm(dim=-1, keepdim=True)
    up = torch.zeros_like(n)
    up[:, 2] = 1.0
    east = torch.zeros_like(n)
    east[:, 0] = 1.0
    ref = torch.where((n[:, 2].abs() > 0.9)[:, None], east, up)
    a = torch.linalg.cross(ref, n)
    a = a / a.norm(dim=-1, keepdim=True)
    b = torch.linalg.cross(n, a)
    return torch.stack([a, b], 1)


def linearise(nominal: Kinematics, records: RecordTable, mean: torch.Tensor, names) -> tuple:
    """Tangent-plane measurement of R records at deviations ``mean`` [R, P] (each record's heliostat's).

    Parameters
    ----------
    nominal : Kinematics
        R entries, one per record.
    records : RecordTable
        R records (the fit's centroids).

    Returns
    -------
    z : torch.Tensor, [R, 2]
        ``-T r``: measured minus model normal in the tangent plane [rad].
    h : torch.Tensor, [R, 2, P]
        ``T dr/dx``.
    normal, concentrator : torch.Tensor, [R, 3]
        The model mirror normal and concentrator at ``mean`` (ENU; m).
    """
    res, jac = record_jacobian(nominal, records, mean, names)
    with torch.no_grad():
        normal, conc = model_normals(apply_deviations(nominal, mean, names), records, per_record=True)
    t = tangent_basis(normal.double())
    z = -torch.einsum("rkc,rc->rk", t, res.double())
    h = torch.einsum("rkc,rcp->rkp", t, jac.double())
    return z, h, normal, conc


def kalman_update(mean: torch.Tensor, cov: torch.Tensor, z: torch.Tensor, h: torch.Tensor,
                  noise_var: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One linear Kalman update of B states at once.

    Parameters
    ----------
    mean : torch.Tensor, [B, P]
    cov : torch.Tensor, [B, P, P]
    z : torch.Tensor, [B, M]
        Innovation (measurement minus prediction at ``mean``).
    h : torch.Tensor, [B, M, P]
        Measurement matrix.
    noise_var : torch.Tensor, [B]
        Measurement noise variance per component (``R = noise_var I_M``).

    Returns
    -------
    mean, cov : the posterior ([B, P], [B, P, P], Joseph form);
    d2 : torch.Tensor, [B]
        Normalised innovation ``z^T S^-1 z`` (at the prior).
    """
    m = z.shape[-1]
    eye_m = torch.eye(m, dtype=cov.dtype, device=cov.device)
    eye_p = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    ph = cov @ h.transpose(1, 2)  # [B, P, M]
    s = h @ ph + noise_var[:, None, None] * eye_m
    chol = torch.linalg.cholesky(s)
    gain = torch.cholesky_solve(ph.transpose(1, 2), chol).transpose(1, 2)  # P H^T S^-1, [B, P, M]
    d2 = (z[:, None, :] @ torch.cholesky_solve(z[:, :, None], chol))[:, 0, 0]
    a = eye_p - gain @ h
    new_cov = a @ cov @ a.transpose(1, 2) + noise_var[:, None, None] * gain @ gain.transpose(1, 2)
    new_cov = 0.5 * (new_cov + new_cov.transpose(1, 2))
    return mean + (gain @ z[:, :, None])[..., 0], new_cov, d2


def false_alarm_rate_for(records_per_heliostat_year: float,
                         budget: float = FALSE_ALARMS_PER_HELIOSTAT_YEAR) -> float:
    """The per-record false-alarm rate [1] that spends ``budget`` false alarms per heliostat-year at a plant's
    record rate (``records_per_heliostat_year`` [1/year]), within :data:`FALSE_ALARM_RATE_RANGE`;
    :data:`FALSE_ALARM_RATE` when the record rate is unknown (NaN, not positive)."""
    r = float(records_per_heliostat_year)
    if not math.isfinite(r) or r <= 0.0:
        return FALSE_ALARM_RATE
    lo, hi = FALSE_ALARM_RATE_RANGE
    return min(max(float(budget) / r, lo), hi)


def alarm_threshold(false_alarm_rate: float = FALSE_ALARM_RATE, validation_d2: torch.Tensor | None = None,
                    tests: int = 1) -> dict:
    """The statistic above which a record raises a step alarm.

    The chi-square (2 dof) quantile of ``1 - false_alarm_rate / tests`` (``-2 ln(rate / tests)``: each record
    is judged by ``tests`` step tests, :func:`assimilate`'s windows, each chi-square under the model), scaled by
    how much wider the bulk of normalised residuals on validation records is than the chi-square's: ``kappa`` =
    their 90 %
    quantile over the chi-square's (``-2 ln 0.1``), at least 1. Without validation values ``kappa`` = 1.

    Parameters
    ----------
    false_alarm_rate : float
        Target share of clean records that raise an alarm, in (0, 1).
    validation_d2 : torch.Tensor, [N], optional
        Normalised residuals of records no update will judge (:func:`leave_one_out_d2`).

    Returns
    -------
    dict
        ``threshold`` (d^2), ``kappa``, ``false_alarm_rate``, ``validation_records``.
    """
    if not (0.0 < float(false_alarm_rate) < 1.0):
        raise ValueError(f"false_alarm_rate must be in (0, 1), got {false_alarm_rate}")
    kappa, n = 1.0, 0
    if validation_d2 is not None:
        v = validation_d2.detach().double().reshape(-1)
        v = v[torch.isfinite(v)]
        n = int(v.numel())
        if n >= 10:
            kappa = max(1.0, float(torch.quantile(v, 0.9)) / (-2.0 * math.log(0.1)))
    return {"threshold": kappa * -2.0 * math.log(float(false_alarm_rate) / max(1, int(tests))), "kappa": kappa,
            "false_alarm_rate": float(false_alarm_rate), "tests": max(1, int(tests)), "validation_records": n}


def leave_one_out_d2(nominal: Kinematics, records: RecordTable, state: FilterState,
                     mean_per_record: torch.Tensor | None = None) -> torch.Tensor:
    """Normalised leave-one-out residuals ``d^2`` [R] of records a calibration saw, under its posterior.

    For record i of heliostat h with tangent residual ``z_i`` and ``H_i``, the in-sample residual has
    covariance ``s^2 I - H_i P H_i^T`` (floored at 5 % of ``s^2`` for high leverage); ``z_i^T C_i^-1 z_i`` is
    the record's normalised error as predicted by a fit without it (Cook & Weisberg 1982).

    Parameters
    ----------
    nominal : Kinematics
        The state's H heliostats.
    records : RecordTable
        R records on the same heliostat axis.
    mean_per_record : torch.Tensor, [R, P], optional
        The deviations each record is judged at (default: its heliostat's ``state.mean``): under a drift model,
        the static part plus the offset smoothed at the record's time, so that a record taken before the offset
        moved is not judged against where it is now.
    """
    if len(records) == 0:
        return torch.zeros(0, dtype=torch.float64)
    hidx = records.heliostat_index
    mean = state.mean[hidx] if mean_per_record is None else mean_per_record.to(state.mean)
    z, h, _, _ = linearise(nominal.index(hidx), records, mean, state.names)
    s2 = state.noise.double()[hidx] ** 2
    eye = torch.eye(2, dtype=torch.float64, device=z.device)
    c = s2[:, None, None] * eye - h @ state.covariance[hidx] @ h.transpose(1, 2)
    ev, vec = torch.linalg.eigh(0.5 * (c + c.transpose(1, 2)))
    ev = torch.maximum(ev, _LEVERAGE_FLOOR * s2[:, None])
    w = torch.einsum("rkj,rk->rj", vec, z)
    return (w ** 2 / ev).sum(-1)


@dataclass(frozen=True)
class AssimilationOptions:
    """How records are assimilated (:func:`assimilate`).

    Attributes
    ----------
    threshold : float
        ``d^2`` of a step alarm (:func:`alarm_threshold`); ``inf``: no alarms.
    reopen : float
        Smallest re-opening of the drifting columns at an alarm [rad] (standard deviation per column).
    iterations : int
        Linearisations per record (1: the extended Kalman filter; more: the iterated one).
    robust : bool
        Down-weight records above :data:`HUBER_D2` (module docstring).
    window : int
        Step tests over the latest 1..``window`` records (module docstring; 1: the single-record test only).
    confirm_threshold : float
        Statistic of the records after an alarm above which its step is confirmed (:func:`confirm_threshold`).
    confirm_records : int
        Records after an alarm that settle it (:data:`CONFIRM_RECORDS`).
    """

    threshold: float = float("inf")
    reopen: float = REOPEN
    iterations: int = 2
    robust: bool = True
    window: int = WINDOW
    confirm_threshold: float = confirm_threshold()
    confirm_records: int = CONFIRM_RECORDS


def rounds(records: RecordTable) -> torch.Tensor:
    """Rows of ``records`` per round, [K, H] (-1: the heliostat has no k-th record): round k holds every
    heliostat's k-th record in time order (records without a time last, in table order)."""
    dev = records.heliostat_index.device
    if len(records) == 0:
        return torch.zeros(0, records.num_heliostats, dtype=torch.long, device=dev)
    t = records.time.double() if records.time is not None else torch.full((len(records),), float("nan"), device=dev)
    key = torch.nan_to_num(t, nan=float("inf"))
    order = torch.argsort(key, stable=True)
    index, mask = padded_index(records.subset(order))
    rows = torch.where(mask, order[index.clamp_min(0)], torch.full_like(index, -1))
    return rows.T.contiguous()


def choose_process_noise(nominal: Kinematics, records: RecordTable, state: FilterState,
                         grid=PROCESS_NOISE_GRID, share: float = VALIDATION_SHARE) -> dict:
    """The random walk's ``q`` chosen on records a calibration saw: chronological validation per heliostat.

    Every grid value at once, all heliostats at once: the residuals of the records at the state's mean are
    linearised once (``z`` [R, 2], tangent plane; ``H_b`` [R, 2, B], the drifting columns), then a Kalman
    filter of the walking offset ``b`` alone runs through each heliostat's timed records in time order,
    predicting each record before it assimilates it (Huber-weighted as :func:`assimilate` is). The offset
    starts from a prior worth one record (the state's offset covariance times the heliostat's records: a
    unit-information prior), so what a validation record is predicted with comes from the records before it,
    not from the calibration's own offset level, which saw it. The score of q is the median over heliostats of
    the mean prediction error ``|z - H_b b|`` [mrad of the mirror normal] of their latest ``share`` of records
    (heliostats with >= 4 timed records; the median: a step in a few heliostats' latest records does not
    choose the walk of the whole plant). The largest q within :data:`PROCESS_NOISE_TIE` of the best wins.

    Parameters
    ----------
    nominal : Kinematics
        The state's H heliostats.
    records : RecordTable
        R records on the same heliostat axis (records without a time are ignored).
    state : FilterState
        The calibration's state: ``mean`` [H, P] (where to linearise), ``covariance`` [H, P, P] (the posterior
        of those records), ``noise`` [H] [rad], ``drift_columns``, ``names``.
    grid : sequence of float
        q values [mrad^2/day], > 0.
    share : float
        Share of each heliostat's latest timed records that validate.

    Returns
    -------
    dict
        ``process_noise_mrad2_per_day`` (the choice; None when no heliostat has >= 4 timed records),
        ``grid_mrad2_per_day`` [G], ``validation_error_mrad`` [G], ``validation_records``,
        ``validation_heliostats`` and ``share``.
    """
    dev = state.mean.device
    dt_ = torch.float64
    q_grid = torch.as_tensor([float(q) for q in grid], dtype=dt_, device=dev)
    out = {"grid_mrad2_per_day": [float(q) for q in grid], "share": float(share), "validation_records": 0,
           "validation_heliostats": 0, "validation_error_mrad": [float("nan")] * len(grid),
           "process_noise_mrad2_per_day": None}
    if len(records) == 0 or records.time is None:
        return out
    records = records.subset(torch.isfinite(records.time.double()))
    order = rounds(records).to(dev)  # [K, H] rows in time order
    n = (order >= 0).sum(0)
    n_val = torch.where(n >= 4, torch.round(float(share) * n).clamp_min(1), torch.zeros_like(n)).long()
    k_index = torch.arange(order.shape[0], device=dev)[:, None]
    is_val = (order >= 0) & (k_index >= (n - n_val)[None])  # [K, H]
    if not bool(is_val.any()):
        return out
    hidx = records.heliostat_index
    cols = torch.as_tensor(list(state.drift_columns), dtype=torch.long, device=dev)
    z, hm, _, _ = linearise(nominal.index(hidx), records, state.mean.double()[hidx], state.names)
    z, hb = z.detach(), hm[:, :, cols].detach()
    g, h, nb = len(q_grid), state.mean.shape[0], len(cols)
    s2 = (state.noise.double() ** 2).repeat(g)  # [G * H], grid-major
    cov0 = state.covariance.double()[:, cols[:, None], cols[None, :]] * n.clamp_min(1).double()[:, None, None]
    cov = cov0.repeat(g, 1, 1)
    b = torch.zeros(g * h, nb, dtype=dt_, device=dev)
    q = (1e-6 * q_grid).repeat_interleave(h)
    t_prev = torch.full((g * h,), float("nan"), dtype=dt_, device=dev)
    err_sum = torch.zeros(g * h, dtype=dt_, device=dev)
    eye = torch.eye(2, dtype=dt_, device=dev)
    rec_t = records.time.double().to(dev)
    for k in range(order.shape[0]):  # rounds: one per record of the busiest heliostat, not heliostats
        rows = order[k].repeat(g)
        ok = rows >= 0
        r = rows.clamp_min(0)
        t = rec_t[r]
        days = torch.nan_to_num((t - t_prev) / _DAY, nan=0.0).clamp_min(0.0)
        p0 = cov + (q * days)[:, None, None] * torch.eye(nb, dtype=dt_, device=dev)
        e = z[r] - torch.einsum("rkb,rb->rk", hb[r], b)  # the record predicted before it is assimilated
        s = hb[r] @ p0 @ hb[r].transpose(1, 2) + s2[:, None, None] * eye
        d2 = (e[:, None, :] @ torch.linalg.solve(s, e[:, :, None]))[:, 0, 0]
        var = s2 * torch.clamp(d2 / HUBER_D2, min=1.0)
        b_new, p_new, _ = kalman_update(b, p0, e, hb[r], var)
        b = torch.where(ok[:, None], b_new, b)
        cov = torch.where(ok[:, None, None], p_new, cov)
        t_prev = torch.where(ok, t, t_prev)
        err_sum = err_sum + torch.where(is_val[k].repeat(g), e.norm(dim=-1), torch.zeros_like(d2))
    has = n_val > 0
    mean_err = (err_sum.view(g, h) / n_val.clamp_min(1).double())[:, has]  # [G, heliostats validated]
    score = 1e3 * mean_err.median(dim=1).values
    best = score.min()
    chosen = int(torch.nonzero(score <= best * (1.0 + PROCESS_NOISE_TIE)).max())
    out.update(process_noise_mrad2_per_day=float(q_grid[chosen]), validation_error_mrad=score.tolist(),
               validation_records=int(n_val.sum()), validation_heliostats=int(has.sum()))
    return out


def assimilate(nominal: Kinematics, records: RecordTable, state: FilterState,
               options: AssimilationOptions = AssimilationOptions(), score_spot: torch.Tensor | None = None
               ) -> tuple[FilterState, dict]:
    """Assimilate new records into the state of their heliostats (module docstring), all heliostats at once.

    Parameters
    ----------
    nominal : Kinematics
        The state's H heliostats (the deviations are relative to these).
    records : RecordTable
        R new records on the same heliostat axis, with the centroids the state is fitted on.
    state : FilterState
        H heliostats (not modified).
    options : AssimilationOptions
    score_spot : torch.Tensor, [R, 3], optional
        The centroids the prediction error is scored on (ENU m; default ``records.spot``).

    Returns
    -------
    state : FilterState
        After the last record of each heliostat.
    history : dict of [R] tensors (in assimilation order)
        ``row`` (into ``records``), ``heliostat`` (index), ``record_id``, ``time`` [s], ``mean`` [R, P] and
        ``variance`` [R, P] after the record, ``innovation`` [R, 2] (rad, tangent plane, at the prior),
        ``d2`` (normalised innovation), ``statistic`` (the largest step test) and ``window`` (its records),
        ``alarm`` (bool), ``predicted_error`` (pointing error of the record predicted by the state before it
        [rad]).
    """
    dev, dt_ = state.mean.device, torch.float64
    mean, cov = state.mean.double().clone(), state.covariance.double().clone()
    time = state.time.double().clone()
    ee = state.drift_embedding().double()
    s2 = state.noise.double() ** 2
    spot = records.spot if score_spot is None else score_spot
    rec_t = records.time.double() if records.time is not None else torch.full((len(records),), float("nan"),
                                                                              device=dev)
    cols = torch.as_tensor(list(state.drift_columns), dtype=torch.long, device=dev)
    nb, w = len(cols), max(1, int(options.window))
    ring_g, ring_f = state.window_g, state.window_f
    if ring_g is None or ring_f is None or tuple(ring_g.shape) != (mean.shape[0], w - 1, nb):
        ring_g = torch.zeros(mean.shape[0], w - 1, nb, dtype=dt_, device=dev)
        ring_f = torch.zeros(mean.shape[0], w - 1, nb, nb, dtype=dt_, device=dev)
    ring_g, ring_f = ring_g.double().clone(), ring_f.double().clone()
    eye_b = torch.eye(nb, dtype=dt_, device=dev)
    out: dict = {k: [] for k in ("row", "heliostat", "record_id", "time", "mean", "variance", "innovation", "d2",
                                 "statistic", "window", "alarm", "predicted_error")}
    closed: dict = {k: [] for k in _CLOSED_FIELDS}
    q_walk = float(state.process_noise)
    op = _open_slots(state, nb, dev)
    settle_k = max(1, int(options.confirm_records))
    for rows in rounds(records):  # rounds: a handful per day (records per heliostat), not heliostats
        rows = rows[rows >= 0].to(dev)
        if len(rows) == 0:
            continue
        batch = records.subset(rows)
        h = batch.heliostat_index
        kin = nominal.index(h)
        t = rec_t[rows]
        days = torch.nan_to_num((t - time[h]) / _DAY, nan=0.0).clamp_min(0.0)
        m0 = mean[h]
        p0 = cov[h] + q_walk * days[:, None, None] * ee
        z, hm, normal, conc = linearise(kin, batch, m0, state.names)
        score = replace(batch, spot=spot[rows])
        predicted = pointing_error_of_normals(normal.double(), conc.double(), score)
        var = s2[h].clone()
        # step tests: a constant jump b of the drifting columns over the latest k = 1..w records (generalised
        # likelihood ratio, Willsky & Jones 1976): g = sum H_b^T S^-1 z, F = sum H_b^T S^-1 H_b, g^T F^-1 g
        sinv = torch.linalg.inv(hm @ p0 @ hm.transpose(1, 2) + var[:, None, None] * torch.eye(2, dtype=dt_, device=dev))
        hb = hm[:, :, cols]
        gi = torch.einsum("rkb,rkl,rl->rb", hb, sinv, z)
        fi = hb.transpose(1, 2) @ sinv @ hb
        g = torch.cat([gi[:, None], gi[:, None] + ring_g[h].flip(1).cumsum(1)], 1)  # [B, w, nb], newest first
        f = torch.cat([fi[:, None], fi[:, None] + ring_f[h].flip(1).cumsum(1)], 1)
        ridge = 1e-9 * torch.diagonal(f, dim1=-2, dim2=-1).sum(-1).clamp_min(1e-300)[..., None, None] * eye_b
        jump = torch.linalg.solve(f + ridge, g[..., None])[..., 0]  # the step's estimate per window, [B, w, nb]
        stat_k = (g * jump).sum(-1)
        stat, k_best = stat_k.max(1)
        d2 = stat_k[:, 0]
        alarm = stat > float(options.threshold)
        _settle(op, closed, h, batch.record_id, t, alarm, stat, k_best, m0, p0, z, hm, hb, s2[h], q_walk, ee, eye_b,
                settle_k, float(options.confirm_threshold))
        single = alarm & (k_best == 0)
        several = alarm & (k_best > 0)
        size = jump[torch.arange(len(rows), device=dev), k_best].pow(2).sum(-1)
        grow = torch.where(single, (z ** 2).sum(-1), size).clamp_min(float(options.reopen) ** 2)
        # a jump seen by several records is real: re-open, then assimilate this record at full weight
        p_use = torch.where(several[:, None, None], p0 + grow[:, None, None] * ee, p0)
        if options.robust:  # Huber: a moderate outlier counts as if it were at the 95 % quantile
            var = torch.where(several, var, var * torch.clamp(d2 / HUBER_D2, min=1.0))
        m = m0
        for _ in range(max(1, int(options.iterations))):  # iterated EKF: relinearise at the updated mean
            if m is not m0:
                zi, hm, _, _ = linearise(kin, batch, m, state.names)
                z_lin = zi + torch.einsum("rkp,rp->rk", hm, m - m0)  # the measurement about m0, linearised at m
            else:
                z_lin = z
            m, p, _ = kalman_update(m0, p_use, z_lin, hm, var)
        # one record alone cannot tell a step from an outlier of its centroid: re-open the offset without
        # assimilating it; the next records, weighed against the open offset, decide
        m = torch.where(single[:, None], m0, m)
        p = torch.where(single[:, None, None], p0 + grow[:, None, None] * ee, p)
        if w > 1:
            keep = (~alarm).double()  # after an alarm the evidence starts afresh
            ring_g[h] = torch.cat([ring_g[h][:, 1:], gi[:, None]], 1) * keep[:, None, None]
            ring_f[h] = torch.cat([ring_f[h][:, 1:], fi[:, None]], 1) * keep[:, None, None, None]
        mean[h], cov[h] = m, p
        time[h] = torch.where(torch.isfinite(t), t, time[h])
        out["row"].append(rows)
        out["heliostat"].append(h)
        out["record_id"].append(batch.record_id)
        out["time"].append(t)
        out["mean"].append(m)
        out["variance"].append(torch.diagonal(p, dim1=1, dim2=2))
        out["innovation"].append(z)
        out["d2"].append(d2)
        out["statistic"].append(stat)
        out["window"].append(k_best + 1)
        out["alarm"].append(alarm)
        out["predicted_error"].append(predicted.double())
    p = mean.shape[-1]
    empty = {"row": torch.zeros(0, dtype=torch.long), "heliostat": torch.zeros(0, dtype=torch.long),
             "record_id": torch.zeros(0, dtype=torch.long), "time": torch.zeros(0, dtype=dt_),
             "mean": torch.zeros(0, p, dtype=dt_), "variance": torch.zeros(0, p, dtype=dt_),
             "innovation": torch.zeros(0, 2, dtype=dt_), "d2": torch.zeros(0, dtype=dt_),
             "statistic": torch.zeros(0, dtype=dt_), "window": torch.zeros(0, dtype=torch.long),
             "alarm": torch.zeros(0, dtype=torch.bool), "predicted_error": torch.zeros(0, dtype=dt_)}
    history = {k: (torch.cat(v) if v else empty[k].to(dev)) for k, v in out.items()}
    history["closed"] = {k: (torch.cat(v) if v else torch.zeros(0, dtype=torch.float64 if k in _CLOSED_FLOAT
                                                                else torch.long, device=dev))
                         for k, v in closed.items()}
    return replace(state, mean=mean, covariance=cov, time=time, window_g=ring_g, window_f=ring_f,
                   alarms=op), history


#: Fields of the closed alarms :func:`assimilate` returns (``history["closed"]``, [C] each): the heliostat
#: (index), the alarm's ``record_id``, ``opened`` (its time [s]), ``statistic`` and ``window``; the record that
#: closed it (``closed_by``, ``closed_at`` [s]), ``outcome`` (:data:`ALARM_OUTCOMES`), the settling statistic
#: ``evidence`` and the ``records`` it summed.
_CLOSED_FIELDS = ("heliostat", "record_id", "opened", "statistic", "window", "closed_by", "closed_at", "outcome",
                  "evidence", "records")
_CLOSED_FLOAT = ("opened", "statistic", "closed_at", "evidence")


def _open_slots(state: FilterState, nb: int, dev) -> dict:
    """The state's open-alarm slots (a copy, float64, on ``dev``), or empty ones when it has none or of
    another shape."""
    h, p = state.mean.shape
    fresh = no_open_alarms(h, p, nb, dev)
    given = state.alarms
    if not isinstance(given, dict) or any(k not in given or tuple(given[k].shape) != tuple(v.shape)
                                          for k, v in fresh.items()):
        return fresh
    return {k: torch.as_tensor(given[k]).to(device=dev, dtype=v.dtype).clone() for k, v in fresh.items()}


def _settle(op: dict, closed: dict, h, record_id, t, alarm, stat, k_best, m0, p0, z, hm, hb, s2, q_walk: float, ee,
            eye_b, settle_k: int, confirm: float) -> None:
    """One round's bookkeeping of the open alarms (module docstring), in place on ``op`` and ``closed``: each
    record of a heliostat with an open alarm adds its step evidence against the pre-alarm state; the
    ``settle_k``-th closes the alarm (confirmed above ``confirm``, else cleared); a new alarm supersedes an open
    one and opens its own slot with this record's prior (``m0`` [B, P], ``p0`` [B, P, P]) as the pre-alarm state.
    ``z`` [B, 2], ``hm`` [B, 2, P], ``hb`` [B, 2, nb]: the record linearised at ``m0``."""
    is_open = op["open"][h]
    if not bool(is_open.any()) and not bool(alarm.any()):
        return
    since = torch.nan_to_num((t - op["time"][h]) / _DAY, nan=0.0).clamp_min(0.0)
    p_pre = op["covariance"][h] + q_walk * since[:, None, None] * ee
    z_pre = z + torch.einsum("rkp,rp->rk", hm, m0 - op["mean"][h])  # the residual at the pre-alarm mean
    eye2 = torch.eye(2, dtype=z.dtype, device=z.device)
    s_inv = torch.linalg.inv(hm @ p_pre @ hm.transpose(1, 2) + s2[:, None, None] * eye2)
    on = is_open.to(z.dtype)
    g = op["g"][h] + on[:, None] * torch.einsum("rkb,rkl,rl->rb", hb, s_inv, z_pre)
    f = op["f"][h] + on[:, None, None] * (hb.transpose(1, 2) @ s_inv @ hb)
    n = op["records"][h] + is_open.long()
    ridge = 1e-9 * torch.diagonal(f, dim1=-2, dim2=-1).sum(-1).clamp_min(1e-300)[:, None, None] * eye_b
    evidence = (g * torch.linalg.solve(f + ridge, g[..., None])[..., 0]).sum(-1)
    settle = is_open & (n >= settle_k)
    superseded = is_open & ~settle & alarm
    done = settle | superseded
    if bool(done.any()):
        outcome = torch.where(superseded, 3, torch.where(evidence > confirm, 1, 2))
        for key, value in (("heliostat", h), ("record_id", op["record_id"][h]), ("opened", op["time"][h]),
                           ("statistic", op["statistic"][h]), ("window", op["window"][h]), ("closed_by", record_id),
                           ("closed_at", t), ("outcome", outcome), ("evidence", evidence), ("records", n)):
            closed[key].append(value[done].to(torch.float64 if key in _CLOSED_FLOAT else torch.long))
    keep = is_open & ~done
    fresh = alarm
    zero = torch.zeros((), dtype=z.dtype, device=z.device)
    op["g"][h] = torch.where(keep[:, None], g, zero)
    op["f"][h] = torch.where(keep[:, None, None], f, zero)
    op["records"][h] = torch.where(keep, n, torch.zeros_like(n))
    op["open"][h] = keep | fresh
    op["record_id"][h] = torch.where(fresh, record_id.to(torch.long), op["record_id"][h])
    op["time"][h] = torch.where(fresh, t, op["time"][h])
    op["statistic"][h] = torch.where(fresh, stat, op["statistic"][h])
    op["window"][h] = torch.where(fresh, k_best + 1, op["window"][h])
    op["mean"][h] = torch.where(fresh[:, None], m0, op["mean"][h])
    op["covariance"][h] = torch.where(fresh[:, None, None], p0, op["covariance"][h])


__all__ = ["FilterState", "AssimilationOptions", "no_open_alarms", "confirm_threshold", "CONFIRM_RECORDS",
           "CONFIRM_LEVEL", "ALARM_OUTCOMES", "tangent_basis", "linearise", "kalman_update", "alarm_threshold",
           "leave_one_out_d2", "rounds", "assimilate", "choose_process_noise", "HUBER_D2", "FALSE_ALARM_RATE", "REOPEN",
           "PROCESS_NOISE_GRID", "PROCESS_NOISE_TIE", "VALIDATION_SHARE"]
