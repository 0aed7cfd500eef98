"""A drifting pointing offset: the rigid body + a random-walk offset of the two axis (encoder zero) offsets.

The issue's analysis of the chrono test error: 57-72 % of the test MSE is the mean offset of the test block,
which drifts or steps over months. Model (a local-level / random-walk state-space model, e.g. Durbin &
Koopman, *Time Series Analysis by State Space Methods*, ch. 2; Sarkka, *Bayesian Filtering and Smoothing*,
ch. 8): the deviations of a heliostat at time t are

    delta(t) = delta_static + E b(t),      b(t) = (d initial_angle_1, d initial_angle_2)(t)  [rad],

``E`` the embedding of the two axis offsets into the Stone/Jülich 8, and ``b`` a random walk that starts at
0 at the heliostat's first training record, with process noise ``q`` per component [rad^2/day]:
``Cov(b(t_i), b(t_j)) = q min(tau_i, tau_j) I_2``, tau [days] since that record. Linearised at the
nominal kinematics (the axis offsets enter the normal almost linearly), a record's residual
``r_i = n_model - n_measured`` at ``delta_static`` is ``-A_i b(t_i) + noise``, ``A_i`` [3, 2] the
columns of the record Jacobian for the two axis offsets, noise ``s`` per component.

* The static part is then a generalised least-squares fit: marginalising ``b``, the residuals of a
  heliostat have covariance ``Sigma = A K A^T + s^2 I`` [3n, 3n]; :func:`whitener` gives
  ``W = s L^-1`` (``Sigma = L L^T``), and :func:`~heliotwin.calibrate.methods.lm.fit_lm` fits ``W r`` instead of
  ``r`` (``q = 0``: ``W = I``, the static fit exactly). Old records weigh less because the offset they saw
  may have moved since: the principled form of the half-life weights.
* The offset given the residuals (:func:`smooth`): the Gaussian conditional ``E[b | r] = K A^T Sigma^-1 y``
  (``y = -r``) at every training record (the Rauch-Tung-Striebel smoother's output, computed in its dense
  batched form: n <= a few hundred records per heliostat, all heliostats at once) and, at the latest
  training time t_l, the filtered state with its covariance ``P_l``. A later record at t is predicted with
  ``b(t_l)`` and covariance ``P_l + q (t - t_l) I`` (the random walk's growth), which
  :func:`heliotwin.calibrate.protocol.pipeline.predict_intervals` adds to the Laplace posterior.

Records without a time cannot be placed on the walk: their offset rows are zero (they inform the static
part only). ``q`` is chosen by leave-heliostats-out CV (:data:`heliotwin.calibrate.protocol.selection.CANDIDATES`) or
by chronological validation inside the training records (``process_noise="auto"``, :func:`choose_q`).
"""
from __future__ import annotations

import torch

from ..io.records import RecordTable
from .metrics import record_jacobian
from .params import STONE8

#: The deviations that drift, per basis: ``"axes"``: the two axis (encoder zero) offsets; ``"rotation"``: a
#: small rotation of the whole heliostat about east (axis-1 offset, joint 1 turns about east), north and up
#: (the first joint's tilts) — a pointing offset fixed in the world frame rather than in the axes.
BASES = {"axes": ("initial_angle_1", "initial_angle_2"),
         "rotation": ("initial_angle_1", "joint_tilt_1_n", "joint_tilt_1_u")}
DRIFT_NAMES = BASES["axes"]
DRIFT_COLUMNS = tuple(STONE8.index(n) for n in DRIFT_NAMES)


def columns(basis: str = "axes") -> list:
    """Columns of :data:`STONE8` that drift in ``basis`` (:data:`BASES`)."""
    if basis not in BASES:
        raise ValueError(f"unknown drift basis {basis!r}; known: {', '.join(BASES)}")
    return [STONE8.index(n) for n in BASES[basis]]

