"""The limb-darkened sun (Dellin 1979, SolarPILOT's default): sampler against its pdf, moments, dispatch."""
import math

import pytest
import torch
from scipy import integrate, stats

from heliotwin import sunshape

N = 40000
ALPHA = 1e-3  # KS significance; seeds are fixed, so the tests are deterministic
R = 4.65e-3


def _cdf_quad(theta):
    """Independent reference: quadrature of the radial density theta (1 - 0.5138 (theta/R)^4)."""
    def f(t):
        return t * (1.0 - 0.5138 * (t / R) ** 4)
    return integrate.quad(f, 0.0, min(theta, R), epsabs=0, epsrel=1e-12)[0] / integrate.quad(f, 0.0, R)[0]


def test_profile_matches_dellin():
    th = torch.tensor([0.0, 0.5 * R, R, 1.01 * R], dtype=torch.float64)
    phi = sunshape.radial_profile("limb-darkened", th, radius=R)
    expect = [1.0, 1.0 - 0.5138 / 16, 1.0 - 0.5138, 0.0]
    assert phi.tolist() == pytest.approx(expect, abs=1e-12)
    assert sunshape.angular_extent("limb-darkened", radius=R) == R


def test_cdf_matches_quadrature():
    for theta in (0.5e-3, 2e-3, 3.5e-3, 4.6e-3):
        got = float(sunshape.limb_darkened_radial_cdf(torch.tensor(theta, dtype=torch.float64), R))
        assert got == pytest.approx(_cdf_quad(theta), abs=1e-10)


@pytest.mark.parametrize("stratified", [False, True])
def test_sampler_ks_against_pdf(stratified):
    s = sunshape.sample("limb-darkened", N, torch.Generator().manual_seed(5), radius=R, dtype=torch.float64,
                        stratified=stratified)
    r = s.norm(dim=1)
    assert float(r.max()) <= R * (1 + 1e-12)
    assert stats.kstest(r.numpy(), lambda x: sunshape.limb_darkened_radial_cdf(torch.as_tensor(x), R).numpy()
                        ).pvalue > ALPHA
    phi = (torch.atan2(s[:, 1], s[:, 0]) / (2 * math.pi)) % 1.0
    assert stats.kstest(phi.numpy(), "uniform").pvalue > ALPHA


def test_ks_detects_a_uniform_disc():
    """The test has power: a pillbox of the same radius is rejected against the limb-darkened CDF."""
    s = sunshape.sample("pillbox", N, torch.Generator().manual_seed(5), radius=R, dtype=torch.float64)
    res = stats.kstest(s.norm(dim=1).numpy(),
                       lambda x: sunshape.limb_darkened_radial_cdf(torch.as_tensor(x), R).numpy())
    assert res.pvalue < ALPHA


def test_second_moment_closed_form_and_sampled():
    var = sunshape.second_moment("limb-darkened", radius=R)
    ref = integrate.quad(lambda t: t ** 3 * (1 - 0.5138 * (t / R) ** 4), 0, R)[0] / \
        integrate.quad(lambda t: t * (1 - 0.5138 * (t / R) ** 4), 0, R)[0] / 2
    assert var == pytest.approx(ref, rel=1e-10)
    assert var < R ** 2 / 4  # darker limb: narrower than the uniform disc
    s = sunshape.sample("limb-darkened", N, torch.Generator().manual_seed(7), radius=R, dtype=torch.float64)
    assert float(s.square().mean()) == pytest.approx(var, rel=0.02)
    assert sunshape.second_moment("limb-darkened", radius=R, slope_error=1e-3) == pytest.approx(var + 4e-6)
