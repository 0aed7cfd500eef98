"""One exception family for heliotwin.

Every error a user can cause (bad file, bad field, out-of-range input) is a :class:`HeliotwinError`,
a ``ValueError`` subclass, whose message is one line naming the file and the field when there is one.
The CLI prints that line and exits non-zero.
"""
from __future__ import annotations


class HeliotwinError(ValueError):
    """Base class of every user-facing heliotwin error."""


class InputFileError(HeliotwinError):
    """A file is missing, unreadable, malformed, or has a bad field.

    Parameters
    ----------
    path : str
        The file concerned.
    message : str
        What is wrong.
    field : str, optional
        The field (JSON key path, HDF5 dataset, CSV column) concerned.
    """

    def __init__(self, path, message: str, field: str | None = None):
        self.path = str(path)
        self.field = field
        where = f"{self.path}" + (f" [{field}]" if field else "")
        super().__init__(f"{where}: {message}")


class OutOfRangeError(HeliotwinError):
    """A physical input is outside its valid range (motor steps, sun below horizon, ...)."""


class ScenarioVersionError(InputFileError):
    """A scenario file is of another or older format version."""
