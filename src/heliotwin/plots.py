"""Plots people would rather look at than read (files are written atomically by :func:`save_figure`).

Figures are made with :class:`matplotlib.figure.Figure`, not ``pyplot``: no backend is selected, no global
figure registry grows, and importing this module never switches the caller's backend (a notebook keeps its
inline plots; a headless run needs no display).
"""
from __future__ import annotations

import numpy as np
import pandas as pd
import torch
from matplotlib.figure import Figure

from .field.targets import CylinderTarget
from .io.images import load_measured_image
from .io.report import save_figure
from .raytrace.flux import target_extent
from .sunangles import paint_angles_from_direction
from .timefmt import sun_text, utc_or_label

__all__ = ["draw_flux", "draw_measured_image", "plot_flux", "plot_demo", "plot_field_demo", "plot_validation",
           "plot_receiver_flux", "receiver_extent", "plot_prediction", "loss_waterfall", "plot_loss_waterfall",
           "angle_origin", "instant_line"]


def draw_flux(ax, flux, title: str, *, measured: dict | None = None) -> None:
    """Draw the first image of a :class:`~heliotwin.raytrace.flux.FluxImage` on ``ax``: title, axes in metres
    on the target (as seen from the field: left = east), colour bar in [kW/m^2] (the bitmap is in [W/m^2]).

    ``measured`` (a ``trace`` report) marks the measured focal spots (HeliOS, UTIS) and the predicted
    centroid, so the figure reads as measured vs predicted.
    """
    ext = flux.extent[0].tolist()
    im = ax.imshow(flux.bitmap[0].detach().cpu().numpy() / 1e3, extent=(ext[0], ext[1], ext[2], ext[3]), cmap="inferno")
    ax.set_title(title)
    ax.set_xlabel("x along target 'right' [m] (left = east)")
    ax.set_ylabel("y up [m]")
    ax.figure.colorbar(im, ax=ax, label="flux [kW/m²]")
    if measured:
        _mark_spots(ax, flux.target, measured)


def draw_measured_image(ax, flux, png, *, measured: dict | None = None) -> None:
    """PAINT's whole-target camera image ``png`` on ``ax``, on the extent of ``flux``'s target (PAINT
    orientation: left = east; axes [m]), relative scale [1] (max = 1), with the measured spots marked."""
    img = load_measured_image(png, normalise="max")
    ext = flux.extent[0].tolist()
    im = ax.imshow(img.numpy(), extent=(ext[0], ext[1], ext[2], ext[3]), cmap="inferno", vmin=0, vmax=1)
    ax.set_title("measured (camera image)")
    ax.set_xlabel("x along target 'right' [m] (left = east)")
    ax.set_ylabel("y up [m]")
    ax.figure.colorbar(im, ax=ax, label="relative intensity [-]")
    if measured:
        _mark_spots(ax, flux.target, {**measured, "centroid_enu_m": None})


def plot_flux(flux, path=None, *, title: str | None = None, measured: dict | None = None, ax=None):
    """A flux image as a figure people read: title, axes [m] on the target, colour bar in [kW/m^2].

    Parameters
    ----------
    flux : FluxImage
        The first image of the batch (bitmap (B, rows, cols) [W/m^2]) is drawn.
    path : str or os.PathLike, optional
        Write the figure here (atomically; format from the extension).
    title : str, optional
        Default: the target's name.
    measured : dict, optional
        A :func:`heliotwin.workflows.trace.trace_record` report: its measured focal spots (HeliOS, UTIS) and
        the predicted centroid are marked, so the figure reads "measured vs predicted"; when the record has
        PAINT's whole-target camera image (``measured_flux_png``) it is drawn on the left, on the same target
        extent (relative scale).
    ax : matplotlib.axes.Axes, optional
        Draw the prediction into this axes (e.g. a notebook's) instead of a new figure (no camera panel).

    Returns
    -------
    matplotlib.figure.Figure
        Made without pyplot (no backend is selected, nothing global changes); in a notebook, display it.
    """
    camera = (measured or {}).get("measured_flux_png") if ax is None else None
    if ax is None:
        fig = Figure(figsize=(12.4, 5.2) if camera else (6.4, 5.2))
        axes = fig.subplots(1, 2 if camera else 1)
        ax = axes[-1] if camera else axes
        if camera:
            draw_measured_image(axes[0], flux, camera, measured=measured)
    fig = ax.figure
    title = title or f"flux on {flux.target.name}"
    if camera:
        fig.suptitle(title)
    draw_flux(ax, flux, "predicted" if camera else title, measured=measured)
    if path is not None:
        save_figure(fig, path)
    return fig


