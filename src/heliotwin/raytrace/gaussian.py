"""Gaussian-footprint (noise-free) flux integrator ("gaussian"): one Gaussian footprint per mirror point.

Every mirror point's reflected sun cone (sunshape plus slope-error scatter, Gaussian-equivalent with
per-axis variance ``sigma^2``, see :func:`heliotwin.sunshape.second_moment`) is mapped onto the target by
the linearisation of the ray -> pixel mapping around the central reflected ray: with the same projective
coefficients as the Monte-Carlo fast path, the mean hit is ``mu = (N_x0 / D_0, N_y0 / D_0)`` and the 2x2
Jacobian w.r.t. the frame offsets ``(a, b)`` is ``J_ij = (N_ij D_0 - N_i0 D_j) / D_0^2``. The footprint is
the Gaussian with covariance ``Sigma = sigma^2 J J^T + s I`` [px^2], where ``s`` (default 1/6 px^2) is
the variance of the one-pixel tent kernel that the Monte-Carlo bilinear splat applies, so both integrators
estimate the same image.

Two evaluation modes (:class:`FootprintSettings` ``mode``):

``window``
    Each point's Gaussian is evaluated at the pixel centres of a square window of ``(2 h + 1)^2`` pixels
    around the nearest pixel of ``mu``; ``h = ceil(n_sigma * max sqrt(lambda_max(Sigma)))`` is chosen once
    per call (capped by ``max_half_window``) so all points batch together. Weights are normalised over
    the *full* window before pixels outside the bitmap (or the target) are dropped, so each point
    deposits exactly its power, however sharp its spot. Cost ~ P (2h+1)^2.
``convolve``
    The points' mean hits are splatted bilinearly (the tent kernel *is* the ``s = 1/6`` term) and each
    sample's image is convolved (FFT) with the Gaussian of the power-weighted mean covariance. Exact when
    all points of a sample share one covariance and accurate to second order in their spread otherwise
    (one heliostat per sample); cost ~ P + pixels log(pixels), typically 100x cheaper.
``auto`` (default) picks ``convolve`` when the covariance spread within every sample is below
``convolve_tolerance``, else ``window``.

Cost is independent of any ray count; the result is differentiable (plain autograd; window chunks are
checkpointed to bound memory). Note that non-Gaussian sunshapes (Buie, pillbox) are represented by their
Gaussian of equal second moment: the spot's core and tails differ from the Monte-Carlo image (for the
default optics -- Buie CSR 0.05, 1 mrad slope error -- L1 ~ 0.15 between the two on a focused heliostat;
pillbox ~ 0.02).

For the cylindrical receiver the footprint lives in the tangent plane at the central ray's hit point
(first-order accurate for spots small compared with the radius); the mean is the exact hit, in unrolled
``(arc, axial)`` coordinates.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch.utils.checkpoint import checkpoint

from .. import sunshape as _sunshape
from ..errors import HeliotwinError
from ..field.plant import SunSettings
from ..field.targets import CylinderTarget, PlanarTarget
from ..geometry import orthonormal_frame, ray_cylinder
from .flux import FluxImage, target_extent
from .montecarlo import _resolution, planar_coefficients, prepare_mirror
from .splat import splat_bilinear

__all__ = ["trace_gaussian", "FootprintSettings", "gaussian_footprints"]

_EPS = 1e-9


@dataclass(frozen=True)
class FootprintSettings:
    """How the Gaussian integrator lays each mirror point's sun-cone footprint on the target (defaults: the
    evaluation mode picked per call, 3.5 standard deviations of support, the Monte-Carlo splat's tent kernel).

    Attributes
    ----------
    mode : {"auto", "window", "convolve"}
        ``window``: every point's own Gaussian evaluated on a ``(2h+1)^2`` pixel window (exact per-point
        covariance, cost P (2h+1)^2). ``convolve``: the points' mean hits are bilinearly splatted and each
        sample's image is convolved (FFT) with one Gaussian of the power-weighted mean covariance (cost
        ~P + pixels log pixels; the splat's tent kernel plays the role of ``smoothing=1/6``). ``auto``
        convolves when, in every sample, no point's covariance differs from the mean by more than
        ``convolve_tolerance`` (relative Frobenius / trace) -- e.g. one heliostat per sample, where the
        error is second order in that spread.
    n_sigma : float
        Window / kernel half-size in footprint standard deviations [1].
    max_half_window : int
        Cap on the window half-size [px] in ``window`` mode (wider footprints are truncated, then
        renormalised); ``convolve`` mode caps at the bitmap size instead.
    smoothing : float
        Variance [px^2] added to every footprint; 1/6 reproduces the Monte-Carlo bilinear splat kernel.
    convolve_tolerance : float
        Relative covariance spread [1] below which ``auto`` convolves (see ``mode``).
    max_pixels_per_chunk : int
        Memory bound of ``window`` mode (points x window pixels per chunk).
    """

    mode: str = "auto"
    n_sigma: float = 3.5
    max_half_window: int = 64
    smoothing: float = 1.0 / 6.0
    convolve_tolerance: float = 0.1
    max_pixels_per_chunk: int = 2 ** 21

    def __post_init__(self):
        if self.mode not in ("auto", "window", "convolve"):
            raise HeliotwinError(f"mode must be 'auto', 'window' or 'convolve', got {self.mode!r}")


def _projective_moments(coef: torch.Tensor):
    """Mean hit and Jacobian from projective coefficients [..., 3, 3] (rows N_col, N_row, D)."""
    d0 = coef[..., 2, 0]
    ok = d0 < -_EPS
    safe = torch.where(ok, d0, -torch.ones_like(d0))
    mu = coef[..., :2, 0] / safe.unsqueeze(-1)  # [..., 2]
    # J[i, j] = (N_i,j+1 D0 - N_i0 D_j+1) / D0^2, j over (a, b)
    num = coef[..., :2, 1:] * safe[..., None, None] - coef[..., :2, :1] * coef[..., 2:3, 1:]
    jac = num / (safe * safe)[..., None, None]
    return mu, jac, ok


def _cylinder_moments(points, reflected, u, v, target: CylinderTarget, extent, rows, cols):
    """Mean hit (pixels) and Jacobian d(px)/d(a, b) on the tangent plane of the cylinder at the central hit."""
    dev, dt = points.device, reflected.dtype
    apex = target.center.to(dev, torch.float64)
    nrm, right, up = (t.to(dev, dt) for t in (target.normal, target.right, target.up))
    r_cyl = float(target.radius)
    o = (points.to(torch.float64) - apex).to(dt)  # offsets from the apex in float64, then ray precision
    axis_point = -r_cyl * nrm
    t, hit, _ = ray_cylinder(o, reflected, axis_point, up, r_cyl)
    hp = o + t.unsqueeze(-1) * reflected  # central hit, relative to the apex
    radial = hp - axis_point
    # dot products over the last axis as matrix products (a sum over a last axis of 3 is ~5x slower)
    radial = radial - (radial @ up).unsqueeze(-1) * up
    m = radial / r_cyl  # outward normal of the tangent plane
    e = torch.linalg.cross(up.expand_as(m), m, dim=-1)  # tangent "right" (arc direction)
    ang = torch.atan2(radial @ right, radial @ nrm)
    arc = r_cyl * ang
    axial = hp @ up
    # tangent-plane Jacobian of (x, y) w.r.t. (a, b) at the central ray
    h = torch.einsum("...i,...i->...", hp - o, m)  # (H - o) . m  (< 0 from the field side)
    basis = torch.stack((reflected, u, v), dim=-2)
    den = torch.einsum("...ji,...i->...j", basis, m)  # [B, P, 3]
    ex = torch.einsum("...ji,...i->...j", basis, e)
    ey = basis @ up
    d0 = den[..., 0]
    ok = hit & (d0 < -_EPS)
    safe = torch.where(ok, d0, -torch.ones_like(d0))
    h_ = h.unsqueeze(-1)
    jx = h_ * (ex[..., 1:] * safe.unsqueeze(-1) - ex[..., :1] * den[..., 1:]) / (safe * safe).unsqueeze(-1)
    jy = h_ * (ey[..., 1:] * safe.unsqueeze(-1) - ey[..., :1] * den[..., 1:]) / (safe * safe).unsqueeze(-1)
    ext = extent.to(dt)
    b = points.shape[0]
    pw = ((ext[:, 1] - ext[:, 0]) / cols).view(b, 1)
    ph = ((ext[:, 3] - ext[:, 2]) / rows).view(b, 1)
    mu = torch.stack(((arc - ext[:, :1]) / pw - 0.5, (ext[:, 3:4] - axial) / ph - 0.5), dim=-1)
    jac = torch.stack((jx / pw.unsqueeze(-1), -jy / ph.unsqueeze(-1)), dim=-2)
    mu = torch.where(ok.unsqueeze(-1), mu, torch.full_like(mu, -1e9))
    return mu, jac, ok


def gaussian_footprints(mu: torch.Tensor, cov: torch.Tensor, weights: torch.Tensor, rows: int, cols: int,
                        n_samples: int, points_per_sample: int, half_window: int, bounds: torch.Tensor | None = None,
                        max_pixels_per_chunk: int = 2 ** 21) -> torch.Tensor:
    """Splat per-point 2-D Gaussians (normalised on their window) into bitmaps.

    Parameters
    ----------
    mu : torch.Tensor, shape (N, 2)
        Means ``(px, py)`` in pixel coordinates (centres at integers), N = n_samples * points_per_sample.
    cov : torch.Tensor, shape (N, 2, 2)
        Covariances [px^2] (symmetric positive definite).
    weights : torch.Tensor, shape (N,)
        Total deposited value per point (before dropping pixels outside the bitmap).
    rows, cols : int
    n_samples, points_per_sample : int
    half_window : int
        ``h`` [px]: each Gaussian is evaluated on ``(2h+1)^2`` pixels around its nearest pixel.
    bounds : torch.Tensor, shape (n_samples, 4), optional
        Pixel-coordinate region ``(lo_x, hi_x, lo_y, hi_y)`` outside which pixels are dropped (the
        target inside a larger window).
    max_pixels_per_chunk : int
        Memory bound (points x window pixels per chunk).

    Returns
    -------
    torch.Tensor, shape (n_samples, rows, cols)
    """
    n = mu.shape[0]
    h = int(half_window)
    side = 2 * h + 1
    dev, dt = mu.device, mu.dtype
    off = torch.arange(-h, h + 1, device=dev, dtype=dt)
    oy, ox = torch.meshgrid(off, off, indexing="ij")
    ox, oy = ox.reshape(1, -1), oy.reshape(1, -1)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0]
    det = torch.clamp(det, min=1e-12)
    ia, ib, ic = cov[:, 1, 1] / det, -0.5 * (cov[:, 0, 1] + cov[:, 1, 0]) / det, cov[:, 0, 0] / det
    sample = torch.arange(n, device=dev) // points_per_sample
    step = max(1, int(max_pixels_per_chunk) // (side * side))

    def chunk(mu_c, ia_c, ib_c, ic_c, w_c, s_c):
        base = torch.round(mu_c.detach()).clamp(-h - 1.0, max(rows, cols) + h + 1.0)
        px = base[:, :1] + ox  # [n, side^2]
        py = base[:, 1:] + oy
        dx = px - mu_c[:, :1]
        dy = py - mu_c[:, 1:]
        q = ia_c.unsqueeze(1) * dx * dx + 2.0 * ib_c.unsqueeze(1) * dx * dy + ic_c.unsqueeze(1) * dy * dy
        g = torch.exp(-0.5 * q)
        g = g / torch.clamp(g.sum(1, keepdim=True), min=1e-30)
        inside = (px >= 0) & (px <= cols - 1) & (py >= 0) & (py <= rows - 1)
        if bounds is not None:
            bd = bounds[s_c]
            inside = inside & (px >= bd[:, :1]) & (px <= bd[:, 1:2]) & (py >= bd[:, 2:3]) & (py <= bd[:, 3:4])
        val = torch.where(inside, g * w_c.unsqueeze(1), torch.zeros_like(g))
        idx = (s_c.unsqueeze(1) * rows + py.clamp(0, rows - 1).long()) * cols + px.clamp(0, cols - 1).long()
        return torch.zeros(n_samples * rows * cols, dtype=dt, device=dev).index_add(0, idx.reshape(-1), val.reshape(-1))

    grad = torch.is_grad_enabled() and any(t.requires_grad for t in (mu, cov, weights))
    out = torch.zeros(n_samples * rows * cols, dtype=dt, device=dev)
    for s0 in range(0, n, step):
        s1 = min(n, s0 + step)
        args = (mu[s0:s1], ia[s0:s1], ib[s0:s1], ic[s0:s1], weights[s0:s1], sample[s0:s1])
        out = out + (checkpoint(chunk, *args, use_reentrant=False) if grad else chunk(*args))
    return out.view(n_samples, rows, cols)


def _fast_fft_size(n: int) -> int:
    """The smallest m >= n whose only prime factors are 2, 3 and 5 (sizes pocketfft and cuFFT handle fastest;
    a canvas side with a large prime factor can cost several times more)."""
    m = max(1, int(n))
    while True:
        k = m
        for p in (2, 3, 5):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += 1


def _fft_convolve(canvas: torch.Tensor, kernel: torch.Tensor, h: int, rows: int, cols: int,
                  summed: bool = False) -> torch.Tensor:
    """Linear convolution of canvases [B, rows+2h, cols+2h] with kernels [B, 2h+1, 2h+1]; the central crop
    [B, rows, cols], or with ``summed`` the sum over B [rows, cols] (one inverse transform instead of B: the
    transform is linear). Transforms are zero-padded to fast sizes >= the linear-convolution size."""
    hc, wc = canvas.shape[-2:]
    n0, n1 = _fast_fft_size(hc + 2 * h), _fast_fft_size(wc + 2 * h)
    prod = torch.fft.rfft2(canvas, s=(n0, n1)) * torch.fft.rfft2(kernel, s=(n0, n1))
    if summed:
        prod = prod.sum(0, keepdim=True)
    full = torch.fft.irfft2(prod, s=(n0, n1))[:, 2 * h:2 * h + rows, 2 * h:2 * h + cols]
    return full[0] if summed else full


def _gaussian_kernels(cov: torch.Tensor, h: int) -> torch.Tensor:
    """Normalised Gaussian kernels [B, 2h+1, 2h+1] (row = py offset, column = px offset) for cov [B, 2, 2]."""
    off = torch.arange(-h, h + 1, dtype=cov.dtype, device=cov.device)
    dy, dx = torch.meshgrid(off, off, indexing="ij")
    det = torch.clamp(cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0], min=1e-12)
    ia, ib, ic = cov[:, 1, 1] / det, -0.5 * (cov[:, 0, 1] + cov[:, 1, 0]) / det, cov[:, 0, 0] / det
    q = ia.view(-1, 1, 1) * dx * dx + 2 * ib.view(-1, 1, 1) * dx * dy + ic.view(-1, 1, 1) * dy * dy
    k = torch.exp(-0.5 * q)
    return k / k.sum((-2, -1), keepdim=True)


def _max_sigma(cov: torch.Tensor, ok: torch.Tensor) -> float:
    with torch.no_grad():
        tr = cov[..., 0, 0] + cov[..., 1, 1]
        dif = cov[..., 0, 0] - cov[..., 1, 1]
        lam = 0.5 * tr + torch.sqrt(0.25 * dif * dif + cov[..., 0, 1] ** 2)
        lam = torch.where(ok, lam, torch.zeros_like(lam))
        return float(lam.max().clamp(min=0).sqrt()) if lam.numel() else 0.0


def _target_bounds(target, extent: torch.Tensor, rows: int, cols: int, dtype) -> torch.Tensor:
    """Pixel-index range [B, 4] (col_min, col_max, row_min, row_max) of a window's pixel centres on the target."""
    full = target_extent(target, extent.shape[0]).to(extent)
    pw = (extent[:, 1] - extent[:, 0]) / cols
    ph = (extent[:, 3] - extent[:, 2]) / rows
    return torch.stack(((full[:, 0] - extent[:, 0]) / pw - 0.5, (full[:, 1] - extent[:, 0]) / pw - 0.5,
                        (extent[:, 3] - full[:, 3]) / ph - 0.5, (extent[:, 3] - full[:, 2]) / ph - 0.5),
                       -1).to(dtype)