#: Process noise values [mrad^2/day] tried by ``process_noise="auto"`` (0 = static). 0.01 mrad^2/day is a
#: 1 mrad standard deviation after 100 days.
Q_GRID = (0.0, 0.001, 0.003, 0.01, 0.03, 0.1)

_DAY = 86400.0


def padded_index(batch: RecordTable, key: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per heliostat, the batch rows of its records: ``index`` [H, n] (``-1`` = padding) and ``mask`` [H, n].
    Each heliostat's rows are in batch order, or ascending in ``key`` [R] (stable) when it is given."""
    hidx = batch.heliostat_index
    h = batch.num_heliostats
    counts = torch.bincount(hidx, minlength=h)
    n = int(counts.max()) if len(hidx) else 0
    order = torch.argsort(hidx, stable=True) if key is None else torch.argsort(key, stable=True)
    if key is not None:
        order = order[torch.argsort(hidx[order], stable=True)]
    start = torch.cumsum(counts, 0) - counts
    pos = torch.arange(len(hidx), device=hidx.device) - start[hidx[order]]
    index = torch.full((h, max(n, 1)), -1, dtype=torch.long, device=hidx.device)
    index[hidx[order], pos] = order
    return index, index >= 0


def elapsed_days(batch: RecordTable) -> tuple[torch.Tensor, torch.Tensor]:
    """Days since the heliostat's first record with a time, per record [R] (NaN: no time), and that
    first time [H] (POSIX s; NaN when no record of the heliostat has one)."""
    t = batch.time.double() if batch.time is not None else torch.full((len(batch),), float("nan"),
                                                                      dtype=torch.float64)
    known = torch.isfinite(t)
    first = torch.full((batch.num_heliostats,), float("inf"), dtype=torch.float64, device=t.device)
    first = first.scatter_reduce(0, batch.heliostat_index[known], t[known], reduce="amin")
    first = torch.where(torch.isfinite(first), first, torch.full_like(first, float("nan")))
    return (t - first[batch.heliostat_index]) / _DAY, first


def offset_jacobian(nominal, batch: RecordTable, delta: torch.Tensor | None = None,
                    basis: str = "axes") -> torch.Tensor:
    """``A`` [R, 3, 2]: derivative of each record's residual w.r.t. its heliostat's two axis offsets [1/rad]
    at deviations ``delta`` [H, 8] (default zero = nominal)."""
    hidx = batch.heliostat_index
    dev = nominal.position.device
    d = torch.zeros(nominal.num_heliostats, len(STONE8), dtype=torch.float64, device=dev) if delta is None \
        else delta.double()
    _, jac = record_jacobian(nominal.index(hidx), batch, d.detach()[hidx], STONE8)
    return jac[:, :, columns(basis)]


def _padded_model(batch: RecordTable, jac: torch.Tensor, q: float):
    """Padded ``A`` [H, n, 3, 2] (zero for padding and records without a time), walk covariance ``K`` [H, n, n]
    (rad^2; ``q`` [rad^2/day]) and the padded index [H, n]."""
    index, mask = padded_index(batch)
    tau, _ = elapsed_days(batch)
    safe = index.clamp_min(0)
    timed = mask & torch.isfinite(tau[safe])
    a = torch.where(timed[..., None, None], jac.double()[safe], 0.0)
    tt = torch.where(timed, tau[safe], 0.0)
    k = float(q) * torch.minimum(tt[:, :, None], tt[:, None, :])
    return a, k, index, mask


def _sigma(a: torch.Tensor, k: torch.Tensor, noise: float) -> torch.Tensor:
    """Marginal residual covariance ``A K A^T + s^2 I`` [H, 3n, 3n]."""
    h, n = k.shape[:2]
    sig = torch.einsum("hikc,hij,hjlc->hikjl", a, k, a).reshape(h, 3 * n, 3 * n)
    return sig + float(noise) ** 2 * torch.eye(3 * n, dtype=torch.float64, device=k.device)


def _time_ordered(batch: RecordTable):
    """Per heliostat its records in time order (records without a time first: they do not move the walk):
    ``index`` [H, n] (-1 = padding), ``mask`` [H, n], days since the heliostat's first timed record ``tt``
    [H, n] (0 where untimed or padding), ``timed`` [H, n] and that first time [H] (POSIX s)."""
    tau, first = elapsed_days(batch)
    index, mask = padded_index(batch, torch.where(torch.isfinite(tau), tau, torch.full_like(tau, -1.0)))
    t = tau[index.clamp_min(0)]
    timed = mask & torch.isfinite(t)
    return index, mask, torch.where(timed, t, torch.zeros_like(t)), timed, first


def _filter_gains(a: torch.Tensor, tt: torch.Tensor, timed: torch.Tensor, q: float, noise: float) -> dict:
    """The Kalman filter of the walk over each heliostat's records in time order, its data-free part.

    ``a`` [H, n, 3, B] (zero where untimed or padding), ``tt`` [H, n] days, ``timed`` [H, n]. Per step k: the
    predicted covariance ``P_k = P_{k-1}^+ + q dt I``, innovation covariance ``S_k = A_k P_k A_k^T + s^2 I`` with
    Cholesky ``L_k``, gain ``K_k = P_k A_k^T S_k^-1``. Returns ``gain`` [H, n, B, 3], ``white`` = ``s L_k^-1``
    [H, n, 3, 3], ``predicted`` / ``filtered`` covariances [H, n, B, B] and the final one [H, B, B]."""
    h, n, _, nb = a.shape
    dev = a.device
    eye_b = torch.eye(nb, dtype=torch.float64, device=dev)
    eye3 = torch.eye(3, dtype=torch.float64, device=dev)
    cov = torch.zeros(h, nb, nb, dtype=torch.float64, device=dev)
    prev = torch.zeros(h, dtype=torch.float64, device=dev)
    gain = torch.empty(h, n, nb, 3, dtype=torch.float64, device=dev)
    white = torch.empty(h, n, 3, 3, dtype=torch.float64, device=dev)
    predicted = torch.empty(h, n, nb, nb, dtype=torch.float64, device=dev)
    filtered = torch.empty(h, n, nb, nb, dtype=torch.float64, device=dev)
    for k in range(n):  # over a heliostat's records (tens to hundreds), every heliostat at once
        dt = torch.where(timed[:, k], (tt[:, k] - prev).clamp_min(0.0), torch.zeros_like(prev))
        prev = torch.where(timed[:, k], tt[:, k], prev)
        cov = cov + (float(q) * dt)[:, None, None] * eye_b
        predicted[:, k] = cov
        ak = a[:, k]
        pa = cov @ ak.transpose(1, 2)  # [H, B, 3]
        chol = torch.linalg.cholesky(ak @ pa + float(noise) ** 2 * eye3)
        linv = torch.linalg.solve_triangular(chol, eye3.expand(h, 3, 3), upper=False)
        k_gain = pa @ (linv.transpose(1, 2) @ linv)
        cov = cov - k_gain @ pa.transpose(1, 2)
        cov = 0.5 * (cov + cov.transpose(1, 2))
        filtered[:, k] = cov
        gain[:, k] = k_gain
        white[:, k] = float(noise) * linv
    return {"gain": gain, "white": white, "predicted": predicted, "filtered": filtered, "last": cov}


def _walk_filter(nominal, batch: RecordTable, q: float, noise: float, basis: str):
    """What :func:`whitener` and :func:`smooth` both run: the time-ordered padding (:func:`_time_ordered`), the
    offset Jacobian ``a`` [H, n, 3, B] (zero where untimed or padding) and the filter (:func:`_filter_gains`)."""
    index, mask, tt, timed, first = _time_ordered(batch)
    jac = offset_jacobian(nominal, batch, basis=basis).double()
    a = torch.where(timed[..., None, None], jac[index.clamp_min(0)], 0.0)
    return index, mask, tt, timed, first, a, _filter_gains(a, tt, timed, q, noise)


def whitener(nominal, batch: RecordTable, q: float, noise: float, basis: str = "axes"):
    """The GLS whitening of :func:`~heliotwin.calibrate.methods.lm.fit_lm` (module docstring).

    ``W = s L^-1`` with ``Sigma = L L^T`` and each heliostat's records in time order: ``L^-1`` is the Kalman
    filter's normalised innovations (the prediction-error decomposition, Durbin & Koopman ch. 7), so it is
    computed by one pass over the records with 3x3 algebra per record (O(n) per heliostat, no [3n, 3n] matrix:
    the dense form, :func:`dense_whitener`, took minutes and gigabytes at a plant of 2,000 heliostats with a
    hundred records each). It equals the dense factor to rounding when the batch lists each heliostat's records
    in time order (tested).

    Parameters
    ----------
    q : float
        Process noise [rad^2/day] per component.
    noise : float
        Residual noise per component [rad] (the fit's ``noise``).

    Returns
    -------
    callable ``w(x)``: ``x`` [R, 3, ...] -> the whitened ``s L^-1 x`` [R, 3, ...] per heliostat (records stay
    on their heliostat's rows, so the Jacobian keeps its block structure).
    """
    index, mask, _, _, _, a, f = _walk_filter(nominal, batch, q, noise, basis)
    gain, white = f["gain"], f["white"]
    h, n = index.shape
    rows = index[mask]
    hh, jj = mask.nonzero(as_tuple=True)

    def apply(x: torch.Tensor) -> torch.Tensor:
        tail = x.shape[2:]
        pad = x.new_zeros((h, n, 3) + tail).reshape(h, n, 3, -1)
        pad[hh, jj] = x[rows].reshape(len(rows), 3, -1)
        state = pad.new_zeros(h, a.shape[-1], pad.shape[-1])
        out = torch.empty_like(pad)
        for k in range(n):  # the filter's linear recursion, applied to every column of x at once
            v = pad[:, k] - a[:, k] @ state
            out[:, k] = white[:, k] @ v
            state = state + gain[:, k] @ v
        y = torch.empty_like(x)
        y[rows] = out[hh, jj].reshape((len(rows), 3) + tail)
        return y

    return apply


def smooth(nominal, batch: RecordTable, delta: torch.Tensor, q: float, noise: float, basis: str = "axes") -> dict:
    """The offset ``b`` given the residuals of the static fit ``delta`` [H, 8] (module docstring).

    A Kalman filter over each heliostat's records in time order gives the offset and its covariance at the
    latest record (where the filter is the smoother), a Rauch-Tung-Striebel pass back the offset at every
    record (Sarkka ch. 8); equal to the dense conditional (:func:`dense_smooth`) to rounding.

    Returns
    -------
    dict
        ``smoothed`` [R, 2] (rad, E[b(t_i) | all records] per record; 0 without a time), ``offset`` [H, 2]
        (rad, at the heliostat's latest training time), ``covariance`` [H, 2, 2] (rad^2), ``time`` [H]
        (POSIX s of that latest record; NaN without one), ``q`` (rad^2/day).
    """
    hidx = batch.heliostat_index
    h = batch.num_heliostats
    res, _ = record_jacobian(nominal.index(hidx), batch, delta.detach().double()[hidx], STONE8)
    index, mask, tt, timed, first, a, f = _walk_filter(nominal, batch, q, noise, basis)
    hn, n = index.shape
    nb = a.shape[-1]
    dev = res.device
    y = torch.zeros(hn, n, 3, 1, dtype=torch.float64, device=dev)
    y[mask] = -res[index[mask]].unsqueeze(-1)
    mean = torch.zeros(hn, nb, 1, dtype=torch.float64, device=dev)
    means = torch.empty(hn, n, nb, 1, dtype=torch.float64, device=dev)
    for k in range(n):
        mean = mean + f["gain"][:, k] @ (y[:, k] - a[:, k] @ mean)
        means[:, k] = mean
    smoothed_pad = means.clone()
    back = mean
    for k in range(n - 2, -1, -1):  # RTS: m_k + C_k (m_{k+1}^s - m_{k+1}^-), C_k = P_k^+ (P_{k+1}^-)^-1
        pred = f["predicted"][:, k + 1]
        c = f["filtered"][:, k] @ torch.linalg.pinv(pred)  # a singular (zero) prediction: pinv 0, no smoothing
        back = means[:, k] + c @ (back - means[:, k])  # the walk's prediction is the filtered mean itself
        smoothed_pad[:, k] = back
    smoothed = torch.zeros(len(batch), nb, dtype=torch.float64, device=dev)
    smoothed[index[mask]] = torch.where(timed[mask][:, None], smoothed_pad[mask][..., 0], 0.0)
    tl = (tt * timed).amax(1)
    time = first + tl * _DAY
    return {"smoothed": smoothed, "offset": mean[..., 0], "covariance": f["last"], "time": time[:h],
            "q": float(q), "columns": torch.tensor(columns(basis), device=dev)}


def dense_whitener(nominal, batch: RecordTable, q: float, noise: float, basis: str = "axes"):
    """:func:`whitener` by the dense Cholesky factor of each heliostat's ``Sigma`` [3n, 3n] (records in the
    batch's order): the reference the recursion is tested against (O(n^3) time, O(n^2) memory per heliostat).
    Arguments and return as :func:`whitener`'s: ``q`` [rad^2/day], ``noise`` [rad]; ``w(x)`` maps ``x``
    [R, 3, ...] to ``s L^-1 x`` [R, 3, ...].
    """
    a, k, index, mask = _padded_model(batch, offset_jacobian(nominal, batch, basis=basis), q)
    h, n = index.shape
    chol = torch.linalg.cholesky(_sigma(a, k, noise))
    eye = torch.eye(3 * n, dtype=torch.float64, device=chol.device).expand(h, -1, -1)
    w = float(noise) * torch.linalg.solve_triangular(chol, eye, upper=False)  # [H, 3n, 3n]
    rows = index[mask]
    hh, jj = mask.nonzero(as_tuple=True)

    def apply(x: torch.Tensor) -> torch.Tensor:
        tail = x.shape[2:]
        pad = x.new_zeros((h, n, 3) + tail)
        pad[hh, jj] = x[rows]
        out = torch.einsum("hij,hj...->hi...", w, pad.reshape((h, 3 * n) + tail)).reshape((h, n, 3) + tail)
        y = torch.empty_like(x)
        y[rows] = out[hh, jj]
        return y

    return apply


def dense_smooth(nominal, batch: RecordTable, delta: torch.Tensor, q: float, noise: float, basis: str = "axes"
                 ) -> dict:
    """:func:`smooth` by the dense Gaussian conditional (the reference the recursion is tested against): the
    same arguments (``delta`` [H, 8], ``q`` [rad^2/day], ``noise`` [rad]) and the same dict."""
    hidx = batch.heliostat_index
    h = batch.num_heliostats
    res, jac = record_jacobian(nominal.index(hidx), batch, delta.detach().double()[hidx], STONE8)
    a, k, index, mask = _padded_model(batch, offset_jacobian(nominal, batch, basis=basis), q)
    hn, n = index.shape
    nb = a.shape[-1]
    dev = res.device
    y = torch.zeros(hn, n, 3, dtype=torch.float64, device=dev)
    y[mask] = -res[index[mask]]
    sig = _sigma(a, k, noise)
    chol = torch.linalg.cholesky(sig)
    z = torch.cholesky_solve(y.reshape(hn, 3 * n, 1), chol).reshape(hn, n, 3)
    u = torch.einsum("hjkc,hjk->hjc", a, z)  # A^T Sigma^-1 y, [H, n, 2]
    mean = torch.einsum("hij,hjc->hic", k, u)  # K A^T Sigma^-1 y
    smoothed = torch.zeros(len(batch), nb, dtype=torch.float64, device=dev)
    smoothed[index[mask]] = mean[mask]
    tau, first = elapsed_days(batch)
    tt = torch.where(mask, tau[index.clamp_min(0)], float("nan"))
    tt = torch.nan_to_num(tt, nan=-1.0)
    last = tt.argmax(1)  # the latest timed record (the walk's state at the latest training time)
    tl = tt.gather(1, last[:, None])[:, 0].clamp_min(0.0)
    ar = torch.arange(hn, device=dev)
    offset = mean[ar, last] * (tt[ar, last] >= 0)[:, None]
    # Cov(b_l, y) = K[:, l] A (per record), [H, 3n, 2]; P_l = q tau_l I - G^T Sigma^-1 G
    g = (a * k[ar, :, last][:, :, None, None]).reshape(hn, 3 * n, nb)
    sg = torch.cholesky_solve(g, chol)
    cov = float(q) * tl[:, None, None] * torch.eye(nb, dtype=torch.float64, device=dev) - g.transpose(1, 2) @ sg
    cov = 0.5 * (cov + cov.transpose(1, 2))
    time = first + tl * _DAY
    return {"smoothed": smoothed, "offset": offset, "covariance": cov, "time": time[:h], "q": float(q),
            "columns": torch.tensor(columns(basis), device=dev)}


def predicted_covariance(state: dict, heliostat_index: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
    """Covariance (R, B, B) [rad^2] of the offset at later records: ``P_l + q max(t - t_l, 0) I``
    (records without a time: ``P_l``).

    ``state`` is :func:`smooth`'s answer (B drifting columns: 2 for the ``axes`` basis); ``heliostat_index``
    (R,) long, each record's heliostat; ``time`` (R,), UTC POSIX seconds [s] (NaN: no time).
    """
    dt = ((time.double() - state["time"].double()[heliostat_index]) / _DAY).clamp_min(0.0)
    dt = torch.nan_to_num(dt, nan=0.0)
    eye = torch.eye(state["covariance"].shape[-1], dtype=torch.float64, device=state["covariance"].device)
    return state["covariance"].double()[heliostat_index] + float(state["q"]) * dt[:, None, None] * eye


def with_offset(delta: torch.Tensor, offset: torch.Tensor, basis: str = "axes") -> torch.Tensor:
    """Deviations [H, 8] (STONE8 order, physical units) with the current offset [H, B] [rad] added to the
    drifting columns of ``basis`` (a new tensor; ``delta`` is not changed)."""
    out = delta.clone()
    cols = columns(basis)
    out[:, cols] = out[:, cols] + offset.to(out)
    return out


def split_for_choice(batch: RecordTable, fraction: float = 0.25) -> tuple[torch.Tensor, torch.Tensor]:
    """Row indices (fit, validate) of a chronological split inside each heliostat's records: the latest
    ``fraction`` (at least 1, only where >= 4 records have a time) validate."""
    index, mask = padded_index(batch)
    tau, _ = elapsed_days(batch)
    fit, val = [], []
    for h in range(index.shape[0]):  # a handful of heliostats, once per run: not a hot path
        rows = index[h][mask[h]]
        timed = rows[torch.isfinite(tau[rows])]
        timed = timed[torch.argsort(tau[timed], stable=True)]
        nv = max(1, int(round(fraction * len(timed)))) if len(timed) >= 4 else 0
        val.append(timed[len(timed) - nv:])
        keep = torch.ones(len(rows), dtype=torch.bool, device=rows.device)
        keep[torch.isin(rows, val[-1])] = False
        fit.append(rows[keep])
    return torch.cat(fit), torch.cat(val)
