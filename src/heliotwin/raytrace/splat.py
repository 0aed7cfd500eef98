"""Differentiable splatting of weighted points (ray hits) into flux bitmaps.

Pixel coordinates
-----------------
``px`` (column) and ``py`` (row) are continuous pixel coordinates with pixel *centres* at integers: pixel
``(r, c)`` covers ``px in [c - 0.5, c + 0.5)``, ``py in [r - 0.5, r + 0.5)``. The bitmap covers
``px in [-0.5, cols - 0.5]``, ``py in [-0.5, rows - 0.5]``; points outside get weight 0.

Bilinear splat with folded edges
--------------------------------
A point's weight is shared between the four pixels around it (tent kernel: the image is the flux
convolved with a one-pixel tent, sampled at pixel centres). Splatting happens on the bitmap plus a
one-pixel ring; the ring is then folded onto the edge pixels, so every point that lands on the bitmap
deposits *all* of its weight in it: ``bitmap.sum() == sum of the weights of the points that landed``. The
result is differentiable w.r.t. coordinates and weights (in the outer half-pixel the position derivative
is 0 -- the weight stays in the edge pixel; the landing test at the bitmap edge is a step, as in physics).

Implementation
--------------
The four corner weights ``w (1-fx)(1-fy), w fx (1-fy), w (1-fx) fy, w fx fy`` are linear combinations of
the *moments* ``w, w fx, w fy, w fx fy`` deposited at the same (lower-left) pixel. The moments are packed
as two complex numbers per ray, so the forward pass is a single ``index_add_`` of two complex rows
(parallel over the rows, half the scattered elements) into moment accumulators, recombined once at the
end. The backward pass is the adjoint: four difference maps of the output gradient (packed the same way)
gathered at the same index. Rays that do not land get the index of an extra "trash" bin, which is
discarded in the forward pass and has zero gradient maps in the backward pass, so no per-ray masking is
needed and all gradients stay finite (no boolean indexing, no division by tiny numbers).

Rays are processed in chunks of at most ``max_rays_per_chunk`` (default 2^17, ~25 reusable buffers of that
size) with in-place ops. The backward pass recomputes the per-ray quantities from the per-point inputs;
the forward pass only keeps the int32 landing index of up to :data:`INDEX_CACHE_RAYS` rays. On the CPU the
chunk buffers, the moment accumulators and the landing index are kept from one call to the next (bounded;
:func:`release_scratch` frees them): fresh buffers on every call would cost a page fault per 4 KiB whenever
the C allocator hands out new pages, which depends on the heap's history, not on this code. By default the
chunks run in the calling thread and each op uses PyTorch's intra-op threads; ``workers=n`` runs them on
``n`` worker threads with one intra-op thread each instead (no OpenMP barriers: degrades more gracefully
when other processes compete for the cores, but scales worse on an idle machine).

:func:`projective_splat` computes the pixel coordinates of the rays inside each chunk from per-point
projective coefficients and a shared offset pattern (the Monte-Carlo tracer's planar fast path);
:func:`splat_bilinear` takes explicit coordinates (generic path, e.g. the cylindrical receiver);
:func:`splat_hard` / :func:`projective_splat_hard` do nearest-pixel binning (not differentiable).
"""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import torch

__all__ = ["splat_bilinear", "splat_hard", "projective_splat", "projective_splat_hard", "DEFAULT_MAX_RAYS_PER_CHUNK",
           "DEN_EPS", "release_scratch"]

#: Rays per chunk (memory: ~25 float32 buffers of this size per worker; 2^17 measured fastest on 2 cores).
DEFAULT_MAX_RAYS_PER_CHUNK = 2 ** 17

#: Rays whose direction has ``d . n_target > -DEN_EPS`` (parallel or leaving the plane) are dropped.
DEN_EPS = 1e-6

#: Moment accumulators of one block of samples are bounded by this many floats per worker.
_ACC_BUDGET = 2 ** 23

#: The forward pass keeps the int32 landing index of up to this many rays for the backward pass
#: (4 bytes per ray; beyond the budget the index is recomputed).
INDEX_CACHE_RAYS = 2 ** 25

_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOL_LOCK = threading.Lock()


def _num_workers(workers) -> int:
    return 0 if workers is None else max(0, int(workers))


def _pool(n: int) -> ThreadPoolExecutor:
    """A pool of ``n`` worker threads whose own intra-op thread count is 1.

    ``torch.set_num_threads`` acts per thread for OpenMP; each worker sets 1 for itself at start-up, then
    the caller's setting is restored (it also seeds threads created later), so nothing else changes.
    The workers' ops then never wait on an OpenMP barrier, which matters on busy machines.
    """
    with _POOL_LOCK:
        pool = _POOLS.get(n)
        if pool is None:
            main_threads = torch.get_num_threads()
            pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="heliotwin-splat")
            barrier = threading.Barrier(n)

            def init():
                torch.set_num_threads(1)
                barrier.wait()

            for f in [pool.submit(init) for _ in range(n)]:
                f.result()
            torch.set_num_threads(main_threads)
            _POOLS[n] = pool
        return pool


def _run(tasks: list, workers: int) -> None:
    """Run the chunk tasks ``t(j)``: inline (``workers == 0``) or on worker threads (worker ``j`` takes every
    ``nw``-th task)."""
    if not tasks:
        return
    if workers <= 0:
        with torch.no_grad():
            for t in tasks:
                t(0)
        return
    nw = max(1, min(workers, len(tasks)))

    def work(j):
        with torch.no_grad():  # grad mode is thread-local: worker threads start with it enabled
            for t in tasks[j::nw]:
                t(j)

    pool = _pool(workers)
    for f in [pool.submit(work, j) for j in range(nw)]:
        f.result()


