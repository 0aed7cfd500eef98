"""Checkpoints of long fits: what an interrupted ``calibrate`` or ``reconstruct`` needs to go on (``--resume``).

One file per run, next to its main output (``<output>.ckpt``, :func:`checkpoint_path`), holding a dict of
*entries*, one per optimisation loop of the run. Every loop that runs while a checkpoint is active
(:func:`active`; the loops ask :func:`current`) claims the next key of its kind (``fit/0``, ``fit/1``, ...,
``surface/0``): a run's loops come in the same order every time (the setup between them is deterministic),
so a resumed run finds each loop's entry under the same key. An entry holds the loop's full state after a
step (parameters, optimiser state, generator state, best-so-far and early-stopping bookkeeping, logs); a
finished loop's entry is its final state, so on resume it is restored instead of run. Loops whose every
iteration is long (``lm``'s bootstrap bags) use :func:`resumable_range` and save after each iteration.

Granularity: a loop saves every :attr:`Checkpoint.every` steps, at most once per
:attr:`Checkpoint.min_interval_s` seconds (the disk is not hammered by fast steps), and always when it
finishes. Whatever the timing, a saved state is a consistent one: resuming redoes at most the steps since
the last save and reaches the same result as an uninterrupted run (bit-identical on the same machine and
device: the same operations run on the same values).

Safety:

* written atomically (temporary file in the same folder + :func:`os.replace`): a kill leaves the previous
  checkpoint or the new one, never half of one, and no temporary file;
* tagged with a hash of the run's settings and inputs (:func:`make_tag`): a resume with other settings or
  changed inputs is refused with one line, and so is a file that is not a readable checkpoint;
* read with ``torch.load(weights_only=True)``: a checkpoint holds tensors, numbers, strings and containers
  only, and loading one runs no code;
* removed by the caller after the run's outputs are written (:meth:`Checkpoint.remove`).
"""
from __future__ import annotations

import contextlib
import contextvars
import hashlib
import json
import os
import tempfile
import time

import torch

from ..errors import HeliotwinError
from .report import _new_file_mode

__all__ = ["Checkpoint", "checkpoint_path", "make_tag", "fingerprint", "save_atomic", "active", "current",
           "resumable_range", "FORMAT", "VERSION"]

FORMAT = "heliotwin-checkpoint"
VERSION = 1

_ACTIVE: contextvars.ContextVar = contextvars.ContextVar("heliotwin_checkpoint", default=None)


def checkpoint_path(output) -> str:
    """The checkpoint file of a run whose main output is ``output``: ``<output>.ckpt``."""
    return os.fspath(output) + ".ckpt"


def fingerprint(path) -> list:
    """What identifies an input path for :func:`make_tag`: per file (a folder: every file below it, sorted)
    its path relative to ``path``, size [bytes] and modification time [ns]; ``None`` for a missing path.
    Checkpoints (``*.ckpt``) and heliotwin's staging files inside a folder are left out.

    Stat only, no reading: a PAINT folder of thousands of files is fingerprinted in milliseconds.
    """
    if path is None:
        return None
    path = os.fspath(path)
    if os.path.isfile(path):
        st = os.stat(path)
        return [["", st.st_size, st.st_mtime_ns]]
    if not os.path.isdir(path):
        return None
    rows = []

    def walk(folder: str, prefix: str) -> None:
        # scandir: one stat per file and no path arithmetic (190k record files of a plant's folder in ~1 s)
        try:
            entries = sorted(os.scandir(folder), key=lambda e: e.name)
        except OSError:
            return
        folders = []
        for e in entries:  # files first, then the subfolders: os.walk's order, so earlier tags stay valid
            # A run's own checkpoint and staging files may lie inside an input folder: not part of the input.
            if e.name.startswith(".heliotwin-"):
                continue
            try:
                if e.is_dir():
                    folders.append(e)
                elif not e.name.endswith(".ckpt"):
                    st = e.stat()
                    rows.append([prefix + e.name, st.st_size, st.st_mtime_ns])
            except OSError:
                continue
        for e in folders:
            walk(e.path, prefix + e.name + os.sep)

    walk(path, "")
    return rows


def make_tag(settings: dict, inputs=()) -> str:
    """SHA-256 (hex) of the run's settings (JSON, sorted keys) and the :func:`fingerprint` of each input."""
    text = json.dumps({"settings": settings, "inputs": [fingerprint(p) for p in inputs]}, sort_keys=True,
                      default=str)
    return hashlib.sha256(text.encode()).hexdigest()


