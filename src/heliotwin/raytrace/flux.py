"""Flux images on a target: the :class:`FluxImage` container, PAINT-style crops and image metrics.

Orientation (PAINT, see ``docs/conventions.md``): a bitmap is ``[..., rows, cols]`` in W/m^2 with row 0
at the top edge (largest local ``y``) and column 0 at the left edge (smallest local ``x``, i.e. east for a
north-facing target whose ``right`` points west). The pixel ``(r, c)`` centre of an image covering the
local rectangle ``[x_min, x_max] x [y_min, y_max]`` is
``x = x_min + (c + 0.5) (x_max - x_min) / cols``, ``y = y_max - (r + 0.5) (y_max - y_min) / rows``.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..errors import HeliotwinError
from ..field.targets import CylinderTarget, PlanarTarget

__all__ = [
    "CENTERED_WINDOW_M",
    "FluxImage",
    "target_extent",
    "pixel_centers",
    "centered_crop",
    "normalized_l1",
    "cross_correlation",
]

#: Side [m] of PAINT's ``-flux-centered.png`` window (square, centred on the measured spot's centroid).
CENTERED_WINDOW_M = 6.0


def _size(value, n: int) -> torch.Tensor:
    """A float or tensor ([] or [B]) as a float64 tensor [n]."""
    t = torch.as_tensor(value, dtype=torch.float64)
    return t.reshape(-1).expand(n) if t.numel() == 1 else t.reshape(n)


def target_extent(target: PlanarTarget | CylinderTarget, n: int = 1, window=None) -> torch.Tensor:
    """Local rectangle covered by a bitmap: the whole target or an explicit window.

    Parameters
    ----------
    target : PlanarTarget or CylinderTarget
        Its ``width``/``height`` may be floats or tensors [n].
    n : int
        Number of samples B.
    window : sequence of 4 floats or torch.Tensor (4,) or (n, 4), optional
        ``(x0, y0, width, height)`` [m] in local target coordinates, ``(x0, y0)`` the lower-left
        (minimum ``x``, minimum ``y``) corner. Default: the whole target centred on its origin.

    Returns
    -------
    torch.Tensor, shape (n, 4), float64
        ``(x_min, x_max, y_min, y_max)`` [m].
    """
    if window is None:
        w, h = _size(target.width, n), _size(target.height, n)
        return torch.stack((-w / 2, w / 2, -h / 2, h / 2), dim=-1)
    win = torch.as_tensor(window, dtype=torch.float64)
    if win.shape[-1] != 4:
        raise HeliotwinError(f"window must be (x0, y0, width, height), got shape {tuple(win.shape)}")
    win = win.reshape(-1, 4).expand(n, 4) if win.dim() == 1 or win.shape[0] == 1 else win.reshape(n, 4)
    if bool((win[:, 2] <= 0).any() | (win[:, 3] <= 0).any()):
        raise HeliotwinError("window width and height must be positive")
    return torch.stack((win[:, 0], win[:, 0] + win[:, 2], win[:, 1], win[:, 1] + win[:, 3]), dim=-1)


def pixel_centers(extent: torch.Tensor, rows: int, cols: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Local coordinates of the pixel centres.

    Parameters
    ----------
    extent : torch.Tensor, shape (B, 4)
        ``(x_min, x_max, y_min, y_max)`` [m].
    rows, cols : int

    Returns
    -------
    x : torch.Tensor, shape (B, cols)
        [m], increasing (column 0 = left = smallest x).
    y : torch.Tensor, shape (B, rows)
        [m], decreasing (row 0 = top = largest y).
    """
    ext = extent.to(torch.float64)
    c = (torch.arange(cols, dtype=torch.float64, device=ext.device) + 0.5) / cols
    r = (torch.arange(rows, dtype=torch.float64, device=ext.device) + 0.5) / rows
    x = ext[:, :1] + c * (ext[:, 1:2] - ext[:, :1])
    y = ext[:, 3:4] - r * (ext[:, 3:4] - ext[:, 2:3])
    return x, y


