"""How sure a calibration is: the predictive distribution of the pointing error at a new sun position.

Laplace approximation of the ``lm`` fit (MacKay 1992; Bishop, *Pattern Recognition and Machine Learning*,
sec. 4.4): around the MAP deviations ``delta`` of a heliostat, the posterior is Gaussian with precision

    Lambda = J^T J / s^2 + Pi,

``J`` [3n, P] the Jacobian of the n training residuals (model minus measured normal), ``s`` the residual
noise per component (estimated from the training residuals), ``Pi`` the prior precision (plant prior:
``W^T W``; field or nominal prior: ``diag(1 / sigma^2)``). At a new record the error of the normal is

    e = J_new (delta_true - delta) + s * noise + tau * offset,
    e ~ N(0, J_new Lambda^-1 J_new^T + (s^2 + tau^2) (I - n n^T)),

(noise and offset lie in the plane normal to the mirror normal ``n``), and the pointing error is ``|e|``. Its
distribution is not Gaussian; :func:`predictive` draws ``samples`` vectors ``e`` per record (seeded) and
reports the mean (expected error) and the 90 % interval of ``|e|``, one-sided: ``[0, q_0.9]``. A pointing
error is non-negative and the plant's question is how large it may be; a central interval would count a
record that is *better* than its 5 % quantile as a miss, and its coverage is not monotone in the spread.

``tau`` (``drift``) is an offset per component that the training records cannot show: the Laplace
posterior knows the noise of the training records and the geometry of extrapolation, not the drift or steps
of the offset over months (the issue's analysis: 57-72 % of the test MSE is the test block's mean offset).
It is chosen by leave-heliostats-out coverage (:func:`heliotwin.calibrate.protocol.selection.choose_drift`), never
on the test records of the heliostat it is applied to; 0 = the plain Laplace approximation.
"""
from __future__ import annotations

import torch

from ..field.plant import Kinematics
from .params import apply_deviations

#: Draws per record of the predictive distribution (quantiles of |e| to ~1 %).
SAMPLES = 4000

#: Records x samples per step of :func:`predictive` (memory ~ 30 doubles each: ~0.5 GB).
PREDICTIVE_CHUNK = 2_000_000

#: Probability mass of the reported interval ``[0, q_LEVEL]``.
LEVEL = 0.9

#: Floor of the residual noise per component [rad] (a fit through 5 records can leave ~0 residual).
MIN_NOISE = 1e-4


def residual_variance(residuals: torch.Tensor, heliostat_index: torch.Tensor, num_heliostats: int,
                      num_parameters: int) -> torch.Tensor:
    """Residual variance per component [H] [rad^2] of a fit of ``num_parameters`` per heliostat: ``residuals``
    [R, 3] [rad] over ``2 n - P`` degrees of freedom per heliostat (the residual lies in the mirror plane), at
    least :data:`MIN_NOISE` squared."""
    f64 = dict(dtype=torch.float64, device=residuals.device)
    ss = torch.zeros(num_heliostats, **f64).index_add_(0, heliostat_index, (residuals ** 2).sum(-1))
    n = torch.bincount(heliostat_index, minlength=num_heliostats).double()
    dof = (2.0 * n - num_parameters).clamp_min(1.0)
    return (ss / dof).clamp_min(MIN_NOISE ** 2)