def _mark_spots(ax, target, report: dict) -> None:
    marks = [(src, enu, m) for (src, enu), m in zip(sorted((report.get("measured_spot_enu_m") or {}).items()),
                                                    ("c+", "gx"))]
    if report.get("centroid_enu_m") is not None:
        marks.append(("predicted centroid", report["centroid_enu_m"], "wo"))
    for label, enu, style in marks:
        xy = target.to_local(torch.tensor([enu], dtype=torch.float64))[0].tolist()
        ax.plot(xy[0], xy[1], style, ms=9, mfc="none" if style == "wo" else None,
                label=f"measured ({label})" if style != "wo" else label)
    if marks:
        ax.legend(loc="upper right", fontsize="small")


def _imshow_flux(ax, flux, title):
    draw_flux(ax, flux, title)


def plot_demo(plant, per_heliostat, receiver_flux, spot, path) -> None:
    """Field layout coloured by cosine efficiency, receiver flux and one calibration spot, saved to ``path``.

    ``per_heliostat``: one dict per heliostat with ``position_enu_m`` [m] and ``cosine_efficiency`` [1];
    ``receiver_flux`` and ``spot``: :class:`~heliotwin.raytrace.flux.FluxImage` (bitmaps [W/m^2], the first
    image drawn in [kW/m^2]).
    """
    fig = Figure(figsize=(17, 5))
    axes = fig.subplots(1, 3)
    xs = [p["position_enu_m"][0] for p in per_heliostat]
    ys = [p["position_enu_m"][1] for p in per_heliostat]
    cs = [p["cosine_efficiency"] for p in per_heliostat]
    sc = axes[0].scatter(xs, ys, c=cs, cmap="viridis", s=30)
    axes[0].plot([0], [0], "k^", ms=10, label="tower")
    axes[0].set_aspect("equal")
    axes[0].set_xlabel("east [m]")
    axes[0].set_ylabel("north [m]")
    axes[0].set_title("heliostat field")
    axes[0].legend()
    fig.colorbar(sc, ax=axes[0], label="cosine efficiency")
    _imshow_flux(axes[1], receiver_flux, "receiver (unrolled cylinder)")
    _imshow_flux(axes[2], spot, f"focal spot on {spot.target.name}")
    save_figure(fig, path, make_folder=True)  # as before: plots make their folder


#: Above this many heliostats :func:`plot_validation` draws distributions instead of a bar per heliostat (a bar per
#: heliostat of a 2,000-heliostat plant is a figure 700 inches wide).
VALIDATION_BARS_MOST = 40


