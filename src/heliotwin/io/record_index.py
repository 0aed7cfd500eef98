"""The incremental record index of a PAINT folder: what each calibration file and metadata CSV held when it
was last parsed, so that reading a folder that gained one day of records parses that day only.

A plant's folder grows every day; parsing its 180,000 record files again every morning is what made a one-day
update take minutes. The index keeps, per record file, the fields the reader parses (record id, motor steps,
target, the focal spots as lat-first WGS84, sun angles, the heliostat the file names), keyed by ``(heliostat,
file name, size, modification time [ns], status-change time [ns], inode)``. A file whose key changed (rewritten,
touched, replaced) or that is gone simply has no valid entry: it invalidates itself and nothing else. The
status-change time cannot be set by a user: a rewrite whose size and modification time are restored
(``touch -d``, ``cp -p``, ``rsync -a``, a backup restore) still changes it, and a replaced file has a new inode.
Geodesy (WGS84 -> ENU), the tower's targets, times, weather and images are applied when the records are
assembled (:mod:`heliotwin.io.paint`), so the entries do not depend on them.

Layout, under :func:`index_dir` (``$HELIOTWIN_CACHE_DIR``, default ``~/.cache/heliotwin/paint-records``)::

    <sha of the folder's absolute path>/
        seg-<time ns>-<pid>-<random>.npz     immutable segments of entries, appended by each read that parsed
        csv-<name>.npz                       one metadata CSV: its size, the digest of its bytes, parsed rows

Safety: a segment is written to a temporary file and renamed into place (:func:`os.replace`), so a killed
reader leaves at most a temporary file (ignored, removed once stale) and a concurrent reader sees whole
segments or none. Two readers that parse the same new files both append them: duplicate entries are
harmless (they are equal) and are merged when the segments are compacted (more than
:data:`MAX_SEGMENTS`). A segment that vanishes under a reader (another one compacted) only costs a re-parse.
A file modified within :data:`RACY_NS` of being indexed is not indexed (its modification time could repeat
with other contents, as git's "racily clean" entries), so it is parsed again next time. A metadata CSV that
grew by appended rows is parsed from where the stored part ends (its stored bytes must be unchanged,
checked by digest); any other change re-parses it whole. Nothing here is ever trusted over the files: an
index that cannot be read or written is ignored, and so is a segment whose columns do not have the dtypes,
shapes and finite values a reader writes (:func:`valid_segment`): such a segment is as if absent.
"""
from __future__ import annotations

import glob
import hashlib
import os
import secrets
import stat
import tempfile
import time
import zipfile

import numpy as np

__all__ = ["INDEX_VERSION", "MAX_SEGMENTS", "RACY_NS", "ENTRY_COLUMNS", "index_dir", "empty_entries",
           "concat_entries", "valid_segment", "read_entries", "append_entries", "compact", "match", "csv_cached",
           "store_csv"]

#: Layout version of the index files; files of another version are never read.
INDEX_VERSION = 3
#: Segments beyond which a read merges them into one (dropping entries of changed or removed files).
MAX_SEGMENTS = 8
#: A file modified less than this long [ns] before it is indexed is left out of the index (parsed next time).
RACY_NS = 2_000_000_000
#: Temporary files older than this [s] are leftovers of a killed reader and are removed at compaction.
STALE_TEMPORARY_S = 3600.0

#: The columns of the entries (numpy arrays over E entries): the key, then what the record file holds.
ENTRY_COLUMNS = ("heliostat", "name", "size", "mtime_ns", "ctime_ns", "inode", "record_id", "motor_steps", "target",
                 "lla", "sun_azimuth", "sun_elevation", "claim")
_INDEX_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile)


def index_dir(root) -> str:
    """The index folder of the PAINT folder ``root``: under ``$HELIOTWIN_CACHE_DIR`` (default
    ``$XDG_CACHE_HOME/heliotwin/paint-records``, ``~/.cache/...``), one folder per absolute folder path."""
    base = os.environ.get("HELIOTWIN_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "heliotwin",
        "paint-records")
    name = hashlib.sha256(os.path.abspath(str(root)).encode()).hexdigest()[:32]
    return os.path.join(base, name)


def empty_entries() -> dict:
    """No entries (every column with its dtype and trailing shape)."""
    return {"heliostat": np.zeros(0, dtype="U1"), "name": np.zeros(0, dtype="S1"),
            "size": np.zeros(0, dtype=np.int64), "mtime_ns": np.zeros(0, dtype=np.int64),
            "ctime_ns": np.zeros(0, dtype=np.int64), "inode": np.zeros(0, dtype=np.int64),
            "record_id": np.zeros(0, dtype=np.int64), "motor_steps": np.zeros((0, 2)),
            "target": np.zeros(0, dtype="U1"), "lla": np.zeros((0, 2, 3)),
            "sun_azimuth": np.zeros(0), "sun_elevation": np.zeros(0), "claim": np.zeros(0, dtype="U1")}


