"""A plant-level prior on facet canting and low-order shape, learned across heliostats.

Heliostats of one plant share their facet design, their canting jig and their installation crew, so the
*low-order* shape of each facet -- its tilt (canting error) and its focus, astigmatism and twist -- repeats
from heliostat to heliostat much more than bumps and waves do. With one or two flux images a surface fit
cannot tell these apart from the sunshape or the camera; the shape the plant's other heliostats show can.

Low-order description (:func:`low_order_coefficients`). Per facet, with in-plane coordinates
``x = (2u - 1) |canting_e|``, ``y = (2v - 1) |canting_n|`` [m] (exact for the flat canted base, and displacements
act along the facet normal only) and the reference length ``L = sqrt(|canting_e| |canting_n|)`` (the facet's
half size), the least-squares fit of the height along the facet normal ``h(x, y)`` [m] in the basis

    1 (piston, fitted and dropped: no image sees it),  x,  y,  (x^2 + y^2) / (2L),  (x^2 - y^2) / (2L),  x y / L

gives K = 5 coefficients per facet, all in radians: the facet's slope along ``canting_e`` and ``canting_n``
(the canting error) and the slope at distance ``L`` from the centre due to focus, astigmatism and twist
(:data:`NAMES`). They are linear in the surface's normal heights (sampled by
:func:`heliotwin.surfaces.learning.normal_heights`), hence differentiable in its control points.

Prior (:class:`SurfacePrior`, :func:`surface_prior`): each heliostat's coefficients ``c`` [F, K] ~
N(mean, covariance) over the plant. Mean = average over the source heliostats; covariance [F K, F K] = their
sample covariance with the correlations shrunk towards the identity by ``shrink`` and the marginal sigmas
floored at :data:`FLOOR_RAD` (as :func:`heliotwin.calibrate.priors.plant_prior` does for kinematics; no
median / winsorising here: with 2-4 sources a median is no more robust than the mean).
At least :data:`MIN_SOURCES` = 2 source heliostats: the covariance is a spread *over heliostats*, and one
heliostat has none (its "prior" would be a copy of that heliostat's shape, held only by the floor).

Penalty (:func:`prior_penalty`): the squared Mahalanobis distance of the surface's coefficients from the
mean, divided by F K (so a surface 1 sigma off in every coefficient costs 1). Its weight is chosen by
:func:`heliotwin.surfaces.generalise.loo_select` from :data:`PRIOR_WEIGHT_GRID` (which includes 0); with
fewer than 3 training images (no held-out image) it is 0 and the prior enters through the start only
(:mod:`heliotwin.surfaces.generalise`, step 8).

No leakage: a heliostat being reconstructed never contributes to its own prior. :func:`prior_from_scenarios`
and :func:`check_leakage` refuse (one line) a prior whose sources include it.

Stored in a scenario under ``/learned/surface_prior`` (:meth:`SurfacePrior.state`): ``names``, ``mean``
[F, K], ``sigma`` [F, K], ``covariance`` [F K, F K], ``heliostats`` (its sources), ``settings`` (JSON str)
-- the layout of the kinematic ``/learned/calibration/prior``. It is a sibling of ``/learned/surfaces``,
not an entry in it, because ``/learned/surfaces`` is keyed by heliostat id and its readers list those keys
as learned heliostats.

Shapes: H source heliostats, F facets, K = 5 coefficients, (su, sv) samples per facet.
Units: metres; coefficients in radians.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass

import torch

from ..errors import HeliotwinError, InputFileError
from ..field.plant import Facets, Surfaces
from ..io.scenario import load_scenario
from ..shrinkage import GaussianPrior, check_positive_definite, shrunk_covariance
from .learning import LearnableSurface, heights_to_displacement, learnable_surfaces, normal_heights
from .state import KEY as SURFACES
from .state import PRIOR_KEY as KEY
from .state import learned_surface

__all__ = ["NAMES", "KEY", "MIN_SOURCES", "FLOOR_RAD", "SHRINK", "PRIOR_WEIGHT_GRID", "SurfacePrior",
           "low_order_coefficients", "low_order_heights", "low_order_start", "surface_prior", "prior_penalty",
           "prior_from_scenarios", "load_surface_prior", "check_leakage", "check_facets", "describe"]

#: Coefficient names, all [rad]: slope along canting_e / canting_n, focus, astigmatism, twist (at distance L).
NAMES = ("slope_e", "slope_n", "focus", "astigmatism", "twist")
#: Fewest source heliostats (a spread over heliostats needs two; see the module docstring).
MIN_SOURCES = 2
#: Smallest marginal prior sigma [rad]: a few sources can agree by accident; no heliostat is trusted to be
#: closer than 0.2 mrad (a fraction of the ~1 mrad slope error of glass facets) to the plant mean.
FLOOR_RAD = 2e-4
#: Weight of the identity in the correlation matrix: H sources estimate an F K x F K (20 x 20 for four facets)
#: correlation matrix of rank <= H - 1, so half of it is the identity. (Set by that argument, not validated:
#: the in-silico benchmark chooses the penalty weight by leave-one-out, not this.)
SHRINK = 0.5
#: Prior-penalty weights tried by leave-one-training-image-out (0 = no penalty; the penalty is a mean
#: Mahalanobis^2, so 0.01 per sigma^2 is comparable to a ~0.01 change of the data L1).
PRIOR_WEIGHT_GRID = (0.0, 0.01, 0.1)
#: Samples per facet side for the coefficients (a least-squares fit of 6 smooth modes: 16 x 16 is plenty).
SAMPLES = (16, 16)


def _design(facets: Facets, samples, dtype=torch.float64, device=None) -> torch.Tensor:
    """Basis ``[F, su sv, 1 + K]`` (piston first) on the cell midpoints of each facet."""
    le = facets.canting_e[0].to(dtype=dtype, device=device).norm(dim=-1)  # [F] half size along e [m]
    ln = facets.canting_n[0].to(dtype=dtype, device=device).norm(dim=-1)
    ref = (le * ln).sqrt()[:, None, None]
    su, sv = (int(s) for s in samples)
    u = (torch.arange(su, dtype=dtype, device=device) + 0.5) / su * 2 - 1
    v = (torch.arange(sv, dtype=dtype, device=device) + 0.5) / sv * 2 - 1
    x = (u[None, :, None] * le[:, None, None]).expand(-1, su, sv)
    y = (v[None, None, :] * ln[:, None, None]).expand(-1, su, sv)
    cols = (torch.ones_like(x), x, y, (x ** 2 + y ** 2) / (2 * ref), (x ** 2 - y ** 2) / (2 * ref), x * y / ref)
    return torch.stack(cols, -1).reshape(x.shape[0], su * sv, len(cols))


def low_order_coefficients(facets: Facets, control_points: torch.Tensor, degree, samples=SAMPLES,
                           weights=None) -> torch.Tensor:
    """Per-facet low-order coefficients (module docstring) of a surface, differentiable.

    Parameters
    ----------
    facets : Facets
        ``[1, F, 3]`` placement.
    control_points : torch.Tensor, [1, F, nu, nv, 3]
        Control net [m], heliostat frame.
    degree : (int, int)
    samples : (int, int)
        Normal-height samples per facet side.
    weights : torch.Tensor, [1, F, nu, nv], optional
        Rational weights.

    Returns
    -------
    torch.Tensor, [F, K]
        [rad], in the order of :data:`NAMES`; dtype of ``control_points``.
    """
    h, _ = normal_heights(facets, control_points, degree, samples, weights)  # [F, su, sv] [m]
    a = _design(facets, samples, h.dtype, h.device)
    coef = torch.linalg.pinv(a) @ h.reshape(h.shape[0], -1, 1)  # [F, 1 + K, 1]
    return coef[:, 1:, 0]


def low_order_heights(facets: Facets, coefficients: torch.Tensor, samples) -> torch.Tensor:
    """Heights along the facet normal [m], ``[F, su, sv]`` on cell midpoints, of coefficients ``[F, K]`` [rad]."""
    su, sv = (int(s) for s in samples)
    a = _design(facets, samples, coefficients.dtype, coefficients.device)[..., 1:]
    return (a @ coefficients[..., None])[..., 0].reshape(-1, su, sv)


def low_order_start(facets: Facets, coefficients: torch.Tensor, num_control_points, degree) -> torch.Tensor:
    """Control net ``[1, F, nu, nv, 3]`` of the facets shaped by ``coefficients`` [F, K] (degree >= 2 holds it).

    The counterpart of :func:`heliotwin.surfaces.generalise.focused_start` for a prior's mean shape.
    """
    # A tiny least-squares fit on the CPU (heights_to_displacement builds its bases there), then to the net.
    c = coefficients.detach().cpu().to(torch.float64)
    cpu = Facets(*(getattr(facets, a).detach().cpu().to(torch.float64)
                   for a in ("translation", "canting_e", "canting_n")))
    h = low_order_heights(cpu, c, (32, 32))
    d = heights_to_displacement(h, num_control_points, degree)
    base = LearnableSurface(facets, num_control_points, degree).base
    return learnable_surfaces(facets, base, d.to(base), degree).control_points.detach()


@dataclass
class SurfacePrior(GaussianPrior):
    """Plant-level prior on the facets' low-order shape: ``c`` [F, K] ~ N(``mean``, ``covariance``).

    Attributes
    ----------
    names : tuple of str, length K
    mean : torch.Tensor, [F, K]
        [rad].
    covariance : torch.Tensor, [F K, F K]
        [rad^2], over ``mean.reshape(-1)`` (facet-major), symmetric positive definite.
    heliostats : list of str
        The source heliostats (the leakage check compares them with the reconstructed one).
    settings : dict
        How it was estimated (JSON values).
    """

    @property
    def facet_count(self) -> int:
        """F, the number of facets the prior covers (rows of ``mean``)."""
        return int(self.mean.shape[0])

    def mahalanobis2(self, coefficients: torch.Tensor) -> torch.Tensor:
        """Mean squared whitened residual of coefficients ``[F, K]`` [rad] (scalar [1]; 1 = one sigma everywhere)."""
        r = (coefficients - self.mean.to(coefficients)).reshape(-1)
        z = self.whitening().to(r) @ r
        return z.pow(2).mean()

    def start(self, facets: Facets, num_control_points, degree) -> torch.Tensor:
        """Control net ``[1, F, nu, nv, 3]`` [m] of the mean shape on ``facets`` (``[1, F, 3]``), the fit's start
        candidate, with ``num_control_points`` (nu, nv) and NURBS ``degree`` (p, q)."""
        check_facets(self, facets)
        return low_order_start(facets, self.mean, num_control_points, degree)

    @classmethod
    def from_state(cls, state: dict, path="") -> SurfacePrior:
        """Read a stored prior; one-line :class:`InputFileError` when malformed."""
        where = f"/learned/{KEY}"
        try:
            names = tuple(str(n) for n in state["names"])
            mean = torch.as_tensor(state["mean"], dtype=torch.float64)
            cov = torch.as_tensor(state["covariance"], dtype=torch.float64)
            heliostats = [str(h) for h in state.get("heliostats", [])]
            settings = json.loads(state["settings"]) if isinstance(state.get("settings"), str) else {}
        except (KeyError, TypeError, ValueError):
            raise InputFileError(path, "malformed surface prior", field=where) from None
        k = len(names)
        n = mean.numel()
        ok = mean.dim() == 2 and mean.shape[1] == k and cov.shape == (n, n)
        if not ok or not bool(torch.isfinite(cov).all() & torch.isfinite(mean).all()):
            raise InputFileError(path, f"surface prior needs mean [F, {k}] and covariance [F {k}, F {k}] of finite "
                                 "numbers", field=where)
        check_positive_definite(cov, path, "surface prior", where)
        return cls(names, mean, cov, heliostats, settings)


def prior_penalty(prior: SurfacePrior, surf: Surfaces, facets: Facets, samples=SAMPLES) -> torch.Tensor:
    """Mean squared Mahalanobis distance (module docstring) of ``surf``'s low-order shape from ``prior``.

    Parameters
    ----------
    prior : SurfacePrior
    surf : Surfaces
        One heliostat, ``control_points`` [1, F, nu, nv, 3] [m].
    facets : Facets
        ``[1, F, 3]`` placement [m].
    samples : (int, int)
        Normal-height samples per facet side.

    Returns
    -------
    torch.Tensor, scalar
        [1]; differentiable in ``surf.control_points`` (and weights).
    """
    c = low_order_coefficients(facets, surf.control_points, (surf.degree_u, surf.degree_v), samples, surf.weights)
    return prior.mahalanobis2(c)


def surface_prior(coefficients: torch.Tensor, heliostats, *, shrink: float = SHRINK, floor: float = FLOOR_RAD,
                  covariance: str = "full") -> SurfacePrior:
    """Plant prior from the source heliostats' coefficients.

    Parameters
    ----------
    coefficients : torch.Tensor, [H, F, K]
        [rad], H >= :data:`MIN_SOURCES`.
    heliostats : list of str, length H
    shrink : float
        Weight of the identity in the correlation matrix, in [0, 1].
    floor : float
        Smallest marginal sigma [rad].
    covariance : str
        ``"full"`` (shrunk sample correlations) or ``"diag"``.

    Returns
    -------
    SurfacePrior
    """
    c = coefficients.detach().to(torch.float64)
    h = c.shape[0]
    if h < MIN_SOURCES:
        raise HeliotwinError(f"a surface prior needs >= {MIN_SOURCES} source heliostats (a spread over heliostats), "
                             f"got {h}")
    mean = c.mean(0)
    cov = shrunk_covariance((c - mean).reshape(h, -1), float(floor), covariance=covariance, shrink=shrink)
    settings = {"covariance": covariance, "shrink": float(shrink), "floor_rad": float(floor), "n_heliostats": h,
                "basis": "per-facet least squares of the normal height: slopes along canting_e/canting_n, "
                         "focus, astigmatism, twist (piston dropped) [rad]"}
    return SurfacePrior(tuple(NAMES), mean, 0.5 * (cov + cov.T), [str(i) for i in heliostats], settings)


def check_facets(prior: SurfacePrior, facets: Facets) -> None:
    """One line when the prior's facet count differs from the heliostat's."""
    nf = int(facets.translation.shape[1])
    if prior.facet_count != nf:
        raise HeliotwinError(f"the surface prior has {prior.facet_count} facets per heliostat, the heliostat has {nf}; "
                             "a prior must come from heliostats of the same design")


def check_leakage(prior: SurfacePrior, heliostat_id: str) -> None:
    """No leakage: one line when ``heliostat_id`` is among the prior's source heliostats."""
    if str(heliostat_id) in set(prior.heliostats):
        raise HeliotwinError(f"the surface prior was learned from heliostat {heliostat_id}, the one being "
                             "reconstructed; a prior must come from other heliostats")


