"""Sharding the field over ``torch.distributed`` ranks.

Every rank holds the whole plant (its geometry is small) and traces a contiguous shard of the heliostats:
all heliostats still shade and block the shard's rays, so the shard's factors are exactly those of a
single-process run. The receiver map is summed over ranks (``all_reduce``) and the per-heliostat factors are
gathered (``all_gather``, padded to the largest shard), so every rank ends with the whole field's
:class:`~heliotwin.raytrace.field.FieldResult`. Works with any backend (gloo on CPU, NCCL on GPU); start
with ``torchrun --nproc-per-node N`` or :func:`torch.multiprocessing.spawn` after :func:`init_process_group`
(this module's: see there why not torch's directly), or let :func:`run_sharded` spawn N local gloo processes.

The map is the single-process one in every ``flux_mode``: the ranks agree on the footprint window, and in
``grouped`` mode on the footprint classes and their kernels (all ranks' footprints), so their maps sum to the
one-process map up to float rounding.

:func:`run_spawned` runs any module-level ``work(job, group)`` that way; the learners that shard (aim points:
:func:`heliotwin.optimise.aimpoints.run_aimpoints_sharded`) build on it, this module knows none of them.
"""
from __future__ import annotations

import atexit
import contextlib
import ctypes
import ctypes.util
import os
import shutil
import signal
import sys
import tempfile
import threading
import time

import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from tqdm import tqdm

from .errors import HeliotwinError
from .raytrace.field import FieldResult, field_optics

__all__ = ["init_process_group", "shard", "gather_rows", "field_optics_sharded", "run_spawned", "run_sharded"]

_PER_HELIOSTAT = ("aim", "normal", "cosine", "shading", "tower_shading", "blocking", "attenuation", "intercept",
                  "reflectance", "efficiency", "power_w", "mirror_area")


def init_process_group(backend: str = "gloo", **kwargs) -> None:
    """:func:`torch.distributed.init_process_group` (same arguments), with ``torch._dynamo`` imported first.

    Why: the first ``torch.optim`` optimiser (the aim-point optimiser's Adam) imports ``torch._dynamo``
    lazily, and imported while a process group exists it keeps references to that group. Then
    :func:`torch.distributed.destroy_process_group` no longer frees the group; the gloo backend is torn down
    at interpreter exit instead, where it can abort the process ("terminate called without an active
    exception", SIGABRT: about one two-rank aim-point run in four with torch 2.13 on CPU). Imported before
    the group exists, it holds nothing. Call this instead of torch's own under ``torchrun`` too.

    The import is here, not at the top of the module: it costs 1-3 s, and only a process that creates a group
    and then exits through the interpreter's teardown needs it (the aim-point optimiser's own Adam,
    :class:`heliotwin.optimise.aimpoints._Adam`, no longer imports it, but any other ``torch.optim`` user
    would). The workers of :func:`run_spawned` skip it: they end without that teardown (``_leave_worker``).
    """
    import torch._dynamo  # noqa: F401, PLC0415  (here, not at the top: for its side effect, see above)
    dist.init_process_group(backend, **kwargs)


def shard(num_heliostats: int, rank: int, world_size: int) -> torch.Tensor:
    """Indices, shape (h,), long, of rank ``rank``'s contiguous shard (sizes differ by at most one).

    ``num_heliostats`` H, ``rank`` and ``world_size`` (the number of processes) are counts [1].
    """
    base, extra = divmod(int(num_heliostats), int(world_size))
    start = rank * base + min(rank, extra)
    return torch.arange(start, start + base + (1 if rank < extra else 0))


def gather_rows(t: torch.Tensor, counts: list[int], group) -> torch.Tensor:
    """Concatenate every rank's ``[h_r, ...]`` tensor in rank order (padded all_gather): ``[sum(counts), ...]``."""
    width = max(counts)
    pad = t.new_zeros((width, *t.shape[1:]))
    pad[: t.shape[0]] = t
    parts = [torch.empty_like(pad) for _ in counts]
    dist.all_gather(parts, pad.contiguous(), group=group)
    return torch.cat([p[:c] for p, c in zip(parts, counts)])