def plot_validation(report: dict, path) -> None:
    """Per-heliostat median pointing error, spot distance and record counts of a validation report.

    Bars are labelled with units; the count panel shows how many records (and images) each median rests on,
    so a reader sees which heliostats' errors are backed by few records. Above :data:`VALIDATION_BARS_MOST`
    heliostats: the share of heliostats at or below each error and distance (empirical CDFs, the worst named) and
    a histogram of the record counts.
    """
    hs = report["heliostats"]
    ids = list(hs)
    if len(ids) > VALIDATION_BARS_MOST:
        _plot_validation_plant(report, path)
        return
    fig = Figure(figsize=(max(8, 0.35 * len(ids)), 9))
    axes = fig.subplots(3, 1, sharex=True, gridspec_kw={"height_ratios": [3, 3, 2]})
    axes[0].bar(ids, [hs[h]["median_pointing_error_mrad"] for h in ids], color="tab:blue")
    axes[0].set_yscale("log")
    axes[0].set_ylabel("median pointing error [mrad]")
    axes[0].axhline(report["overall"]["median_pointing_error_mrad"], color="k", ls="--", lw=1,
                    label="median over heliostats")
    axes[0].legend()
    axes[1].bar(ids, [hs[h]["median_distance_m"] for h in ids], color="tab:orange")
    axes[1].set_yscale("log")
    axes[1].set_ylabel("median spot distance [m]")
    counts = [hs[h].get("records", 0) for h in ids]
    images = [hs[h].get("images", 0) for h in ids]
    axes[2].bar(ids, counts, color="tab:gray", label="records")
    axes[2].bar(ids, images, color="tab:green", label="with a centred image")
    axes[2].set_ylabel("records [-]")
    axes[2].legend(fontsize="small")
    axes[2].tick_params(axis="x", rotation=90)
    axes[2].set_xlabel("heliostat")
    _validation_title(fig, report)
    save_figure(fig, path, make_folder=True)  # as before: plots make their folder


def _validation_title(fig, report: dict) -> None:
    settings = report.get("settings") or {}
    fig.suptitle(f"{settings.get('kinematics', 'nominal')} kinematics, {settings.get('surface', 'ideal')} surface "
                 f"vs measured focal spots")


def _plot_validation_plant(report: dict, path) -> None:
    """:func:`plot_validation` for a plant: distributions over heliostats, a fixed-size figure."""
    hs = report["heliostats"]
    ids = list(hs)
    fig = Figure(figsize=(13, 4))
    axes = fig.subplots(1, 3)
    for ax, key, label, colour in ((axes[0], "median_pointing_error_mrad", "median pointing error [mrad]", "tab:blue"),
                                   (axes[1], "median_distance_m", "median spot distance [m]", "tab:orange")):
        v = np.array([hs[h].get(key) if hs[h].get(key) is not None else np.nan for h in ids], dtype=float)
        ok = np.isfinite(v) & (v > 0)
        order = np.argsort(v[ok])
        ax.step(v[ok][order], np.arange(1, ok.sum() + 1) / max(1, ok.sum()), where="post", color=colour)
        ax.set_xscale("log")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
        worst = [ids[i] for i in np.flatnonzero(ok)[order][::-1][:5]]
        ax.set_title("worst: " + ", ".join(worst), fontsize=8)
    axes[0].set_ylabel(f"share of the {len(ids)} heliostats at or below")
    counts = np.array([hs[h].get("records", 0) for h in ids], dtype=float)
    axes[2].hist(counts, bins=30, color="tab:gray")
    axes[2].set_xlabel("records per heliostat [-]")
    axes[2].set_ylabel("heliostats [-]")
    _validation_title(fig, report)
    save_figure(fig, path, make_folder=True)


