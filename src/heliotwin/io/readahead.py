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
"""
from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import tempfile

__all__ = ["read_ahead", "READ_AHEAD_MIN_FILES"]

#: Fewer files than this are read without a helper (its start-up would cost more than it saves).
READ_AHEAD_MIN_FILES = 2000

# The helper's whole program: paths NUL-separated in the file named by argv[1], in reading order.
_HELPER = """
import os, sys
with open(sys.argv[1], "rb") as fh:
    paths = fh.read().split(b"\\0")
for p in paths:
    try:
        fd = os.open(p, os.O_RDONLY)
    except OSError:
        continue
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_WILLNEED)
    except OSError:
        pass
    finally:
        os.close(fd)
"""


@contextlib.contextmanager
def read_ahead(paths: list[str], *, min_files: int = READ_AHEAD_MIN_FILES):
    """Within the block, a helper process asks the kernel to read ``paths`` (in this order) ahead of the caller.

    Yields whether a helper runs. It is stopped when the block ends (it has usually finished long before); its
    list file is removed. Nothing happens for fewer than ``min_files`` paths, without ``os.posix_fadvise`` or an
    interpreter to start (an embedded Python), or when ``HELIOTWIN_READ_AHEAD=0``.
    """
    if (len(paths) < min_files or not hasattr(os, "posix_fadvise") or not sys.executable
            or os.environ.get("HELIOTWIN_READ_AHEAD", "1") == "0"):
        yield False
        return
    fd, listing = tempfile.mkstemp(prefix="heliotwin-read-ahead-", suffix=".txt")
    child = None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(b"\0".join(os.fsencode(p) for p in paths))
        try:
            child = subprocess.Popen([sys.executable, "-I", "-S", "-c", _HELPER, listing], stdin=subprocess.DEVNULL,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        except OSError:
            child = None
        yield child is not None
    finally:
        if child is not None:
            if child.poll() is None:
                child.kill()
            child.wait()
        with contextlib.suppress(OSError):
            os.remove(listing)
