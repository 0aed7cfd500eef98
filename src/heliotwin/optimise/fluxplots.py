"""Figures of a receiver map against its allowable flux: utilisation ``flux / limit`` per cell, binding cells marked.

Imported by the command line only when a figure is asked for (matplotlib, without pyplot).
"""
from __future__ import annotations

import numpy as np
import torch
from matplotlib.figure import Figure

from ..field.targets import CylinderTarget
from ..io.report import save_figure
from ..plots import receiver_extent
from .problem import BINDING_WITHIN, FluxLimit

__all__ = ["plot_utilisation"]


def plot_utilisation(maps: dict, receiver, limit: FluxLimit, path=None, *, title: str | None = None):
    """Panels of ``flux / limit`` [-] (one per map: label -> [rows, cols] W/m^2, row 0 = top) on one scale from 0 to
    at least 1, the allowable-flux map itself [kW/m^2] beside them, and the binding cells (within
    :data:`~heliotwin.optimise.problem.BINDING_WITHIN` of their limit) marked with a dot, cells over it with a cross.

    Returns
    -------
    matplotlib.figure.Figure
    """
    cells = limit.cells.detach().cpu().numpy()
    util = {k: (v.detach().cpu().numpy() if torch.is_tensor(v) else np.asarray(v)) / cells for k, v in maps.items()}
    ext = receiver_extent(receiver)
    n = len(util) + 1
    fig = Figure(figsize=(min(5.5 * n, 20), 3.8), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, n, sharey=True))
    vmax = max([1.0] + [float(u.max()) for u in util.values()])
    rows, cols = cells.shape
    xs = ext[0] + (np.arange(cols) + 0.5) * (ext[1] - ext[0]) / cols
    ys = ext[3] - (np.arange(rows) + 0.5) * (ext[3] - ext[2]) / rows
    im = None
    for ax, (label, u) in zip(axes, util.items()):
        im = ax.imshow(u, extent=ext, aspect="auto", vmin=0.0, vmax=vmax, cmap="viridis", interpolation="nearest")
        binding = (u >= 1.0 - BINDING_WITHIN) & (u <= 1.0)
        over = u > 1.0
        r, c = np.nonzero(binding)
        ax.plot(xs[c], ys[r], "o", ms=3, color="red", ls="none", label=f"binding ({int(binding.sum())} cells)")
        r, c = np.nonzero(over)
        if len(r):
            ax.plot(xs[c], ys[r], "x", ms=5, color="white", ls="none", label=f"over the limit ({len(r)})")
        ax.set_title(f"{label}: max flux/limit {float(u.max()):.3f}", fontsize=10)
        ax.legend(loc="lower right", fontsize=7, framealpha=0.6)
    fig.colorbar(im, ax=list(axes[:-1]), label="flux / allowable flux [-]", shrink=0.95)
    lim = axes[-1].imshow(cells / 1e3, extent=ext, aspect="auto", cmap="magma", interpolation="nearest")
    axes[-1].set_title(f"allowable flux ({limit.source})", fontsize=10)
    fig.colorbar(lim, ax=axes[-1], label="limit [kW/m²]", shrink=0.95)
    for ax in axes:
        ax.set_xlabel("arc along the unrolled receiver [m]" if isinstance(receiver, CylinderTarget)
                      else "across the receiver, 'right' [m]")
    axes[0].set_ylabel("height on the receiver [m]")
    if title:
        fig.suptitle(title, fontsize=11)
    if path is not None:
        save_figure(fig, path, tight=False)
    return fig
