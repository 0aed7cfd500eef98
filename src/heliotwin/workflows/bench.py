"""The ``bench`` workflow: forward / backward throughput and time-to-accuracy of the tracers (``heliotwin bench``).

The scene is synthetic and self-contained: one focused square heliostat (``surface_points`` points on a
4 m x 4 m paraboloid-like mirror, focal length = slant range) about 110 m north of an 8 m x 8 m
north-facing target, traced with the default optics (Buie sun, 1 mrad slope error).
"""
from __future__ import annotations

import math
import os
import platform
import resource
import time

import torch

from ..devices import resolve_device, to_device
from ..field.plant import SunSettings
from ..field.targets import PlanarTarget
from ..progress import Stages
from ..raytrace.flux import normalized_l1
from ..raytrace.gaussian import trace_gaussian
from ..raytrace.montecarlo import RaySampling, trace_mc
from .sizes import MAX_SURFACE_POINTS, check_range, check_trace_sizes

__all__ = ["run_benchmark", "benchmark_scene"]


def benchmark_scene(surface_points: int = 10000, dtype=torch.float32):
    """A focused heliostat facing a planar target.

    Parameters
    ----------
    surface_points : int
        Approximate number of mirror points P (rounded to a square grid) on a 4 m x 4 m mirror.
    dtype : torch.dtype
        Of the returned point/normal/area tensors.

    Returns
    -------
    points : torch.Tensor, shape (1, P, 3)
        Mirror points [m], ENU.
    normals : torch.Tensor, shape (1, P, 3)
        Unit normals [1].
    areas : torch.Tensor, shape (1, P)
        Area per point [m^2].
    sun_direction : torch.Tensor, shape (1, 3), float64
        Unit vector towards the sun [1].
    target : PlanarTarget
    """
    d64 = torch.float64
    target = PlanarTarget.from_center_normal("bench", [0.0, 0.0, 55.0], [0.0, 1.0, 0.0], 8.0, 8.0)
    pos = torch.tensor([15.0, 100.0, 2.0], dtype=d64)
    az, el = math.radians(170.0), math.radians(40.0)
    sun = torch.tensor([math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)], dtype=d64)
    to_t = target.center - pos
    slant = float(to_t.norm())
    to_t = to_t / slant
    n0 = (to_t + sun) / (to_t + sun).norm()
    e1 = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=d64), n0)
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(n0, e1)
    m = max(1, int(round(math.sqrt(surface_points))))
    side = 4.0
    g = (torch.arange(m, dtype=d64) + 0.5) / m * side - side / 2
    a, b = torch.meshgrid(g, g, indexing="ij")
    a, b = a.reshape(-1, 1), b.reshape(-1, 1)
    f = slant  # focal length: on-axis focusing at the slant range
    sag = (a * a + b * b) / (4 * f)
    pts = pos + a * e1 + b * e2 + sag * n0
    nrm = n0 - a / (2 * f) * e1 - b / (2 * f) * e2
    nrm = nrm / nrm.norm(dim=-1, keepdim=True)
    areas = torch.full((m * m,), (side / m) ** 2, dtype=d64)
    return (pts.unsqueeze(0).to(dtype), nrm.unsqueeze(0).to(dtype), areas.unsqueeze(0).to(dtype),
            sun.unsqueeze(0), target)


def _synced(fn, device):
    """``fn`` followed by a CUDA synchronisation on a GPU (kernels run asynchronously: time them finished)."""
    if torch.device(device).type != "cuda":
        return fn

    def run():
        out = fn()
        torch.cuda.synchronize(device)
        return out
    return run


def _best_time(fn, repeats: int, min_total: float = 0.0, device="cpu") -> float:
    """Best wall time [s] of ``fn()`` over at least ``repeats`` calls and ``min_total`` seconds (one warm-up)."""
    fn = _synced(fn, device)
    fn()  # warm-up
    best = float("inf")
    t_start = time.perf_counter()
    i = 0
    while i < repeats or (time.perf_counter() - t_start) < min_total:
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
        i += 1
        if i >= 40 * max(1, repeats):
            break
    return best


def _peak_rss_mb() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 1024.0 if platform.system() != "Darwin" else r / 1024.0 ** 2


