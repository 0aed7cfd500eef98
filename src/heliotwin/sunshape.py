"""Sunshapes: angular distributions of the incoming sunlight, sampled as 2-D angular offsets.

A sample is a pair ``(alpha, beta)`` [rad] of small angular offsets in a ray's own orthonormal frame
``(u, v)`` (see :func:`heliotwin.geometry.orthonormal_frame`); the ray tracer perturbs a reflected
direction ``r`` to ``r + tan(alpha) u + tan(beta) v``. All sunshapes here are rotationally symmetric.

Sunshapes
---------
``gaussian``
    Independent normal offsets with standard deviation ``sigma`` per axis.
``pillbox``
    Uniform over the solar disc of half-angle ``radius`` (4.65 mrad): ``theta = radius sqrt(U)``.
``buie``
    Buie et al. (2003) profile with circumsolar ratio ``csr`` (chi). Radial intensity with ``theta`` in
    mrad: ``phi = cos(0.326 theta) / cos(0.308 theta)`` on the disc (``theta <= 4.65``) and
    ``exp(kappa) theta^gamma`` in the aureole (``4.65 < theta <= 43.6``), with
    ``kappa = 0.9 ln(13.5 chi) chi^-0.3`` and ``gamma = 2.2 ln(0.52 chi) chi^0.43 - 0.1``. The radius is
    drawn by inverse-CDF lookup of the tabulated density ``theta phi(theta)``, the azimuth uniformly.
``limb-darkened``
    The limb-darkened solar disc of DELSOL3 and SolarPILOT (their default sun), after Dellin (1979):
    ``phi = 1 - 0.5138 (theta / radius)^4`` on the disc of half-angle ``radius`` (4.65 mrad), 0 outside.
    The radius is drawn by inverting the closed-form radial CDF (Newton steps), the azimuth uniformly.

    T. A. Dellin, "An improved Hermite expansion calculation of the flux distribution from heliostats",
    Sandia National Laboratories, SAND79-8619 (1979); B. L. Kistler, "A user's manual for DELSOL3",
    SAND86-8018 (1986).

Slope error
-----------
A mirror normal tilted by a small angle deflects the reflected ray by twice that angle, so a slope error
with standard deviation ``sigma_s`` per axis adds an independent Gaussian of ``2 sigma_s`` per axis to
the reflected scatter (:func:`sample_with_slope_error`).

Randomness
----------
Every draw takes a :class:`torch.Generator`; nothing here touches the global RNG. ``stratified=True``
draws a Latin-hypercube design over the two uniform variables that generate a sample (lower variance,
still exactly distributed marginally).
"""
from __future__ import annotations

import math
from functools import lru_cache

import torch

from .errors import HeliotwinError

__all__ = [
    "SUNSHAPES",
    "SOLAR_DISC_RADIUS",
    "BUIE_AUREOLE_LIMIT",
    "sample",
    "sample_with_slope_error",
    "second_moment",
    "radial_profile",
    "angular_extent",
    "buie_profile",
    "buie_table",
    "buie_radial_cdf",
    "LIMB_DARKENING",
    "limb_darkened_profile",
    "limb_darkened_radial_cdf",
]

SUNSHAPES = ("gaussian", "pillbox", "buie", "limb-darkened")
SOLAR_DISC_RADIUS = 4.65e-3  #: half-angle of the solar disc [rad]
BUIE_AUREOLE_LIMIT = 43.6e-3  #: outer edge of the Buie aureole [rad]
LIMB_DARKENING = 0.5138  #: Dellin's (1979) limb-darkening coefficient: phi = 1 - 0.5138 (theta / radius)^4

_TABLE_DISC = 4001  #: knots of the Buie table on the disc
_TABLE_AUREOLE = 8001  #: knots of the Buie table in the aureole


