"""Opening HDF5 files for reading with heliotwin's one-line errors (shared by the file formats)."""
from __future__ import annotations

import os

import h5py

from ..errors import InputFileError


def open_for_reading(path):
    """Open an HDF5 file read-only.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    h5py.File
        Use it as a context manager.

    Raises
    ------
    InputFileError
        ``file not found`` (also for a folder) or ``not an HDF5 file (...)``, naming the file.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputFileError(path, "file not found")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise InputFileError(path, f"not an HDF5 file ({exc})") from None