class Checkpoint:
    """The checkpoint file of one run (see the module docstring).

    Parameters
    ----------
    path : str or os.PathLike
        The checkpoint file (:func:`checkpoint_path` of the main output).
    tag : str
        :func:`make_tag` of the run's settings and inputs.
    resume : bool
        Continue from the file at ``path`` (its tag must be ``tag``); without it an existing file is an error
        (it holds an interrupted run's work: resume it or delete it). Resuming without a file starts afresh.
    every : int
        Loop steps between saves.
    min_interval_s : float
        Least time between two saves of unfinished loops [s] (0: every ``every`` steps).
    hook : callable, optional
        ``hook(event, key, step)`` after every loop step (``"step"``) and every save (``"saved"``): tests
        interrupt a run there.
    """

    def __init__(self, path, tag: str, *, resume: bool = False, every: int = 10, min_interval_s: float = 30.0,
                 hook=None):
        if int(every) < 1:
            raise HeliotwinError(f"checkpoint: every must be >= 1, got {every}")
        self.path = os.fspath(path)
        self.tag = str(tag)
        self.every = int(every)
        self.min_interval_s = float(min_interval_s)
        self.hook = hook
        self.entries: dict = {}
        self.resumed = False
        self._claimed: dict = {}
        self._last_save = time.monotonic()
        exists = os.path.exists(self.path)
        if exists and not resume:
            raise HeliotwinError(f"{self.path}: a checkpoint of an interrupted run exists; rerun with --resume to "
                                 f"continue it, or delete the file to start over")
        if exists:
            self.entries = self._read()
            self.resumed = True

    def _read(self) -> dict:
        try:
            data = torch.load(self.path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 -- any unreadable file is the same one-line error
            raise HeliotwinError(f"{self.path}: not a readable heliotwin checkpoint ({type(exc).__name__}); delete "
                                 f"it to start over") from None
        if not isinstance(data, dict) or data.get("format") != FORMAT or not isinstance(data.get("entries"), dict):
            raise HeliotwinError(f"{self.path}: not a heliotwin checkpoint (field 'format'); delete it to start over")
        if data.get("version") != VERSION:
            raise HeliotwinError(f"{self.path}: checkpoint version {data.get('version')!r}, this heliotwin reads "
                                 f"{VERSION}; delete it to start over")
        if data.get("tag") != self.tag:
            raise HeliotwinError(f"{self.path}: checkpoint of a run with other settings or inputs (field 'tag'); "
                                 f"rerun with the same settings to resume, or delete it to start over")
        return data["entries"]

    # ------------------------------------------------------------------ what the loops call
    def claim(self, kind: str) -> str:
        """The key of the next loop of this kind (``"fit/0"``, ``"fit/1"``, ...)."""
        n = self._claimed.get(kind, 0)
        self._claimed[kind] = n + 1
        return f"{kind}/{n}"

    def get(self, key: str):
        """The saved entry of loop ``key`` (None if it never saved)."""
        return self.entries.get(key)

    def due(self, step: int) -> bool:
        """Whether an unfinished loop at ``step`` should save now."""
        return step % self.every == 0 and time.monotonic() - self._last_save >= self.min_interval_s

    def put(self, key: str, entry: dict) -> None:
        """Store loop ``key``'s entry and write the file (atomically)."""
        self.entries[key] = entry
        self._write()
        self._last_save = time.monotonic()
        self.notify("saved", key, entry.get("step"))

    def notify(self, event: str, key: str, step) -> None:
        """Tell the ``hook`` (if any) that loop ``key`` reached ``event`` (``"step"`` / ``"saved"``) at ``step``."""
        if self.hook is not None:
            self.hook(event, key, step)

    def _write(self) -> None:
        save_atomic({"format": FORMAT, "version": VERSION, "tag": self.tag, "entries": self.entries}, self.path)

    def remove(self) -> None:
        """Delete the file (after the run's outputs are written)."""
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)


def save_atomic(obj, path) -> None:
    """``torch.save(obj)`` to ``path`` atomically: a temporary file in the same folder, then :func:`os.replace`
    (a kill leaves the previous file or none, never half of one); the new file gets the mode of a fresh file."""
    path = os.fspath(path)
    fd, tmp = tempfile.mkstemp(prefix=".heliotwin-ckpt-", dir=os.path.dirname(os.path.abspath(path)))
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(obj, f)
        os.chmod(tmp, _new_file_mode())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def active(checkpoint: Checkpoint | None):
    """Make ``checkpoint`` the one the loops inside this block use (None: no checkpointing); loop keys are
    claimed afresh from 0."""
    if checkpoint is not None:
        checkpoint._claimed = {}
    token = _ACTIVE.set(checkpoint)
    try:
        yield checkpoint
    finally:
        _ACTIVE.reset(token)


def current() -> Checkpoint | None:
    """The active checkpoint (None outside :func:`active`)."""
    return _ACTIVE.get()


def resumable_range(kind: str, total: int, dump, load):
    """``range(total)`` of a loop whose iterations are long (e.g. one Levenberg-Marquardt fit each), under the
    active checkpoint: the state after the last finished iteration is restored (``load(state)``) and the loop
    goes on from there; after every iteration ``dump()`` (a copy of the state: tensors, numbers, containers) is
    saved. Without an active checkpoint it is ``range(total)``. Yields the iteration indices (scalar ints).
    """
    ck = current()
    key = ck.claim(kind) if ck is not None else None
    first = 0
    saved = ck.get(key) if key is not None else None
    if saved is not None:
        load(saved["state"])
        first = int(saved["step"])
    for i in range(first, total):
        yield i
        if key is not None:
            ck.put(key, {"step": i + 1, "state": dump()})
            ck.notify("step", key, i + 1)
