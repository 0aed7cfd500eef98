"""Priors towards nominal and the field prior (empirical Bayes over the heliostats of a run).

With 10 records per heliostat an 8-parameter fit is barely determined: near-degenerate directions (axis-1
offset versus mirror tilt at small axis-2 angles, pylon tilt versus axis-2 offset) absorb noise and ruin
extrapolation to another season. Heliostats of one field share most of their systematic deviations
(same design, same installation crew); the *field prior* learns that from the run's own training records:

1. fit every heliostat alone with a loose prior (:data:`LOOSE_SIGMA`);
2. prior mean = median of the fits over heliostats, prior sigma = 1.4826 x their median absolute
   deviation (robust: one broken heliostat does not move it), floored by :data:`FLOOR_SIGMA`;
3. fit again with that prior.

Only training records enter (every heliostat's own ``--train`` records); with fewer than
:data:`MIN_HELIOSTATS` heliostats in the run the nominal prior is used. The choice of these constants was
made on validation splits that never touch the test records (chronological pseudo-splits inside the
training pools and the small heliostats that are not part of the benchmark).

Without a field prior the fits fall back to a *nominal* prior towards zero deviation. There are two, one
per kind of fit, and they differ on purpose: :data:`STONE8_SIGMA` for the 8-parameter Levenberg-Marquardt
fits (``lm``), :data:`CHAIN_SIGMA` for the gradient fits of the whole chain (``gradient``, ``images``).

The *plant prior* (:class:`PlantPrior`, :func:`plant_prior`) is the hierarchical version learned from
*other* heliostats with long histories instead of the run's own first records: mean + a full covariance
(shrunk towards its diagonal), so the near-degenerate pairs (axis-2 initial angle <-> first-joint tilt
north) are held to the combination the plant shows. It is built by :mod:`heliotwin.calibrate.protocol.archive` and used
by ``lm`` with ``--prior plant`` / ``--prior-from``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import torch

from ..errors import InputFileError
from ..shrinkage import GaussianPrior, check_positive_definite, shrunk_covariance
from .params import kinds

#: Nominal prior of the Stone/Jülich LM fits (physical units). Encoder offsets are unconstrained in practice
#: (the nominal error is tens of mrad); tilts of a few mrad and gear errors of ~1 % are typical. Chosen by
#: validation on early records (chronological pseudo-splits of the training pools, not the test sets).
STONE8_SIGMA = {"angle": 0.2, "tilt": 3e-3, "increment": 5e-3, "translation": 0.02, "actuator_length": 2e-3}

#: Nominal prior of the chain fits (``gradient``, ``images``; physical units) where no field prior is
#: available. In practice it acts on the parameters outside the Stone/Jülich 8 (which the methods pre-align
#: and usually cover with the field prior); it was never tuned together with :data:`STONE8_SIGMA`.
CHAIN_SIGMA = {"angle": 0.02, "tilt": 0.03, "increment": 5e-3, "translation": 0.02, "actuator_length": 2e-3}

#: Loose prior for the first pass (physical units): keeps degenerate directions finite, nothing more.
LOOSE_SIGMA = {"angle": 0.2, "tilt": 0.1, "increment": 0.02, "translation": 0.05, "actuator_length": 5e-3}

#: Smallest field-prior sigma per kind: the field spread estimated from a handful of heliostats can be
#: accidentally tiny; no heliostat is trusted to be closer than this to the field median.
FLOOR_SIGMA = {"angle": 1e-3, "tilt": 1e-3, "increment": 1e-3, "translation": 1e-3, "actuator_length": 1e-4}

#: Fewest heliostats with training records for a field prior (a median of 2 is not robust).
MIN_HELIOSTATS = 4


def sigma_vector(names, sigma: dict) -> torch.Tensor:
    """Per-parameter sigma [P] from a per-kind dict (missing kind = no prior = inf), float64.

    ``sigma`` maps a kind to its prior standard deviation in physical units: [rad] for angles and tilts, [m]
    for lengths, [1] for relative increments.
    """
    return torch.tensor([float(sigma.get(k, float("inf"))) for k in kinds(names)], dtype=torch.float64)


def field_prior(first_pass: torch.Tensor, usable: torch.Tensor, names, *, floor: dict | None = None,
                widen: float = 1.0) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Field prior from first-pass deviations.

    Parameters
    ----------
    first_pass : torch.Tensor, [H, P]
        Loosely regularised per-heliostat fits.
    usable : torch.Tensor, [H], bool
        Heliostats whose fit counts (enough training records, not flagged).
    names : sequence of str
    widen : float
        Multiplies the robust spread (1 = as estimated).

    Returns
    -------
    (mean [P], sigma [P]) or None when fewer than :data:`MIN_HELIOSTATS` are usable.
    """
    if int(usable.sum()) < MIN_HELIOSTATS:
        return None
    d = first_pass[usable].detach().double()
    mu = d.median(0).values
    mad = (d - mu).abs().median(0).values * 1.4826 * widen
    fl = sigma_vector(names, floor or FLOOR_SIGMA).to(mad.device)
    return mu, torch.maximum(mad, fl)


