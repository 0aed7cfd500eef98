"""Plant-level Gaussian priors from few heliostats: sample correlations shrunk towards the identity.

One home for what both plant priors share (:class:`GaussianPrior`: its fields, whitening and stored form;
the covariance estimate :func:`shrunk_covariance`): the kinematic deviations
(:func:`heliotwin.calibrate.priors.plant_prior`) and the facets' low-order surface shape
(:func:`heliotwin.surfaces.plantprior.surface_prior`). With H ~ 10-30 heliostats a P x P covariance is
poorly determined, so the sample *correlation* is shrunk towards the identity (a Ledoit-Wolf-style target,
Ledoit & Wolf 2004, J. Multivariate Anal. 88, 365) and each marginal standard deviation is floored: a
parameter on which the archive heliostats happen to agree must not become a hard constraint.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import torch

from .errors import InputFileError


def shrunk_covariance(centred: torch.Tensor, floor_sd, *, covariance: str = "full", shrink: float = 0.2,
                      widen: float = 1.0) -> torch.Tensor:
    """Shrunk covariance of centred samples.

    Parameters
    ----------
    centred : torch.Tensor, [H, P]
        Samples minus their centre (mean or robust centre), H >= 2.
    floor_sd : float or torch.Tensor [P]
        Smallest marginal standard deviation per parameter (units of the samples).
    covariance : str
        ``"full"`` (sample correlations, shrunk towards the identity by ``shrink``) or ``"diag"``.
    shrink : float
        Weight of the identity in the correlation matrix, in [0, 1].
    widen : float
        Multiplies every marginal standard deviation (1 = as estimated).

    Returns
    -------
    torch.Tensor, [P, P]
        Symmetric covariance (dtype and device of ``centred``). A parameter without spread keeps a
        correlation of 1 with itself and the floor as its standard deviation.
    """
    x = centred
    h, p = x.shape
    cov = x.T @ x / max(1, h - 1)
    sd_old = cov.diagonal().clamp_min(1e-30).sqrt()
    eye = torch.eye(p, dtype=x.dtype, device=x.device)
    if covariance == "diag":
        corr = eye
    elif covariance == "full":
        corr = cov / (sd_old[:, None] * sd_old[None, :])
        corr.diagonal().fill_(1.0)  # a parameter all samples agree on is still fully correlated with itself
        corr = (1.0 - shrink) * corr + shrink * eye
    else:
        raise ValueError(f"covariance must be 'full' or 'diag', got {covariance!r}")
    floor = torch.as_tensor(floor_sd, dtype=x.dtype, device=x.device)
    sd = torch.maximum(cov.diagonal(), floor ** 2).sqrt() * widen
    out = corr * sd[:, None] * sd[None, :]
    return 0.5 * (out + out.T)


def whitening(covariance: torch.Tensor) -> torch.Tensor:
    """``W`` [P, P] with ``W^T W = covariance^-1`` (the inverse Cholesky factor), float64.

    A prior residual ``W (x - mean)`` then has unit covariance: its squared norm is the Mahalanobis distance.
    ``covariance`` [P, P] must be symmetric positive definite (what :func:`shrunk_covariance` returns).
    """
    chol = torch.linalg.cholesky(covariance.double())
    eye = torch.eye(chol.shape[0], dtype=torch.float64, device=chol.device)
    return torch.linalg.solve_triangular(chol, eye, upper=False)


@dataclass
class GaussianPrior:
    """A prior ``x ~ N(mean, covariance)`` learned from other heliostats (the base of both plant priors).

    Attributes
    ----------
    names : tuple of str
        One per column of ``mean``.
    mean : torch.Tensor, [P] or [F, K]
        Physical units of the parameters.
    covariance : torch.Tensor, [N, N]
        Over ``mean.reshape(-1)`` (N = ``mean.numel()``), symmetric positive definite.
    heliostats : list of str
        The source heliostats (leakage checks compare them with the calibrated / reconstructed ones).
    settings : dict
        How it was estimated (JSON values).
    """

    names: tuple
    mean: torch.Tensor
    covariance: torch.Tensor
    heliostats: list = field(default_factory=list)
    settings: dict = field(default_factory=dict)

    @property
    def sigma(self) -> torch.Tensor:
        """Marginal standard deviation, same shape as ``mean`` ([P] or [F, K]; the parameters' units)."""
        return self.covariance.diagonal().clamp_min(0).sqrt().reshape(self.mean.shape)

    def whitening(self) -> torch.Tensor:
        """``W`` [N, N] with ``W^T W = covariance^-1`` (inverse Cholesky factor): prior residual ``W (x - mean)``."""
        return whitening(self.covariance)

    def state(self) -> dict:
        """The stored entry (``sigma`` kept for readers of a diagonal prior; ``settings`` as JSON text)."""
        return {"names": [str(n) for n in self.names], "mean": self.mean.detach().double().cpu(),
                "sigma": self.sigma.detach().double().cpu(), "covariance": self.covariance.detach().double().cpu(),
                "heliostats": [str(h) for h in self.heliostats], "settings": json.dumps(self.settings)}


def check_positive_definite(covariance: torch.Tensor, path, what: str, where: str) -> None:
    """One-line :class:`~heliotwin.errors.InputFileError` (``what`` covariance, at ``where`` of ``path``) unless
    ``covariance`` [N, N] has a Cholesky factor."""
    try:
        torch.linalg.cholesky(covariance)
    except RuntimeError:
        raise InputFileError(path, f"{what} covariance is not positive definite", field=where) from None
