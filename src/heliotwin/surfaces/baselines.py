"""Data-driven flux baseline: a NeRF-style coordinate MLP that predicts an image from its conditions.

The thesis behind the surface study compares physics against a data-driven flux predictor that maps the sun
position and motor steps straight to a flux image. This module is that baseline, so the surface reports can
show where physics wins: a coordinate network (Mildenhall et al. 2020, "NeRF", ECCV; Tancik et al. 2020,
"Fourier features let networks learn high frequency functions in low dimensional domains", NeurIPS)

    I(u, v | c) = softplus(f(γ(u, v), c)),   then each image divided by its sum,

with γ a Fourier positional encoding of the pixel centre and c the conditioning vector (e.g. the unit sun
vector (3) and the two motor steps, standardised over the training images). It is trained with the L1 of
unit-sum images (the metric the surface reports are judged on), Adam, full batches over images and pixels.
No physics: it can only interpolate between the training images' conditions.

:func:`fit_flux_predictor` fits one model; :func:`predict_flux` predicts; :func:`select_flux_predictor`
chooses width and step count by leave-one-training-image-out and refits on all training images (the test
images are never seen).

Shapes: N training images of H x W pixels, D conditioning features, M queried conditions. Float32.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..errors import HeliotwinError

__all__ = ["FluxPredictor", "fit_flux_predictor", "predict_flux", "select_flux_predictor", "fourier_encoding"]

_EPS = 1e-12


@dataclass
class FluxPredictor:
    """A fitted coordinate MLP.

    Attributes
    ----------
    weights, biases : list of torch.Tensor
        Layer ``k`` maps ``[.., in_k] -> [.., out_k]``; the last has one output (pre-softplus intensity).
    cond_mean, cond_scale : torch.Tensor, [D]
        Standardisation of the conditioning (from the training images; a column with scale ``< 1e-6`` is
        centred only).
    shape : tuple of int
        ``(H, W)`` of the images.
    frequencies : int
        L of the encoding :func:`fourier_encoding`.
    """

    weights: list
    biases: list
    cond_mean: torch.Tensor
    cond_scale: torch.Tensor
    shape: tuple
    frequencies: int


def fourier_encoding(coords: torch.Tensor, frequencies: int) -> torch.Tensor:
    """NeRF positional encoding ``γ(p) = (p, sin(2^k π p), cos(2^k π p))_{k<L}``, ``[.., 2] -> [.., 2 + 4L]``.

    ``coords`` are pixel centres in ``[-1, 1]`` (so the highest band, ``k = L - 1``, has a period of
    ``2^(2-L)`` in ``p``, i.e. ``2^(1-L)`` of the image's side: 2 pixels, the Nyquist limit, for L = 6 on 64
    pixels).
    """
    out = [coords]
    for k in range(frequencies):  # L (<= ~10) bands, each batched over every pixel
        a = (2.0 ** k) * torch.pi * coords
        out += [torch.sin(a), torch.cos(a)]
    return torch.cat(out, -1)


def _pixel_grid(shape, device) -> torch.Tensor:
    """Pixel centres ``[H*W, 2]`` in ``[-1, 1]`` (row, column), float32."""
    h, w = shape
    r = (torch.arange(h, device=device, dtype=torch.float32) + 0.5) / h * 2 - 1
    c = (torch.arange(w, device=device, dtype=torch.float32) + 0.5) / w * 2 - 1
    return torch.stack(torch.meshgrid(r, c, indexing="ij"), -1).reshape(-1, 2)


def _init(sizes, generator, device) -> tuple[list, list]:
    # He-uniform weights from the caller's generator (nn.Linear would draw from the global RNG).
    ws, bs = [], []
    for n_in, n_out in zip(sizes[:-1], sizes[1:]):
        bound = (6.0 / n_in) ** 0.5
        w = (torch.rand(n_in, n_out, generator=generator, dtype=torch.float32) * 2 - 1) * bound
        ws.append(w.to(device).requires_grad_(True))
        bs.append(torch.zeros(n_out, device=device, dtype=torch.float32, requires_grad=True))
    ws[-1].data.mul_(0.1)  # start near a flat image: the conditioning enters gradually
    return ws, bs


def _forward(weights, biases, features: torch.Tensor) -> torch.Tensor:
    """``[.., F] -> [..]`` non-negative intensity."""
    x = features
    for w, b in zip(weights[:-1], biases[:-1]):
        x = torch.relu(x @ w + b)
    return torch.nn.functional.softplus(x @ weights[-1] + biases[-1]).squeeze(-1)


def _images(weights, biases, enc: torch.Tensor, cond: torch.Tensor, shape) -> torch.Tensor:
    """Unit-sum images ``[M, H, W]`` for standardised conditions ``[M, D]`` and encoded pixels ``[P, F]``."""
    m, p = cond.shape[0], enc.shape[0]
    feats = torch.cat([enc.expand(m, p, -1), cond[:, None, :].expand(m, p, -1)], -1)
    img = _forward(weights, biases, feats)
    return (img / img.sum(-1, keepdim=True).clamp_min(_EPS)).reshape(m, *shape)


def _l1(pred: torch.Tensor, meas: torch.Tensor) -> torch.Tensor:
    """Per-image L1 of unit-sum images ``[M]`` (``meas`` already unit-sum)."""
    return (pred - meas).abs().sum((-2, -1))


def _prepare(inputs, images):
    x = torch.as_tensor(inputs).to(torch.float32)
    y = torch.as_tensor(images).to(torch.float32)
    if x.ndim != 2 or y.ndim != 3 or x.shape[0] != y.shape[0] or x.shape[0] < 1:
        raise HeliotwinError(f"fit_flux_predictor: expected inputs [N, D] and images [N, H, W] with the same N >= 1, "
                             f"got {tuple(x.shape)} and {tuple(y.shape)}")
    y = y.to(x.device).clamp_min(0)
    return x, y / y.sum((-2, -1), keepdim=True).clamp_min(_EPS)


def fit_flux_predictor(train_inputs: torch.Tensor, train_images: torch.Tensor, *, generator=None, seed: int = 0,
                       steps: int = 400, width: int = 64, layers: int = 3, frequencies: int = 6, lr: float = 3e-3,
                       validation=None, checkpoints=()) -> FluxPredictor | tuple[FluxPredictor, dict]:
    """Fit the coordinate MLP to N images.

    Parameters
    ----------
    train_inputs : torch.Tensor, [N, D]
        Conditioning per image (e.g. unit sun vector [1] and motor positions [steps]); standardised here over
        the N rows, so any units do.
    train_images : torch.Tensor, [N, H, W]
        Measured images, any scale (each is normalised to unit sum, so [1]; negatives clipped to 0).
    generator : torch.Generator, optional
        Draws the initial weights; default ``torch.Generator().manual_seed(seed)``.
    steps, width, layers, frequencies, lr
        Adam steps (full batch), hidden width (neurons per layer, a count, not a length), hidden layers,
        Fourier bands L, learning rate.
    validation : tuple (inputs [V, D], images [V, H, W]), optional
        Held-out images scored at each step in ``checkpoints`` (for model selection).
    checkpoints : iterable of int
        Step counts (<= ``steps``) at which ``validation`` is scored.

    Returns
    -------
    FluxPredictor
        Or, with ``validation``, ``(model, {step: mean held-out L1 [1]})`` (L1 of unit-sum images).
    """
    x, y = _prepare(train_inputs, train_images)
    shape = tuple(y.shape[-2:])
    mean = x.mean(0)
    scale = x.std(0, unbiased=False) if x.shape[0] > 1 else torch.ones_like(mean)
    scale = torch.where(scale > 1e-6, scale, torch.ones_like(scale))
    if generator is None:
        generator = torch.Generator().manual_seed(int(seed))
    enc = fourier_encoding(_pixel_grid(shape, x.device), frequencies)
    ws, bs = _init([enc.shape[-1] + x.shape[-1]] + [width] * layers + [1], generator, x.device)
    opt = torch.optim.Adam(ws + bs, lr=lr)
    cond = (x - mean) / scale
    checks = sorted({int(c) for c in checkpoints if 0 <= int(c) <= steps})
    scores = {}
    if validation is not None:
        vx, vy = _prepare(*validation)
        vcond = (vx.to(x.device) - mean) / scale
    for step in range(steps + 1):
        if validation is not None and step in checks:
            with torch.no_grad():
                scores[step] = float(_l1(_images(ws, bs, enc, vcond, shape), vy.to(x.device)).mean())
        if step == steps:
            break
        opt.zero_grad()
        loss = _l1(_images(ws, bs, enc, cond, shape), y).mean()
        loss.backward()
        opt.step()
    model = FluxPredictor([w.detach() for w in ws], [b.detach() for b in bs], mean, scale, shape, frequencies)
    return (model, scores) if validation is not None else model


def predict_flux(model: FluxPredictor, inputs: torch.Tensor) -> torch.Tensor:
    """Unit-sum, non-negative images ``[M, H, W]`` (float32) for conditions ``inputs`` ``[M, D]``."""
    x = torch.as_tensor(inputs).to(torch.float32).to(model.cond_mean.device)
    enc = fourier_encoding(_pixel_grid(model.shape, x.device), model.frequencies)
    with torch.no_grad():
        return _images(model.weights, model.biases, enc, (x - model.cond_mean) / model.cond_scale, model.shape)


def select_flux_predictor(train_inputs: torch.Tensor, train_images: torch.Tensor, *, seed: int = 0,
                          widths=(32, 64), steps=(25, 50, 100, 200, 400), **kw) -> tuple[FluxPredictor, dict]:
    """Choose ``width`` and ``steps`` by leave-one-training-image-out, then refit on all N images.

    Each fold fits on N - 1 images for ``max(steps)`` steps and scores the held-out image at every count in
    ``steps``; the (width, steps) with the lowest mean held-out L1 wins (ties: fewer steps, then narrower).
    With N = 1 nothing can be held out: the largest width and step count are used.

    Returns
    -------
    model : FluxPredictor
    selection : dict
        ``width``, ``steps``, ``cv`` (``{"width/steps": mean held-out L1}``).
    """
    x, y = _prepare(train_inputs, train_images)
    n, top = x.shape[0], max(steps)
    cv = {}
    if n >= 2:
        for w in widths:
            sums = dict.fromkeys(steps, 0.0)
            for i in range(n):  # N (a handful of) folds
                keep = [j for j in range(n) if j != i]
                _, sc = fit_flux_predictor(x[keep], y[keep], seed=seed, steps=top, width=w,
                                           validation=(x[i:i + 1], y[i:i + 1]), checkpoints=steps, **kw)
                for s in steps:
                    sums[s] += sc[s] / n
            cv.update({(w, s): v for s, v in sums.items()})
        width, best = min(cv, key=lambda k: (round(cv[k], 6), k[1], k[0]))
    else:
        width, best = max(widths), top
    model = fit_flux_predictor(x, y, seed=seed, steps=best, width=width, **kw)
    return model, {"width": int(width), "steps": int(best), "cv": {f"{w}/{s}": v for (w, s), v in cv.items()}}
