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