class _Workspace:
    """Reusable scratch buffers of one worker (no fresh page faults for every temporary).

    ``get`` returns a view of a per-name buffer; views are memoised by (name, shape, dtype), so the
    per-chunk Python overhead stays small.
    """

    def __init__(self):
        self._bufs: dict[tuple, torch.Tensor] = {}
        self._views: dict[tuple, torch.Tensor] = {}

    @property
    def nbytes(self) -> int:
        return sum(b.numel() * b.element_size() for b in self._bufs.values())

    def get(self, name: str, shape, dtype, device) -> torch.Tensor:
        key = (name, tuple(shape), dtype)
        view = self._views.get(key)
        if view is not None:
            return view
        numel = 1
        for s in shape:
            numel *= int(s)
        bkey = (name, dtype)
        buf = self._bufs.get(bkey)
        if buf is None or buf.numel() < numel:
            buf = torch.empty(max(numel, 1), dtype=dtype, device=device)
            self._bufs[bkey] = buf
            self._views = {k: v for k, v in self._views.items() if (k[0], k[2]) != bkey}
        if len(self._views) >= _MAX_VIEWS:  # many distinct chunk shapes over the calls: start afresh
            self._views.clear()
        view = buf[:numel].view(*shape)
        self._views[key] = view
        return view


#: Idle CPU scratch memory kept between calls: workspaces (bytes, all together) and landing-index buffers.
_KEEP_WORKSPACE_BYTES = 2 ** 27
_KEEP_INDEX_BYTES = 2 ** 26
_MAX_VIEWS = 256


class _CpuScratch:
    """Scratch memory reused from one call to the next (CPU only).

    Every call of the splats needs ~25 chunk-sized buffers per worker (tens of MB in all) and, with
    gradients, the landing-index cache. Allocated afresh per call, whether they cost anything depends on
    the C allocator's state: glibc serves blocks of this size from the heap or by ``mmap`` depending on its
    dynamic mmap/trim thresholds, i.e. on what the process allocated and freed before (imports, other
    code); served by fresh pages, every call pays a page fault and the kernel's zeroing for each 4 KiB,
    which halves the tracer's throughput. Kept here, the buffers are touched once and then reused, so the
    speed no longer depends on the heap's history. Bounded by ``_KEEP_WORKSPACE_BYTES`` /
    ``_KEEP_INDEX_BYTES`` (larger or surplus buffers are simply freed); :func:`release_scratch` frees
    everything. Other devices are left to their own (caching) allocators. Thread-safe: a buffer is lent to
    one call at a time.
    """

    def __init__(self):
        self._lock = threading.Lock()
        self._workspaces: list[_Workspace] = []
        self._indices: list[torch.Tensor] = []

    def workspaces(self, n: int, device) -> list:
        if torch.device(device).type != "cpu":
            return [_Workspace() for _ in range(n)]
        with self._lock:
            got = [self._workspaces.pop() for _ in range(min(n, len(self._workspaces)))]
        return got + [_Workspace() for _ in range(n - len(got))]

    def give_workspaces(self, wss: list, device) -> None:
        if torch.device(device).type != "cpu":
            return
        with self._lock:
            kept = sum(w.nbytes for w in self._workspaces)
            for w in wss:
                nb = w.nbytes
                if kept + nb <= _KEEP_WORKSPACE_BYTES:
                    self._workspaces.append(w)
                    kept += nb

    def index(self, numel: int, device) -> torch.Tensor:
        """A flat int32 buffer of ``numel`` elements (contents undefined)."""
        if torch.device(device).type == "cpu":
            with self._lock:
                for i, buf in enumerate(self._indices):
                    if buf.numel() >= numel:
                        return self._indices.pop(i)[:numel]
        return torch.empty(numel, dtype=torch.int32, device=device)

    def give_index(self, buf: torch.Tensor) -> None:
        if buf.device.type != "cpu":
            return
        base = buf if buf._base is None else buf._base
        with self._lock:
            kept = sum(b.numel() * 4 for b in self._indices)
            if kept + base.numel() * 4 <= _KEEP_INDEX_BYTES:
                self._indices.append(base)

    def clear(self) -> None:
        with self._lock:
            self._workspaces.clear()
            self._indices.clear()


_SCRATCH = _CpuScratch()


def release_scratch() -> None:
    """Free the scratch buffers the splats keep between calls (at most 192 MB, see
    :class:`_CpuScratch`); the next call allocates them again."""
    _SCRATCH.clear()


class _IndexCache:
    """The forward pass's int32 landing index of the first ``size`` rays of a call (flat ray order: point
    chunk by point chunk, k-slice by k-slice), kept for the backward pass in one (reused) buffer."""

    def __init__(self, total_rays: int, device):
        self.size = min(int(total_rays), INDEX_CACHE_RAYS)
        self.buf = _SCRATCH.index(self.size, device) if self.size > 0 else None

    @staticmethod
    def _start(s, e, k0, k_total):
        return s * k_total + (e - s) * k0

    def slot(self, s, e, k0, k1, k_total):
        """The view that holds chunk (s..e, k0..k1), or None beyond the budget."""
        a = self._start(s, e, k0, k_total)
        b = a + (e - s) * (k1 - k0)
        return None if self.buf is None or b > self.size else self.buf[a:b]

    def release(self):
        if self.buf is not None:
            _SCRATCH.give_index(self.buf)
        self.buf = None