def field_optics_sharded(plant, sun_direction, *, group=None, **kwargs) -> FieldResult:
    """:func:`heliotwin.raytrace.field.field_optics` with the heliostats sharded over the process group.

    Parameters
    ----------
    plant, sun_direction, **kwargs
        As for ``field_optics`` (same on every rank): ``sun_direction`` is the unit vector towards the sun,
        shape (3,), ENU.
    group : ProcessGroup, optional
        Default: the world.

    Returns
    -------
    FieldResult
        The whole field's result, identical on every rank (map summed, per-heliostat tensors gathered back
        to shape (H,) in heliostat order).
    """
    group = group if group is not None else dist.group.WORLD  # field_optics reads None as "not sharded"
    rank, world = dist.get_rank(group), dist.get_world_size(group)
    h = len(plant.field.ids)
    rows = shard(h, rank, world)
    r = field_optics(plant, sun_direction, heliostats=rows, group=group, **kwargs)
    flux = r.flux.detach().clone()
    dist.all_reduce(flux, group=group)
    counts = [len(shard(h, k, world)) for k in range(world)]
    gathered = {name: gather_rows(getattr(r, name).detach(), counts, group) for name in _PER_HELIOSTAT}
    extras = {k: gather_rows(v.detach(), counts, group) for k, v in r.extras.items()}
    return FieldResult(**gathered, flux=flux, extent=r.extent, sun=r.sun, dni=r.dni, extras=extras)


def _trace_shard(job: dict, group) -> FieldResult:
    with torch.no_grad():
        return field_optics_sharded(job["plant"], job["sun"], group=group, **job["kwargs"])


def _die_with_parent(parent: int, folder: str) -> None:
    """End this worker when the parent goes away (killed, or exiting without ending it): the kernel's
    parent-death signal on Linux, and a watchdog thread everywhere (the parent id changes when it dies). A
    worker that finds its parent gone also removes the shared folder, which a killed parent could not."""
    with contextlib.suppress(Exception):
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG

    def orphaned() -> None:
        shutil.rmtree(folder, ignore_errors=True)
        os._exit(1)

    if os.getppid() != parent:  # the parent died while this worker was starting
        orphaned()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        orphaned()

    threading.Thread(target=watch, daemon=True).start()


def _run_rank(rank: int, work, world: int, folder: str, threads: int, parent: int) -> None:
    # Ctrl-C reaches the whole process group: the parent alone decides, and ends the workers itself.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent(parent, folder)
    # tqdm's default write lock is a multiprocessing RLock: a named POSIX semaphore that the shared resource
    # tracker records. A worker ended by a signal (the parent's terminate, or SIGTERM to the process group) never
    # unlinks it, and the tracker then warns of a "leaked semaphore" as the command exits. A worker's bars only
    # need to be safe among its own threads.
    tqdm.set_lock(threading.RLock())
    torch.set_num_threads(threads)
    try:
        # torch's own init, not init_process_group's: its torch._dynamo import (1-3 s of a worker's start) only
        # keeps a group that a later torch.optim optimiser holds from being torn down at interpreter exit, where
        # gloo can abort the process; a worker never reaches that teardown (_leave_worker)
        dist.init_process_group("gloo", init_method=f"file://{folder}/store", rank=rank, world_size=world)
        try:
            job = torch.load(f"{folder}/job.pt", weights_only=False)  # written by the parent just now
            result = work(job, dist.group.WORLD)
            if rank == 0:
                torch.save(result, f"{folder}/result.pt")
        finally:
            dist.destroy_process_group()
    except BaseException as exc:  # noqa: BLE001 -- reported to the parent as one line, never as a traceback
        kind = "input" if isinstance(exc, HeliotwinError) else "internal"
        text = " ".join(str(exc).split()) or type(exc).__name__
        with open(f"{folder}/error-{rank}.txt", "w", encoding="utf-8") as fh:
            fh.write(f"{kind}\t{type(exc).__name__}\t{text}")
        _leave_worker(1)
    _leave_worker(0)