def concat_entries(parts: list) -> dict:
    """Entries of several parts, in order."""
    parts = [p for p in parts if len(p["record_id"])]
    if not parts:
        return empty_entries()
    return {k: np.concatenate([p[k] for p in parts]) for k in ENTRY_COLUMNS}


def _take(entries: dict, rows) -> dict:
    return {k: v[rows] for k, v in entries.items()}


def _segments(folder: str) -> list:
    return sorted(glob.glob(os.path.join(folder, "seg-*.npz")))


#: Per column: the dtype kind a reader writes (``i`` signed integer, ``f`` float, ``U`` text, ``S`` bytes) and
#: the trailing shape of one entry.
_COLUMN_SPEC = {"heliostat": ("U", ()), "name": ("S", ()), "size": ("i", ()), "mtime_ns": ("i", ()),
                "ctime_ns": ("i", ()), "inode": ("i", ()), "record_id": ("i", ()), "motor_steps": ("f", (2,)),
                "target": ("U", ()), "lla": ("f", (2, 3)), "sun_azimuth": ("f", ()), "sun_elevation": ("f", ()),
                "claim": ("U", ())}
#: Columns whose every value must be finite (``lla`` is NaN where a source is absent: checked per source).
_FINITE = ("motor_steps", "sun_azimuth", "sun_elevation")


def valid_segment(part: dict) -> bool:
    """Whether ``part`` (a segment's columns) is what a reader writes: every column of :data:`ENTRY_COLUMNS` with
    its dtype kind and trailing shape, one length, finite numbers (a focal spot NaN in all three coordinates or
    none), record ids and sizes >= 0. A segment that is not is ignored: trusted, record ids stored as text
    would make every record one "without a time", NaN steps would pass into the table."""
    try:
        n = len(part["record_id"])
        for k, (kind, tail) in _COLUMN_SPEC.items():
            v = part[k]
            if v.dtype.kind != kind or v.shape != (n, *tail):
                return False
        if not all(bool(np.isfinite(part[k]).all()) for k in _FINITE):
            return False
        lla = np.isnan(part["lla"])
        if bool((lla.any(-1) != lla.all(-1)).any()) or bool(np.isinf(part["lla"]).any()):
            return False
        return bool((part["record_id"] >= 0).all() and (part["size"] >= 0).all())
    except (KeyError, TypeError, ValueError, AttributeError):
        return False


def read_entries(root) -> tuple[dict, list]:
    """Every entry of ``root``'s index, oldest segment first (a later entry of a key supersedes an earlier
    one), and the segment files read. Unreadable, foreign or invalid (:func:`valid_segment`) segments are
    skipped."""
    folder = index_dir(root)
    parts, read = [], []
    for path in _segments(folder):
        try:
            with np.load(path, allow_pickle=False) as z:
                if int(z["version"]) != INDEX_VERSION:
                    continue
                part = {k: z[k] for k in ENTRY_COLUMNS}
        except _INDEX_ERRORS:
            continue
        if not valid_segment(part):
            continue
        parts.append(part)
        read.append(path)
    return concat_entries(parts), read


def _write_npz(folder: str, final: str, arrays: dict) -> bool:
    """Write ``arrays`` to ``folder/final`` atomically; False (nothing left behind) when it cannot."""
    tmp = None
    try:
        os.makedirs(folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".npz", dir=folder)
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, os.path.join(folder, final))
        return True
    except OSError:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass
        return False


def append_entries(root, entries: dict, *, now_ns: int | None = None) -> int:
    """Append ``entries`` as one new segment (those of files modified within :data:`RACY_NS` of ``now_ns``
    left out); returns how many were stored (0 when none or the index cannot be written)."""
    now_ns = time.time_ns() if now_ns is None else now_ns
    settled = entries["mtime_ns"] < now_ns - RACY_NS
    if not bool(settled.any()):
        return 0
    keep = _take(entries, settled)
    name = f"seg-{time.time_ns():020d}-{os.getpid()}-{secrets.token_hex(4)}.npz"
    ok = _write_npz(index_dir(root), name, {"version": np.array(INDEX_VERSION), **keep})
    return int(settled.sum()) if ok else 0


def compact(root, entries: dict, valid, read: list) -> None:
    """Replace the segments ``read`` by one holding ``entries[valid]`` (duplicates of a key merged, the latest
    kept) when there are more than :data:`MAX_SEGMENTS`; remove stale temporary files. Segments written by
    others meanwhile are kept."""
    folder = index_dir(root)
    if len(read) <= MAX_SEGMENTS:
        return
    keep = _take(entries, np.asarray(valid, dtype=bool))
    # latest entry per (heliostat, name): reversed unique keeps the last occurrence
    key = np.char.add(np.char.add(keep["heliostat"].astype("U"), "/"), keep["name"].astype("U"))
    _, last = np.unique(key[::-1], return_index=True)
    rows = np.sort(len(key) - 1 - last)
    name = f"seg-{time.time_ns():020d}-{os.getpid()}-{secrets.token_hex(4)}.npz"
    if not _write_npz(folder, name, {"version": np.array(INDEX_VERSION), **_take(keep, rows)}):
        return
    for path in read:
        try:
            os.unlink(path)
        except OSError:
            pass
    cutoff = time.time() - STALE_TEMPORARY_S
    for path in glob.glob(os.path.join(folder, ".tmp-*")):
        try:
            if os.stat(path).st_mtime < cutoff:
                os.unlink(path)
        except OSError:
            pass