def _central_moments(mirror, target, extent: torch.Tensor, rows: int, cols: int):
    """Mean hit [B, P, 2] [px], Jacobian d(px)/d(a, b) [B, P, 2, 2] and validity [B, P] of each point's
    central reflected ray, on a planar target or the cylinder's tangent plane."""
    u, v = orthonormal_frame(mirror.reflected)
    if isinstance(target, PlanarTarget):
        coef, in_front = planar_coefficients(mirror.points, mirror.reflected, u, v, target, extent, rows, cols)
        mu, jac, ok = _projective_moments(coef)
        return mu, jac, ok & in_front
    if isinstance(target, CylinderTarget):
        return _cylinder_moments(mirror.points, mirror.reflected, u, v, target, extent, rows, cols)
    raise HeliotwinError(f"unsupported target type {type(target).__name__}")


def _convolved_image(mu, weights, kcov, lit, n_sigma: float, rows: int, cols: int, bounds, dtype):
    """``convolve`` mode: mean hits mu [B, P, 2] [px] splatted bilinearly with weights [B, P], convolved with
    each sample's Gaussian kcov [B, 2, 2] [px^2] (support ``n_sigma`` standard deviations over the lit
    samples ``lit`` [B]); pixels outside ``bounds`` [B, 4] dropped. Returns [B, rows, cols]."""
    half = int(min(max(rows, cols), max(1, math.ceil(n_sigma * _max_sigma(kcov, lit)))))
    canvas = splat_bilinear((mu[..., 0] + half).to(dtype), (mu[..., 1] + half).to(dtype), weights.to(dtype),
                            rows + 2 * half, cols + 2 * half)
    bitmap = _fft_convolve(canvas, _gaussian_kernels(kcov.to(dtype), half), half, rows, cols)
    if bounds is not None:
        c = torch.arange(cols, dtype=dtype, device=bitmap.device)
        r = torch.arange(rows, dtype=dtype, device=bitmap.device)
        inx = (c >= bounds[:, :1]) & (c <= bounds[:, 1:2])
        iny = (r >= bounds[:, 2:3]) & (r <= bounds[:, 3:4])
        bitmap = bitmap * (iny.unsqueeze(-1) & inx.unsqueeze(-2)).to(dtype)
    return bitmap