def plot_field_demo(folder, plant, before, aimed, rep, limit: float, time_utc: str) -> None:
    """The whole-field demo's four figures in ``folder`` (colour bars, titles, units): ``field_efficiency.png``,
    ``losses.png``, ``flux_equator.png`` and ``flux_optimised.png``.

    Parameters
    ----------
    folder : pathlib.Path
    plant : Plant
        On the CPU.
    before : heliotwin.raytrace.field.FieldResult
        Equator aiming (flux [rows, cols] [W/m^2], efficiency [H]).
    aimed : heliotwin.optimise.aimpoints.AimResult
        Optimised aim points (flux [rows, cols] [W/m^2], power [W]).
    rep : dict
        The demo's report so far (``sun``, ``field``, ``receiver``, ``losses`` and ``chain``: the demo's chain
        with the tower's shadow, in the efficiency map, its title and the waterfall; the receiver maps are the
        field model's, without it, and say so).
    limit : float
        Peak-flux limit [W/m^2].
    time_utc : str
        The instant [UTC] named in the title (ISO).
    """
    pos = plant.field.kinematics.position.numpy()
    sun = rep["sun"]
    instant = {"time_utc": time_utc, "sun_enu": sun.get("direction_enu")}
    when = instant_line(instant)  # the one time format, the sun in PAINT's convention, labelled
    chain = rep.get("chain") or {}
    fig = Figure(figsize=(7, 6))
    ax = fig.add_subplot()
    # the demo's chain: each heliostat's efficiency with the tower's shadow (the field model's product leaves it out)
    sc = ax.scatter(pos[:, 0], pos[:, 1], c=(before.efficiency * before.tower_shading).numpy(), s=5, cmap="viridis")
    ax.plot([0.0], [0.0], marker="^", color="k", markersize=8, linestyle="none", label="tower")
    fig.colorbar(sc, ax=ax, label="optical efficiency per heliostat, tower's shadow included [-]")
    total = chain.get("efficiency", rep["field"]["efficiency_power_weighted"]["total"])
    ax.set(xlabel="east [m]", ylabel="north [m]", aspect="equal",
           title=f"{len(pos)} heliostats, {when}\nfield efficiency {total:.3f} (power-weighted, tower's shadow "
                 "included)")
    ax.legend(loc="lower right")
    save_figure(fig, folder / "field_efficiency.png")

    plot_loss_waterfall(rep["losses"], rep["dni_w_m2"] * rep["mirror_area_m2"], folder / "losses.png",
                        title=f"{len(pos)} heliostats, {when}")

    receiver = plant.targets["receiver"]
    maps = {"equator aiming": before.flux, "optimised aim points": aimed.flux}
    powers = {"equator aiming": rep["receiver"]["power_w"], "optimised aim points": aimed.power_w}
    vmax = max(float(before.flux.max()), float(aimed.flux.max()))
    tower = chain.get("tower_shading_power_weighted")
    without = ("" if tower is None else
               f"\nmaps and MW without the tower's shadow ({100 * (1 - tower):.1f} % of the power: losses.png)")
    plot_receiver_flux(maps, receiver, folder / "flux_before_after.png", limit_w_m2=limit, powers_w=powers,
                       title=f"{len(pos)} heliostats: peak-flux limit {limit / 1e3:.0f} kW/m²{without}",
                       instant=instant)
    for name, label in (("flux_equator", "equator aiming"), ("flux_optimised", "optimised aim points")):
        plot_receiver_flux({label: maps[label]}, receiver, folder / f"{name}.png", limit_w_m2=limit,
                           powers_w=powers, vmax_w_m2=vmax, instant=instant, title=without.strip() or None)


# ----------------------------------------------------------------------------------------- loss waterfall
#: The waterfall's bar label of a chain stage where it is not the factor's name.
STAGE_LABELS = {"tower_shading": "tower shadow"}


def loss_waterfall(losses: dict, dni_area_w: float) -> list[dict]:
    """The steps of the loss waterfall: from the DNI on the mirror area down to the receiver.

    Parameters
    ----------
    losses : dict
        Per stage of the chain, in chain order, ``{"power_w": lost [W]}``: the power lost at that stage (cosine
        first, reflectance last), as the demo's report holds it (:data:`~heliotwin.raytrace.field.FACTORS`, and
        in the demo the tower's shadow, ``tower_shading``, after the heliostats' shading); entries that are not
        such dicts are skipped.
    dni_area_w : float
        DNI x total mirror area [W]: the top of the waterfall.

    Returns
    -------
    list of dict
        One per factor: ``name``, ``lost_pct`` (the power lost at that stage, in % of DNI x mirror area, so the
        steps add up to the plant's loss), ``top_pct`` (what remains before the stage [%]), ``power_w`` [W]
        and ``own_loss_pct`` (1 - the factor, power-weighted over what reaches that stage [%]).
    """
    total = max(float(dni_area_w), 1e-30)
    remaining, steps = total, []
    for name in [k for k, v in losses.items() if isinstance(v, dict) and "power_w" in v]:
        lost = float(losses[name]["power_w"])
        steps.append({"name": name, "lost_pct": 100.0 * lost / total, "top_pct": 100.0 * remaining / total,
                      "power_w": lost, "own_loss_pct": 100.0 * lost / max(remaining, 1e-30)})
        remaining -= lost
    return steps


