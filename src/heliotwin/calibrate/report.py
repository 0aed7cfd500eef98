"""The calibration report's layout and the plots a plant engineer reads at a glance.

The report is written by :func:`heliotwin.io.report.write_json` (strict JSON, atomic). Layout
(``heliotwin calibrate --json report.json``); over heliostats, ``<stat>_of_<stat>`` names which statistic
over heliostats of which per-heliostat statistic::

    config              the run's options
    overall             median_of_mean_test_mrad (median over heliostats of each heliostat's mean test
                        error: the headline figure), mean_of_mean_test_mrad, median_of_median_test_mrad,
                        nominal_median_of_mean_test_mrad, nominal_mean_of_mean_test_mrad,
                        median_of_mean_train_mrad, median_of_median_test_miss_m,
                        mean_of_mean_train_test_distance_rad, seconds, fit_seconds, skipped_heliostats,
                        skipped_records, dropped_no_time, method_info
    heliostats.<HID>    status ("ok"/"skipped"), reason, split (sizes, dropped_no_time, coverage,
                        mean_train_test_distance_rad), train/validation/test/nominal_test
                        ({n, median_mrad, mean_mrad, max_mrad, median_miss_m}), mean_test_mrad,
                        median_test_mrad, nominal_mean_test_mrad, fit_seconds_share, parameters,
                        suspicious, method_info
    skipped_records     [{record_id, heliostat_id, reason}]
    plots               file names of the figures written next to the JSON

Plots (matplotlib, Agg): ``<stem>-sky.png`` test error against sun azimuth and elevation,
``<stem>-heliostats.png`` per-heliostat mean test error before/after, ``<stem>-training-size.png``
test error against the number of training records; for ``heliotwin plan --json``, ``<stem>-plan.png``
(:func:`plot_plan`) the year's candidate sun positions coloured by the predictive spread of the normal, with
the proposed records numbered.
"""
from __future__ import annotations

import os

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from ..io.report import save_figure
from ..timefmt import AZIMUTH_LABEL

#: Above this many heliostats the per-heliostat plots change form: one colour and legend entry per heliostat (sky),
#: one bar pair per heliostat (heliostats) stop being readable, and a bar per heliostat of a 2,000-heliostat plant made
#: a 100,000-pixel-wide PNG in 20 s.
PER_HELIOSTAT_MOST = 20


def plot_sky(path, arrays: dict, title: str = "") -> None:
    """Per-record test error against sun azimuth and elevation: one colour per heliostat up to
    :data:`PER_HELIOSTAT_MOST` heliostats; above, every record in one colour with the median per 10-degree bin."""
    fig = Figure(figsize=(11, 4))
    axes = fig.subplots(1, 2, sharey=True)
    ids = arrays["heliostat_ids"]
    err = np.asarray(arrays["test_error_mrad"], dtype=float)
    few = len(ids) <= PER_HELIOSTAT_MOST
    cmap = matplotlib.colormaps["tab20"]
    for ax, key, label in ((axes[0], "test_azimuth", AZIMUTH_LABEL),
                           (axes[1], "test_elevation", "sun elevation [deg]")):
        x = np.degrees(np.asarray(arrays[key], dtype=float))
        if few:
            for h, hid in enumerate(ids):
                m = arrays["test_heliostat"] == h
                if m.any():
                    ax.scatter(x[m], err[m], s=12, color=cmap(h % 20), label=hid)
        elif x.size:
            ax.scatter(x, err, s=3, color="tab:blue", alpha=0.25, linewidths=0, rasterized=True,
                       label=f"{x.size} test records, {len(ids)} heliostats")
            edges = np.arange(np.floor(x.min() / 10) * 10, x.max() + 10, 10.0)
            which = np.digitize(x, edges)
            mid = [(0.5 * (edges[b - 1] + edges[b]), np.median(err[which == b]))
                   for b in range(1, len(edges)) if (which == b).sum() >= 5]
            if mid:
                ax.plot(*zip(*mid), "o-", color="tab:red", label="median per 10 deg")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("calibrated test pointing error [mrad]")
    axes[1].legend(fontsize=7, ncol=2 if few else 1, loc="upper right")
    fig.suptitle(title or "test error against sun position")
    save_figure(fig, path)


