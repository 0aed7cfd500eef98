"""Bounds on the size arguments of the tracing and learning commands, checked before any work starts.

A size argument that is absurd (``--control-points 200x200``, ``--resolution 100000``, ``--samples 10**5``)
would otherwise allocate until the machine swaps or the kernel kills the run. Each is refused up front with one
line naming the option: a value outside its range is a :class:`~heliotwin.errors.HeliotwinError` (exit 2), a
run whose estimated memory exceeds this machine's is a ``MemoryError`` (the command line's out-of-memory
message, as ``field`` gives for huge maps and layouts).
"""
from __future__ import annotations

import os

from ..errors import HeliotwinError

__all__ = ["MAX_RESOLUTION", "MAX_SAMPLES", "MAX_RAYS", "MAX_RAYS_PER_POINT", "MAX_SURFACE_POINTS", "check_range",
           "check_memory_estimate", "check_trace_sizes", "physical_memory"]

#: Largest flux-image side [pixels] (the field commands' largest map has 4096 x 4096 cells).
MAX_RESOLUTION = 4096
#: Largest number of mirror samples per facet and direction.
MAX_SAMPLES = 1000
#: Most rays per mirror point (the command line's range).
MAX_RAYS_PER_POINT = 100_000
#: Most rays one trace may cast (about an hour on a CPU core; a sharper image needs rays, not more).
MAX_RAYS = 10 ** 10
#: Most mirror points of ``bench``'s synthetic heliostat (the command line's range).
MAX_SURFACE_POINTS = 10_000_000
#: Bytes per traced mirror point (position, normal, area, their world copies, rays' bookkeeping) and per pixel
#: (bitmap, its splat weights and a copy for the report), from the tracer's tensors, with headroom.
BYTES_PER_POINT, BYTES_PER_PIXEL = 256, 64


def physical_memory() -> int:
    """This machine's memory [bytes] (64 GiB when the system does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 64 * 2 ** 30


def check_range(option: str, value, low: int, high: int, why: str = "") -> int:
    """``value`` as an int in ``[low, high]``, else a one-line :class:`HeliotwinError` naming ``option``."""
    ok = not isinstance(value, bool) and isinstance(value, (int, float)) and float(value).is_integer()
    if not ok or not low <= int(value) <= high:
        raise HeliotwinError(f"{option}: expected an integer in [{low}, {high}]{' (' + why + ')' if why else ''}, "
                             f"got {value!r}")
    return int(value)


def check_memory_estimate(what: str, need_bytes: float) -> None:
    """``MemoryError`` (the out-of-memory message) when ``need_bytes`` exceed half of this machine's memory."""
    total = physical_memory()
    if need_bytes > total / 2:
        raise MemoryError(f"{what} needs about {need_bytes / 2 ** 30:.1f} GiB (this machine has "
                          f"{total / 2 ** 30:.0f} GiB)")


def check_trace_sizes(*, resolution: int, samples: int | None = None, facets: int = 1,
                      rays_per_point: int | None = None, points: int | None = None, images: int = 1) -> None:
    """Bounds of one trace: ``resolution`` [px] per side, ``samples`` per facet side (or ``points`` in all),
    ``rays_per_point`` (Monte Carlo), ``images`` traced at once; refuses before anything is allocated
    (:class:`~heliotwin.errors.HeliotwinError`, or the out-of-memory line; memory estimate [bytes])."""
    check_range("--resolution", resolution, 8, MAX_RESOLUTION)
    if samples is not None:
        check_range("--samples", samples, 1, MAX_SAMPLES)
        points = int(facets) * int(samples) ** 2
    if rays_per_point is not None:
        check_range("--rays-per-point", rays_per_point, 1, MAX_RAYS_PER_POINT)
        if points is not None and points * rays_per_point * images > MAX_RAYS:
            raise HeliotwinError(f"--rays-per-point: {points} mirror points x {rays_per_point} rays is more than "
                                 f"{MAX_RAYS:.0e} rays; lower --rays-per-point or --samples")
    need = images * (BYTES_PER_POINT * (points or 0) + BYTES_PER_PIXEL * resolution ** 2)
    check_memory_estimate(f"a trace of {images} image(s) at {resolution}x{resolution} px from {points or 0} "
                          "mirror points", need)
