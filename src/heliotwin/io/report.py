"""The package's one way to write output files: nothing half-written is ever left behind.

* :func:`atomic_path` -- a temporary file next to the destination, renamed onto it only on success.
  Every writer (JSON, CSV, PNG, HDF5) goes through it.
* :func:`write_json` -- strict JSON (NaN/inf become ``null``; tensors and arrays become lists).
* :func:`save_figure` -- a matplotlib figure, atomically, then closed.

Cheap to import: neither torch, numpy nor matplotlib is imported here (the command line's ``--help``
imports this module).
"""
from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import sys
import tempfile
import threading
import time
from contextlib import contextmanager

from ..errors import HeliotwinError, InputFileError

__all__ = ["atomic_path", "write_json", "save_figure", "json_safe", "OutputSet", "output_set", "same_file",
           "plant_inputs", "sweep_stale", "STALE_AGE_S"]

_UMASK_LOCK = threading.Lock()

#: A temporary without its owner's pid in the name (written before pids were) is stale after this long [s].
STALE_AGE_S = 3600.0
# Our temporaries: ``.tmp-<pid>-XXXXXXXX<ext>`` (atomic_path) and ``.heliotwin-<pid>-XXXXXXXX`` (staging folders),
# and the older pid-less names of the same two (tempfile's 8 random characters); nothing else is touched.
_WITH_PID = re.compile(r"^\.(?:tmp|heliotwin)-(\d+)-[a-z0-9_]{8}(?:\.[^.]*)?$")
_WITHOUT_PID = re.compile(r"^\.(?:tmp-[a-z0-9_]{8}(?:\.[^.]*)?|heliotwin-[a-z0-9_]{8})$")
_swept: set = set()


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, OSError):
        return True  # someone else's live process, or a pid we cannot ask about: never swept
    return True


def sweep_stale(folder, *, now: float | None = None) -> list:
    """Remove the temporaries a killed run left in ``folder``: a ``.tmp-*`` file of :func:`atomic_path` or a
    ``.heliotwin-*`` staging folder of :class:`OutputSet` whose owner (the pid in its name) is gone, or, named
    without a pid, older than :data:`STALE_AGE_S`. Symlinks are removed, never followed; errors are ignored (a
    sweep is housekeeping and never fails the command). Returns the names removed."""
    now = time.time() if now is None else now
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        m = _WITH_PID.match(entry.name)
        try:
            if m:
                stale = not _alive(int(m.group(1)))
            elif _WITHOUT_PID.match(entry.name):
                stale = now - entry.stat(follow_symlinks=False).st_mtime > STALE_AGE_S
            else:
                continue
            if not stale:
                continue
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
            removed.append(entry.name)
        except OSError:
            continue
    return removed


def _sweep_once(folder: str) -> None:
    """:func:`sweep_stale` of ``folder`` the first time this process writes there."""
    key = os.path.abspath(folder)
    if key not in _swept:
        _swept.add(key)
        sweep_stale(key)


def _one_line(text) -> str:
    return " ".join(str(text).split())


def _umask() -> int:
    with _UMASK_LOCK:
        mask = os.umask(0)
        os.umask(mask)
    return mask


def _new_file_mode() -> int:
    """The mode ``open()`` gives a new file: 0666 less the umask (``mkstemp`` would leave 0600)."""
    return 0o666 & ~_umask()


def _file_mode(path: str) -> int:
    """An existing destination keeps its own permissions; a new one gets the umask's."""
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        return _new_file_mode()


@contextmanager
def atomic_path(path, *, make_folder: bool = False):
    """Yield a temporary path in the destination's folder; it becomes ``path`` only if the block succeeds.

    On any exception (including ``KeyboardInterrupt``) the temporary file is removed and an existing
    ``path`` is left untouched. The temporary file has the destination's extension, so writers that infer
    the format from the name (matplotlib, PIL) still work. A missing folder is an error (like ``open``)
    unless ``make_folder`` is true.

    Raises
    ------
    InputFileError
        The destination cannot be written (missing permissions, disk full, a folder in the way): the
        message names ``path``, never the temporary file. An ``OSError`` about another file (say, one the
        block reads) is re-raised unchanged, since its message already names that file.
    """
    path = os.fspath(path)
    tmp = None
    try:
        try:
            folder = os.path.dirname(os.path.abspath(path))
            if make_folder:
                os.makedirs(folder, exist_ok=True)
            _sweep_once(folder)
            # the pid in the name lets a later run tell a killed run's temporary from a live one's
            fd, tmp = tempfile.mkstemp(prefix=f".tmp-{os.getpid()}-", suffix=os.path.splitext(path)[1], dir=folder)
            os.close(fd)
        except OSError as exc:
            raise _cannot_write(path, exc, tmp) from exc
        try:
            yield tmp
        except OSError as exc:
            if exc.filename not in (None, tmp):
                raise
            raise _cannot_write(path, exc, tmp) from exc
        try:
            # Data on disk before the rename: after a crash the destination is the old file or the new one.
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
            os.chmod(tmp, _file_mode(path))
            os.replace(tmp, path)
        except OSError as exc:
            raise _cannot_write(path, exc, tmp) from exc
        tmp = None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.remove(tmp)


