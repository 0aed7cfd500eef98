"""Figures for surface learning (matplotlib figures without pyplot; written atomically next to the report).

* :func:`plot_normal_deviation` -- per facet, the angle [mrad] between the learned and the ideal
  (flat canted) surface normal, as in the paper's Fig. 1d.
* :func:`plot_flux_comparison` -- measured / ideal / learned centred flux side by side per test image.
* :func:`plot_residual_deviation` -- per facet, the normal deviation [mrad] beyond the facet's tilt and
  quadratic shape (:func:`heliotwin.surfaces.edges.residual_map_mrad`): where facet-edge ridges show.
"""
from __future__ import annotations

import torch
from matplotlib.figure import Figure

from ..field import facets as facet_ops
from ..field.plant import Facets
from ..geometry import angle_between
from ..io.images import CENTERED_WINDOW_M
from ..io.report import save_figure
from .edges import residual_map_mrad
from .learning import normal_heights

__all__ = ["normal_deviation_map", "plot_normal_deviation", "plot_flux_comparison", "plot_residual_deviation"]


def normal_deviation_map(facets: Facets, control_points: torch.Tensor, degree, reference: torch.Tensor | None = None,
                         reference_degree=None, samples=(48, 48)) -> torch.Tensor:
    """Angle between a surface's normals and the reference's (default: flat canted facet normal).

    ``control_points`` (and ``reference``): nets ``[1, F, nu, nv, 3]`` [m], heliostat frame, of NURBS degree
    ``degree`` (``reference_degree``, default ``degree``); sampled at ``samples`` = (su, sv) per facet.

    Returns
    -------
    torch.Tensor, [F, su, sv]
        [mrad].
    """
    _, n = normal_heights(facets, control_points, degree, samples)
    if reference is None:
        ref = facet_ops.facet_normals(facets.canting_e, facets.canting_n)[0].to(n)[:, None, None, :].expand_as(n)
    else:
        _, ref = normal_heights(facets, reference, reference_degree or degree, samples)
    return angle_between(n, ref) * 1e3


def plot_normal_deviation(facets: Facets, control_points: torch.Tensor, degree, path, title: str = "") -> None:
    """Per-facet map of the normal deviation [mrad] from the ideal facet, arranged like the heliostat.

    Facets are placed by their centre (east right, north up, seen from above the mirror lying flat).
    ``control_points``: the surface's net ``[1, F, nu, nv, 3]`` [m], heliostat frame, of NURBS ``degree``
    (p, q); ``facets``: its ``[1, F, 3]`` placement [m]. Writes the figure to ``path``.
    """
    dev = normal_deviation_map(facets, control_points, degree).detach().cpu()
    tr = facets.translation[0].detach().cpu()
    ce = facets.canting_e[0].detach().cpu()
    cn = facets.canting_n[0].detach().cpu()
    vmax = float(dev.max()) if dev.numel() else 1.0
    fig = Figure(figsize=(6, 5))
    ax = fig.subplots()
    im = None
    for f in range(dev.shape[0]):
        hx, hy = float(ce[f].norm()), float(cn[f].norm())
        x0, y0 = float(tr[f, 0]), float(tr[f, 1])
        # u runs along canting_e (east), v along canting_n (north): transpose so rows = north.
        im = ax.imshow(dev[f].T.flip(0).numpy(), extent=(x0 - hx, x0 + hx, y0 - hy, y0 + hy), vmin=0.0, vmax=vmax,
                       cmap="viridis")
    ax.set_xlim(float((tr[:, 0] - ce.norm(dim=-1)).min()) - 0.05, float((tr[:, 0] + ce.norm(dim=-1)).max()) + 0.05)
    ax.set_ylim(float((tr[:, 1] - cn.norm(dim=-1)).min()) - 0.05, float((tr[:, 1] + cn.norm(dim=-1)).max()) + 0.05)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title(title or "surface normal deviation from ideal [mrad]")
    fig.colorbar(im, ax=ax, label="mrad")
    save_figure(fig, path, tight=False)


def plot_flux_comparison(measured: torch.Tensor, ideal: torch.Tensor, learned: torch.Tensor, labels, path,
                         l1_ideal=None, l1_learned=None, window_m: float = CENTERED_WINDOW_M, title: str = "") -> None:
    """Rows = test images; columns = measured / ideal / learned (each ``[B, R, R]``, any scale), each normalised
    to its own maximum; ``window_m`` [m] the window side.

    Every panel shows the spot-centred window in metres on the target (PAINT orientation: image left = east),
    with one colour bar for the relative flux; the L1 of sum-normalised images against the measured one is
    in the panel titles.
    """
    n = measured.shape[0]
    fig = Figure(figsize=(8.2, 2.6 * n + 0.6))
    axes = fig.subplots(n, 3, squeeze=False)
    half = window_m / 2
    im = None
    for i in range(n):
        for j, (name, img) in enumerate((("measured", measured), ("ideal", ideal), ("learned", learned))):
            a = img[i].detach().cpu().float()
            a = a / a.max().clamp_min(1e-30)
            ax = axes[i, j]
            im = ax.imshow(a.numpy(), vmin=0, vmax=1, cmap="inferno", extent=(-half, half, -half, half))
            text = f"{labels[i]} {name}"
            if j == 1 and l1_ideal is not None:
                text += f"\nL1 {l1_ideal[i]:.3f}"
            if j == 2 and l1_learned is not None:
                text += f"\nL1 {l1_learned[i]:.3f}"
            ax.set_title(text, fontsize=8)
            ax.tick_params(labelsize=6)
            if i == n - 1:
                ax.set_xlabel("[m] (left = east)", fontsize=7)
            if j == 0:
                ax.set_ylabel("up [m]", fontsize=7)
    fig.suptitle(title or "centred flux: measured vs ideal vs learned surface", fontsize=10)
    fig.tight_layout(rect=(0, 0, 0.9, 0.98))
    cax = fig.add_axes((0.91, 0.1, 0.02, 0.8))
    fig.colorbar(im, cax=cax, label="flux / its maximum")
    save_figure(fig, path, tight=False)


def plot_residual_deviation(learned, reference, facets: Facets, path, title: str = "", limit_mrad: float = 5.0) -> None:
    """One panel per facet: the learned surface's normal deviation from ``reference`` beyond each facet's tilt
    and quadratic shape [mrad] (:func:`heliotwin.surfaces.edges.residual_map_mrad`), colour scale from 0 to
    ``max(limit_mrad, largest value)`` so a map under the limit reads as such.

    Parameters
    ----------
    learned, reference : Surfaces
        One heliostat, ``control_points`` [1, F, nu, nv, 3] [m].
    facets : Facets
        ``[1, F, 3]`` [m].
    """
    res = residual_map_mrad(learned, reference, facets).detach().cpu()
    fig = Figure(figsize=(2.0 * res.shape[0] + 0.8, 2.4))
    axes = fig.subplots(1, res.shape[0], squeeze=False)[0]
    im = None
    for f, ax in enumerate(axes):
        im = ax.imshow(res[f].T.flip(0).numpy(), vmin=0.0, vmax=max(limit_mrad, float(res.max())), cmap="viridis")
        ax.set_title(f"facet {f}", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=9)
    fig.colorbar(im, ax=list(axes), label=f"mrad ({limit_mrad:g} = limit)")
    save_figure(fig, path, tight=False)