# --------------------------------------------------------------------------------------- plant prior
#: Fewest records of an archive heliostat for its fit to enter a plant prior (more than the 8 Stone/Jülich
#: parameters, so that its loose fit is determined by data rather than by the loose prior).
MIN_PRIOR_RECORDS = 9

#: Default settings of a plant prior (see :meth:`PriorArchive.prior`); :mod:`heliotwin.calibrate.protocol.selection`
#: chooses among alternatives by leave-heliostats-out cross-validation.
PLANT_PRIOR_DEFAULTS = {"covariance": "full", "shrink": 0.2, "widen": 1.0, "min_records": MIN_PRIOR_RECORDS}


@dataclass
class PlantPrior(GaussianPrior):
    """Hierarchical (plant-level) prior: a heliostat's deviations ~ N(``mean``, ``covariance``).

    Each heliostat's parameters are the plant mean plus an individual deviation; the covariance is the
    spread of those deviations over the plant's heliostats, estimated from heliostats with long histories.
    A full covariance holds the near-degenerate pairs (axis-2 initial angle <-> first-joint tilt north,
    which few records cannot tell apart) to the *combination* the plant shows, so a heliostat with 10
    records is not pushed far along that direction by noise.

    Attributes
    ----------
    names : tuple of str, length P
    mean : torch.Tensor, [P]
        Physical units (rad, m, relative for increments).
    covariance : torch.Tensor, [P, P]
        Symmetric positive definite.
    heliostats : list of str
        Heliostats the prior was learned from (the leakage check compares them with the calibrated ones).
    settings : dict
        How it was estimated (JSON values).
    """

    @classmethod
    def from_state(cls, state: dict, path="") -> PlantPrior:
        """Read a stored prior; one with only ``sigma`` (a diagonal field prior) becomes a diagonal covariance."""
        try:
            names = tuple(str(n) for n in state["names"])
            mean = torch.as_tensor(state["mean"], dtype=torch.float64).reshape(-1)
            if "covariance" in state:
                cov = torch.as_tensor(state["covariance"], dtype=torch.float64)
            else:
                cov = torch.diag(torch.as_tensor(state["sigma"], dtype=torch.float64).reshape(-1) ** 2)
            heliostats = [str(h) for h in state.get("heliostats", [])]
            settings = json.loads(state["settings"]) if isinstance(state.get("settings"), str) else {}
        except (KeyError, TypeError, ValueError):
            raise InputFileError(path, "malformed calibration prior", field="/learned/calibration/prior") from None
        p = len(names)
        finite = bool(torch.isfinite(cov).all() & torch.isfinite(mean).all())
        if mean.shape != (p,) or cov.shape != (p, p) or not finite:
            raise InputFileError(path, f"calibration prior needs mean [{p}] and covariance [{p}, {p}] of finite "
                                 "numbers", field="/learned/calibration/prior")
        check_positive_definite(cov, path, "calibration prior", "/learned/calibration/prior")
        return cls(names, mean, cov, heliostats, settings)


def winsorised(deviations: torch.Tensor, limit: float = 3.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-parameter median [P] of ``deviations`` [H, P] and the deviations clipped to ``limit`` robust sigmas
    (1.4826 MAD) around it [H, P]: what a plant prior's covariance is estimated from."""
    mu = deviations.median(0).values
    mad = ((deviations - mu).abs().median(0).values * 1.4826).clamp_min(1e-12)
    return mu, mu + ((deviations - mu) / mad).clamp(-limit, limit) * mad


def plant_prior(deviations: torch.Tensor, names, heliostats, *, covariance: str = "full", shrink: float = 0.2,
                widen: float = 1.0, floor: dict | None = None) -> PlantPrior:
    """Plant prior from per-heliostat deviations fitted on long histories.

    Parameters
    ----------
    deviations : torch.Tensor, [H, P]
        One fit per archive heliostat (physical units), H >= :data:`MIN_HELIOSTATS`.
    names : sequence of str, length P
    heliostats : list of str, length H
    covariance : str
        ``"full"`` (the plant's covariance, shrunk towards its diagonal by ``shrink``) or ``"diag"``.
    shrink : float
        Ledoit-Wolf-style weight of the diagonal, in [0, 1] (H ~ 10-30 heliostats estimate a P x P matrix).
    widen : float
        Multiplies the covariance's standard deviations (1 = as estimated).
    floor : dict, optional
        Smallest marginal sigma per kind (default :data:`FLOOR_SIGMA`).

    Returns
    -------
    PlantPrior

    Notes
    -----
    Robust: mean = per-parameter median; heliostats farther than 3 robust sigmas are clipped (winsorised)
    to 3 sigmas before the covariance, so one heliostat with a broken history cannot set it.
    """
    d = deviations.detach().double()
    if len(d) < MIN_HELIOSTATS:
        raise ValueError(f"a plant prior needs >= {MIN_HELIOSTATS} heliostats, got {len(d)}")
    mu, clipped = winsorised(d)
    cov = shrunk_covariance(clipped - clipped.mean(0), sigma_vector(names, floor or FLOOR_SIGMA),
                            covariance=covariance, shrink=shrink, widen=widen)
    settings = {"covariance": covariance, "shrink": float(shrink), "widen": float(widen), "n_heliostats": len(d)}
    return PlantPrior(tuple(names), mu, cov, list(heliostats), settings)