def _leave_worker(status: int) -> None:
    """End a worker with exit ``status`` after its exit functions (finalizers, temporary folders) and a flush of
    its output, without the interpreter's teardown of modules and torch's C++ state: a process group that a
    lazily imported ``torch._dynamo`` kept past ``destroy_process_group`` would be torn down there, and gloo can
    then abort the process (SIGABRT), although its work is saved (as :func:`heliotwin.cli.common.leave`)."""
    with contextlib.suppress(Exception):
        atexit._run_exitfuncs()  # what the interpreter's exit runs first (CPython's own function)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            if stream is not None:
                stream.flush()
    os._exit(status)


def _worker_error(folder: str, world: int, processes) -> BaseException | None:
    """The first worker's error (as the exception to raise in the parent), or None when all ended well."""
    for rank in range(world):
        path = os.path.join(folder, f"error-{rank}.txt")
        if os.path.exists(path):
            with open(path, encoding="utf-8") as fh:
                kind, name, text = (fh.read().split("\t", 2) + ["", ""])[:3]
            if kind == "input":
                return HeliotwinError(text)
            return RuntimeError(f"worker {rank}: {name}: {text}")
    for rank, p in enumerate(processes):
        if p.exitcode:
            how = f"signal {-p.exitcode}" if p.exitcode < 0 else f"exit status {p.exitcode}"
            return RuntimeError(f"worker {rank} ended with {how}")
    return None


def _end(processes, grace: float = 2.0) -> None:
    """Terminate the workers still running (SIGTERM, then SIGKILL after ``grace`` s) and reap them all."""
    for p in processes:
        if p.is_alive():
            p.terminate()
    deadline = time.monotonic() + grace
    for p in processes:
        p.join(max(0.0, deadline - time.monotonic()))
    for p in processes:
        if p.is_alive():
            p.kill()
            p.join()


def run_spawned(work, job: dict, nproc: int):
    """Run ``work(job, group)`` on ``nproc`` spawned local gloo processes; rank 0's return value.

    The machine's threads are split evenly over the processes (at least one each). The workers end with the
    parent: an error in one ends the others (raised here as one line: a
    :class:`~heliotwin.errors.HeliotwinError` as itself, anything else as ``RuntimeError``), Ctrl-C or
    SIGTERM in the parent ends them before the exception goes on, and a parent killed outright takes them
    along (parent-death signal, and a watchdog). Their shared folder is removed only once all have ended.

    Parameters
    ----------
    work : callable
        A module-level function (spawned processes pickle it by name) of the job dict and the world group.
    job : dict
        What every rank starts from (saved once with :func:`torch.save`, loaded by each rank).
    nproc : int
        Number of processes [-].
    """
    nproc = int(nproc)
    threads = max(1, torch.get_num_threads() // nproc)
    context = mp.get_context("spawn")
    with tempfile.TemporaryDirectory(prefix="heliotwin-ranks-") as folder:
        torch.save(job, f"{folder}/job.pt")
        processes = []
        try:
            for rank in range(nproc):
                p = context.Process(target=_run_rank, args=(rank, work, nproc, folder, threads, os.getpid()))
                p.start()
                processes.append(p)
            while any(p.is_alive() for p in processes):
                if any(p.exitcode for p in processes):  # one failed: the others would wait for it forever
                    break
                processes[0].join(0.1)
        finally:
            _end(processes)
        error = _worker_error(folder, nproc, processes)
        if error is not None:
            raise error
        return torch.load(f"{folder}/result.pt", weights_only=False)  # written by rank 0 just now


def run_sharded(plant, sun_direction, nproc: int, **kwargs) -> FieldResult:
    """Spawn ``nproc`` local gloo processes that trace the field sharded; rank 0's (= every rank's) result.

    The machine's threads are split evenly over the processes (at least one each).
    """
    return run_spawned(_trace_shard, {"plant": plant, "sun": sun_direction, "kwargs": kwargs}, nproc)