def prior_from_scenarios(paths, exclude=(), **kwargs) -> SurfacePrior:
    """Surface prior from the learned surfaces (``/learned/surfaces/<HID>``) in scenario files.

    Every learned heliostat of every file is a source. One-line :class:`HeliotwinError` for: a missing file,
    a file without learned surfaces, a heliostat in two files, a source in ``exclude`` (leakage), different
    facet counts, fewer than :data:`MIN_SOURCES` sources. ``kwargs`` go to :func:`surface_prior`.
    """
    coefs, ids, where = [], [], {}
    exclude = {str(e) for e in exclude}
    for path in paths:
        if not os.path.isfile(path):
            raise HeliotwinError(f"{path}: no such scenario file (--surface-prior-from)")
        sc = load_scenario(path)
        hids = sorted(sc.learned.get(SURFACES) or {})
        if not hids:
            raise HeliotwinError(f"{path}: no learned surface in this scenario (run 'heliotwin reconstruct -o' first)")
        for hid in hids:
            if hid in where:
                raise HeliotwinError(f"heliostat {hid} has a learned surface in both {where[hid]} and {path}; "
                                     "give each source heliostat once")
            if hid in exclude:
                raise HeliotwinError(f"{path}: holds heliostat {hid}'s learned surface, the one being reconstructed; "
                                     "a prior must come from other heliostats (no leakage)")
            item = learned_surface(sc, hid)
            cp = item["surfaces"].control_points.to(torch.float64)
            fac = Facets(*(getattr(item["facets"], a).to(torch.float64)
                           for a in ("translation", "canting_e", "canting_n")))
            with torch.no_grad():
                c = low_order_coefficients(fac, cp, (item["surfaces"].degree_u, item["surfaces"].degree_v))
            if coefs and c.shape != coefs[0].shape:
                raise HeliotwinError(f"{path}: heliostat {hid} has {c.shape[0]} facets, {ids[0]} has "
                                     f"{coefs[0].shape[0]}; a surface prior needs heliostats of one design")
            coefs.append(c)
            ids.append(hid)
            where[hid] = os.fspath(path)
    if len(ids) < MIN_SOURCES:
        raise HeliotwinError(f"{', '.join(map(os.fspath, paths))}: {len(ids)} learned surface(s); a surface prior "
                             f"needs >= {MIN_SOURCES} source heliostats (a spread over heliostats)")
    prior = surface_prior(torch.stack(coefs), ids, **kwargs)
    prior.settings["sources"] = sorted(set(where.values()))
    return prior