def plot_loss_waterfall(losses: dict, dni_area_w: float, path=None, *, title: str | None = None):
    """The loss chain as a waterfall (:func:`loss_waterfall`): a bar for DNI x mirror area (100 %), one
    falling bar per factor (its loss in % of DNI x mirror area and in MW; its own loss 1 - factor in brackets),
    and the bar of what reaches the receiver; the falling bars add up to the plant's loss.

    Parameters
    ----------
    losses : dict
        Per factor ``{"power_w": lost [W]}`` (:func:`loss_waterfall`).
    dni_area_w : float
        DNI x total mirror area [W].
    path : str or os.PathLike, optional
        Write the figure here (atomically).
    title : str, optional
        First title line (the second says what the losses add up to [%]).

    Returns
    -------
    matplotlib.figure.Figure
        Made without pyplot; the falling bars are the axes' patches with the gid ``"loss"``.
    """
    steps = loss_waterfall(losses, dni_area_w)
    left = steps[-1]["top_pct"] - steps[-1]["lost_pct"] if steps else 100.0
    fig = Figure(figsize=(8.5, 4.6), layout="constrained")
    ax = fig.add_subplot()
    names = ["DNI x mirror area"] + [STAGE_LABELS.get(s["name"], s["name"]) for s in steps] + ["on the receiver"]
    ax.bar(names[0], 100.0, color="tab:gray")
    ax.annotate(f"100 %\n{dni_area_w / 1e6:.2f} MW", (0, 100.0), ha="center", va="bottom", fontsize=8)
    for i, s in enumerate(steps, 1):
        ax.bar(names[i], s["lost_pct"], bottom=s["top_pct"] - s["lost_pct"], color="tab:red", gid="loss")
        ax.annotate(f"-{s['lost_pct']:.1f} %\n{s['power_w'] / 1e6:.2f} MW\n({s['own_loss_pct']:.1f} % of its input)",
                    (i, s["top_pct"]), ha="center", va="bottom", fontsize=7)
    ax.bar(names[-1], left, color="tab:green")
    ax.annotate(f"{left:.1f} %\n{left * dni_area_w / 1e8:.2f} MW", (len(names) - 1, left), ha="center",
                va="bottom", fontsize=8)
    ax.set(ylabel="share of DNI x mirror area [%]", ylim=(0, 125))
    ax.tick_params(axis="x", rotation=20)
    head = f"loss waterfall: the losses add up to {100.0 - left:.1f} %, {left:.1f} % reaches the receiver"
    ax.set_title(f"{title}\n{head}" if title else head, fontsize=10)
    if path is not None:
        save_figure(fig, path, tight=False)
    return fig


# ------------------------------------------------------------------------------------ the receiver's axes
def _compass(azimuth_deg: float) -> str:
    return ("N", "NE", "E", "SE", "S", "SW", "W", "NW")[round((azimuth_deg % 360.0) / 45.0) % 8]


def angle_origin(receiver) -> str:
    """Where 0 deg of a cylindrical receiver's angle axis points, in words: ``"0° = aperture normal, facing
    N (compass bearing 0°); + towards E"`` (bearings clockwise from north [deg], of the horizontal parts of the
    receiver's ``normal`` and ``right``: a direction on the ground, named so, never a sun azimuth)."""
    n, r = (v.detach().cpu().to(torch.float64).tolist() for v in (receiver.normal, receiver.right))
    az = float(np.degrees(np.arctan2(n[0], n[1]))) % 360.0
    az_r = float(np.degrees(np.arctan2(r[0], r[1]))) % 360.0
    return f"0° = aperture normal, facing {_compass(az)} (compass bearing {az:.0f}°); + towards {_compass(az_r)}"


