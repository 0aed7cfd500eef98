"""The predictive interval of many records: per-chunk factorisation equals the whole one (the result does not
depend on how the records are chunked), and the record inputs hold no zero walk copy."""
from __future__ import annotations

import torch

import heliotwin.calibrate.uncertainty as uncertainty
from heliotwin.calibrate.uncertainty import predictive


def _case(r=37, p=6, seed=2):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(r, p, p, generator=g, dtype=torch.float64) * 1e-3
    cov = a @ a.transpose(1, 2) + 1e-8 * torch.eye(p, dtype=torch.float64)
    jac = torch.randn(r, 3, p, generator=g, dtype=torch.float64)
    normal = torch.nn.functional.normalize(torch.randn(r, 3, generator=g, dtype=torch.float64), dim=1)
    noise = 1e-4 * (1 + torch.rand(r, generator=g, dtype=torch.float64))
    return jac, normal, cov, noise


def test_predictive_independent_of_chunking(monkeypatch):
    jac, normal, cov, noise = _case()
    whole = predictive(jac, normal, cov, noise, drift=2e-4, samples=500, generator=torch.Generator().manual_seed(1))
    monkeypatch.setattr(uncertainty, "PREDICTIVE_CHUNK", 500 * 4)  # 4 records per chunk, last one partial
    chunked = predictive(jac, normal, cov, noise, drift=2e-4, samples=500,
                         generator=torch.Generator().manual_seed(1))
    for k in ("expected", "median", "upper"):
        torch.testing.assert_close(chunked[k], whole[k], rtol=1e-12, atol=0)
    # physics: the expected pointing error exceeds the noise's own (parameters add variance), upper > median
    assert bool((whole["upper"] > whole["median"]).all())
    assert bool((whole["expected"] > noise).all())


def _explicit(jac, normal, cov, noise, drift, samples, seed):
    """The predictive samples written out term by term (J L xi, then the noise projected on the mirror plane)."""
    g = torch.Generator().manual_seed(seed)
    p = cov.shape[-1]
    xi = torch.randn(samples, p, generator=g, dtype=torch.float64)
    eta = torch.randn(samples, 3, generator=g, dtype=torch.float64)
    sd = (noise ** 2 + drift ** 2).sqrt()
    chol = torch.linalg.cholesky(cov + 1e-18 * torch.eye(p, dtype=torch.float64))
    e = (jac @ chol) @ xi.T
    e = e + sd[:, None, None] * (eta.T[None] - normal[:, :, None] * (normal @ eta.T)[:, None, :])
    e = (e * e).sum(1).sqrt()
    return e.mean(1), torch.quantile(e, 0.5, dim=1), torch.quantile(e, 0.9, dim=1)


def test_predictive_equals_the_term_by_term_samples():
    jac, normal, cov, noise = _case(r=23, p=8, seed=4)
    got = predictive(jac, normal, cov, noise, drift=3e-4, samples=800, generator=torch.Generator().manual_seed(6))
    mean, median, upper = _explicit(jac, normal, cov, noise, 3e-4, 800, 6)
    torch.testing.assert_close(got["expected"], mean, rtol=1e-12, atol=0)
    torch.testing.assert_close(got["median"], median, rtol=1e-12, atol=0)
    torch.testing.assert_close(got["upper"], upper, rtol=1e-12, atol=0)