def posterior(residuals: torch.Tensor, jacobian: torch.Tensor, heliostat_index: torch.Tensor, prior_precision,
              num_heliostats: int, num_parameters: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Laplace posterior covariance [H, P, P] and residual noise per component [H] (rad).

    Parameters
    ----------
    residuals : torch.Tensor, [R, 3]
        Training residuals at the fit (rad).
    jacobian : torch.Tensor, [R, 3, P]
        Their derivative w.r.t. the heliostat's own deviations (physical units).
    heliostat_index : torch.Tensor, [R]
    prior_precision : torch.Tensor, [P, P] or [H, P, P]
    """
    h, p = num_heliostats, num_parameters
    f64 = dict(dtype=torch.float64, device=jacobian.device)
    jtj = torch.zeros(h, p, p, **f64).index_add_(0, heliostat_index, torch.einsum("rci,rcj->rij", jacobian, jacobian))
    s2 = residual_variance(residuals, heliostat_index, h, p)
    prec = jtj / s2[:, None, None] + torch.as_tensor(prior_precision).to(**f64).expand(h, p, p)
    eye = torch.eye(p, **f64)
    cov = torch.linalg.solve(prec + 1e-12 * eye, eye.expand(h, p, p))
    return 0.5 * (cov + cov.transpose(-1, -2)), s2.sqrt()


def predictive(jacobian: torch.Tensor, normal: torch.Tensor, covariance: torch.Tensor, noise: torch.Tensor, *,
               drift: float = 0.0, samples: int = SAMPLES, level: float = LEVEL,
               generator: torch.Generator | None = None) -> dict:
    """Predictive pointing error of R new records: expected value and central interval [rad].

    Parameters
    ----------
    jacobian : torch.Tensor, [R, 3, P]
        Derivative of each record's model normal w.r.t. its heliostat's deviations.
    normal : torch.Tensor, [R, 3]
        Model mirror normal (unit).
    covariance : torch.Tensor, [R, P, P]
        Posterior covariance of each record's heliostat.
    noise : torch.Tensor, [R]
        Residual noise per component of each record's heliostat (rad).
    drift : float
        Offset drift per component [rad] added to the noise (module docstring).

    Returns
    -------
    dict of [R] tensors: ``expected`` (mean), ``median``, ``lower`` (0) and ``upper`` (the ``level``
    quantile) of the pointing error (rad).
    """
    g = generator if generator is not None else torch.Generator().manual_seed(0)
    r, p = covariance.shape[0], covariance.shape[-1]
    if r == 0:
        z = normal.new_zeros(0)
        return {"expected": z, "median": z, "lower": z, "upper": z}
    dev = covariance.device
    eye = torch.eye(p, dtype=torch.float64, device=dev)
    # the same draws for every record (drawn once, on the generator's device, then moved)
    xi = torch.randn(samples, p, generator=g, dtype=torch.float64).to(dev)
    eta = torch.randn(samples, 3, generator=g, dtype=torch.float64).to(dev)
    sd = (noise.double() ** 2 + float(drift) ** 2).sqrt()  # noise and drift: independent, both in the mirror plane
    draws = torch.cat([xi, eta], 1).T.contiguous()  # [P + 3, S]
    eye3 = torch.eye(3, dtype=torch.float64, device=dev)
    chunk = max(1, PREDICTIVE_CHUNK // samples)  # memory ~ chunk x samples
    # One set of sample buffers reused by every chunk: a fresh ~16-48 MB set per chunk fragments the C heap,
    # and the process then held 1-2 GB more at random (allocator state), growing with the records.
    size = min(chunk, r)
    e_buf = torch.empty(size, 3, samples, dtype=torch.float64, device=dev)
    norm_buf = torch.empty(size, samples, dtype=torch.float64, device=dev)
    # only the order statistics from the lower quantile's up are needed: the largest ``top`` of each row, sorted (a
    # partial sort, about half a full one's cost at 4,000 samples; the same values)
    first = int(min(0.5, float(level)) * (samples - 1))
    top = samples - first
    sorted_buf = (torch.empty(size, top, dtype=torch.float64, device=dev),
                  torch.empty(size, top, dtype=torch.long, device=dev))
    expected, medians, uppers = [], [], []
    for rows in torch.arange(r, device=dev).split(chunk):
        # e[r, :, s] = J_r L_r xi_s + sd_r (I - n_r n_r^T) eta_s: parameters, then noise in the mirror plane, as
        # one [r, 3, P + 3] x [P + 3, S] product (one pass over the samples instead of five elementwise ones)
        m = len(rows)
        n = normal[rows].double()
        chol = torch.linalg.cholesky(covariance[rows].double() + 1e-18 * eye)  # per chunk: no [R, P, P] copies
        plane = sd[rows, None, None] * (eye3 - n[:, :, None] * n[:, None, :])  # [r, 3, 3]
        e = torch.matmul(torch.cat([jacobian[rows].double() @ chol, plane], 2), draws, out=e_buf[:m])  # [r, 3, S]
        e = torch.sum(e.mul_(e), dim=1, out=norm_buf[:m]).sqrt_()  # [r, S]
        expected.append(e.mean(1))
        e = torch.topk(e, top, dim=1, out=(sorted_buf[0][:m], sorted_buf[1][:m])).values.flip(1)  # ascending
        medians.append(_quantile(e, 0.5, samples))
        uppers.append(_quantile(e, level, samples))
    upper = torch.cat(uppers)
    return {"expected": torch.cat(expected), "median": torch.cat(medians), "lower": torch.zeros_like(upper),
            "upper": upper}


def _quantile(x: torch.Tensor, q: float, samples: int | None = None) -> torch.Tensor:
    """``torch.quantile(v, q, dim=1)`` (linear interpolation) of rows ``v`` of ``samples`` values (default
    ``x.shape[1]``) given the largest ``x.shape[1]`` of each, ascending: ``x`` [r, k] = ``sort(v)[:, samples - k:]``."""
    n = x.shape[1] if samples is None else int(samples)
    pos = q * (n - 1)
    lo = int(pos)
    skip = n - x.shape[1]
    if lo < skip:
        raise ValueError(f"quantile {q} is below the {x.shape[1]} largest of {n} values given")
    a = x[:, lo - skip]
    if lo + 1 >= n or pos == lo:
        return a.clone()  # not a view: ``x`` may be a reused buffer
    return a + (pos - lo) * (x[:, lo + 1 - skip] - a)


def posterior_draws(kin: Kinematics, names, covariance: torch.Tensor, draws: int, seed: int) -> list[Kinematics]:
    """``draws`` kinematics of heliostats ``kin`` (Hc), each ``kin`` plus a draw ``L z`` of the Laplace posterior
    ``covariance`` [Hc, P, P] of the deviations ``names`` (seeded ``torch.Generator``, ``z ~ N(0, I)``)."""
    gen = torch.Generator().manual_seed(int(seed))
    cov = covariance.to(torch.float64)
    p = cov.shape[-1]
    jitter = 1e-18 * torch.eye(p, dtype=torch.float64)
    chol = torch.linalg.cholesky(0.5 * (cov + cov.transpose(-1, -2)) + jitter)
    out = []
    for _ in range(int(draws)):  # a handful of draws, each batched over heliostats
        z = torch.randn(cov.shape[0], p, 1, generator=gen, dtype=torch.float64)
        delta = (chol @ z).squeeze(-1)
        out.append(apply_deviations(kin, delta.to(kin.position.dtype), list(names)))
    return out