def run_benchmark(surface_points: int = 10000, rays_per_point=(10, 100), resolution: int = 256, seed: int = 0,
                  threads: int | None = 2, repeats: int = 10, time_to_accuracy: bool = True, device="cpu",
                  progress: bool = False) -> dict:
    """Measure the Monte-Carlo tracer's throughput and compare integrators at equal accuracy.

    Parameters
    ----------
    surface_points : int
        Mirror points P.
    rays_per_point : int or sequence of int
        K values to time.
    resolution : int
        Bitmap side [px] (square bitmap).
    seed : int
        Generator seed.
    threads : int or None
        ``torch.set_num_threads`` during the run (restored afterwards); None keeps the current setting.
    repeats : int
        Minimum timed repetitions per measurement (more are run until ~2 s have passed); the best time is
        reported, i.e. the run least disturbed by other load on the machine.
    time_to_accuracy : bool
        Also run the reference / gaussian / MC-convergence comparison.
    device : str or torch.device
        Where to trace (``"auto"``: CUDA when present); timings wait for the device to finish, and
        ``peak_device_mb`` reports the GPU's peak allocated memory there.
    progress : bool
        One progress line (or bar) per measurement (:class:`heliotwin.progress.Stages`).

    Returns
    -------
    dict
        ``mc.forward_rays_per_s`` and ``mc.forward_backward_rays_per_s`` (for the largest K; float32,
        eager PyTorch, gradients w.r.t. mirror points and normals), ``mc.per_k`` (per-K timings),
        ``peak_rss_mb``, and ``time_to_accuracy`` (Gaussian sun: reference image and its noise, gaussian
        integrator time and L1 vs the reference, Monte-Carlo rays/time to reach that L1, measured or extrapolated).
    """
    check_range("--surface-points", surface_points, 1, MAX_SURFACE_POINTS)
    for k in [rays_per_point] if isinstance(rays_per_point, int) else rays_per_point:
        check_trace_sizes(resolution=resolution, rays_per_point=k, points=int(surface_points))
    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(int(threads))
    try:
        return _run(surface_points, rays_per_point, resolution, seed, repeats, time_to_accuracy, device, progress)
    finally:
        torch.set_num_threads(old_threads)


def _run(surface_points, rays_per_point, resolution, seed, repeats, time_to_accuracy, device="cpu", progress=False):
    device = resolve_device(device)
    ks = [int(rays_per_point)] if isinstance(rays_per_point, int) else [int(k) for k in rays_per_point]
    stages = Stages(2 * len(ks) + bool(time_to_accuracy), "heliotwin bench", enabled=progress)
    pts, nrm, areas, sun_dir, target = to_device(benchmark_scene(surface_points), device)
    p = pts.shape[1]
    optics = SunSettings()
    gen = torch.Generator(device=device).manual_seed(seed)
    weights = torch.rand(1, resolution, resolution, generator=torch.Generator().manual_seed(seed + 1)).to(device)
    if device != "cpu":
        torch.cuda.reset_peak_memory_stats(device)
    per_k = {}
    for k in ks:
        def fwd():
            with torch.no_grad():
                trace_mc(pts, nrm, areas, sun_dir, target, resolution=resolution, sun=optics,
                         sampling=RaySampling(k), generator=gen)

        n_leaf = nrm.clone().requires_grad_(True)
        p_leaf = pts.clone().requires_grad_(True)

        def fwd_bwd():
            n_leaf.grad = p_leaf.grad = None
            f = trace_mc(p_leaf, n_leaf, areas, sun_dir, target, resolution=resolution, sun=optics,
                         sampling=RaySampling(k), generator=gen)
            (f.bitmap * weights).sum().backward()

        rays = p * k
        stages.start(f"forward, {k} rays per point")
        t_f = _best_time(fwd, repeats, min_total=2.0, device=device)
        stages.step(f"forward, {k} rays per point")
        stages.start(f"forward and backward, {k} rays per point")
        t_fb = _best_time(fwd_bwd, repeats, min_total=2.0, device=device)
        stages.step(f"forward and backward, {k} rays per point")
        per_k[str(k)] = {
            "rays": rays,
            "forward_s": t_f,
            "forward_backward_s": t_fb,
            "forward_rays_per_s": rays / t_f,
            "forward_backward_rays_per_s": rays / t_fb,
        }
    top = per_k[str(max(ks))]
    result = {
        "device": str(device),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "surface_points": p,
        "resolution": resolution,
        "sunshape": optics.sunshape,
        "mc": {
            "rays_per_point": max(ks),
            "forward_rays_per_s": top["forward_rays_per_s"],
            "forward_backward_rays_per_s": top["forward_backward_rays_per_s"],
            "per_k": per_k,
        },
    }
    if time_to_accuracy:
        stages.start("time to accuracy")
        result["time_to_accuracy"] = _time_to_accuracy(pts, nrm, areas, sun_dir, target, resolution, seed, repeats)
        stages.step("time to accuracy")
    stages.close()
    result["peak_rss_mb"] = _peak_rss_mb()
    if device != "cpu":
        result["peak_device_mb"] = torch.cuda.max_memory_allocated(device) / 2 ** 20
    return result


