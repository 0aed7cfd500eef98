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
import sys
import tempfile
from contextlib import contextmanager

from ..errors import InputFileError

__all__ = ["atomic_path", "write_json", "save_figure", "json_safe"]

#: Permissions of a new output file. ``mkstemp`` creates 0600 files; a report should be as readable as one
#: written by ``open()``. An existing destination keeps its own permissions (as ``io.scenario`` does).
_NEW_FILE_MODE = 0o644


def _one_line(text) -> str:
    return " ".join(str(text).split())


def _file_mode(path: str) -> int:
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        return _NEW_FILE_MODE


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
            fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.splitext(path)[1], dir=folder)
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
    """A strict-JSON copy of ``obj``: tensors/arrays to lists, numpy scalars to Python, NaN/inf to ``None``,
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
