"""The shrunk covariance both plant priors use (kinematic deviations, facet shape)."""
import pytest
import torch

from heliotwin.shrinkage import shrunk_covariance


def _samples(h=12, seed=0):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(h, 3, generator=g, dtype=torch.float64)
    x = torch.stack([z[:, 0], 0.9 * z[:, 0] + 0.1 * z[:, 1], 2.0 * z[:, 2]], 1)  # 0 and 1 strongly coupled
    return x - x.mean(0)


def test_shrinkage_between_the_sample_covariance_and_its_diagonal():
    x = _samples()
    sample = x.T @ x / (len(x) - 1)
    tiny = torch.full((3,), 1e-9, dtype=torch.float64)
    assert torch.allclose(shrunk_covariance(x, tiny, shrink=0.0), sample, atol=1e-12)
    assert torch.allclose(shrunk_covariance(x, tiny, shrink=1.0), torch.diag(sample.diagonal()), atol=1e-12)
    assert torch.allclose(shrunk_covariance(x, tiny, covariance="diag"), torch.diag(sample.diagonal()), atol=1e-12)
    half = shrunk_covariance(x, tiny, shrink=0.5)
    corr = half[0, 1] / (half[0, 0] * half[1, 1]).sqrt()
    sample_corr = sample[0, 1] / (sample[0, 0] * sample[1, 1]).sqrt()
    assert float(corr) == pytest.approx(0.5 * float(sample_corr), rel=1e-9)
    assert torch.linalg.eigvalsh(half).min() > 0  # a shrunk correlation is positive definite
    # widen scales every standard deviation
    assert torch.allclose(shrunk_covariance(x, tiny, shrink=0.5, widen=2.0), 4.0 * half, atol=1e-12)


def test_a_parameter_without_spread_keeps_its_floor_not_a_fraction_of_it():
    x = _samples()
    x[:, 2] = 0.0  # every source agrees on parameter 2
    floor = torch.tensor([1e-9, 1e-9, 0.3], dtype=torch.float64)
    cov = shrunk_covariance(x, floor, shrink=0.2)
    assert float(cov[2, 2]) == pytest.approx(0.09, rel=1e-12)
    assert float(cov[0, 2]) == 0.0
    with pytest.raises(ValueError, match="covariance must be"):
        shrunk_covariance(x, floor, covariance="nope")


def test_whitening_gives_unit_covariance():
    from heliotwin.shrinkage import whitening

    cov = shrunk_covariance(_samples(), torch.full((3,), 1e-9, dtype=torch.float64), shrink=0.3)
    w = whitening(cov)
    assert torch.allclose(w @ cov @ w.T, torch.eye(3, dtype=torch.float64), atol=1e-10)