def _cannot_write(path: str, exc: OSError, tmp: str | None) -> InputFileError:
    reason = str(exc.strerror or exc)
    if tmp:
        reason = reason.replace(tmp, path)
    return InputFileError(path, f"cannot write ({_one_line(reason)})")


def json_safe(obj):
    """A strict-JSON copy of ``obj``: tensors/arrays of any shape ``(...)`` to nested lists (0-d ones to numbers),
    numpy scalars to Python, NaN/inf to ``None``,
    paths to strings, tuples to lists, dict keys to strings.

    Anything else JSON cannot hold (sets, arbitrary objects) is left as is, so :func:`json.dump` raises
    ``TypeError`` on it: a report that silently stringifies an object hides a bug.
    """
    # Only look for tensor/array types when their library is already loaded: nothing else can hold them.
    torch = sys.modules.get("torch")
    np = sys.modules.get("numpy")
    if torch is not None and isinstance(obj, torch.Tensor):
        obj = obj.detach().cpu().tolist()
    elif np is not None and isinstance(obj, np.ndarray):
        obj = obj.tolist()
    elif np is not None and isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return obj


def write_json(path, obj, *, make_folder: bool = True) -> None:
    """Write ``obj`` as strict, indented JSON, atomically (see :func:`json_safe` for the conversions).

    The folder is created when missing (``make_folder``), as the package's report writers always did.

    Raises
    ------
    InputFileError
        ``path`` cannot be written.
    TypeError
        ``obj`` holds something JSON cannot represent (a bug in the caller; nothing is written).
    """
    data = json_safe(obj)
    text = json.dumps(data, indent=1, allow_nan=False) + "\n"
    with atomic_path(path, make_folder=make_folder) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)


def save_figure(fig, path, *, dpi: int = 110, tight: bool = True, make_folder: bool = False) -> None:
    """Write a matplotlib figure atomically and close it (also when writing fails).

    The format follows the extension of ``path`` (PNG when it has none or matplotlib does not know it).
    Works for figures made with :class:`matplotlib.figure.Figure` (no backend, no global state: what
    :mod:`heliotwin.plots` does) and with ``pyplot`` (closed there, so figures do not pile up in long runs);
    the global backend is never switched.
    """
    ext = os.path.splitext(os.fspath(path))[1].lower().lstrip(".")
    fmt = ext if ext in fig.canvas.get_supported_filetypes() else "png"
    try:
        with atomic_path(path, make_folder=make_folder) as tmp:
            fig.savefig(tmp, dpi=dpi, format=fmt, **({"bbox_inches": "tight"} if tight else {}))
    finally:
        pyplot = sys.modules.get("matplotlib.pyplot")
        if pyplot is not None:
            pyplot.close(fig)  # a no-op for figures pyplot does not manage


# ------------------------------------------------------------------------------------------ output sets
def same_file(a, b) -> bool:
    """Whether paths ``a`` and ``b`` name one file: the same path once symlinks are resolved, or (both existing)
    the same inode (a hard link, a bind mount)."""
    a, b = os.fspath(a), os.fspath(b)
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return False