def _compose(acc: torch.Tensor, ns: int, rows: int, cols: int, ws: _Workspace) -> torch.Tensor:
    """Bitmap [ns, rows, cols] from the complex moment accumulators acc [2, ns*(rows+2)*(cols+2)] =
    (S0 + i Sxy, Sy + i Sx) on the padded grid: bilinear recombination, then the one-pixel ring is folded
    onto the edge pixels. The result is a view of workspace memory (``ws``): copy it out."""
    r = torch.view_as_real(acc[:, :ns * (rows + 2) * (cols + 2)])  # the last element is the trash bin
    s0, sxy, sy, sx = (t.view(ns, rows + 2, cols + 2) for t in (r[0, :, 0], r[0, :, 1], r[1, :, 0], r[1, :, 1]))
    shape, dt, dev = s0.shape, s0.dtype, s0.device
    pad = torch.sub(s0, sx, out=ws.get("pad", shape, dt, dev)).sub_(sy).add_(sxy)
    t = ws.get("pad_t", shape, dt, dev)
    pad[:, :, 1:] += torch.sub(sx, sxy, out=t)[:, :, :-1]
    pad[:, 1:, :] += torch.sub(sy, sxy, out=t)[:, :-1, :]
    pad[:, 1:, 1:] += sxy[:, :-1, :-1]
    # fold the ring: rows first (with the corner columns), then columns
    pad[:, 1, :] += pad[:, 0, :]
    pad[:, rows, :] += pad[:, rows + 1, :]
    pad[:, :, 1] += pad[:, :, 0]
    pad[:, :, cols] += pad[:, :, cols + 1]
    return pad[:, 1:rows + 1, 1:cols + 1]


def _grad_maps(g: torch.Tensor, ws: _Workspace) -> torch.Tensor:
    """Adjoint of :func:`_compose`: complex maps [2, ns*(rows+2)*(cols+2) + 1] = (A + i D, Cy + i Bx) from the
    grad [ns, rows, cols] (the fold's adjoint is replicate padding); the trash bin at the end is 0. The maps
    live in the workspace ``ws``."""
    ns, rows, cols = g.shape
    m = ns * (rows + 2) * (cols + 2)
    flat = ws.get("maps", (2, m + 1, 2), g.dtype, g.device).zero_()
    maps = flat[:, :m].view(2, ns, rows + 2, cols + 2, 2)
    gp = maps[0, ..., 0]  # A: g with replicate padding
    gp[:, 1:-1, 1:-1] = g
    gp[:, 0, 1:-1] = g[:, 0]
    gp[:, -1, 1:-1] = g[:, -1]
    gp[:, :, 0] = gp[:, :, 1]
    gp[:, :, -1] = gp[:, :, -2]
    d = torch.sub(gp[:, 1:, 1:], gp[:, 1:, :-1], out=maps[0, :, :-1, :-1, 1])  # D
    d.sub_(gp[:, :-1, 1:]).add_(gp[:, :-1, :-1])
    torch.sub(gp[:, 1:, :], gp[:, :-1, :], out=maps[1, :, :-1, :, 0])  # Cy
    torch.sub(gp[:, :, 1:], gp[:, :, :-1], out=maps[1, :, :, :-1, 1])  # Bx
    return torch.view_as_complex(flat)


