"""What the camera does to a flux image, applied to the *model* image before it is compared (functional).

Measured PAINT images are not flux maps: the camera saturates (flat plateaus at the maximum) and the image
processing cuts everything below a level to exactly 0. A surface fitted to raw model images has to absorb
both (e.g. flatten its peak, grow or shrink its tails). Here both are estimated from each *measured* image by
stated rules and applied to the model image, so the surface only has to explain the optics.

Rules (per measured image ``m``, scaled to max 1):

* **Background cut** ``t``: the 10th percentile (``CUT_QUANTILE``) of the measured spot's *boundary* pixels
  (non-zero pixels with a zero 4-neighbour). A hard cut at level ``t`` of a smooth image leaves boundary
  values in ``[t, t + slope x pixel]``, so a low quantile sits just above the cut; box-averaging (256 -> 64 px)
  lowers some of them, so the estimate errs on the low (conservative) side.
* **Saturation**: ``n_sat`` = the number of measured pixels >= ``SATURATED`` (0.98) of the max. The model
  image (scaled to max 1) is multiplied by a gain ``g = 1 / p_(n_sat)`` (its ``n_sat``-th largest value),
  then clipped at 1, so it shows the same number of plateau pixels. ``g`` is computed from the current model
  image and detached (a camera setting, not a surface property).
* **Blur** (:func:`gaussian_blur`): a per-image isotropic Gaussian (one scalar ``sigma`` [px] per image) for
  what varies between images minutes apart -- seeing, sunshape, focus -- so that the surface does not absorb it.

Model image -> ``blur`` -> ``/ max`` -> ``min(g x, 1)`` -> ``x < t: 0`` -> compared after unit-sum normalisation.

Shapes: images ``[B, R, C]``. Units: ``t`` fraction of the max; ``sigma`` pixels.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

__all__ = ["CameraModel", "estimate_camera", "apply_camera", "gaussian_blur", "SATURATED", "BLUR_RADIUS_PX",
           "CUT_QUANTILE"]

#: Fraction of the max at and above which a measured pixel counts as saturated (plateau).
SATURATED = 0.98
#: Quantile of the boundary pixels' values taken as the background cut.
CUT_QUANTILE = 0.1
#: Support of the per-image blur kernel [px] (fixed, so the blur is differentiable in sigma).
BLUR_RADIUS_PX = 8


@dataclass
class CameraModel:
    """Per-image camera nuisance estimated from measured images.

    Attributes
    ----------
    threshold : torch.Tensor, [B]
        Background cut, fraction of each image's max [1] (float32).
    n_saturated : torch.Tensor, [B], int64
        Measured plateau pixels.
    """

    threshold: torch.Tensor
    n_saturated: torch.Tensor

    def subset(self, idx) -> "CameraModel":
        """The camera model of the images ``idx`` (a sequence of k indices into B): tensors ``(k,)``, in that order."""
        idx = list(idx)
        return CameraModel(self.threshold[idx], self.n_saturated[idx])

    def as_dict(self, ids) -> dict:
        """JSON-ready ``{id: {"threshold": fraction of the max [1], "saturated_pixels": count}}``, one entry per
        image, keyed by ``str`` of the B ``ids`` (in the order of the ``(B,)`` tensors)."""
        return {str(i): {"threshold": float(t), "saturated_pixels": int(n)}
                for i, t, n in zip(ids, self.threshold, self.n_saturated)}


def estimate_camera(measured: torch.Tensor) -> CameraModel:
    """The background cut and plateau size of each measured image (rules in the module docstring).

    Parameters
    ----------
    measured : torch.Tensor, [B, R, C]
        Any scale, non-negative.

    Returns
    -------
    CameraModel
        ``threshold`` ``[B]`` [1] (float32) and ``n_saturated`` ``[B]`` (int64).
    """
    m = measured / measured.amax((-2, -1), keepdim=True).clamp_min(1e-30)
    pos = m > 0
    z = ~pos
    pad = F.pad(z[:, None].float(), (1, 1, 1, 1), value=1.0)[:, 0] > 0  # outside the window counts as cut
    zero_nb = pad[:, :-2, 1:-1] | pad[:, 2:, 1:-1] | pad[:, 1:-1, :-2] | pad[:, 1:-1, 2:]
    boundary = pos & zero_nb
    thr = []
    for i in range(m.shape[0]):  # B is a handful of images
        vals = m[i][boundary[i]]
        thr.append(vals.quantile(CUT_QUANTILE) if vals.numel() else m.new_zeros(()))
    n_sat = (m >= SATURATED).sum((-2, -1))
    return CameraModel(torch.stack(thr).to(torch.float32), n_sat.to(torch.int64))


def gaussian_blur(images: torch.Tensor, sigma_px: torch.Tensor) -> torch.Tensor:
    """Per-image Gaussian blur of ``images`` ``[B, R, C]`` (same shape out, zero padding), differentiable in
    ``sigma_px`` ``[B]`` [px], the standard deviation per image (fixed support ``BLUR_RADIUS_PX`` [px]).

    ``sigma_px`` is clamped to at least 0.05 px, where the kernel is a delta to float precision, so
    ``sigma_px <= 0.05`` leaves the image unchanged.
    """
    r = BLUR_RADIUS_PX
    x = torch.arange(-r, r + 1, dtype=images.dtype, device=images.device)
    s = sigma_px.to(images).clamp_min(0.05)[:, None]
    g = torch.exp(-0.5 * (x[None, :] / s) ** 2)
    g = g / g.sum(-1, keepdim=True)  # [B, K]
    # The separable zero-padded convolution as two banded matrices, out = T_rows @ image @ T_cols^T: the same
    # sums as a grouped conv2d, several times cheaper forward and backward (w.r.t. sigma too) on a CPU.
    return _band(g, images.shape[-2]) @ images @ _band(g, images.shape[-1]).transpose(-1, -2)


def _band(g: torch.Tensor, n: int) -> torch.Tensor:
    """``[B, n, n]`` matrices ``T[b, i, j] = g[b, j - i + r]`` (0 where ``|j - i| > r``) of kernels ``g`` ``[B, 2r+1]``:
    ``T @ x`` is the zero-padded correlation of ``x`` with ``g`` along ``x``'s rows."""
    r = (g.shape[-1] - 1) // 2
    i = torch.arange(n, device=g.device)
    off = i[None, :] - i[:, None] + r  # [n, n]
    inside = (off >= 0) & (off <= 2 * r)
    return g[:, off.clamp(0, 2 * r)] * inside.to(g)