def trace_gaussian(points, normals, areas, sun_direction, target: PlanarTarget | CylinderTarget, *,
                   resolution=(256, 256), sun: SunSettings | None = None, window=None, clip_to_target: bool = True,
                   footprint: FootprintSettings | None = None, dtype: torch.dtype = torch.float32) -> FluxImage:
    """Noise-free flux image: each mirror point's sun-cone footprint as a Gaussian on the target.

    Parameters
    ----------
    points, normals : torch.Tensor, shape (B, P, 3) (or (P, 3))
        Mirror points [m] and unit normals, world ENU.
    areas : torch.Tensor, shape (B, P) (or (P,))
        [m^2].
    sun_direction : torch.Tensor, shape (B, 3) (or (3,))
        Unit vector towards the sun.
    target : PlanarTarget or CylinderTarget
    resolution : int or (rows, cols)
    sun : SunSettings, optional
        Uses the Gaussian-equivalent second moment of the sunshape plus ``(2 slope_error)^2``.
    window : (x0, y0, width, height) or torch.Tensor (4,) or (B, 4), optional
        Local rectangle [m] to image instead of the whole target (``(x0, y0)`` = lower-left corner).
    clip_to_target : bool
        With a window beyond the target, drop flux outside the physical target.
    footprint : FootprintSettings, optional
        Evaluation mode (window / convolve / auto), support, added smoothing [px^2], memory bound (default
        ``FootprintSettings()``).
    dtype : torch.dtype
        Precision of the footprint evaluation and bitmap.

    Returns
    -------
    FluxImage
        ``method="gaussian"``.
    """
    sun = sun or SunSettings()
    fp = footprint or FootprintSettings()
    mode, n_sigma, smoothing = fp.mode, fp.n_sigma, fp.smoothing
    rows, cols = _resolution(resolution)
    mirror = prepare_mirror(points, normals, areas, sun_direction, sun, dtype)
    b, p = mirror.batch, mirror.num_points
    extent = target_extent(target, b, window).to(mirror.points.device)
    pixel_area = (extent[:, 1] - extent[:, 0]) / cols * (extent[:, 3] - extent[:, 2]) / rows
    mu, jac, ok = _central_moments(mirror, target, extent, rows, cols)
    var = _sunshape.second_moment(sun.sunshape, sigma=float(sun.sigma), radius=float(sun.radius),
                                  csr=float(sun.csr), slope_error=float(sun.slope_error))
    eye = torch.eye(2, dtype=jac.dtype, device=jac.device)
    cov0 = var * (jac @ jac.transpose(-1, -2))  # [B, P, 2, 2] footprint covariance [px^2]
    cov0 = torch.where(ok[..., None, None], cov0, eye)
    weights = mirror.power / pixel_area.to(mirror.power).unsqueeze(1)
    weights = torch.where(ok, weights, torch.zeros_like(weights))
    mu = torch.where(ok.unsqueeze(-1), mu, torch.full_like(mu, -1e9))
    # power-weighted mean covariance per sample
    wsum = weights.sum(1)
    wn = weights / torch.where(wsum > 0, wsum, torch.ones_like(wsum)).unsqueeze(1)
    cov_mean = (wn[..., None, None] * cov0).sum(1)  # [B, 2, 2]
    if mode == "auto":
        with torch.no_grad():
            tr = (cov_mean[:, 0, 0] + cov_mean[:, 1, 1]).clamp(min=1e-30).view(b, 1)
            spread = torch.linalg.matrix_norm(cov0 - cov_mean.unsqueeze(1)) / tr
            spread = torch.where(ok & (weights > 0), spread, torch.zeros_like(spread))
            mode = "convolve" if float(spread.max()) <= fp.convolve_tolerance else "window"
    bounds = _target_bounds(target, extent, rows, cols, dtype) if window is not None and clip_to_target else None
    if mode == "window":
        cov = cov0 + float(smoothing) * eye
        half = int(min(int(fp.max_half_window), max(1, math.ceil(float(n_sigma) * _max_sigma(cov, ok)))))
        bitmap = gaussian_footprints(mu.reshape(b * p, 2).to(dtype), cov.reshape(b * p, 2, 2).to(dtype),
                                     weights.reshape(b * p).to(dtype), rows, cols, b, p, half, bounds,
                                     fp.max_pixels_per_chunk)
    else:
        kcov = cov_mean + max(float(smoothing) - 1.0 / 6.0, 0.0) * eye
        bitmap = _convolved_image(mu, weights, kcov, wsum > 0, float(n_sigma), rows, cols, bounds, dtype)
    intercepted = bitmap.sum((-2, -1)) * pixel_area.to(bitmap)
    return FluxImage(bitmap, target, extent, mirror.power.to(torch.float64).sum(-1), intercepted, "gaussian")