class OutputSet:
    """Every output of one command, staged and then moved into place together, only when all has succeeded.

    Each destination folder gets one hidden staging folder (``.heliotwin-XXXX``); :meth:`file` returns a path
    there with the destination's own name, so writers that derive further files from it (plots next to a
    report) stage those too. :meth:`commit` moves everything into place with Ctrl-C and SIGTERM held back;
    :meth:`discard` (any failure) removes the staging folders and leaves existing files untouched.

    The rules, checked when an output is declared (before any work is done):

    * its folder must exist (nothing creates folders, except :meth:`folder` for an output that *is* a folder);
    * it may not be an existing folder (for :meth:`file`), the same file as another output, an input file,
      or an existing file inside an input folder (a report written over a PAINT file).

    Parameters
    ----------
    inputs : iterable of (str, path)
        ``(flag, path)`` of every input the command reads (files or folders); ``None`` paths are ignored.
    """

    def __init__(self, inputs=()):
        self.inputs = [(flag, os.fspath(p)) for flag, p in inputs if p is not None]
        self._staging: dict[str, str] = {}  # destination folder -> staging folder
        self._declared: list[tuple[str, str]] = []  # (flag, destination)

    def _check(self, path: str, flag: str, *, is_folder: bool) -> str:
        folder = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(folder):
            raise InputFileError(path, f"output folder {folder} does not exist (create it first)", field=flag)
        if not is_folder and os.path.isdir(path):
            raise InputFileError(path, "is a folder; expected a file name", field=flag)
        if is_folder and os.path.exists(path) and not os.path.isdir(path):
            raise InputFileError(path, "is a file; expected a folder", field=flag)
        for other_flag, other in self._declared:
            if same_file(path, other):
                raise InputFileError(path, f"is also the output of {other_flag}; give each output its own name",
                                     field=flag)
        for in_flag, src in self.inputs:
            if same_file(path, src):
                raise InputFileError(path, f"is the input {in_flag}; an output may not replace an input", field=flag)
            inside = os.path.realpath(path).startswith(os.path.realpath(src) + os.sep)
            if os.path.isdir(src) and inside and os.path.exists(path):
                raise InputFileError(path, f"would replace a file of the input folder {in_flag} {src}", field=flag)
        self._declared.append((flag, path))
        return folder

    def _stage(self, folder: str) -> str:
        if folder not in self._staging:
            try:
                _sweep_once(folder)
                self._staging[folder] = tempfile.mkdtemp(prefix=f".heliotwin-{os.getpid()}-", dir=folder)
            except OSError as exc:
                raise InputFileError(folder, f"cannot write ({_one_line(exc.strerror or exc)})") from exc
        return self._staging[folder]

    def plant(self, path, flag: str) -> str | None:
        """Declare a plant file that its own writer replaces (locked and atomic: :func:`heliotwin.workflows.update.
        locked_plant_write`), so it is not staged; checked like every output, before the lock is taken or any work
        is done. Returns ``path``."""
        if path is None:
            return None
        path = os.fspath(path)
        self._check(path, flag, is_folder=False)
        return path

    def file(self, path, flag: str):
        """Declare output file ``path`` (given by ``flag``); return where to write it now (same name)."""
        if path is None:
            return None
        path = os.fspath(path)
        folder = self._check(path, flag, is_folder=False)
        return os.path.join(self._stage(folder), os.path.basename(path))

    def folder(self, path, flag: str) -> str:
        """Declare an output folder (created when missing; existing files in it are replaced one by one)."""
        path = os.fspath(path).rstrip(os.sep) or os.sep
        parent = self._check(path, flag, is_folder=True)
        # basename of the absolute path: "." or "sub/.." name a real folder, not a staging entry "."
        staged = os.path.join(self._stage(parent), os.path.basename(os.path.abspath(path)))
        os.mkdir(staged)
        return staged

    def commit(self) -> None:
        """Move every staged file into place (signals held back meanwhile), then remove the staging folders."""
        with _signals_held():
            for folder, staging in self._staging.items():
                for name in sorted(os.listdir(staging)):
                    _move(os.path.join(staging, name), os.path.join(folder, name))
            self.discard()

    def unstage_message(self, exc: BaseException) -> None:
        """Make a :class:`~heliotwin.errors.HeliotwinError` raised while writing a staged output (disk full, say)
        name the destination the user gave, not the staging folder that is about to be removed (in place)."""
        if not isinstance(exc, HeliotwinError) or not exc.args or not isinstance(exc.args[0], str):
            return
        text = exc.args[0]
        for folder, staging in self._staging.items():
            text = text.replace(staging + os.sep, folder.rstrip(os.sep) + os.sep)
            if isinstance(getattr(exc, "path", None), str) and exc.path.startswith(staging + os.sep):
                exc.path = os.path.join(folder, os.path.relpath(exc.path, staging))
        exc.args = (text, *exc.args[1:])

    def discard(self) -> None:
        """Remove the staging folders (and whatever a failed run had written there)."""
        for staging in self._staging.values():
            shutil.rmtree(staging, ignore_errors=True)
        self._staging.clear()


def _move(src: str, dest: str) -> None:
    """Rename ``src`` onto ``dest``; a folder onto an existing folder merges file by file."""
    if os.path.isdir(src):
        if os.path.isdir(dest):
            for name in sorted(os.listdir(src)):
                _move(os.path.join(src, name), os.path.join(dest, name))
            return
        os.chmod(src, 0o777 & ~_umask())
    else:
        os.chmod(src, _file_mode(dest))
    try:
        os.replace(src, dest)
    except OSError as exc:
        raise _cannot_write(dest, exc, src) from exc


@contextmanager
def _signals_held():
    """Block SIGINT and SIGTERM (delivered afterwards) so that the renames of a commit are not cut short."""
    blockable = hasattr(signal, "pthread_sigmask") and threading.current_thread() is threading.main_thread()
    sigs = {signal.SIGINT, signal.SIGTERM}
    old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs) if blockable else None
    try:
        yield
    finally:
        if blockable:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def plant_inputs(plant, output, *others, flag: str = "--scenario") -> list:
    """The inputs of a command that reads plant file ``plant`` and writes the plant to ``output``: ``others``
    (``(flag, path)``) and ``plant`` itself unless ``output`` is the same file (the plant updated in place: its
    own writer replaces it atomically under the lock)."""
    same = plant is not None and output is not None and same_file(output, plant)
    return [*others] + ([] if same or plant is None else [(flag, plant)])


@contextmanager
def output_set(inputs=()):
    """An :class:`OutputSet` committed when the block succeeds and discarded on any exception (Ctrl-C too)::

        with output_set([("--paint", args.paint)]) as out:
            json_path = out.file(args.json, "--json")   # checks now, before the work
            ...                                          # compute; write to json_path
        # here every output is in place, or none is
    """
    outputs = OutputSet(inputs)
    try:
        yield outputs
    except BaseException as exc:
        outputs.unstage_message(exc)
        outputs.discard()
        raise
    outputs.commit()
