"""Scale-invariant image losses and surface regularisers (functional).

Image losses
------------
PAINT flux PNGs are max-normalised (relative), so predicted and measured images are compared after
normalising each to unit *sum* (:func:`normalize`): the losses then measure the spot's shape only, never its
absolute power. ``l1 = sum |p - m|`` (in [0, 2]), ``l2 = R^2 sum (p - m)^2`` (the ``R^2`` makes it
resolution-independent for a fixed window), ``kl = sum m log(m / p)``.

Regularisers
------------
Ridge ``mean(d^2)``, lasso ``mean(|d|)`` and Laplacian smoothness ``mean((Lap d)^2)`` of the displacement
field on each facet's control grid, with ``d`` in millimetres. Their weights are FIXED numbers: they are
*added* to the data loss and never divided by it (a ratio like ``reg / data`` rescaled every step would make
the total's gradient w.r.t. the regulariser vanish where it is needed).

Shapes: images ``[B, rows, cols]``; displacements ``[..., F, nu, nv]``.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ..errors import HeliotwinError
from ..io.images import subtract_background
from ..raytrace.flux import normalized_l1

__all__ = ["normalize", "image_loss", "l1", "l2", "kl", "ridge", "lasso", "laplacian", "laplacian_per_row",
           "IMAGE_LOSSES", "threshold_background"]

_EPS = 1e-12


def normalize(images: torch.Tensor) -> torch.Tensor:
    """Each image divided by its sum, ``[B, rows, cols]`` -> same (an empty image stays 0)."""
    s = images.sum((-2, -1), keepdim=True)
    return images / s.clamp_min(_EPS)


def l1(pred: torch.Tensor, meas: torch.Tensor) -> torch.Tensor:
    """``sum |p - m|`` of unit-sum images, per image ``[B]`` (0 identical, 2 disjoint)."""
    return normalized_l1(pred, meas, eps=_EPS)


def l2(pred: torch.Tensor, meas: torch.Tensor) -> torch.Tensor:
    """``R C sum (p - m)^2`` of unit-sum images, per image ``[B]`` (pixel-count scaled)."""
    n = pred.shape[-1] * pred.shape[-2]
    return n * (normalize(pred) - normalize(meas)).pow(2).sum((-2, -1))


def kl(pred: torch.Tensor, meas: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """``KL(m || p) = sum m log(m / p)`` of unit-sum images, per image ``[B]``.

    ``eps`` (relative to a uniform pixel's share) keeps ``log p`` finite where the prediction is dark.
    """
    n = pred.shape[-1] * pred.shape[-2]
    p = normalize(pred) + eps / n
    m = normalize(meas)
    return (m * (torch.log(m + eps / n) - torch.log(p))).sum((-2, -1))


IMAGE_LOSSES = {"l1": l1, "l2": l2, "kl": kl}


def image_loss(name: str, pred: torch.Tensor, meas: torch.Tensor) -> torch.Tensor:
    """Mean over images of the named loss (``l1``, ``l2``, ``kl``): scalar, of ``[B, R, C]`` images (any scale;
    normalised to unit sum inside each loss)."""
    try:
        fn = IMAGE_LOSSES[name.lower()]
    except KeyError:
        raise HeliotwinError(f"unknown image loss {name!r}; expected one of {', '.join(IMAGE_LOSSES)}") from None
    return fn(pred, meas).mean()


def ridge(d_mm: torch.Tensor) -> torch.Tensor:
    """Mean squared displacement [mm^2], a scalar ``()``, of displacements ``d_mm`` ``[..., F, nu, nv]`` [mm]."""
    return d_mm.pow(2).mean()


def lasso(d_mm: torch.Tensor, smooth: float = 1e-3) -> torch.Tensor:
    """Mean absolute displacement [mm], a scalar ``()``, of displacements ``d_mm`` ``[..., F, nu, nv]`` [mm]
    (``sqrt(d^2 + s^2) - s`` with ``smooth`` = s [mm]: a subgradient that is defined at 0)."""
    return (torch.sqrt(d_mm * d_mm + smooth * smooth) - smooth).mean()


def laplacian(d_mm: torch.Tensor) -> torch.Tensor:
    """Mean squared discrete Laplacian of the displacement on each facet's control grid [mm^2], a scalar ``()``.

    ``d_mm``: displacements ``[..., F, nu, nv]`` [mm] (nu, nv >= 2); the 5-point stencil is in grid steps, so
    the result does not depend on the facet's size.

    The grid is padded by linear extrapolation, so planes (facet tilts, pistons) cost nothing -- ridge
    handles those -- while bumps and ripples do, including at the free edges.
    """
    return _laplacian_stencil(d_mm).pow(2).mean()


def laplacian_per_row(d_mm: torch.Tensor) -> torch.Tensor:
    """:func:`laplacian` of each row of ``d_mm`` ``[K, F, nu, nv]`` [mm] (K independent surfaces): ``[K]`` [mm^2]."""
    return _laplacian_stencil(d_mm).pow(2).reshape(d_mm.shape[0], -1).mean(-1)


def _laplacian_stencil(d_mm: torch.Tensor) -> torch.Tensor:
    # The 5-point Laplacian of [..., nu, nv] grids padded by linear extrapolation: [prod(...), 1, nu, nv].
    shape = d_mm.shape
    x = d_mm.reshape(-1, 1, shape[-2], shape[-1])
    k = x.new_tensor([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]]).reshape(1, 1, 3, 3)
    # Linear extrapolation at the border makes planes (tilts) free: pad with 2 x edge - inner.
    top = 2 * x[..., :1, :] - x[..., 1:2, :]
    bottom = 2 * x[..., -1:, :] - x[..., -2:-1, :]
    x = torch.cat((top, x, bottom), -2)
    left = 2 * x[..., :, :1] - x[..., :, 1:2]
    right = 2 * x[..., :, -1:] - x[..., :, -2:-1]
    x = torch.cat((left, x, right), -1)
    return F.conv2d(x, k)


def threshold_background(image: torch.Tensor, level: float = 0.02) -> torch.Tensor:
    """Measured-image preprocessing: :func:`heliotwin.io.images.subtract_background` (one implementation).

    Parameters
    ----------
    image : torch.Tensor, [..., rows, cols]
        Any scale; the result has the same shape.
    level : float
        Fraction of each image's maximum [1], subtracted from that image before clipping at 0.
    """
    return subtract_background(image, level)
