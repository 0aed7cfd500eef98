"""Tests of heliotwin.sunshape: samplers against their distributions (KS tests), moments, determinism."""
import math

import numpy as np
import pytest
import torch
from scipy import integrate, stats

from heliotwin import sunshape
from heliotwin.errors import HeliotwinError

N = 40000
ALPHA = 1e-3  # KS significance; the seeds are fixed, so the tests are deterministic


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


@pytest.mark.parametrize("stratified", [False, True])
def test_gaussian_ks(stratified):
    s = sunshape.sample("gaussian", N, _gen(1), sigma=2.5e-3, dtype=torch.float64, stratified=stratified)
    assert s.shape == (N, 2) and s.dtype == torch.float64
    for axis in range(2):
        assert stats.kstest(s[:, axis].numpy() / 2.5e-3, "norm").pvalue > ALPHA
    # the two axes are independent: the radius^2 / sigma^2 is chi^2 with 2 dof
    r2 = (s.square().sum(1) / 2.5e-3 ** 2).numpy()
    assert stats.kstest(r2, stats.chi2(2).cdf).pvalue > ALPHA


def test_gaussian_ks_detects_wrong_sigma():
    s = sunshape.sample("gaussian", N, _gen(1), sigma=2.6e-3, dtype=torch.float64)
    assert stats.kstest(s[:, 0].numpy() / 2.5e-3, "norm").pvalue < ALPHA


@pytest.mark.parametrize("stratified", [False, True])
def test_pillbox_radius_squared_uniform(stratified):
    R = 4.65e-3
    s = sunshape.sample("pillbox", N, _gen(2), radius=R, dtype=torch.float64, stratified=stratified)
    r2 = s.square().sum(1) / R ** 2
    assert float(r2.max()) <= 1.0 + 1e-12
    assert stats.kstest(r2.numpy(), "uniform").pvalue > ALPHA
    phi = (torch.atan2(s[:, 1], s[:, 0]) / (2 * math.pi)) % 1.0
    assert stats.kstest(phi.numpy(), "uniform").pvalue > ALPHA


def _buie_cdf_quad(theta, csr):
    """Independent reference: adaptive quadrature of theta * phi(theta)."""
    kappa = 0.9 * math.log(13.5 * csr) * csr ** -0.3
    gamma = 2.2 * math.log(0.52 * csr) * csr ** 0.43 - 0.1

    def f(t):  # t in mrad
        if t <= 4.65:
            return t * math.cos(0.326 * t) / math.cos(0.308 * t)
        return t * math.exp(kappa) * t ** gamma

    def cum(t):
        a = integrate.quad(f, 0, min(t, 4.65), epsabs=0, epsrel=1e-11)[0]
        if t > 4.65:
            a += integrate.quad(f, 4.65, t, epsabs=0, epsrel=1e-11, limit=200)[0]
        return a

    return cum(theta * 1e3) / cum(43.6)


@pytest.mark.parametrize("csr", [0.02, 0.05, 0.2])
def test_buie_table_matches_quadrature(csr):
    for theta in (1e-3, 3e-3, 4.65e-3, 6e-3, 15e-3, 40e-3):
        ref = _buie_cdf_quad(theta, csr)
        assert float(sunshape.buie_radial_cdf(torch.tensor(theta), csr)) == pytest.approx(ref, abs=2e-5)


@pytest.mark.parametrize("csr,stratified", [(0.05, False), (0.2, True)])
def test_buie_ks(csr, stratified):
    s = sunshape.sample("buie", N, _gen(3), csr=csr, dtype=torch.float64, stratified=stratified)
    r = s.norm(dim=1)
    assert float(r.max()) <= sunshape.BUIE_AUREOLE_LIMIT + 1e-12
    res = stats.kstest(r.numpy(), lambda x: sunshape.buie_radial_cdf(torch.as_tensor(x), csr).numpy())
    assert res.pvalue > ALPHA
    # the aureole holds roughly the circumsolar ratio of the power
    frac = float((r > sunshape.SOLAR_DISC_RADIUS).double().mean())
    assert frac == pytest.approx(1 - float(sunshape.buie_radial_cdf(torch.tensor(4.65e-3), csr)), abs=0.01)
    # a different CSR is detected
    wrong = stats.kstest(r.numpy(), lambda x: sunshape.buie_radial_cdf(torch.as_tensor(x), csr * 2).numpy())
    assert wrong.pvalue < ALPHA


@pytest.mark.parametrize("name,kw", [("gaussian", {"sigma": 2e-3}), ("pillbox", {"radius": 4.65e-3}),
                                     ("buie", {"csr": 0.1})])
def test_second_moment_matches_samples(name, kw):
    s = sunshape.sample_with_slope_error(name, 200000, _gen(4), slope_error=1e-3, dtype=torch.float64, **kw)
    var = float(s.square().mean())
    assert var == pytest.approx(sunshape.second_moment(name, slope_error=1e-3, **kw), rel=0.02)
    assert sunshape.second_moment("pillbox", radius=4e-3) == pytest.approx(4e-6)
    assert sunshape.second_moment("gaussian", sigma=3e-3, slope_error=1e-3) == pytest.approx(9e-6 + 4e-6)


def test_slope_error_doubles():
    s0 = sunshape.sample_with_slope_error("gaussian", 100000, _gen(5), sigma=1e-9, slope_error=2e-3,
                                          dtype=torch.float64)
    assert float(s0.std(0).mean()) == pytest.approx(4e-3, rel=0.02)


def test_stratification_reduces_variance():
    def mean_r(seed, strat):
        s = sunshape.sample("pillbox", 256, _gen(seed), dtype=torch.float64, stratified=strat)
        return float(s.norm(dim=1).mean())

    plain = np.std([mean_r(i, False) for i in range(60)])
    strat = np.std([mean_r(i, True) for i in range(60)])
    assert strat < 0.3 * plain


def test_determinism_and_dtypes():
    a = sunshape.sample("buie", 1000, _gen(7))
    b = sunshape.sample("buie", 1000, _gen(7))
    c = sunshape.sample("buie", 1000, _gen(8))
    assert a.dtype == torch.float32
    assert torch.equal(a, b) and not torch.equal(a, c)
    # the global RNG is not touched
    torch.manual_seed(0)
    x = torch.rand(1)
    torch.manual_seed(0)
    sunshape.sample_with_slope_error("gaussian", 10, _gen(1), slope_error=1e-3)
    assert torch.equal(torch.rand(1), x)


def test_errors():
    with pytest.raises(HeliotwinError, match="unknown sunshape"):
        sunshape.sample("tophat", 10, _gen())
    with pytest.raises(HeliotwinError):
        sunshape.second_moment("buie", csr=1.5)
    with pytest.raises(HeliotwinError):
        sunshape.sample("gaussian", 10, None)