@dataclass
class FluxImage:
    """Flux on a target (or a window of it) for a batch of B samples.

    Attributes
    ----------
    bitmap : torch.Tensor, shape (B, rows, cols)
        Flux density [W/m^2] in PAINT orientation.
    target : PlanarTarget or CylinderTarget
    extent : torch.Tensor, shape (B, 4), float64
        Local rectangle ``(x_min, x_max, y_min, y_max)`` [m] the bitmap covers.
    total_power_w : torch.Tensor, shape (B,), optional
        Reflected power ``DNI sum(A cos(theta_i)) rho`` [W] (all mirror points, landing or not).
    intercepted_power_w : torch.Tensor, shape (B,), optional
        Power deposited in the bitmap ``sum(bitmap) * pixel_area`` [W].
    method : str
        ``"mc"``, ``"gaussian"`` or ``"conv"`` (the integrator that made it).
    """

    bitmap: torch.Tensor
    target: PlanarTarget | CylinderTarget
    extent: torch.Tensor
    total_power_w: torch.Tensor | None = None
    intercepted_power_w: torch.Tensor | None = None
    method: str = "mc"

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)``."""
        return int(self.bitmap.shape[-2]), int(self.bitmap.shape[-1])

    @property
    def pixel_area(self) -> torch.Tensor:
        """Pixel area [m^2], shape (B,), float64 (in the target's own surface)."""
        rows, cols = self.shape
        ext = self.extent
        return (ext[:, 1] - ext[:, 0]) / cols * (ext[:, 3] - ext[:, 2]) / rows

    def total_power(self) -> torch.Tensor:
        """Power in the bitmap ``sum(bitmap) * pixel_area`` [W], shape (B,) (differentiable)."""
        return self.bitmap.sum((-2, -1)) * self.pixel_area.to(self.bitmap)

    def centroid_local(self) -> torch.Tensor:
        """Flux-weighted centroid in local target coordinates.

        Returns
        -------
        torch.Tensor, shape (B, 2)
            ``(x, y)`` [m] in the bitmap's dtype (differentiable); the extent centre for an empty image.
        """
        rows, cols = self.shape
        x, y = pixel_centers(self.extent, rows, cols)
        x, y = x.to(self.bitmap), y.to(self.bitmap)
        b = self.bitmap
        tot = b.sum((-2, -1))
        safe = torch.where(tot > 0, tot, torch.ones_like(tot))
        cx = (b.sum(-2) * x).sum(-1) / safe
        cy = (b.sum(-1) * y).sum(-1) / safe
        ext = self.extent.to(b)
        cx = torch.where(tot > 0, cx, (ext[:, 0] + ext[:, 1]) / 2)
        cy = torch.where(tot > 0, cy, (ext[:, 2] + ext[:, 3]) / 2)
        return torch.stack((cx, cy), dim=-1)

    def centroid_enu(self) -> torch.Tensor:
        """Flux centroid as an ENU point on the target surface, shape (B, 3), float64 [m]."""
        return self.target.to_world(self.centroid_local().to(torch.float64))


def centered_crop(bitmap_or_flux, target: PlanarTarget | CylinderTarget | None, center_local: torch.Tensor,
                  size_m: float = CENTERED_WINDOW_M, resolution=64) -> torch.Tensor:
    """Resample the flux in a square window centred on a local point (PAINT ``-flux-centered.png`` style).

    Bilinear resampling (``grid_sample``, differentiable w.r.t. the bitmap and the centre); outside the
    source bitmap the flux is 0. Values stay in the source units (W/m^2). For full-resolution centred
    images trace directly into a window instead (``trace_mc(..., window=...)``).

    Parameters
    ----------
    bitmap_or_flux : FluxImage or torch.Tensor, shape (B, rows, cols) or (rows, cols)
        Flux [W/m^2] (or any per-pixel value); a raw bitmap is taken to cover the whole target.
    target : PlanarTarget or CylinderTarget or None
        Needed for a raw bitmap (its extent); ignored for a FluxImage.
    center_local : torch.Tensor, shape (B, 2) or (2,)
        Window centre ``(x, y)`` [m] in local target coordinates (e.g. the flux centroid).
    size_m : float
        Window side [m].
    resolution : int or (int, int)
        Output ``rows, cols``.

    Returns
    -------
    torch.Tensor, shape (B, r, c) (or (r, c) for a 2-D input bitmap)
    """
    squeeze = False
    if isinstance(bitmap_or_flux, FluxImage):
        bitmap, extent = bitmap_or_flux.bitmap, bitmap_or_flux.extent
    else:
        bitmap = bitmap_or_flux
        if bitmap.dim() == 2:
            bitmap, squeeze = bitmap.unsqueeze(0), True
        if target is None:
            raise HeliotwinError("centered_crop of a raw bitmap needs its target")
        extent = target_extent(target, bitmap.shape[0])
    b = bitmap.shape[0]
    rows, cols = (resolution, resolution) if isinstance(resolution, int) else tuple(resolution)
    center = torch.as_tensor(center_local).to(bitmap).reshape(-1, 2).expand(b, 2)
    ext = extent.to(bitmap)
    ju = (torch.arange(cols, dtype=bitmap.dtype, device=bitmap.device) + 0.5) / cols - 0.5
    iu = (torch.arange(rows, dtype=bitmap.dtype, device=bitmap.device) + 0.5) / rows - 0.5
    x = center[:, :1] + ju * size_m  # [B, cols]
    y = center[:, 1:] - iu * size_m  # [B, rows]
    gx = 2 * (x - ext[:, :1]) / (ext[:, 1:2] - ext[:, :1]) - 1
    gy = 2 * (ext[:, 3:4] - y) / (ext[:, 3:4] - ext[:, 2:3]) - 1
    grid = torch.stack(torch.broadcast_tensors(gx[:, None, :], gy[:, :, None]), dim=-1)  # [B, rows, cols, 2]
    out = F.grid_sample(bitmap.unsqueeze(1), grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    out = out.squeeze(1)
    return out.squeeze(0) if squeeze else out


def normalized_l1(a: torch.Tensor, b: torch.Tensor, eps: float = 1e-30) -> torch.Tensor:
    """L1 distance of two images after normalising each to unit sum: ``sum |a/sum a - b/sum b|``.

    Parameters
    ----------
    a, b : torch.Tensor, shape (..., rows, cols)

    Returns
    -------
    torch.Tensor, shape (...)
        In [0, 2]; 0 for identical shapes, 2 for disjoint supports.
    """
    sa = a.sum((-2, -1), keepdim=True).clamp(min=eps)
    sb = b.sum((-2, -1), keepdim=True).clamp(min=eps)
    return (a / sa - b / sb).abs().sum((-2, -1))


def cross_correlation(a: torch.Tensor, b: torch.Tensor, eps: float = 1e-30) -> torch.Tensor:
    """Zero-mean normalised cross-correlation of two images (Pearson correlation of the pixels).

    Parameters
    ----------
    a, b : torch.Tensor, shape (..., rows, cols)

    Returns
    -------
    torch.Tensor, shape (...)
        In [-1, 1]; 0 if either image is constant.
    """
    a0 = a - a.mean((-2, -1), keepdim=True)
    b0 = b - b.mean((-2, -1), keepdim=True)
    num = (a0 * b0).sum((-2, -1))
    den = torch.sqrt(((a0 * a0).sum((-2, -1)) * (b0 * b0).sum((-2, -1))).clamp(min=eps))
    return num / den