def instant_line(instant: dict | None) -> str:
    """``"2023-03-20T11:30Z, sun azimuth 7.6° (PAINT: 0 = south, +90 = east), elevation 38.1°"`` of ``instant``
    (``time_utc`` ISO text and/or ``sun_enu`` [3], the unit vector towards the sun, ENU): the time in the one
    format of :func:`heliotwin.timefmt.utc_text`, the sun in PAINT's convention, the convention of the flags and
    the JSON (:func:`heliotwin.timefmt.sun_text`)."""
    if not instant:
        return ""
    parts = []
    if instant.get("time_utc"):
        parts.append(utc_or_label(str(instant["time_utc"])))  # a label may name the sun angles instead
    sun = instant.get("sun_enu")
    if sun is not None:
        parts.append(sun_text(*(float(torch.rad2deg(a)) for a in paint_angles_from_direction(sun))))
    return ", ".join(parts)


# --------------------------------------------------------------------------------------- receiver maps
def receiver_extent(receiver) -> list[float]:
    """``[arc_min, arc_max, height_min, height_max]`` [m] of the receiver map of ``receiver`` (a cylinder
    unrolled along its arc, or a planar receiver's own right/up axes), as the field model draws it."""
    return [float(v) for v in target_extent(receiver, 1)[0].cpu()]


def plot_receiver_flux(maps: dict, receiver, path=None, *, limit_w_m2: float | None = None,
                       title: str | None = None, powers_w: dict | None = None, vmax_w_m2: float | None = None,
                       instant: dict | None = None):
    """Receiver flux maps side by side on ONE colour scale, so that before and after compare by eye.

    Parameters
    ----------
    maps : dict
        Panel label -> flux map [rows, cols] [W/m^2] (torch or numpy; row 0 = top of the receiver).
    receiver : CylinderTarget or PlanarTarget
        Gives the axes: the arc along the unrolled cylinder [m] (and, on a cylinder, the angle around it
        [deg] on the top axis) or the planar receiver's width [m]; height [m] up.
    path : str or os.PathLike, optional
        Write the figure here (atomically; format from the extension).
    limit_w_m2 : float, optional
        The peak-flux limit: drawn as a dashed contour on every panel, named in the colour bar.
    title : str, optional
        Figure title.
    powers_w : dict, optional
        Panel label -> receiver power [W], printed in the panel title.
    vmax_w_m2 : float, optional
        Top of the colour scale [W/m^2] (default: the largest value of all panels, or the limit when higher):
        give the same value to figures drawn one by one so that they compare.
    instant : dict, optional
        ``time_utc`` (ISO) and/or ``sun_enu`` [3] (unit vector towards the sun): named in the figure's title
        (:func:`instant_line`), so that two saved maps can be told apart.

    Returns
    -------
    matplotlib.figure.Figure
        Made without pyplot. Each panel's title gives its peak [kW/m^2] and its cell of the peak; the colour
        bar is in kW/m^2 from 0 to the largest value of all panels (or the limit, when higher).
    """
    arrays = {k: (v.detach().cpu().numpy() if torch.is_tensor(v) else np.asarray(v)).astype(float) / 1e3
              for k, v in maps.items()}
    ext = receiver_extent(receiver)
    vmax = max([float(a.max()) for a in arrays.values()] + [limit_w_m2 / 1e3 if limit_w_m2 else 0.0]
               + [vmax_w_m2 / 1e3 if vmax_w_m2 else 0.0]) or 1.0
    n = len(arrays)
    width = ext[1] - ext[0]
    fig = Figure(figsize=(min(6.5 * n, 20), 3.6 if width > 2 * (ext[3] - ext[2]) else 4.8), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, n, sharey=True))
    im = None
    for ax, (label, a) in zip(axes, arrays.items()):
        im = ax.imshow(a, extent=ext, aspect="auto", vmin=0.0, vmax=vmax, cmap="inferno", interpolation="nearest")
        rows, cols = a.shape
        r, c = np.unravel_index(int(np.argmax(a)), a.shape)
        px = ext[0] + (c + 0.5) * (ext[1] - ext[0]) / cols
        py = ext[3] - (r + 0.5) * (ext[3] - ext[2]) / rows
        ax.plot(px, py, marker="+", color="cyan", ms=10, mew=1.5, ls="none", label="peak")
        if limit_w_m2 and float(a.max()) > 0:
            xs = ext[0] + (np.arange(cols) + 0.5) * (ext[1] - ext[0]) / cols
            ys = ext[3] - (np.arange(rows) + 0.5) * (ext[3] - ext[2]) / rows
            if a.min() < limit_w_m2 / 1e3 < a.max():
                ax.contour(xs, ys, a, levels=[limit_w_m2 / 1e3], colors="cyan", linestyles="--", linewidths=1.2)
        power = (powers_w or {}).get(label)
        ax.set_title(f"{label}: peak {float(a.max()):.0f} kW/m²" + (f", {power / 1e6:.2f} MW" if power else ""),
                     fontsize=10)
        if isinstance(receiver, CylinderTarget):
            ax.set_xlabel("arc along the unrolled receiver [m]")
            radius = float(receiver.radius)
            top = ax.secondary_xaxis("top", functions=(lambda x, r=radius: np.degrees(x / r),
                                                       lambda d, r=radius: np.radians(d) * r))
            top.set_xlabel(f"angle around the receiver axis [deg] ({angle_origin(receiver)})", fontsize=8)
        else:
            ax.set_xlabel("across the receiver, 'right' [m]")
    axes[0].set_ylabel("height on the receiver [m]")
    label = "flux [kW/m²]" + (f"  (dashed: limit {limit_w_m2 / 1e3:.0f})" if limit_w_m2 else "")
    bar = fig.colorbar(im, ax=list(axes), label=label, shrink=0.95)
    if limit_w_m2:
        bar.ax.axhline(limit_w_m2 / 1e3, color="cyan", ls="--", lw=1.5)
        axes[-1].plot([], [], color="cyan", ls="--", label=f"limit {limit_w_m2 / 1e3:.0f} kW/m²")
    axes[-1].legend(loc="lower right", fontsize=8, framealpha=0.6)
    when = instant_line(instant)
    if title or when:
        fig.suptitle("\n".join(t for t in (when, title) if t), fontsize=10 if n == 1 else 12)
    if path is not None:
        save_figure(fig, path, tight=False)
    return fig


