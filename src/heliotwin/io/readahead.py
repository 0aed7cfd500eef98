"""Read-ahead of many small files: the kernel is asked for them before the parser needs them.

A PAINT folder holds one small JSON file per calibration record (190,000 for a 2,000-heliostat plant over three
years). Read one after the other from a disk that does not hold them in its page cache, each costs a round trip to
the storage: at 2,000 heliostats 28 s against 9 s from the page cache, about a third of ``calibrate``. Reading
ahead on threads of the parsing process does not help: the threads wait for the interpreter lock behind the
parser (tried: 9 s became 24 s from the page cache). So a separate small process (no heliotwin, no torch; about
30 ms to start) walks the list in reading order and calls ``posix_fadvise(POSIX_FADV_WILLNEED)`` on every file:
the kernel queues the reads at once, many in flight, and the parser then finds most files in the page cache.
A hint only: the parser reads every file itself, so a file that changes or goes meanwhile is read as it is then,
and nothing changes where the call does not exist (not Linux) or the helper cannot start.

The paths reach the helper on its standard input (a pipe, written by a daemon thread so that a helper that does
not read can never block the caller): there is no list file, so a full or unwritable ``$TMPDIR`` changes nothing
and a killed command leaves nothing behind. The helper opens each path with ``O_NONBLOCK`` (a FIFO in the folder
does not stall it) and only advises regular files. Any error in setting it up means it does not run: it never
fails a command.
"""
from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading

__all__ = ["read_ahead", "READ_AHEAD_MIN_FILES"]

#: Fewer files than this are read without a helper (its start-up would cost more than it saves).
READ_AHEAD_MIN_FILES = 2000

# The helper's whole program: paths NUL-separated on stdin, in reading order.
_HELPER = """
import os, stat, sys
paths = sys.stdin.buffer.read().split(b"\\0")
for p in paths:
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    except OSError:
        continue
    try:
        if stat.S_ISREG(os.fstat(fd).st_mode):
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_WILLNEED)
    except OSError:
        pass
    finally:
        os.close(fd)
"""


def _feed(child: subprocess.Popen, data: bytes) -> None:
    """Write ``data`` to the helper's stdin and close it (in a daemon thread: a dead helper only ends it)."""
    try:
        child.stdin.write(data)
    except (OSError, ValueError):  # the helper died or was stopped: it was a hint
        pass
    finally:
        with contextlib.suppress(OSError, ValueError):
            child.stdin.close()


def _start(paths: list[str]) -> subprocess.Popen | None:
    """The helper, fed ``paths`` on its stdin; None when it cannot be set up (any OSError, a path that is not
    encodable)."""
    try:
        data = b"\0".join(os.fsencode(p) for p in paths)
        child = subprocess.Popen([sys.executable, "-I", "-S", "-c", _HELPER], stdin=subprocess.PIPE,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except (OSError, ValueError, UnicodeError):
        return None
    try:
        threading.Thread(target=_feed, args=(child, data), name="heliotwin-read-ahead", daemon=True).start()
    except RuntimeError:  # no thread can start: stop the helper, read without it
        _stop(child)
        return None
    return child


def _stop(child: subprocess.Popen) -> None:
    with contextlib.suppress(OSError):
        if child.poll() is None:
            child.kill()
        child.wait()
    with contextlib.suppress(OSError, ValueError):
        child.stdin.close()


@contextlib.contextmanager
def read_ahead(paths: list[str], *, min_files: int = READ_AHEAD_MIN_FILES):
    """Within the block, a helper process asks the kernel to read ``paths`` (in this order) ahead of the caller.

    Yields whether a helper runs. It is stopped when the block ends (it has usually finished long before).
    Nothing happens for fewer than ``min_files`` paths, without ``os.posix_fadvise`` or an interpreter to start
    (an embedded Python), when ``HELIOTWIN_READ_AHEAD=0``, or when the helper cannot be set up (the block then
    simply runs without it; no error of the helper ever reaches the caller).
    """
    if (len(paths) < min_files or not hasattr(os, "posix_fadvise") or not sys.executable
            or os.environ.get("HELIOTWIN_READ_AHEAD", "1") == "0"):
        yield False
        return
    child = _start(paths)
    try:
        yield child is not None
    finally:
        if child is not None:
            _stop(child)