def match(entries: dict, heliostat, name, size, mtime_ns, ctime_ns=None, inode=None) -> np.ndarray:
    """For each listed file the row of its valid entry in ``entries``, or -1 (none, or the file changed since it
    was indexed). A later entry of the same file wins.

    Parameters
    ----------
    entries : dict
        Index entries (:data:`ENTRY_COLUMNS`, arrays over E entries).
    heliostat, name : sequence, [F]
        Each listed file's heliostat id and file name (bytes).
    size, mtime_ns : np.ndarray of int, [F]
        Its size and modification time as the file system counts them [1] (bytes, nanoseconds).
    ctime_ns, inode : np.ndarray of int, [F], optional
        Its status-change time [ns] and inode number [1]; None: not compared (callers that have no stat).

    Returns
    -------
    np.ndarray, [F]
        Row into ``entries`` or -1 [1].
    """
    n = len(heliostat)
    if not len(entries["record_id"]) or not n:
        return np.full(n, -1, dtype=np.int64)
    at = dict(zip(zip(entries["heliostat"].tolist(), entries["name"].tolist()), range(len(entries["record_id"]))))
    rows = np.fromiter((at.get(k, -1) for k in zip(list(heliostat), list(name))), dtype=np.int64, count=n)
    found = rows >= 0
    same = np.zeros(n, dtype=bool)
    r = rows[found]
    same[found] = ((entries["size"][r] == np.asarray(size)[found])
                   & (entries["mtime_ns"][r] == np.asarray(mtime_ns)[found]))
    for key, now in (("ctime_ns", ctime_ns), ("inode", inode)):
        if now is not None:
            same[found] &= entries[key][r] == np.asarray(now, dtype=np.int64)[found]
    return np.where(same, rows, -1)


# --------------------------------------------------------------------------------------- metadata CSVs
def _digest(path: str, size: int) -> str | None:
    """SHA-256 of the first ``size`` bytes of the regular file ``path`` (None when it is not one, is shorter or
    cannot be read; opened non-blocking, so a FIFO in its place cannot stall the caller)."""
    h = hashlib.sha256()
    left = size
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
    except OSError:
        return None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 20))
            if not chunk:
                return None
            h.update(chunk)
            left -= len(chunk)
    except OSError:
        return None
    finally:
        os.close(fd)
    return h.hexdigest()


def _valid_csv(stored: dict) -> bool:
    """Whether a stored CSV parse has the columns, dtypes and lengths a reader writes."""
    try:
        m = len(stored["ids"])
        ok = (stored["ids"].dtype.kind == "i" and stored["values"].dtype.kind == "f"
              and stored["values"].shape[:1] == (m,) and stored["text"].shape == (m,)
              and stored["text"].dtype.kind == "U" and stored["text_none"].shape == (m,)
              and stored["text_none"].dtype.kind == "b" and stored["heliostat"].shape == (m,)
              and stored["heliostat"].dtype.kind == "U" and stored["size"].dtype.kind == "i"
              and stored["lines"].dtype.kind == "i" and stored["header"].dtype.kind == "U")
        # NaN is a value: a record without a time or a weather reading; infinities are not written
        return bool(ok and int(stored["size"]) >= 0 and not np.isinf(stored["values"]).any())
    except (KeyError, TypeError, ValueError, AttributeError):
        return False


def csv_cached(root, path: str) -> tuple[dict | None, int]:
    """The stored parse of the CSV ``path`` of ``root``'s folder and how many of its bytes it covers: the
    whole file (its size and bytes unchanged), a prefix (rows were appended since: parse from that byte on),
    or ``(None, 0)`` (nothing usable: parse the whole file)."""
    store = os.path.join(index_dir(root), f"csv-{os.path.basename(path)}.npz")
    try:
        with np.load(store, allow_pickle=False) as z:
            if int(z["version"]) != INDEX_VERSION:
                return None, 0
            stored = {k: z[k] for k in z.files}
        size = os.stat(path).st_size
    except _INDEX_ERRORS:
        return None, 0
    if not _valid_csv(stored):
        return None, 0
    covered = int(stored["size"])
    if size < covered or _digest(path, covered) != str(stored["digest"]):
        return None, 0
    return stored, covered


def store_csv(root, path: str, size: int, arrays: dict) -> None:
    """Store the parse (``arrays``: ``ids`` [M], ``lines`` and the parsed columns [M, ...]) of the first ``size``
    bytes [1] of the CSV ``path``; those bytes must end with a line break (a partly written last line is not
    stored)."""
    digest = _digest(path, size)
    if digest is None:
        return
    _write_npz(index_dir(root), f"csv-{os.path.basename(path)}.npz",
               {"version": np.array(INDEX_VERSION), "size": np.array(size), "digest": np.array(digest), **arrays})
