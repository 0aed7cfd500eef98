"""One writer per plant file: an advisory lock beside it and a stamp that tells whether it changed.

Two scheduled ``update --in-place`` runs on one plant must not both read the plant, update it and write it
back: the second write would lose the first update. A command that replaces a plant file holds
:func:`plant_lock` on it for the whole read-update-write::

    with plant_lock(path):                 # a second command refuses at once: "another heliotwin ..."
        stamp = file_stamp(path)
        scenario = load_scenario(path)
        ...                                # compute
        check_unchanged(path, stamp)       # refuses when someone replaced the file meanwhile
        write_scenario(new, path)

The lock is ``fcntl.flock`` on a sidecar file ``<path>.lock`` (never on the plant file itself, which the
atomic writer replaces by rename, so a lock on it would stay on the old inode). The kernel drops the lock when
the process ends, killed or not, so a stale ``.lock`` file left behind is harmless and is not removed (removing
it would let two processes hold locks on two different inodes). Locks are advisory: they order heliotwin
commands, not other programs. :func:`file_stamp` / :func:`check_unchanged` cover writers that do not take the
lock (another tool, a copy of the plant file put in place by hand) and file systems without ``flock``.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import stat
import time
from dataclasses import dataclass

from ..errors import HeliotwinError, InputFileError

#: Suffix of the sidecar lock file of a plant file.
LOCK_SUFFIX = ".lock"
#: Seconds between two attempts while waiting for a lock (``plant_lock(timeout=...)``).
POLL_S = 0.05


def lock_path(path) -> str:
    """The sidecar lock file of ``path``: ``<path>.lock`` in the same folder (:func:`plant_lock` takes the one of
    the resolved path, ``os.path.realpath``, so that a symlink and its target share one lock)."""
    return os.fspath(path) + LOCK_SUFFIX


@contextlib.contextmanager
def plant_lock(path, *, timeout: float | None = None):
    """Hold the exclusive lock of plant file ``path`` for the ``with`` block.

    Parameters
    ----------
    path : str or Path
        The plant (scenario) file; it need not exist yet. The lock file ``<path>.lock`` is created beside it
        (mode 0o666 minus the umask) and left there.
    timeout : float, optional
        Seconds [s] to wait for a lock another process holds; None or 0 (default): do not wait.

    Yields
    ------
    str
        The lock file's path.

    Raises
    ------
    HeliotwinError
        ``another heliotwin command is updating <path>`` when the lock is held elsewhere (after ``timeout``).
    InputFileError
        The lock file cannot be created or locked (missing folder, permissions; names the lock file).
    """
    if timeout is not None and not (isinstance(timeout, (int, float)) and timeout >= 0 and timeout < float("inf")):
        raise HeliotwinError(f"lock timeout must be a finite number of seconds >= 0, got {timeout!r}")
    target = os.fspath(path)
    # One plant, one lock: a symlink to the plant and the plant itself are the same file (the lock lives beside
    # the file that is replaced, the link's target).
    lock = lock_path(os.path.realpath(target))
    try:
        # O_NOFOLLOW: a lock path that is a symlink (dangling or not) would make us create or lock its target
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOFOLLOW", 0)
                     | getattr(os, "O_NONBLOCK", 0), 0o666)
    except OSError as exc:
        if exc.errno == errno.ELOOP or os.path.islink(lock):
            raise InputFileError(lock, f"the lock file of {target} is a symbolic link; not followed (remove it: "
                                       f"a lock file is a plain file heliotwin creates)") from None
        raise InputFileError(lock, f"cannot create the lock file of {target} ({exc.strerror})") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise InputFileError(lock, f"the lock file of {target} is not a regular file (remove it: a lock file is "
                                       f"a plain file heliotwin creates)")
        _acquire(fd, target, lock, timeout or 0.0)
        try:
            yield lock
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


def _acquire(fd: int, target: str, lock: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise InputFileError(lock, f"cannot lock ({exc.strerror})") from None
        left = deadline - time.monotonic()
        if left <= 0:
            waited = f" (waited {timeout:g} s)" if timeout > 0 else ""
            raise HeliotwinError(f"another heliotwin command is updating {target}{waited}; try again when it has "
                                 f"finished")
        time.sleep(min(POLL_S, left))


@dataclass(frozen=True)
class FileStamp:
    """What identifies one version of a file: size [bytes], modification time [ns] and inode (an atomic
    replace gives a new inode even when size and time match). ``exists`` is False for a missing file."""

    exists: bool
    size: int = -1
    mtime_ns: int = -1
    inode: int = -1
    device: int = -1


def file_stamp(path) -> FileStamp:
    """The :class:`FileStamp` of ``path`` now (``exists=False`` when there is no such file).

    Raises
    ------
    InputFileError
        ``path`` exists but cannot be examined (permissions).
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return FileStamp(False)
    except OSError as exc:
        raise InputFileError(path, f"cannot examine ({exc.strerror})") from None
    return FileStamp(True, int(st.st_size), int(st.st_mtime_ns), int(st.st_ino), int(st.st_dev))


def check_unchanged(path, stamp: FileStamp) -> None:
    """Refuse to replace ``path`` when it is not the version ``stamp`` (:func:`file_stamp`) recorded.

    Raises
    ------
    InputFileError
        One line naming ``path``: it was replaced, changed, created or removed since it was read.
    """
    now = file_stamp(path)
    if now == stamp:
        return
    if not stamp.exists:
        what = "was created"
    elif not now.exists:
        what = "was removed"
    elif (now.inode, now.device) != (stamp.inode, stamp.device):
        what = "was replaced"
    else:
        what = "was modified"
    raise InputFileError(path, f"{what} by another process since this command read it; not overwritten (run the "
                               f"command again on the current file)")