def _check(sunshape: str) -> str:
    name = str(sunshape).lower()
    if name not in SUNSHAPES:
        raise HeliotwinError(f"unknown sunshape {sunshape!r}; expected one of {', '.join(SUNSHAPES)}")
    return name


def _buie_coefficients(csr: float) -> tuple[float, float]:
    if not 0.0 < csr < 1.0:
        raise HeliotwinError(f"Buie circumsolar ratio must be in (0, 1), got {csr!r}")
    kappa = 0.9 * math.log(13.5 * csr) * csr ** -0.3
    gamma = 2.2 * math.log(0.52 * csr) * csr ** 0.43 - 0.1
    return kappa, gamma


def buie_profile(theta: torch.Tensor, csr: float = 0.05) -> torch.Tensor:
    """Buie radial intensity ``phi(theta)`` (unnormalised, 1 at the disc centre).

    Parameters
    ----------
    theta : torch.Tensor, shape (...)
        Angle from the sun centre [rad].
    csr : float
        Circumsolar ratio chi [-].

    Returns
    -------
    torch.Tensor, shape (...)
        Relative radiance [-]; 0 beyond 43.6 mrad.
    """
    kappa, gamma = _buie_coefficients(csr)
    t = theta * 1e3  # mrad
    disc = torch.cos(0.326 * t) / torch.cos(0.308 * t)
    aureole = math.exp(kappa) * torch.clamp(t, min=1e-6) ** gamma
    out = torch.where(t <= SOLAR_DISC_RADIUS * 1e3, disc, aureole)
    return torch.where(t <= BUIE_AUREOLE_LIMIT * 1e3, out, torch.zeros_like(out))


@lru_cache(maxsize=16)
def _buie_table_cached(csr: float) -> tuple[torch.Tensor, torch.Tensor, float]:
    th_disc = torch.linspace(0.0, SOLAR_DISC_RADIUS, _TABLE_DISC, dtype=torch.float64)
    th_aur = torch.linspace(SOLAR_DISC_RADIUS, BUIE_AUREOLE_LIMIT, _TABLE_AUREOLE, dtype=torch.float64)
    # The profile jumps at the disc edge: evaluate each segment with its own formula (the knot at
    # 4.65 mrad appears twice, once per side, joined by a zero-width step).
    kappa, gamma = _buie_coefficients(csr)
    t1 = th_disc * 1e3
    f_disc = torch.cos(0.326 * t1) / torch.cos(0.308 * t1)
    f_aur = math.exp(kappa) * (th_aur * 1e3) ** gamma
    theta = torch.cat((th_disc, th_aur))
    density = theta * torch.cat((f_disc, f_aur))  # radial density ~ theta phi(theta)
    steps = 0.5 * (density[1:] + density[:-1]) * (theta[1:] - theta[:-1])
    cdf = torch.cat((torch.zeros(1, dtype=torch.float64), torch.cumsum(steps, 0)))
    total = float(cdf[-1])
    cdf = cdf / total
    # E[theta^2] with the same trapezoid rule on theta^3 phi(theta).
    m2 = theta * theta * density
    second = float((0.5 * (m2[1:] + m2[:-1]) * (theta[1:] - theta[:-1])).sum()) / total
    return theta, cdf, second


