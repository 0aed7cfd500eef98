"""Yearly flux prediction of one heliostat with a learned surface (sun every N minutes of daylight, pvlib).

For every daylight instant of a year the heliostat is aimed at its target's centre
(:func:`~heliotwin.field.kinematics.aimed_pose`) and its flux is computed with the learned and with the ideal
surface (same optics, same centred 6 m window). Without measurements the per-instant quantities are the
shape difference ``L1(ideal, learned)``, peak flux and power of both. When a ground-truth surface is known
(in silico) the IMP ``L1(ideal, truth) / L1(learned, truth) - 1`` is reported per instant with its
statistics over the year.

Shapes: T instants; R window pixels per side.
"""
from __future__ import annotations

import math
import statistics
from dataclasses import dataclass

import torch

from ..errors import HeliotwinError
from ..field import kinematics as kin_ops
from ..field.plant import Kinematics, SunSettings, Surfaces
from ..field.targets import PlanarTarget
from ..io.images import CENTERED_WINDOW_M
from ..progress import iterate
from ..sun import daylight_times, direction_from_paint_angles
from . import losses
from .imaging import predict_images
from .observations import Observations

__all__ = ["yearly_flux", "YearSampling", "CenteredImaging", "summarize"]


@dataclass(frozen=True)
class YearSampling:
    """Which instants of a year :func:`yearly_flux` visits.

    Attributes
    ----------
    year : int
    every : str
        pandas frequency, e.g. ``"30min"``.
    min_elevation_deg : float
        Instants with the sun lower than this [deg] are left out.
    """

    year: int = 2023
    every: str = "30min"
    min_elevation_deg: float = 5.0


@dataclass(frozen=True)
class CenteredImaging:
    """How :func:`yearly_flux` renders each instant (the centred window of the PAINT images).

    Attributes
    ----------
    samples : (int, int)
        Surface samples per facet (u, v).
    resolution : int
        Window pixels per side (R).
    size_m : float
        Window side [m].
    chunk : int
        Instants rendered per batch (memory bound).
    kernel_supersample : int
        Sub-samples per pixel and axis of the sun-cone footprint kernel (training uses 4; 2 changes the
        images by < 1e-3 in L1 and is 4x cheaper -- the kernel is the dominant cost of a yearly run).
    """

    samples: tuple = (24, 24)
    resolution: int = 64
    size_m: float = CENTERED_WINDOW_M
    chunk: int = 48
    kernel_supersample: int = 2


def yearly_flux(kinematics: Kinematics, target: PlanarTarget, site: tuple, learned: Surfaces, ideal: Surfaces,
                sun: SunSettings, *, when: YearSampling = YearSampling(), imaging: CenteredImaging = CenteredImaging(),
                truth: Surfaces | None = None, progress: bool = True) -> dict:
    """Flux of one heliostat on ``target`` over a year.

    Parameters
    ----------
    kinematics : Kinematics
        One heliostat.
    target : PlanarTarget
    site : (lat_deg, lon_deg, alt_m)
        Latitude and longitude [deg], altitude [m].
    learned, ideal : Surfaces
        Control points ``[1, F, nu, nv, 3]`` [m], heliostat frame.
    sun : SunSettings
        Sunshape, slope error, DNI and reflectivity (the flux scales with DNI x reflectivity).
    when : YearSampling
        Year, time step and lowest sun.
    imaging : CenteredImaging
        Samples, window and batch size of the renders.
    truth : Surfaces, optional
        Ground truth (in silico): enables IMP.

    Returns
    -------
    dict of lists (length T): ``time`` (ISO [UTC]), ``sun_azimuth_deg`` [deg] (PAINT convention: 0 = south,
    +90 = east), ``sun_elevation_deg`` [deg], ``l1_ideal_vs_learned`` [1] (of unit-sum images),
    ``peak_learned_w_m2``, ``peak_ideal_w_m2`` [W/m^2], ``power_w`` [W] (learned surface, inside the window)
    and, with ``truth``, ``l1_ideal``, ``l1_learned``, ``imp`` [1].
    """
    times, az, el = daylight_times(when.year, when.every, site[0], site[1], site[2],
                                   min_elevation_deg=when.min_elevation_deg)
    if len(times) == 0:
        raise HeliotwinError(f"no daylight instants in {when.year} every {when.every}")
    sund = direction_from_paint_angles(az, el).to(kinematics.position.device)  # pvlib's angles are on the CPU
    out = {k: [] for k in ("l1_ideal_vs_learned", "peak_learned_w_m2", "peak_ideal_w_m2", "power_w")}
    if truth is not None:
        out.update({"l1_ideal": [], "l1_learned": [], "imp": []})
    kw = dict(samples=imaging.samples, resolution=imaging.resolution, size_m=imaging.size_m,
              kernel_supersample=imaging.kernel_supersample)
    chunk = imaging.chunk
    for start in iterate(range(0, len(times), chunk), "heliotwin predict: year", unit="chunk", enabled=progress):
        sl = slice(start, start + chunk)
        s = sund[sl]
        aim = target.center.to(torch.float64).expand(s.shape[0], 3)
        rot, conc = kin_ops.aimed_pose(kinematics, aim, s)
        obs = Observations(s, rot, conc, [target] * s.shape[0], None, [])
        with torch.no_grad():
            kernels: dict = {}
            img_l, _, _ = predict_images(learned, obs, sun, kernels=kernels, **kw)
            # Same kernels for every surface at an instant: the comparison isolates the shape.
            img_i, _, _ = predict_images(ideal, obs, sun, kernels=kernels, **kw)
            out["l1_ideal_vs_learned"] += losses.l1(img_i, img_l).tolist()
            out["peak_learned_w_m2"] += img_l.amax((-2, -1)).tolist()
            out["peak_ideal_w_m2"] += img_i.amax((-2, -1)).tolist()
            pix = (imaging.size_m / imaging.resolution) ** 2
            out["power_w"] += (img_l.sum((-2, -1)) * pix).tolist()
            if truth is not None:
                img_t, _, _ = predict_images(truth, obs, sun, kernels=kernels, **kw)
                a, b = losses.l1(img_i, img_t), losses.l1(img_l, img_t)
                out["l1_ideal"] += a.tolist()
                out["l1_learned"] += b.tolist()
                out["imp"] += (a / b.clamp_min(1e-12) - 1.0).tolist()
    out["time"] = [t.isoformat() for t in times]
    out["sun_azimuth_deg"] = [math.degrees(float(x)) for x in az]
    out["sun_elevation_deg"] = [math.degrees(float(x)) for x in el]
    return out


def _stats(values) -> dict:
    v = sorted(float(x) for x in values)
    if not v:
        return {}
    q = lambda p: v[min(len(v) - 1, max(0, int(round(p * (len(v) - 1)))))]  # noqa: E731
    return {"mean": statistics.fmean(v), "median": statistics.median(v), "p05": q(0.05), "p95": q(0.95),
            "min": v[0], "max": v[-1]}


def summarize(series: dict) -> dict:
    """Statistics over the year of every numeric series in :func:`yearly_flux`'s output."""
    return {k: _stats(v) for k, v in series.items() if k != "time" and v and isinstance(v[0], float)}