def _blocks(n_samples: int, rows: int, cols: int):
    """Consecutive sample blocks whose (padded) moment accumulators (4 floats per pixel) fit the budget."""
    per = max(1, _ACC_BUDGET // (4 * (rows + 2) * (cols + 2)))
    for b0 in range(0, n_samples, per):
        yield b0, min(n_samples, b0 + per)


def _point_chunks(p0: int, p1: int, k: int, max_rays: int):
    """Point ranges [s, e) of at most max_rays rays (at least one point)."""
    step = max(1, int(max_rays) // max(1, k))
    for s in range(p0, p1, step):
        yield s, min(p1, s + step)


def _k_slices(k: int, max_rays: int):
    step = max(1, int(max_rays))
    for k0 in range(0, k, step):
        yield k0, min(k, k0 + step)


# ----------------------------------------------------------------------------------------------------
# per-chunk kernels. Coordinates of a chunk live in one [2, n, k] tensor q2 = (qy, qx) (row first) of
# *padded* pixel coordinates q = p + 1: the bitmap plus a one-pixel ring, so a landing ray
# (p in [-0.5, size - 0.5], i.e. q in [0.5, size + 0.5]) has all four corners on the padded grid and the
# ring is folded back onto the edge pixels afterwards (no per-ray clamping or edge masks). Every per-axis
# step is a single op; all ops are in place in workspace buffers.
# ----------------------------------------------------------------------------------------------------

def _clamp2(q2, lo, hi, out):
    """Clamp rows (qy, qx) of q2 [2, ...] to [lo[i], hi[i]] (scalars when both axes agree)."""
    if lo[0] == lo[1] and hi[0] == hi[1]:
        return torch.clamp(q2, lo[0], hi[0], out=out)
    shape = (2,) + (1,) * (q2.dim() - 1)
    lo_t = torch.tensor(lo, dtype=q2.dtype, device=q2.device).view(shape)
    hi_t = torch.tensor(hi, dtype=q2.dtype, device=q2.device).view(shape)
    return torch.clamp(q2, lo_t, hi_t, out=out)


def _project(ws, c3, pat, with_bad=True):
    """Padded pixel coordinates of the rays ``q = pat[:, k] = (1, a_k, b_k)`` of points with coefficients
    c3 [3, n, 3] (rows N_row + D, N_col + D, D). One batched GEMM.

    Returns q2 = (qy, qx) [2, n, k] (unclamped), inv = 1/den [n, k] (den clamped below -DEN_EPS) and
    bad [n, k] (> 0: drop the ray); q2 and inv are views of the workspace buffer "proj".
    """
    n, k = c3.shape[1], pat.shape[1]
    dt, dev = c3.dtype, c3.device
    o = ws.get("proj", (3, n, k), dt, dev)
    torch.bmm(c3, pat.expand(3, 3, k), out=o)
    den = o[2]
    bad = torch.add(den, DEN_EPS, out=ws.get("bad", (n, k), dt, dev)).clamp_(min=0.0) if with_bad else None
    inv = den.clamp_(max=-DEN_EPS).reciprocal_()
    q2 = o[0:2]
    q2.mul_(inv)
    return q2, inv, bad


def _bounds_check(ws, q2, bad, bounds):
    """Add the squared distance outside per-point bounds [n, 4] = (lo_x, hi_x, lo_y, hi_y) (unpadded pixel
    coordinates) to ``bad``."""
    lo = torch.stack((bounds[:, 2], bounds[:, 0])).unsqueeze(-1) + 1.0
    hi = torch.stack((bounds[:, 3], bounds[:, 1])).unsqueeze(-1) + 1.0
    t = ws.get("t2", q2.shape, q2.dtype, q2.device)
    torch.sub(q2, torch.clamp(q2, lo, hi), out=t)
    bad.addcmul_(t[0], t[0]).addcmul_(t[1], t[1])


def _flat_index(ws, v2, width, offset, bad, trash, i32_out=None):
    """Fractions f2 = (fy, fx) and flat int64 index ``floor(vy) * width + floor(vx)`` of v2 >= 0 (consumed);
    rays with ``bad > 0`` get the index ``trash`` (a bin that is discarded / whose gradient maps are 0), so
    no per-ray masking is needed anywhere else.

    The index is formed in floating point (exact below 2^24) and converted via int32 (much faster than a
    direct float -> int64 conversion); the int32 copy goes to ``i32_out`` when given.
    """
    shape, dt, dev = v2.shape[1:], v2.dtype, v2.device
    f2 = torch.frac(v2, out=ws.get("f2", v2.shape, dt, dev))
    v2.sub_(f2)
    flat = torch.add(v2[1], v2[0], alpha=width, out=ws.get("flat", shape, dt, dev))
    if offset is not None:
        flat.add_(offset)
    flat.add_(bad.sign_(), alpha=float(trash) + 1.0).clamp_(max=float(trash))
    i32 = (ws.get("i32", shape, torch.int32, dev) if i32_out is None else i32_out.view(shape)).copy_(flat)
    return f2, ws.get("i64", shape, torch.int64, dev).copy_(i32), i32


def _land(ws, q2, bad, rows, cols, trash, offset=None, keep=False, i32_out=None):
    """Landing test and padded-grid index/fractions of rays at q2 = (qy, qx) (``bad`` is consumed).

    q2 is consumed unless ``keep``. Returns f2 = (fy, fx) [2, n, k], the flat int64 index [n, k] into the
    padded (rows + 2) x (cols + 2) grid(s) (``trash`` for rays that do not land) and its int32 copy.
    """
    shape, dt, dev = q2.shape, q2.dtype, q2.device
    v = _clamp2(q2, (0.5, 0.5), (rows + 0.5, cols + 0.5), out=ws.get("v2", shape, dt, dev))
    d = torch.sub(q2, v, out=ws.get("t2", shape, dt, dev)) if keep else q2.sub_(v)
    bad.addcmul_(d[0], d[0]).addcmul_(d[1], d[1])  # 0 iff the ray lands on the bitmap
    return _flat_index(ws, v, cols + 2, offset, bad, trash, i32_out)


def _land_hard(ws, q2, bad, rows, cols, trash, offset=None):
    """Nearest-pixel landing (q2, bad consumed): flat index of the (unpadded) pixel containing each ray."""
    v = _clamp2(q2, (0.5, 0.5), (rows + 0.5, cols + 0.5), out=ws.get("v2", q2.shape, q2.dtype, q2.device))
    d = q2.sub_(v)
    bad.addcmul_(d[0], d[0]).addcmul_(d[1], d[1])
    v.sub_(0.5)  # unpadded p + 0.5 in [0, size]; floor = containing pixel
    _clamp2(v, (0.0, 0.0), (rows - 0.5, cols - 0.5), out=v)
    return _flat_index(ws, v, cols, offset, bad, trash)[1]  # noqa: RET504


def _moments(ws, w, f2):
    """Moments packed as complex numbers [2, n*k]: (w + i w fx fy, w fy + i w fx) for weights w [n, 1] or
    [n, k]. Packing halves the scattered elements (a complex add is two float adds)."""
    n, k = f2.shape[1:]
    mom = ws.get("mom", (2, n, k, 2), f2.dtype, f2.device)
    mom[0, ..., 0] = w
    torch.mul(f2, w, out=mom[1].permute(2, 0, 1))  # (w fy, w fx)
    torch.mul(mom[1, ..., 0], f2[1], out=mom[0, ..., 1])  # w fy fx
    return torch.view_as_complex(mom).view(2, n * k)


def _sample_offset(s, e, points_per_sample, b0, rows, cols, dtype, device):
    """Flat-index offset of the block-local sample of points s..e-1: None, a float, or a [n, 1] tensor."""
    first = s // points_per_sample
    last = (e - 1) // points_per_sample
    if first == last:
        return None if first == b0 else float((first - b0) * rows * cols)
    local = torch.arange(s, e, device=device) // points_per_sample - b0
    return (local * (rows * cols)).to(dtype).unsqueeze(1)


def _backward_chunk(ws, maps, f2, idx, w, inv, q2, need_w, need_p):
    """Shared backward step for a chunk [n, k] (dropped rays gather zeros from the trash bin).

    Returns (dw [n, k] or None, g3 [3, n, k]): d loss / d weight per ray, and the gradients w.r.t.
    (N_row, N_col, D) for the projective chain (``inv`` given) or w.r.t. (py, px) in the first two rows of
    g3 for explicit coordinates (``inv`` None).
    """
    dt, dev = f2.dtype, f2.device
    n, k = f2.shape[1:]
    flat = idx.view(1, -1).expand(2, n * k)
    gc = torch.gather(maps, 1, flat, out=ws.get("gather", (2, n * k), maps.dtype, dev))
    g = torch.view_as_real(gc).view(2, n, k, 2)
    g_a, g_d, g_bx = g[0, ..., 0], g[0, ..., 1], g[1, ..., 1]
    g3 = ws.get("g3", (3, n, k), dt, dev)
    t2 = g3[0:2]
    torch.mul(g_d, f2[1], out=t2[0])
    torch.mul(g_d, f2[0], out=t2[1])
    t2.add_(g[1].permute(2, 0, 1))  # (Cy + D fx, Bx + D fy) = d out / d (fy, fx) per unit weight
    dw = None
    if need_w:
        dw = torch.addcmul(g_a, t2[0], f2[0], out=ws.get("dw", (n, k), dt, dev)).addcmul_(g_bx, f2[1])
    if need_p:
        if inv is not None:
            t2.mul_(torch.mul(inv, w, out=ws.get("wi", (n, k), dt, dev)))
            torch.mul(t2[0], q2[0], out=g3[2]).addcmul_(t2[1], q2[1]).neg_()
        else:
            t2.mul_(w)
    return dw, g3


# ----------------------------------------------------------------------------------------------------
# fused projective splat (planar targets)
# ----------------------------------------------------------------------------------------------------

def _to_c3(coef):
    """API coefficients [N, 3, 3] (rows N_col, N_row, D) -> internal [3, N, 3] with rows
    (N_row + D, N_col + D, D): padded pixel coordinates q = p + 1."""
    c3 = torch.empty(3, coef.shape[0], 3, dtype=coef.dtype, device=coef.device)
    torch.add(coef[:, 1], coef[:, 2], out=c3[0])
    torch.add(coef[:, 0], coef[:, 2], out=c3[1])
    c3[2] = coef[:, 2]
    return c3


def _proj_forward(c3, weights, pattern, bounds, rows, cols, n_samples, pps, max_rays, workers, hard=False,
                  cache=None):
    dev = c3.device
    wss = _SCRATCH.workspaces(max(1, workers), dev)
    out = _proj_forward_ws(wss, c3, weights, pattern, bounds, rows, cols, n_samples, pps, max_rays, workers, hard,
                           cache)
    _SCRATCH.give_workspaces(wss, dev)
    return out


def _accumulators(wss, shape, dtype, device):
    """Zeroed moment accumulators, one per worker (workspace memory)."""
    return [ws.get("acc", shape, dtype, device).zero_() for ws in wss]


def _proj_forward_ws(wss, c3, weights, pattern, bounds, rows, cols, n_samples, pps, max_rays, workers, hard, cache):
    dt, dev = c3.dtype, c3.device
    k_total = pattern.shape[1]
    out = torch.zeros(n_samples, rows, cols, dtype=dt, device=dev)
    for b0, b1 in _blocks(n_samples, rows, cols):
        ns = b1 - b0
        if hard:
            trash = ns * rows * cols
            accs = _accumulators(wss, (1, trash + 1), dt, dev)
        else:
            trash = ns * (rows + 2) * (cols + 2)
            accs = _accumulators(wss, (2, trash + 1), dt.to_complex(), dev)
        tasks = []
        for s, e in _point_chunks(b0 * pps, b1 * pps, k_total, max_rays):
            def task(j, s=s, e=e):
                ws, acc = wss[j], accs[j]
                c, w = c3[:, s:e], weights[s:e].unsqueeze(1)
                bnd = None if bounds is None else bounds[s:e]
                off = _sample_offset(s, e, pps, b0, rows + 2, cols + 2, dt, dev)
                off_hard = _sample_offset(s, e, pps, b0, rows, cols, dt, dev)
                for k0, k1 in _k_slices(k_total, max_rays):
                    q2, _, bad = _project(ws, c, pattern[:, k0:k1])
                    if bnd is not None:
                        _bounds_check(ws, q2, bad, bnd)
                    if hard:
                        idx = _land_hard(ws, q2, bad, rows, cols, trash, off_hard)
                        acc[0].index_add_(0, idx.view(-1), w.expand(idx.shape).reshape(-1))
                        continue
                    slot = None if cache is None else cache.slot(s, e, k0, k1, k_total)
                    f2, idx, _ = _land(ws, q2, bad, rows, cols, trash, off, i32_out=slot)
                    acc.index_add_(1, idx.view(-1), _moments(ws, w, f2))
            tasks.append(task)
        _run(tasks, workers)
        acc = accs[0]
        for other in accs[1:]:
            acc += other
        out[b0:b1] = acc[0, :trash].view(ns, rows, cols) if hard else _compose(acc, ns, rows, cols, wss[0])
    return out


class _ProjectiveSplat(torch.autograd.Function):
    @staticmethod
    def forward(ctx, coef, weights, pattern, bounds, rows, cols, n_samples, pps, max_rays, workers):
        c3 = _to_c3(coef)
        cache = _IndexCache(coef.shape[0] * pattern.shape[1], coef.device) if any(ctx.needs_input_grad[:2]) else None
        out = _proj_forward(c3, weights, pattern, bounds, rows, cols, n_samples, pps, max_rays, workers,
                            cache=cache)
        ctx.save_for_backward(coef, weights, pattern, bounds)
        ctx.cfg = (rows, cols, n_samples, pps, max_rays, workers)
        ctx.cache = cache
        return out

    @staticmethod
    def backward(ctx, grad_out):
        coef, weights, pattern, bounds = ctx.saved_tensors
        rows, cols, n_samples, pps, max_rays, workers = ctx.cfg
        need_c, need_w = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if not (need_c or need_w):
            return (None,) * 10
        cache, ctx.cache = ctx.cache, None  # a second backward (retain_graph) recomputes the index
        dev = coef.device
        nslots = max(1, workers)
        wss = _SCRATCH.workspaces(nslots, dev)
        grads = _ProjectiveSplat._backward(wss, cache, grad_out, coef, weights, pattern, bounds, rows, cols, n_samples,
                                           pps, max_rays, workers, need_c, need_w)
        _SCRATCH.give_workspaces(wss, dev)
        if cache is not None:
            cache.release()
        return grads + (None,) * 8

    @staticmethod
    def _backward(wss, cache, grad_out, coef, weights, pattern, bounds, rows, cols, n_samples, pps, max_rays, workers,
                  need_c, need_w):
        dt, dev = coef.dtype, coef.device
        c3 = _to_c3(coef)
        grad3 = torch.zeros_like(c3)
        grad_w = torch.zeros_like(weights)
        grad_out = grad_out.to(dt).contiguous()
        k_total = pattern.shape[1]
        for b0, b1 in _blocks(n_samples, rows, cols):
            maps = _grad_maps(grad_out[b0:b1], wss[0])
            trash = maps.shape[1] - 1
            tasks = []
            for s, e in _point_chunks(b0 * pps, b1 * pps, k_total, max_rays):
                def task(j, s=s, e=e):
                    ws = wss[j]
                    c, w = c3[:, s:e], weights[s:e].unsqueeze(1)
                    bnd = None if bounds is None else bounds[s:e]
                    off = _sample_offset(s, e, pps, b0, rows + 2, cols + 2, dt, dev)
                    for k0, k1 in _k_slices(k_total, max_rays):
                        pat = pattern[:, k0:k1]
                        n, k = e - s, k1 - k0
                        cached = None if cache is None else cache.slot(s, e, k0, k1, k_total)
                        if cached is not None:  # forward's index: landing rays have q2 = v2, f2 = frac(q2)
                            q2, inv, _ = _project(ws, c, pat, with_bad=False)
                            f2 = torch.frac(q2, out=ws.get("f2", q2.shape, dt, dev))
                            idx = ws.get("i64", (n, k), torch.int64, dev).copy_(cached.view(n, k))
                        else:
                            q2, inv, bad = _project(ws, c, pat)
                            if bnd is not None:
                                _bounds_check(ws, q2, bad, bnd)
                            f2, idx, _ = _land(ws, q2, bad, rows, cols, trash, off, keep=True)
                        dw, g3 = _backward_chunk(ws, maps, f2, idx, w, inv, q2, need_w, need_c)
                        if need_w:
                            grad_w[s:e] += dw.sum(1)
                        if need_c:
                            flat_g = g3.view(3 * n, k)
                            gcs = grad3[:, s:e]
                            gcs[..., 0] += flat_g.sum(1).view(3, n)
                            gcs[..., 1] += torch.mv(flat_g, pat[1]).view(3, n)
                            gcs[..., 2] += torch.mv(flat_g, pat[2]).view(3, n)
                tasks.append(task)
            _run(tasks, workers)
        grad_c = None
        if need_c:  # adjoint of _to_c3
            grad_c = torch.empty_like(coef)
            grad_c[:, 0] = grad3[1]
            grad_c[:, 1] = grad3[0]
            torch.add(grad3[2], grad3[0], out=grad_c[:, 2]).add_(grad3[1])
        return grad_c, grad_w if need_w else None


def projective_splat(coef: torch.Tensor, weights: torch.Tensor, pattern: torch.Tensor, rows: int, cols: int,
                     n_samples: int, points_per_sample: int, bounds: torch.Tensor | None = None,
                     max_rays_per_chunk: int = DEFAULT_MAX_RAYS_PER_CHUNK, workers: int | None = None) -> torch.Tensor:
    """Trace-and-splat for planar targets: rays given by projective coefficients, bilinear splat.

    Ray ``k`` of point ``i`` lands at pixel coordinates ``px = N_x . q_k / D . q_k``,
    ``py = N_y . q_k / D . q_k`` with ``q_k = (1, a_k, b_k)`` a column of ``pattern``. It reaches the
    plane only if ``D . q_k < -DEN_EPS`` (the direction has a component against the target normal);
    points behind the target must be given weight 0 by the caller.

    Parameters
    ----------
    coef : torch.Tensor, shape (N, 3, 3)
        ``coef[i, 0] = N_x``, ``coef[i, 1] = N_y``, ``coef[i, 2] = D`` over the basis ``(1, a, b)``, in
        pixel units (see module docs). Points are ordered sample-major: point ``i`` belongs to sample
        ``i // points_per_sample``.
    weights : torch.Tensor, shape (N,)
        Value each ray of the point deposits (e.g. W/m^2 per ray); 0 drops the point.
    pattern : torch.Tensor, shape (3, K)
        Rows ``1, a_k, b_k`` (not differentiated).
    rows, cols : int
        Bitmap size.
    n_samples, points_per_sample : int
        ``N = n_samples * points_per_sample``.
    bounds : torch.Tensor, shape (N, 4), optional
        Extra landing region per point ``(px_lo, px_hi, py_lo, py_hi)`` (e.g. the target inside a larger
        window); rays outside get weight 0.
    max_rays_per_chunk : int
        Rays per chunk (memory: ~25 buffers of this size per worker).
    workers : int, optional
        None/0: run the chunks in the calling thread (ops use PyTorch's intra-op threads); n >= 1: on n
        worker threads with one intra-op thread each (more robust on oversubscribed machines).

    Returns
    -------
    torch.Tensor, shape (n_samples, rows, cols)
        Sum of deposited weights per pixel; differentiable w.r.t. ``coef`` and ``weights``.
    """
    dt = coef.dtype
    coef = coef.reshape(-1, 3, 3)
    pattern = pattern.to(dt).contiguous()
    if bounds is not None:
        bounds = bounds.to(dt).contiguous()
    return _ProjectiveSplat.apply(coef, weights.to(dt).contiguous(), pattern, bounds, int(rows), int(cols),
                                  int(n_samples), int(points_per_sample), int(max_rays_per_chunk),
                                  _num_workers(workers))


@torch.no_grad()
def projective_splat_hard(coef: torch.Tensor, weights: torch.Tensor, pattern: torch.Tensor, rows: int, cols: int,
                          n_samples: int, points_per_sample: int, bounds: torch.Tensor | None = None,
                          max_rays_per_chunk: int = DEFAULT_MAX_RAYS_PER_CHUNK,
                          workers: int | None = None) -> torch.Tensor:
    """Nearest-pixel version of :func:`projective_splat` (one scatter per chunk; not differentiable).

    Parameters and result as in :func:`projective_splat` (``coef`` (n_samples * points_per_sample, 3, 3),
    result (n_samples, rows, cols) [W/m^2]); each landing ray deposits its whole weight in the pixel that
    contains it.
    """
    dt = coef.dtype
    c3 = _to_c3(coef.detach().reshape(-1, 3, 3))
    bounds = None if bounds is None else bounds.detach().to(dt).contiguous()
    return _proj_forward(c3, weights.detach().to(dt).contiguous(), pattern.to(dt).contiguous(), bounds,
                         int(rows), int(cols), int(n_samples), int(points_per_sample), int(max_rays_per_chunk),
                         _num_workers(workers), hard=True)


# ----------------------------------------------------------------------------------------------------
# generic splat (explicit coordinates)
# ----------------------------------------------------------------------------------------------------

def _explicit_chunks(total: int, max_rays: int):
    step = max(1, int(max_rays))
    for s in range(0, total, step):
        yield s, min(total, s + step)


def _load(ws, fpx, fpy, s, e):
    """Padded coordinates q2 = (py + 1, px + 1) [2, n, 1] of points s..e-1 (NaN -> far off the bitmap)."""
    q2 = ws.get("proj", (2, e - s, 1), fpx.dtype, fpx.device)
    q2[0].copy_(fpy[s:e])
    q2[1].copy_(fpx[s:e])
    return q2.nan_to_num_(nan=-1e30).add_(1.0)


class _BilinearSplat(torch.autograd.Function):
    @staticmethod
    def forward(ctx, px, py, w, rows, cols, max_rays, workers):
        n_samples, m = px.shape
        dt, dev = px.dtype, px.device
        fpx, fpy, fw = px.reshape(-1, 1), py.reshape(-1, 1), w.reshape(-1, 1)
        out = torch.zeros(n_samples, rows, cols, dtype=dt, device=dev)
        wss = _SCRATCH.workspaces(max(1, workers), dev)
        for b0, b1 in _blocks(n_samples, rows, cols):
            ns = b1 - b0
            trash = ns * (rows + 2) * (cols + 2)
            accs = _accumulators(wss, (2, trash + 1), dt.to_complex(), dev)
            tasks = []
            for s, e in _explicit_chunks(ns * m, max_rays):
                def task(j, s=s + b0 * m, e=e + b0 * m):
                    ws = wss[j]
                    q2 = _load(ws, fpx, fpy, s, e)
                    bad = ws.get("bad", (e - s, 1), dt, dev).zero_()
                    f2, idx, _ = _land(ws, q2, bad, rows, cols, trash,
                                       _sample_offset(s, e, m, b0, rows + 2, cols + 2, dt, dev))
                    accs[j].index_add_(1, idx.view(-1), _moments(ws, fw[s:e], f2))
                tasks.append(task)
            _run(tasks, workers)
            acc = accs[0]
            for other in accs[1:]:
                acc += other
            out[b0:b1] = _compose(acc, ns, rows, cols, wss[0])
        _SCRATCH.give_workspaces(wss, dev)
        ctx.save_for_backward(px, py, w)
        ctx.cfg = (rows, cols, max_rays, workers)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        px, py, w = ctx.saved_tensors
        rows, cols, max_rays, workers = ctx.cfg
        n_samples, m = px.shape
        dt, dev = px.dtype, px.device
        need_p = ctx.needs_input_grad[0] or ctx.needs_input_grad[1]
        need_w = ctx.needs_input_grad[2]
        gpx = torch.zeros_like(px).view(-1, 1)
        gpy = torch.zeros_like(py).view(-1, 1)
        gw = torch.zeros_like(w).view(-1, 1)
        fpx, fpy, fw = px.reshape(-1, 1), py.reshape(-1, 1), w.reshape(-1, 1)
        grad_out = grad_out.to(dt).contiguous()
        wss = _SCRATCH.workspaces(max(1, workers), dev)
        for b0, b1 in _blocks(n_samples, rows, cols):
            ns = b1 - b0
            maps = _grad_maps(grad_out[b0:b1], wss[0])
            trash = maps.shape[1] - 1
            tasks = []
            for s, e in _explicit_chunks(ns * m, max_rays):
                def task(j, s=s + b0 * m, e=e + b0 * m):
                    ws = wss[j]
                    q2 = _load(ws, fpx, fpy, s, e)
                    bad = ws.get("bad", (e - s, 1), dt, dev).zero_()
                    f2, idx, _ = _land(ws, q2, bad, rows, cols, trash,
                                       _sample_offset(s, e, m, b0, rows + 2, cols + 2, dt, dev), keep=True)
                    dw, g3 = _backward_chunk(ws, maps, f2, idx, fw[s:e], None, q2, need_w, need_p)
                    if need_w:
                        gw[s:e] = dw
                    if need_p:
                        gpy[s:e] = g3[0]
                        gpx[s:e] = g3[1]
                tasks.append(task)
            _run(tasks, workers)
        _SCRATCH.give_workspaces(wss, dev)
        return (gpx.view_as(px) if need_p else None, gpy.view_as(py) if need_p else None,
                gw.view_as(w) if need_w else None, None, None, None, None)


def _as_batched(px, py, w):
    px, py, w = torch.broadcast_tensors(px, py, w)
    if px.dim() == 1:
        px, py, w = px.unsqueeze(0), py.unsqueeze(0), w.unsqueeze(0)
    b = px.shape[0]
    return px.reshape(b, -1), py.reshape(b, -1), w.reshape(b, -1)


def splat_bilinear(px: torch.Tensor, py: torch.Tensor, weights: torch.Tensor, rows: int, cols: int,
                   max_rays_per_chunk: int = DEFAULT_MAX_RAYS_PER_CHUNK, workers: int | None = None) -> torch.Tensor:
    """Bilinear (tent-kernel) splat of weighted points, differentiable w.r.t. coordinates and weights.

    Parameters
    ----------
    px, py : torch.Tensor, shape (B, ...) or (M,)
        Column / row pixel coordinates (pixel centres at integers; see module docs). NaN counts as off
        the bitmap.
    weights : torch.Tensor, shape (B, ...) or (M,), broadcastable to ``px``
        Deposited value per point (e.g. [W/m^2] per ray).
    rows, cols : int
        Bitmap size.
    max_rays_per_chunk : int
        Points per chunk (memory bound).
    workers : int, optional
        Worker threads (default ``torch.get_num_threads()``).

    Returns
    -------
    torch.Tensor, shape (B, rows, cols) (B = 1 for 1-D input)
        Per-pixel sums; every point inside ``[-0.5, cols-0.5] x [-0.5, rows-0.5]`` deposits its whole weight.
    """
    px, py, w = _as_batched(px, py, weights)
    dtype = torch.promote_types(px.dtype, w.dtype)
    return _BilinearSplat.apply(px.to(dtype).contiguous(), py.to(dtype).contiguous(), w.to(dtype).contiguous(),
                                int(rows), int(cols), int(max_rays_per_chunk), _num_workers(workers))


@torch.no_grad()
def splat_hard(px: torch.Tensor, py: torch.Tensor, weights: torch.Tensor, rows: int, cols: int) -> torch.Tensor:
    """Nearest-pixel binning (histogram) of weighted points; not differentiable.

    Parameters
    ----------
    px, py : torch.Tensor, shape (B, ...) or (M,)
        Pixel coordinates (centres at integers).
    weights : torch.Tensor, shape (B, ...) or (M,), broadcastable to ``px``
        Deposited value per point.
    rows, cols : int

    Returns
    -------
    torch.Tensor, shape (B, rows, cols)
    """
    px, py, w = _as_batched(px, py, weights)
    b, m = px.shape
    dt = torch.promote_types(px.dtype, w.dtype)
    ws = _Workspace()
    q2 = _load(ws, px.reshape(-1, 1).to(dt), py.reshape(-1, 1).to(dt), 0, b * m)
    bad = torch.zeros(b * m, 1, dtype=dt, device=px.device)
    trash = rows * cols
    idx = _land_hard(ws, q2, bad, rows, cols, trash)
    if b > 1:  # integer sample offsets (a large batch's flat index is not exact in float32)
        sample = (torch.arange(b * m, device=px.device) // m).unsqueeze(1)
        idx.add_(torch.where(idx == trash, b * rows * cols - trash, sample * (rows * cols)))
    out = torch.zeros(b * rows * cols + 1, dtype=dt, device=px.device)
    out.index_add_(0, idx.view(-1), w.reshape(-1).to(dt))
    return out[:-1].view(b, rows, cols)