def apply_camera(pred: torch.Tensor, camera: CameraModel, sigma_px: torch.Tensor | None = None) -> torch.Tensor:
    """Model image as the camera would record it (``[B, R, C]`` -> same, max 1, cut and clipped).

    Parameters
    ----------
    pred : torch.Tensor, [B, R, C]
        Model flux [W/m^2] (any scale).
    camera : CameraModel
        Of the measured images these are compared with (B of them).
    sigma_px : torch.Tensor, [B], optional
        Per-image blur [px].
    """
    x = pred if sigma_px is None else gaussian_blur(pred, sigma_px)
    x = x / x.amax((-2, -1), keepdim=True).clamp_min(1e-30)
    flat = x.detach().flatten(1)
    k = camera.n_saturated.clamp(1, flat.shape[1])
    # The k-th largest value per image: the largest k_max values sorted (topk), not a sort of all pixels.
    top = torch.topk(flat, int(k.max()), dim=1, sorted=True).values
    gain = 1.0 / top.gather(1, (k.to(x.device) - 1)[:, None]).clamp_min(1e-6)  # [B, 1], detached
    x = torch.clamp(x * gain[:, :, None], max=1.0)
    keep = (x.detach() >= camera.threshold.to(x)[:, None, None]).to(x)
    return x * keep