def buie_table(csr: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
    """Tabulated radial CDF of the Buie sunshape.

    Parameters
    ----------
    csr : float
        Circumsolar ratio chi [-].

    Returns
    -------
    theta : torch.Tensor, shape (T,), float64
        Knots [rad] from 0 to 43.6 mrad (the disc edge appears twice).
    cdf : torch.Tensor, shape (T,), float64
        ``P(radius <= theta)``, from 0 to 1.
    """
    theta, cdf, _ = _buie_table_cached(float(csr))
    return theta.clone(), cdf.clone()


def buie_radial_cdf(theta: torch.Tensor, csr: float = 0.05) -> torch.Tensor:
    """``P(radius <= theta)`` of the Buie sunshape, interpolated from the table.

    Parameters
    ----------
    theta : torch.Tensor, shape (...)
        [rad].
    csr : float
        Circumsolar ratio chi [-].

    Returns
    -------
    torch.Tensor, shape (...), float64
    """
    tab_t, tab_c, _ = _buie_table_cached(float(csr))
    th = torch.as_tensor(theta, dtype=torch.float64).clamp(0.0, BUIE_AUREOLE_LIMIT)
    i = torch.searchsorted(tab_t, th.reshape(-1), right=True).clamp(1, tab_t.numel() - 1)
    t0, t1, c0, c1 = tab_t[i - 1], tab_t[i], tab_c[i - 1], tab_c[i]
    span = torch.where(t1 > t0, t1 - t0, torch.ones_like(t0))
    w = torch.where(t1 > t0, (th.reshape(-1) - t0) / span, torch.ones_like(t0))
    return (c0 + w * (c1 - c0)).reshape(th.shape)


def _buie_inverse_cdf(u: torch.Tensor, csr: float) -> torch.Tensor:
    tab_t, tab_c, _ = _buie_table_cached(float(csr))
    tab_t, tab_c = tab_t.to(u.device), tab_c.to(u.device)
    i = torch.searchsorted(tab_c, u, right=True).clamp(1, tab_c.numel() - 1)
    c0, c1, t0, t1 = tab_c[i - 1], tab_c[i], tab_t[i - 1], tab_t[i]
    dc = c1 - c0
    w = torch.where(dc > 0, (u - c0) / torch.where(dc > 0, dc, torch.ones_like(dc)), torch.zeros_like(dc))
    return t0 + w * (t1 - t0)


def limb_darkened_profile(theta: torch.Tensor, radius: float = SOLAR_DISC_RADIUS) -> torch.Tensor:
    """Limb-darkened radiance ``phi(theta) = 1 - 0.5138 (theta / radius)^4`` on the disc (Dellin 1979).

    Parameters
    ----------
    theta : torch.Tensor, shape (...)
        Angle from the sun centre [rad].
    radius : float
        Half-angle of the solar disc [rad] (SolarPILOT: 4.65 mrad).

    Returns
    -------
    torch.Tensor, shape (...)
        Relative radiance [-] (1 at the centre, 0.4862 at the limb, 0 outside the disc).
    """
    x = theta / float(radius)
    return torch.where(x <= 1.0, 1.0 - LIMB_DARKENING * x ** 4, torch.zeros_like(x))


def _limb_darkened_cdf_x(x: torch.Tensor) -> torch.Tensor:
    """Radial CDF in ``x = theta / radius`` (x in [0, 1]): integral of ``x (1 - a x^4)``, normalised."""
    a = LIMB_DARKENING
    return (0.5 * x * x - a * x ** 6 / 6.0) / (0.5 - a / 6.0)


def limb_darkened_radial_cdf(theta: torch.Tensor, radius: float = SOLAR_DISC_RADIUS) -> torch.Tensor:
    """``P(radius of a sample <= theta)`` for the limb-darkened sun (closed form).

    Parameters
    ----------
    theta : torch.Tensor, shape (...)
        [rad].
    radius : float
        Disc half-angle [rad].

    Returns
    -------
    torch.Tensor, shape (...)
        In [0, 1]: ``(x^2 / 2 - 0.5138 x^6 / 6) / (1/2 - 0.5138 / 6)`` with ``x = min(theta / radius, 1)``.
    """
    x = (torch.as_tensor(theta, dtype=torch.float64) / float(radius)).clamp(0.0, 1.0)
    return _limb_darkened_cdf_x(x)


def _limb_darkened_inverse_cdf(u: torch.Tensor) -> torch.Tensor:
    """``x = theta / radius`` with CDF(x) = u, by Newton steps from the uniform-disc guess ``sqrt(u)``."""
    a = LIMB_DARKENING
    norm = 0.5 - a / 6.0
    x = torch.sqrt(u).clamp(1e-6, 1.0)
    for _ in range(30):  # the CDF is smooth and monotone on [0, 1]; converges to round-off in < 10 steps
        f = _limb_darkened_cdf_x(x) - u
        x = (x - f * norm / (x * (1.0 - a * x ** 4))).clamp(1e-9, 1.0)
    return torch.where(u > 0, x, torch.zeros_like(x))


def _uniform_pair(n: int, generator: torch.Generator, stratified: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Two uniform [0, 1) vectors of length n (float64), optionally a Latin hypercube design."""
    dev = generator.device
    u = torch.rand(2, n, generator=generator, dtype=torch.float64, device=dev)
    if stratified and n > 1:
        p1 = torch.randperm(n, generator=generator, device=dev).to(torch.float64)
        p2 = torch.randperm(n, generator=generator, device=dev).to(torch.float64)
        u = torch.stack(((p1 + u[0]) / n, (p2 + u[1]) / n))
    return u[0], u[1]


def sample(sunshape: str, n: int, generator: torch.Generator, *, sigma: float = 2.51e-3,
           radius: float = SOLAR_DISC_RADIUS, csr: float = 0.05, dtype: torch.dtype = torch.float32,
           device=None, stratified: bool = False) -> torch.Tensor:
    """Draw angular offsets from a sunshape.

    Parameters
    ----------
    sunshape : {"gaussian", "pillbox", "buie", "limb-darkened"}
    n : int
        Number of samples.
    generator : torch.Generator
        Source of randomness (its device is where the draw happens).
    sigma : float
        Gaussian standard deviation per axis [rad].
    radius : float
        Pillbox / limb-darkened disc half-angle [rad].
    csr : float
        Buie circumsolar ratio [-].
    dtype, device
        Of the result (default float32 on the generator's device).
    stratified : bool
        Latin-hypercube stratification of the underlying uniforms.

    Returns
    -------
    torch.Tensor, shape (n, 2)
        Offsets ``(alpha, beta)`` [rad] along the ray frame's ``u`` and ``v``.
    """
    name = _check(sunshape)
    if generator is None:
        raise HeliotwinError("sunshape sampling needs an explicit torch.Generator")
    n = int(n)
    u1, u2 = _uniform_pair(n, generator, stratified)
    if name == "gaussian":
        tiny = 1e-15
        g1 = torch.special.ndtri(u1.clamp(tiny, 1.0 - tiny))
        g2 = torch.special.ndtri(u2.clamp(tiny, 1.0 - tiny))
        out = torch.stack((g1, g2), dim=-1) * float(sigma)
    else:
        if name == "pillbox":
            r = float(radius) * torch.sqrt(u1)
        elif name == "limb-darkened":
            r = float(radius) * _limb_darkened_inverse_cdf(u1)
        else:
            r = _buie_inverse_cdf(u1, float(csr))
        phi = 2.0 * math.pi * u2
        out = torch.stack((r * torch.cos(phi), r * torch.sin(phi)), dim=-1)
    return out.to(dtype=dtype, device=device if device is not None else out.device)


def sample_with_slope_error(sunshape: str, n: int, generator: torch.Generator, *, slope_error: float = 0.0,
                            sigma: float = 2.51e-3, radius: float = SOLAR_DISC_RADIUS, csr: float = 0.05,
                            dtype: torch.dtype = torch.float32, device=None,
                            stratified: bool = False) -> torch.Tensor:
    """Sunshape offsets plus the mirror slope-error scatter of the reflected ray.

    Parameters
    ----------
    sunshape, n, generator, sigma, radius, csr, dtype, device, stratified
        As in :func:`sample`.
    slope_error : float
        Mirror slope error, standard deviation per axis [rad]; the reflected ray gets an independent
        Gaussian of ``2 * slope_error`` per axis added.

    Returns
    -------
    torch.Tensor, shape (n, 2)
        Offsets [rad] in the reflected ray's frame.
    """
    out = sample(sunshape, n, generator, sigma=sigma, radius=radius, csr=csr, dtype=torch.float64,
                 stratified=stratified)
    if slope_error > 0.0:
        out = out + (2.0 * float(slope_error)) * torch.randn(out.shape, generator=generator, dtype=torch.float64,
                                                             device=out.device)
    return out.to(dtype=dtype, device=device if device is not None else out.device)


def second_moment(sunshape: str, *, sigma: float = 2.51e-3, radius: float = SOLAR_DISC_RADIUS,
                  csr: float = 0.05, slope_error: float = 0.0) -> float:
    """Variance per axis of a sunshape's angular offsets (the Gaussian-equivalent ``sigma^2``).

    Parameters
    ----------
    sunshape : {"gaussian", "pillbox", "buie", "limb-darkened"}
    sigma, radius, csr : float
        As in :func:`sample` ([rad], [rad], [-]).
    slope_error : float
        Mirror slope error per axis [rad]; adds ``(2 slope_error)^2``.

    Returns
    -------
    float
        ``E[alpha^2] = E[theta^2] / 2`` [rad^2]: ``sigma^2`` (gaussian), ``radius^2 / 4`` (pillbox), the
        tabulated value (buie), ``radius^2 (1/4 - a/8) / (1/2 - a/6) / 2`` (limb-darkened, a = 0.5138),
        plus the slope-error term.
    """
    name = _check(sunshape)
    if name == "gaussian":
        var = float(sigma) ** 2
    elif name == "pillbox":
        var = float(radius) ** 2 / 4.0
    elif name == "limb-darkened":
        a = LIMB_DARKENING  # E[x^2] = (1/4 - a/8) / (1/2 - a/6) for the radial density x (1 - a x^4)
        var = float(radius) ** 2 * (0.25 - a / 8.0) / (0.5 - a / 6.0) / 2.0
    else:
        var = _buie_table_cached(float(csr))[2] / 2.0
    return var + (2.0 * float(slope_error)) ** 2


def radial_profile(sunshape: str, theta: torch.Tensor, *, sigma: float = 2.51e-3, radius: float = SOLAR_DISC_RADIUS,
                   csr: float = 0.05) -> torch.Tensor:
    """Unnormalised radiance of a sunshape at angle ``theta`` from the sun centre (tabulated kernels).

    Parameters
    ----------
    sunshape : {"gaussian", "pillbox", "buie", "limb-darkened"}
    theta : torch.Tensor, shape (...)
        Angle from the sun centre [rad].
    sigma, radius, csr : float
        As in :func:`sample` ([rad], [rad], [-]).

    Returns
    -------
    torch.Tensor, shape (...)
        Relative radiance [-] (1 at the centre): ``exp(-theta^2 / 2 sigma^2)``, the disc indicator, or
        :func:`buie_profile`. Callers normalise the tabulated density themselves.
    """
    name = _check(sunshape)
    if name == "buie":
        return buie_profile(theta, float(csr))
    if name == "pillbox":
        return (theta <= float(radius)).to(theta.dtype)
    if name == "limb-darkened":
        return limb_darkened_profile(theta, float(radius))
    return torch.exp(-0.5 * theta * theta / (float(sigma) * float(sigma)))


def angular_extent(sunshape: str, *, sigma: float = 2.51e-3, radius: float = SOLAR_DISC_RADIUS) -> float:
    """Half-angle [rad] beyond which :func:`radial_profile` is (numerically) zero.

    ``4.5 sigma`` (gaussian), ``radius`` (pillbox, limb-darkened), the outer edge of the aureole (buie).
    """
    name = _check(sunshape)
    if name == "buie":
        return BUIE_AUREOLE_LIMIT
    if name in ("pillbox", "limb-darkened"):
        return float(radius)
    return 4.5 * float(sigma)