def load_surface_prior(paths, heliostat_id: str | None = None) -> SurfacePrior:
    """``--surface-prior-from``: one scenario holding a stored prior (``/learned/surface_prior``) is read as it
    is; otherwise the prior is built from the learned surfaces of all ``paths``
    (:func:`prior_from_scenarios`). Either way the reconstructed ``heliostat_id`` must not be a source."""
    paths = [p for p in paths if str(p).strip()]
    if not paths:
        raise HeliotwinError("--surface-prior-from: give one or more scenario files (comma-separated)")
    if len(paths) == 1 and os.path.isfile(paths[0]):
        sc = load_scenario(paths[0])
        if sc.learned.get(KEY):
            prior = SurfacePrior.from_state(sc.learned[KEY], paths[0])
            if heliostat_id is not None:
                check_leakage(prior, heliostat_id)
            return prior
    return prior_from_scenarios(paths, exclude=() if heliostat_id is None else (heliostat_id,))


def _mrad(x: torch.Tensor) -> list:
    return [[round(1e3 * float(v), 4) for v in row] for row in x.reshape(-1, len(NAMES))]


def describe(prior: SurfacePrior) -> dict:
    """JSON summary: sources, mean and sigma [mrad] per facet and coefficient, settings."""
    return {"heliostats": list(prior.heliostats), "names": list(prior.names), "mean_mrad": _mrad(prior.mean),
            "sigma_mrad": _mrad(prior.sigma), "settings": dict(prior.settings)}
