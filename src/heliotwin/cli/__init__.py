"""The ``heliotwin`` command line. Only argument parsing, reporting and plots live here; every command is a
thin shell over library calls a notebook can make too.

Layout: :mod:`.common` (error reporting, argument types), then one module per command group, each with a
``register(subparsers)``:

* :mod:`.plant` -- ``demo``, ``scenario from-paint``, ``trace``, ``validate``, ``bench``
* :mod:`.calibrate` -- ``calibrate``, ``split``, ``aim``
* :mod:`.surfaces` -- ``reconstruct``, ``predict``

The groups are ordinary imports: a command whose module fails to import breaks ``heliotwin`` loudly instead
of disappearing from it. Library modules never import this package. Building the parser imports no torch
(commands import the library when they run), so ``heliotwin --help`` is instant.

Every command has ``--help``. Errors a user can cause are printed as one line (``heliotwin: error: ...``
naming the file and field) with exit code 2, and no partial output file is left behind.
"""
from __future__ import annotations

import argparse

from .. import __version__
from . import calibrate, field, plant, surfaces
from .common import run_command

__all__ = ["build_parser", "main", "run_command"]

#: Command groups in the order of ``heliotwin --help``.
GROUPS = (plant, calibrate, surfaces, field)


def build_parser() -> argparse.ArgumentParser:
    """The ``heliotwin`` parser with every command group's subcommands."""
    parser = argparse.ArgumentParser(prog="heliotwin",
                                     description="Differentiable digital twin of a solar tower plant.")
    parser.add_argument("--version", action="version", version=f"heliotwin {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for group in GROUPS:
        group.register(sub)
    return parser


def main(argv=None) -> int:
    """Parse ``argv`` (default: ``sys.argv[1:]``), run the command, return its exit status."""
    return run_command(build_parser().parse_args(argv))