def plot_plan(path, ans: dict) -> None:
    """Sky map of a :func:`heliotwin.calibrate.protocol.plan.plan` answer computed with ``sky=True``: every candidate
    time at its sun azimuth (PAINT: 0 = south, +90 = east) and elevation [deg], coloured by the predicted error of
    the normal there on the plan's day [mrad], and the proposed records numbered in the order they are taken; the
    title gives the predicted pointing spread (:mod:`heliotwin.calibrate.spread`) before and after them."""
    grid = ans["sky"]
    fig = Figure(figsize=(8, 4.5))
    ax = fig.subplots()
    sc = ax.scatter(grid["sun_azimuth_deg"], grid["sun_elevation_deg"], c=grid["std_now_mrad"], s=6,
                    cmap=matplotlib.colormaps["viridis"])
    fig.colorbar(sc, ax=ax, label=f"predicted error of the normal on {ans['spread_day']} [mrad]")
    for i, p in enumerate(ans["proposals"], 1):
        ax.scatter([p["sun_azimuth_deg"]], [p["sun_elevation_deg"]], s=90, facecolors="none", edgecolors="tab:red")
        ax.annotate(str(i), (p["sun_azimuth_deg"], p["sun_elevation_deg"]), xytext=(5, 5),
                    textcoords="offset points", color="tab:red")
    after = ans["proposals"][-1]["spread_after_mrad"] if ans["proposals"] else np.nan
    ax.set_xlabel(AZIMUTH_LABEL)
    ax.set_ylabel("sun elevation [deg]")
    ax.invert_xaxis()  # east on the left, as a person facing south sees the sky
    ax.grid(alpha=0.3)
    ax.set_title(f"{ans['heliostat']} (target {ans['target']}): predicted pointing spread on {ans['spread_day']} "
                 f"{ans['spread_now_mrad']:.3f} -> {after:.3f} mrad after {len(ans['proposals'])} records")
    save_figure(fig, path)


def plot_heliostats(path, report: dict, title: str = "") -> None:
    """Per-heliostat mean test error, nominal vs calibrated (log scale): a bar pair per heliostat up to
    :data:`PER_HELIOSTAT_MOST` heliostats; above, both as the share of heliostats at or below each error (empirical
    CDFs) with the worst calibrated heliostats named."""
    rows = [(h, r) for h, r in report["heliostats"].items() if r.get("status") == "ok"]
    few = len(rows) <= PER_HELIOSTAT_MOST
    fig = Figure(figsize=(max(5, 0.6 * len(rows) + 2), 4) if few else (8, 4.5))
    ax = fig.subplots()
    nom = np.array([r["nominal_mean_test_mrad"] or np.nan for _, r in rows], dtype=float)
    cal = np.array([r["mean_test_mrad"] or np.nan for _, r in rows], dtype=float)
    method = report["config"].get("method")
    if few:
        x = np.arange(len(rows))
        ax.bar(x - 0.2, nom, 0.4, label="nominal", color="0.7")
        ax.bar(x + 0.2, cal, 0.4, label=f"calibrated ({method})", color="tab:blue")
        ax.set_xticks(x, [h for h, _ in rows], rotation=45)
        ax.set_yscale("log")
        ax.set_ylabel("mean test pointing error [mrad]")
        ax.grid(alpha=0.3, axis="y")
    else:
        for values, label, colour in ((nom, "nominal", "0.5"), (cal, f"calibrated ({method})", "tab:blue")):
            v = np.sort(values[np.isfinite(values) & (values > 0)])
            if v.size:
                ax.step(v, np.arange(1, v.size + 1) / v.size, where="post", color=colour,
                        label=f"{label}: median {np.median(v):.3g} mrad")
        ax.set_xscale("log")
        ax.set_xlabel("mean test pointing error [mrad]")
        ax.set_ylabel(f"share of the {len(rows)} heliostats at or below")
        ax.grid(alpha=0.3)
        worst = sorted((c, h) for (h, _), c in zip(rows, cal) if np.isfinite(c))[-5:][::-1]
        if worst:
            ax.text(0.99, 0.02, "worst: " + ", ".join(f"{h} {c:.2f}" for c, h in worst), transform=ax.transAxes,
                    ha="right", va="bottom", fontsize=7)
    ax.legend()
    ax.set_title(title or "per-heliostat test error before/after calibration")
    save_figure(fig, path)


def plot_training_size(path, curves: dict, title: str = "") -> None:
    """Median over heliostats of the mean test error against the number of training records.

    Parameters
    ----------
    curves : dict of label -> list of (n_train, median_of_mean_test_mrad)
    """
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    for label, pts in curves.items():
        pts = [(n, e) for n, e in pts if e is not None]
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=label)
    ax.set_xlabel("training records per heliostat (incl. validation)")
    ax.set_ylabel("median over heliostats of mean test error [mrad]")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title(title or "test error vs number of training records")
    save_figure(fig, path)


def write_plots(json_path, report: dict, arrays: dict, curves: dict | None = None) -> list[str]:
    """Write the standard figures next to ``json_path``; returns their paths."""
    stem = os.path.splitext(os.fspath(json_path))[0]
    out = []
    if arrays.get("heliostat_ids"):
        p = f"{stem}-sky.png"
        plot_sky(p, arrays)
        out.append(p)
        p = f"{stem}-heliostats.png"
        plot_heliostats(p, report)
        out.append(p)
    if curves:
        p = f"{stem}-training-size.png"
        plot_training_size(p, curves)
        out.append(p)
    return out