def _time_to_accuracy(pts, nrm, areas, sun_dir, target, resolution, seed, repeats):
    """Gaussian sun (the gaussian integrator's exact case): reference, gaussian, MC convergence."""
    optics = SunSettings(sunshape="gaussian", sigma=2.51e-3, slope_error=1e-3)
    p, device = pts.shape[1], pts.device
    ref_rays_per_point, ref_runs = 4000, 8
    t0 = time.perf_counter()
    halves = [None, None]
    with torch.no_grad():
        for i in range(ref_runs):
            gen = torch.Generator(device=device).manual_seed(10_000 + seed + i)
            f = trace_mc(pts, nrm, areas, sun_dir, target, resolution=resolution, sun=optics,
                         sampling=RaySampling(ref_rays_per_point, stratified=True), generator=gen)
            h = i % 2
            halves[h] = f.bitmap if halves[h] is None else halves[h] + f.bitmap
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t_ref = time.perf_counter() - t0
    ref = (halves[0] + halves[1]) / ref_runs
    # noise floor of the reference: L1 between its halves, scaled to the full reference (1/sqrt(2) x 1/sqrt(2))
    ref_noise = float(normalized_l1(halves[0], halves[1])[0]) / 2.0

    def gaussian():
        with torch.no_grad():
            return trace_gaussian(pts, nrm, areas, sun_dir, target, resolution=resolution, sun=optics)

    t_an = _best_time(gaussian, max(1, repeats // 2), device=device)
    l1_an = float(normalized_l1(gaussian().bitmap, ref)[0])
    curve = []
    reached = None
    for k in (10, 30, 100, 300, 1000, 3000, 10000):
        gen = torch.Generator(device=device).manual_seed(seed + 77)

        def mc():
            with torch.no_grad():
                return trace_mc(pts, nrm, areas, sun_dir, target, resolution=resolution, sun=optics,
                                sampling=RaySampling(k), generator=gen)

        t_mc = _best_time(mc, 3 if k <= 1000 else 1, device=device)
        l1 = float(normalized_l1(mc().bitmap, ref)[0])
        curve.append({"rays_per_point": k, "rays": p * k, "time_s": t_mc, "l1": l1})
        if l1 <= l1_an:
            reached = {"rays_per_point": k, "rays": p * k, "time_s": t_mc, "l1": l1}
            break
    estimate = None
    if reached is None and curve:
        # MC's own error ~ 1/sqrt(rays); remove the reference noise (independent) before extrapolating
        last = curve[-1]
        own = math.sqrt(max(last["l1"] ** 2 - ref_noise ** 2, 1e-12))
        target = math.sqrt(max(l1_an ** 2 - ref_noise ** 2, 1e-12))
        factor = (own / target) ** 2
        estimate = {"rays": last["rays"] * factor, "time_s": last["time_s"] * factor,
                    "note": "extrapolated with L1 ~ 1/sqrt(rays) after removing the reference noise"}
    return {
        "sunshape": "gaussian",
        "reference": {"rays": p * ref_rays_per_point * ref_runs, "time_s": t_ref, "noise_l1": ref_noise},
        "mc_to_same_l1_estimate": estimate,
        "gaussian": {"time_s": t_an, "l1_vs_reference": l1_an},
        "mc_to_same_l1": reached,
        "mc_curve": curve,
    }
