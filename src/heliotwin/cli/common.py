"""What every command shares: error reporting (:func:`run_command`), argument types, output checks.

Imports nothing heavy: building the parser (``heliotwin --help``) must not pay for torch.
"""
from __future__ import annotations

import argparse
import os
import sys

from ..errors import HeliotwinError

__all__ = ["run_command", "csv_list", "int_list", "positive_int", "check_output_folder"]


def _is_user_key_error(exc: KeyError) -> bool:
    """A ``KeyError`` the library raised for a name the user gave (``"unknown heliostat 'ZZ99'; ..."``).

    The plant containers and the PAINT reader raise ``KeyError`` with a sentence; a bare
    ``KeyError('median_test_mrad')`` from a dict lookup is a bug and must show its traceback.
    """
    return len(exc.args) == 1 and isinstance(exc.args[0], str) and " " in exc.args[0].strip()


def run_command(args, prefix: str = "heliotwin: ") -> int:
    """Run a parsed command (``args.func(args)``) and return its exit status.

    Errors a user can cause -- :class:`~heliotwin.errors.HeliotwinError`, unknown names (``KeyError`` with
    a message), unsupported combinations (``NotImplementedError``) and files that cannot be read or
    written (``OSError``) -- become one line ``<prefix>error: ...`` on stderr and exit status 2. Anything
    else is a bug and propagates with its traceback.
    """
    try:
        return int(args.func(args) or 0)
    except KeyError as exc:
        if not _is_user_key_error(exc):
            raise
        # str(KeyError) adds quotes around the message: print the message itself.
        return _report(prefix, exc.args[0])
    except (HeliotwinError, NotImplementedError, OSError) as exc:
        return _report(prefix, str(exc) or type(exc).__name__)
    except KeyboardInterrupt:
        print(f"{prefix}interrupted", file=sys.stderr)
        return 130


def _report(prefix: str, message: str) -> int:
    lines = [ln for ln in message.splitlines() if ln.strip()]
    print(f"{prefix}error: {lines[0] if lines else message}", file=sys.stderr)
    return 2


# ------------------------------------------------------------------------------------------ argument types
def csv_list(text: str | None) -> list[str] | None:
    """``"AA39, AB38"`` -> ``["AA39", "AB38"]``; empty or missing -> ``None`` (meaning: all)."""
    return [t.strip() for t in text.split(",") if t.strip()] if text else None


def int_list(text: str) -> list[int]:
    """argparse type: comma-separated integers (at least one)."""
    try:
        values = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        values = []
    if not values:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}")
    return values


def positive_int(text: str) -> int:
    """argparse type: an integer > 0."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def check_output_folder(path, flag: str) -> None:
    """Fail before a long run, not after it, when the folder of an output file does not exist."""
    if path is None:
        return
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    if not os.path.isdir(folder):
        raise HeliotwinError(f"{flag}: output folder {folder} does not exist")