def plot_prediction(report: dict, path=None):
    """A year of one heliostat's predicted flux (:func:`heliotwin.workflows.predict.predict`'s report): the
    power on the target [kW], the peak flux [kW/m^2] of the learned and the ideal surface, and how far
    the two images differ (L1 of unit-sum images) at every daylight instant, so the seasons read at a glance.

    Returns
    -------
    matplotlib.figure.Figure
        Made without pyplot.
    """
    series = report.get("series") or {}
    times = pd.to_datetime(series.get("time", []), utc=True).tz_convert(None)
    fig = Figure(figsize=(10, 7), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    panels = ((("power_w", "learned surface"),), (("peak_learned_w_m2", "learned surface"),
                                                   ("peak_ideal_w_m2", "ideal surface")),
              (("l1_ideal_vs_learned", "ideal vs learned"),))
    labels = ("power on the target [kW]", "peak flux [kW/m²]", "L1 of the unit-sum images [-]")
    scales = (1e-3, 1e-3, 1.0)
    for ax, keys, label, scale in zip(axes, panels, labels, scales):
        for key, name in keys:
            values = series.get(key)
            if values is not None and len(times):
                ax.plot(times, np.asarray(values, dtype=float) * scale, ".", ms=2, label=name)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if len(keys) > 1:
            ax.legend(fontsize=8, markerscale=4)
    axes[-1].set_xlabel("date (UTC)")
    fig.suptitle(f"{report.get('heliostat')} on {report.get('target')}, {report.get('year')}, every "
                 f"{report.get('every')} ({report.get('instants')} daylight instants)")
    if path is not None:
        save_figure(fig, path, tight=False)
    return fig

