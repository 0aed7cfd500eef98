"""The ``heliotwin`` command line. Only argument parsing, reporting and plots live here; every command is a
thin shell over library calls a notebook can make too.

Layout: :mod:`.common` (error reporting, argument types), then one module per command group, each with a
``register(subparsers)``:

* :mod:`.plant` -- ``demo``, ``scenario from-paint``, ``trace``, ``validate``, ``bench``
* :mod:`.calibrate` -- ``calibrate``, ``split``, ``aim``
* :mod:`.update` -- ``update``, ``history``
* :mod:`.surfaces` -- ``reconstruct``, ``predict``
* :mod:`.simulate` -- ``simulate``, ``score``
* :mod:`.year` -- ``year`` (the plant's year heliostat by heliostat)
* :mod:`.report` -- ``report`` (the plant at a glance, one HTML page)

The groups are ordinary imports: a command whose module fails to import breaks ``heliotwin`` loudly instead
of disappearing from it. Library modules never import this package. Building the parser imports no torch
(commands import the library when they run), so ``heliotwin --help`` is instant.

Every command has ``--help`` and ``--debug``. Every error is printed as one line (``heliotwin: error: ...``
naming the file and field): exit code 2 for bad input, 1 for an internal error (the traceback only with
``--debug`` or ``HELIOTWIN_DEBUG=1``), 3 when what was asked is not met (``aim``: the aim point is outside the
actuator range; ``aimpoints``: ``--peak-limit`` not held at some instant, outputs still written), 130/143 for
Ctrl-C/SIGTERM; no partial output file is left behind (see :mod:`.common` for the exit codes).
"""
from __future__ import annotations

import argparse
import sys

from .. import __version__
from . import calibrate, field, plan, plant, report, simulate, surfaces, update, year
from .common import ArgumentParser, leave, run_command

__all__ = ["build_parser", "console", "main", "run_command"]

#: Command groups in the order of ``heliotwin --help``.
GROUPS = (plant, calibrate, plan, update, surfaces, field, year, simulate, report)


def build_parser() -> argparse.ArgumentParser:
    """The ``heliotwin`` parser with every command group's subcommands."""
    parser = ArgumentParser(prog="heliotwin",
                                     description="Differentiable digital twin of a solar tower plant.")
    parser.add_argument("--version", action="version", version=f"heliotwin {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for group in GROUPS:
        group.register(sub)
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error (or HELIOTWIN_DEBUG=1)")
    _add_shared_flags(sub)
    return parser


#: Commands that compute (and so take ``--device``); the others only read and write files.
COMPUTE_COMMANDS = ("demo", "trace", "validate", "bench", "calibrate", "reconstruct", "predict", "field", "aimpoints",
                    "year")


def _add_shared_flags(sub) -> None:
    """The flags every command shares, added once here so that no command can miss them:

    * ``--debug`` (also before the command; SUPPRESS keeps a sub-parser's default from overwriting the main
      parser's value);
    * ``--quiet``: no progress bars and no summary line (errors still go to stderr);
    * ``--device auto|cpu|cuda`` on the computing commands (:func:`.common.resolve_device`).
    """
    for name, p in sub.choices.items():
        inner = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        if inner:
            _add_shared_flags(inner[0])
            continue
        flags = {o for a in p._actions for o in a.option_strings}
        if "--quiet" not in flags:
            p.add_argument("--quiet", action="store_true", help="no progress bars and no summary line")
        if name in COMPUTE_COMMANDS and "--device" not in flags:
            p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                           help="where to compute: auto = CUDA when present and the command supports it "
                                "(default: %(default)s)")
        if "--debug" not in flags:
            p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                           help="show the traceback of an error (or HELIOTWIN_DEBUG=1)")


#: Options whose value may start with a minus sign (``--aim -1,-3.24,36``): argparse would take the value
#: for an option, so :func:`main` joins it to its option (``--aim=-1,-3.24,36``) first.
SIGNED_VALUE_OPTIONS = ("--aim",)


def _join_signed_values(argv: list[str]) -> list[str]:
    out, i = [], 0
    while i < len(argv):
        value = argv[i + 1] if i + 1 < len(argv) else ""
        if argv[i] in SIGNED_VALUE_OPTIONS and value[:1] == "-" and (value[1:2].isdigit() or value[1:2] == "."):
            out.append(f"{argv[i]}={value}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


def main(argv=None) -> int:
    """Parse ``argv`` (default: ``sys.argv[1:]``), run the command, return its exit status."""
    argv = _join_signed_values(list(sys.argv[1:] if argv is None else argv))
    return run_command(build_parser().parse_args(argv))


def console() -> None:
    """The ``heliotwin`` command (console script and ``python -m heliotwin``): :func:`main` on ``sys.argv``,
    then :func:`.common.leave` with its exit status (no interpreter teardown after the work is done)."""
    leave(main())
