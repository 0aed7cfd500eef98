"""What every command shares: the safety net (:func:`run_command`), argument types with ranges, output checks.

Imports nothing heavy: building the parser (``heliotwin --help``) must not pay for torch.

Exit codes (documented in the README):

* 0 -- success;
* 1 -- internal error (a bug: please report it; ``--debug`` or ``HELIOTWIN_DEBUG=1`` shows the traceback);
* 2 -- bad input: a file, a field or an argument the user can fix (one line naming it);
* 3 -- the run ended but what was asked is not met: ``aim``'s aim point is outside the actuator range, or
  ``aimpoints`` could not hold the peak-flux limit at some instant (its outputs are written: the best it
  found, with ``limit_met: false`` in the report, and a console line saying so);
* 130 / 143 -- interrupted by Ctrl-C (SIGINT) / terminated (SIGTERM); nothing is left behind.

A reader that closes the pipe early (``heliotwin scenario show plant.h5 | head``) ends the command quietly:
no message, and the command's own exit status (0 while it was still printing: the reader took what it wanted).
"""
from __future__ import annotations

import argparse
import atexit
import contextlib
import datetime as _dt
import math
import os
import re
import signal
import sys
import threading
import time
import traceback

from ..errors import HeliotwinError

__all__ = ["ArgumentParser", "run_command", "resolve_device", "stage", "add_resume_flags", "checkpoint_file",
           "checkpointed", "debug_requested", "Terminated", "csv_list",
           "int_list", "positive_int", "int_range", "float_range", "finite_float", "peak_limit", "seed_int",
           "frequency",
           "utc_time", "utc_date", "check_output_folder", "EXIT_OK", "EXIT_INTERNAL", "EXIT_INPUT", "EXIT_INTERRUPTED",
           "EXIT_TERMINATED", "EXIT_NOT_MET", "check_input_files", "OUT_OF_MEMORY", "share_of_cores", "default_threads"]

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT = 0, 1, 2
EXIT_NOT_MET = 3  # aim point out of the actuator range (aim); peak-flux limit not met (aimpoints);
# some heliostats failed (reconstruct --heliostats: the others are written)
EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143  # 128 + SIGINT, 128 + SIGTERM (the shell's convention)


class Terminated(KeyboardInterrupt):
    """SIGTERM, delivered like Ctrl-C: every ``finally`` and :func:`~heliotwin.io.report.atomic_path` cleans up."""


def debug_requested(args=None) -> bool:
    """``--debug`` on the command line or ``HELIOTWIN_DEBUG`` set to anything but ``""``/``0``/``false``/``no``."""
    if args is not None and getattr(args, "debug", False):
        return True
    return os.environ.get("HELIOTWIN_DEBUG", "").strip().lower() not in ("", "0", "false", "no")


def _is_user_key_error(exc: KeyError) -> bool:
    """A ``KeyError`` the library raised for a name the user gave (``"unknown heliostat 'ZZ99'; ..."``).

    The plant containers and the PAINT reader raise ``KeyError`` with a sentence; a bare
    ``KeyError('median_test_mrad')`` from a dict lookup is a bug (exit 1, not a user error).
    """
    return len(exc.args) == 1 and isinstance(exc.args[0], str) and " " in exc.args[0].strip()


#: The one message of every allocation that fails (Python's ``MemoryError``, torch's "can't allocate").
OUT_OF_MEMORY = "out of memory (try fewer heliostats, rays or a lower --resolution)"


def _is_allocation_failure(exc: BaseException) -> bool:
    """torch reports a failed allocation as a ``RuntimeError`` (CPU: "can't allocate memory", "not enough
    memory"; CUDA: ``torch.OutOfMemoryError``), numpy as ``numpy.core._exceptions._ArrayMemoryError``."""
    if isinstance(exc, MemoryError) or type(exc).__name__ in ("OutOfMemoryError", "_ArrayMemoryError"):
        return True
    text = str(exc).lower()
    return isinstance(exc, RuntimeError) and any(
        s in text for s in ("can't allocate memory", "not enough memory", "out of memory", "bad_alloc"))


def _classify(exc: BaseException) -> tuple[int, str]:
    """Exit status and the one-line message of an exception that reached the command line's edge."""
    if _is_allocation_failure(exc):
        detail = " ".join(str(exc).split()) if isinstance(exc, MemoryError) and str(exc) else ""
        return EXIT_INTERNAL, f"{OUT_OF_MEMORY}{': ' + detail if detail else ''}"
    if isinstance(exc, KeyError) and _is_user_key_error(exc):
        return EXIT_INPUT, exc.args[0]  # str(KeyError) would add quotes around the message
    if isinstance(exc, (HeliotwinError, NotImplementedError)):
        return EXIT_INPUT, str(exc) or type(exc).__name__
    if isinstance(exc, OSError):
        # A file the user named (missing, unreadable, disk full): name it, with the reason.
        if exc.filename is not None and exc.strerror:
            return EXIT_INPUT, f"{exc.filename}: {exc.strerror}"
        return EXIT_INPUT, str(exc) or type(exc).__name__
    if isinstance(exc, RecursionError):
        return EXIT_INTERNAL, "internal error: recursion too deep (rerun with --debug; please report it)"
    text = " ".join(str(exc).split())
    what = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return EXIT_INTERNAL, f"internal error: {what} (rerun with --debug for the traceback; please report it)"


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """Turn SIGTERM into :class:`Terminated` while a command runs (main thread only), then restore."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


#: Environment variables of the thread pools a computing command starts (torch's OpenMP, BLAS).
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def share_of_cores(cpus: int, load: float) -> int:
    """Threads for a command on a machine with ``cpus`` cores of which others keep ``load`` busy: the
    cores the others leave idle, at least one. Spinning OpenMP threads on cores another process keeps busy
    made a 2-thread calibration 2.3x slower than 1 thread beside one busy process; on an idle machine every
    core is used."""
    if not (isinstance(load, (int, float)) and math.isfinite(load)) or load < 0:
        load = 0.0
    return max(1, min(int(cpus), int(math.floor(cpus - load + 0.5))))


#: Samples and spacing [s] of :func:`busy_cores`' reading of the kernel's runnable count.
BUSY_SAMPLES, BUSY_SPACING_S = 7, 0.004


def busy_cores(stat_path: str = "/proc/stat") -> float:
    """Cores other processes keep busy *now*: the median over :data:`BUSY_SAMPLES` readings (about 25 ms) of the
    kernel's runnable threads (``procs_running`` of ``/proc/stat``), less this process. Where that count does not
    exist (not Linux), the 1-minute load average.

    Why not the load average alone: it trails by a minute. A command started right after another one ended (a
    scheduled job, the daily loop, a benchmark) read the finished command's load, took one thread on an idle
    2-core machine and ran 1.5x slower (a 2,000-heliostat ``calibrate``: 38 s with two threads, 55 s with one).
    """
    counts = []
    for k in range(BUSY_SAMPLES):
        try:
            with open(stat_path, "rb") as fh:
                line = next((ln for ln in fh if ln.startswith(b"procs_running")), None)
        except OSError:
            line = None
        if line is None:
            break
        counts.append(int(line.split()[1]))
        if k + 1 < BUSY_SAMPLES:
            time.sleep(BUSY_SPACING_S)
    if counts:
        return max(0.0, float(sorted(counts)[len(counts) // 2]) - 1.0)
    try:
        return float(os.getloadavg()[0])
    except (AttributeError, OSError):
        return 0.0


def default_threads(environ=None) -> int | None:
    """Set the thread pools' size for this process (before torch is imported) to :func:`share_of_cores` of
    the cores it may run on and the cores others keep busy now (:func:`busy_cores`), unless ``OMP_NUM_THREADS``
    (or ``HELIOTWIN_THREADS``) says otherwise; returns the count set (None: left to the environment)."""
    env = os.environ if environ is None else environ
    if env.get("OMP_NUM_THREADS"):
        return None
    given = env.get("HELIOTWIN_THREADS", "").strip()
    if given.isdigit() and int(given) > 0:
        n = int(given)
    else:
        try:
            cpus = len(os.sched_getaffinity(0))
        except (AttributeError, OSError):
            cpus = os.cpu_count() or 1
        n = share_of_cores(cpus, busy_cores())
    for name in THREAD_VARIABLES:
        env.setdefault(name, str(n))
    return n


def run_command(args, prefix: str = "heliotwin: ") -> int:
    """Run a parsed command (``args.func(args)``) and return its exit status: the command line's safety net.

    Every exception becomes one line ``<prefix>error: ...`` on stderr: exit status 2 for errors a user can
    cause (:class:`~heliotwin.errors.HeliotwinError`, unknown names -- ``KeyError`` with a message --,
    unsupported combinations -- ``NotImplementedError`` -- and files that cannot be read or written --
    ``OSError``), 1 for anything else (a bug; the line says so). The traceback is printed only with
    ``--debug`` or ``HELIOTWIN_DEBUG=1``. Ctrl-C exits 130 and SIGTERM 143 after the writers have removed
    their temporary files.
    """
    debug = debug_requested(args)
    code = EXIT_OK
    if "torch" not in sys.modules:  # the command imports the library (and torch) below: size its pools first
        default_threads()
    try:
        with _sigterm_as_interrupt():
            check_input_files(args)
            if getattr(args, "device", None) is not None:
                args.device = resolve_device(args.device, getattr(args.func, "supports_cuda", False),
                                             getattr(args, "command", None))
            code = int(args.func(args) or 0)
            if sys.stdout is not None:  # (redirect_stdout(None) in a caller)
                sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
            return code
    except BrokenPipeError:
        _stdout_to_devnull()
        return code
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, Terminated)
        if debug:
            traceback.print_exc()
        kept = getattr(args, "checkpoint_kept", None)
        tail = (f"; the fit's checkpoint {kept} is kept: rerun the same command with --resume to continue"
                if kept and os.path.exists(kept) else "")
        print(f"{prefix}{'terminated' if terminated else 'interrupted'}; nothing was written{tail}", file=sys.stderr)
        return EXIT_TERMINATED if terminated else EXIT_INTERRUPTED
    except Exception as exc:  # noqa: BLE001 -- the one place that turns every error into one line
        code, message = _classify(exc)
        if debug:
            traceback.print_exc()
        lines = [ln for ln in str(message).splitlines() if ln.strip()]
        print(f"{prefix}error: {lines[0] if lines else message}", file=sys.stderr)
        return code


def leave(status: int):
    """End the process with exit ``status`` after a command: the exit functions run and stdout and stderr are
    flushed, but not the interpreter's teardown of every module.

    Python's finalization destroys each module and torch's C++ state one by one, ~0.3 s on a 2-core machine
    after any command that imported torch: a tenth of the budget of ``field``, ``scenario show`` or an
    ``update``, paid after the work is done. Nothing is lost by skipping it: a command writes, closes and
    renames its outputs before it returns, and the exit functions that matter (logging's flush,
    multiprocessing's joins, temporary folders' finalizers) are the ones run here. Where torch was never
    imported (``--help``, a refused argument), another non-daemon thread still runs (the interpreter would
    wait for it) or a profiler or tracer watches (``python -m cProfile -m heliotwin`` writes its statistics
    after the command returns), the ordinary exit happens instead.
    """
    others = [t for t in threading.enumerate() if t is not threading.main_thread() and t.is_alive() and not t.daemon]
    if others or "torch" not in sys.modules or sys.getprofile() is not None or sys.gettrace() is not None:
        sys.exit(status)
    atexit._run_exitfuncs()  # what the interpreter's exit runs first (CPython's own function)
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:
                stream.flush()
        except (OSError, ValueError):  # a reader gone (| head) or a closed stream: nothing left to show
            pass
    os._exit(status)


def _stdout_to_devnull() -> None:
    """After the reader of stdout went away (``| head``): point stdout at /dev/null, so that the interpreter's
    final flush neither fails nor prints ``Exception ignored ... BrokenPipeError``."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # replaced by a non-file (a test's StringIO)
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    finally:
        os.close(devnull)


def _named_paths(args):
    """``(flag, text)`` of every string argument (and every string in a list argument) of a parsed command."""
    for dest, value in sorted(vars(args).items()):
        if dest in ("func", "command") or callable(value):
            continue
        flag = "--" + dest.replace("_", "-")
        for v in value if isinstance(value, (list, tuple)) else [value]:
            if isinstance(v, str) and v and "\x00" not in v:
                yield flag, v


def check_input_files(args) -> None:
    """Refuse, before anything is opened, a path argument that names a FIFO, a device or a socket.

    Reading one blocks until some other process writes (a FIFO) or never ends (a device), so a command handed
    one would hang instead of failing. Every string argument that names an existing path is checked (inputs
    and outputs alike: an output is replaced by a rename, which a device cannot be), and so is the checkpoint a
    ``--resume`` would read. Folders and missing paths are left to the commands.
    """
    import stat

    named = list(_named_paths(args))
    if getattr(args, "resume", False):
        main = getattr(args, "output", None) or getattr(args, "json", None)
        if isinstance(main, str):
            named.append(("--resume", f"{main}.ckpt"))
    for flag, text in named:
        try:
            mode = os.stat(text).st_mode
        except (OSError, ValueError):
            continue
        if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
            kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode)
                    else "a device")
            raise HeliotwinError(f"{flag} {text}: is {kind}, not a regular file (reading it could wait forever)")


def resolve_device(name: str, supports_cuda: bool, command: str | None = None) -> str:
    """``--device``: ``auto`` -> ``"cuda"`` when a CUDA device is present and the command can use it, else
    ``"cpu"``; ``cuda`` without a device, or on a command that runs on the CPU only so far, is an error."""
    if name == "cpu":
        return "cpu"
    import torch

    available = torch.cuda.is_available()
    if name == "auto":
        return "cuda" if available and supports_cuda else "cpu"
    if name != "cuda":
        raise HeliotwinError(f"--device {name}: expected auto, cpu or cuda")
    if not available:
        raise HeliotwinError("--device cuda: no CUDA device is available (torch.cuda.is_available() is False; "
                             "use --device cpu or install a CUDA build of torch)")
    if not supports_cuda:
        raise HeliotwinError(f"--device cuda: {command or 'this command'} runs on the CPU only so far "
                             f"(use --device cpu or auto)")
    return "cuda"


def stage(args, text: str, stream=None) -> None:
    """Name the stage a long command has reached (``heliotwin calibrate: fitting (lm) ...``) on stderr.

    Only when stderr is a terminal and ``--quiet`` is not given: piped or captured stderr then holds nothing
    but the one-line error, and the per-step progress bars (tqdm) show below the stage line.
    """
    stream = sys.stderr if stream is None else stream
    if getattr(args, "quiet", False) or not getattr(stream, "isatty", lambda: False)():
        return
    print(f"heliotwin {getattr(args, 'command', None) or ''}: {text}".replace(" :", ":"), file=stream, flush=True)


# ------------------------------------------------------------------------------------------------ resume
def add_resume_flags(p) -> None:
    """``--resume`` and ``--checkpoint-interval`` of the commands with long fits (``calibrate``, ``reconstruct``)."""
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from its checkpoint (<output>.ckpt next to -o, else --json); "
                        "refused when the settings or inputs differ")
    p.add_argument("--checkpoint-interval", type=float_range(0.0, 86400.0, what="seconds"), default=30.0,
                   help="least seconds between two checkpoint saves of a running fit (0: every 10 steps; default "
                        "%(default)s); finished fits are always saved")


def checkpoint_file(args) -> str | None:
    """Where a command's checkpoint lives: next to its main output (``-o``, else ``--json``), or None."""
    from ..io.checkpoint import checkpoint_path

    main = getattr(args, "output", None) or getattr(args, "json", None)
    if main is None:
        if getattr(args, "resume", False):
            raise HeliotwinError("--resume needs -o or --json: the checkpoint lives next to the output")
        return None
    return checkpoint_path(main)


@contextlib.contextmanager
def checkpointed(args, checkpoint):
    """Around a command's fit and output writing: the checkpoint is removed once the outputs are written, kept
    when the command is interrupted (Ctrl-C, SIGTERM: the message says how to resume) or cannot write
    (``OSError``: disk full), and removed after any other error (a resume would meet it again)."""
    if checkpoint is None:
        yield
        return
    args.checkpoint_kept = checkpoint.path
    try:
        yield
    except (KeyboardInterrupt, OSError):
        raise
    except BaseException:
        checkpoint.remove()
        raise
    checkpoint.remove()


# ------------------------------------------------------------------------------------------ argument types
class ArgumentParser(argparse.ArgumentParser):
    """argparse with the command line's one-line errors: ``heliotwin: error: trace: argument --steps: ...``
    and a pointer to ``--help`` instead of the usage block (exit status 2, as argparse's)."""

    def error(self, message):
        command = self.prog.split(" ", 1)[1] if " " in self.prog else ""
        where = f"{command}: " if command else ""
        self.exit(EXIT_INPUT, f"heliotwin: error: {where}{' '.join(message.split())} "
                              f"(see '{self.prog} --help')\n")


def csv_list(text: str | None) -> list[str] | None:
    """``"AA39, AB38"`` -> ``["AA39", "AB38"]``; empty or missing -> ``None`` (meaning: all)."""
    return [t.strip() for t in text.split(",") if t.strip()] if text else None


def int_list(text: str, hi: int = 10**9) -> list[int]:
    """argparse type: comma-separated positive integers (at least one, each at most ``hi``)."""
    try:
        values = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        values = []
    if not values or not all(0 < v <= hi for v in values):
        raise argparse.ArgumentTypeError(f"expected comma-separated integers in 1..{hi}, got {text!r}")
    return values


def int_range(lo: int | None = None, hi: int | None = None, what: str = "an integer"):
    """argparse type factory: an integer in ``[lo, hi]`` (either bound may be None)."""
    def parse(text: str) -> int:
        try:
            v = int(str(text).strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            span = f"{'-inf' if lo is None else lo}..{'inf' if hi is None else hi}"
            raise argparse.ArgumentTypeError(f"expected {what} in {span}, got {text!r}")
        return v
    parse.__name__ = what  # argparse names the type in its messages
    return parse


#: argparse type: an integer > 0 (at most 10**9: larger counts are typos, not plans).
positive_int = int_range(1, 10**9, "a positive integer")

#: argparse type: a random seed, 0 .. 2**63 - 1 (what ``torch.Generator.manual_seed`` accepts).
seed_int = int_range(0, 2**63 - 1, "a seed")


def float_range(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, what: str = "a number"):
    """argparse type factory: a finite float in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``); NaN never passes."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        bad_lo = lo is not None and (v <= lo if lo_open else v < lo)
        if not math.isfinite(v) or bad_lo or (hi is not None and v > hi):
            span = f"{'(' if lo_open else '['}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]"
            raise argparse.ArgumentTypeError(f"expected {what} in {span}, got {text!r}")
        return v
    parse.__name__ = what
    return parse


#: argparse type: any finite float.
finite_float = float_range(what="a finite number")

#: argparse type: a receiver peak-flux limit [W/m2], 1 kW/m2 .. 100 MW/m2 (the library's
#: ``heliotwin.optimise.aimstate.PEAK_LIMIT_RANGE_W_M2``; kept literal here so that ``--help`` stays torch-free).
peak_limit = float_range(1e3, 1e8, what="a receiver flux limit [W/m2] (1 kW/m2 .. 100 MW/m2)")

_FREQ = re.compile(r"^\s*(\d+)\s*(s|sec|min|t|h|d)\s*$", re.IGNORECASE)
_FREQ_SECONDS = {"s": 1, "sec": 1, "min": 60, "t": 60, "h": 3600, "d": 86400}


def frequency(text: str) -> str:
    """argparse type: a time step like ``30min``, ``1h``, ``90s`` or ``1d``, between 1 minute and 31 days.

    Returns a pandas frequency in whole minutes (``"60min"`` for ``1h``), valid in every pandas version.
    """
    m = _FREQ.match(str(text))
    if not m:
        raise argparse.ArgumentTypeError(f"expected a time step like 30min, 1h or 1d, got {text!r}")
    seconds = int(m.group(1)) * _FREQ_SECONDS[m.group(2).lower()]
    if seconds < 60 or seconds > 31 * 86400 or seconds % 60:
        raise argparse.ArgumentTypeError(f"expected a time step of whole minutes between 1min and 31d, got {text!r}")
    return f"{seconds // 60}min"


def utc_time(text: str) -> str:
    """argparse type: an ISO 8601 time (``2023-03-20T11:30:00Z``; no zone means UTC), years 1900-2100.

    Returns the time as ISO text in UTC (``...+00:00``), which pandas and pvlib read unambiguously.
    """
    s = str(text).strip()
    try:
        t = _dt.datetime.fromisoformat(s[:-1] + "+00:00" if s.endswith(("Z", "z")) else s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an ISO time like 2023-03-20T11:30:00Z, got {text!r}") from None
    t = t.replace(tzinfo=_dt.timezone.utc) if t.tzinfo is None else t.astimezone(_dt.timezone.utc)
    if not 1900 <= t.year <= 2100:
        raise argparse.ArgumentTypeError(f"expected a time between 1900 and 2100, got {text!r}")
    return t.isoformat()


#: Years a planned day may fall in: the PAINT era and a plant's lifetime ahead (pvlib's solar position and the
#: plant's clock are meaningless for 1850; pandas' nanosecond times end in 2262).
DAY_YEARS = (1950, 2200)


def utc_date(text: str) -> str:
    """argparse type: a UTC date ``YYYY-MM-DD`` in :data:`DAY_YEARS`; returned as ISO text. A date that cannot be
    read and one that reads but lies outside the years are told apart (``--day 1850-06-21`` is "out of range")."""
    s = str(text).strip()
    try:
        d = _dt.date.fromisoformat(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a UTC date like 2024-06-21, got {text!r}") from None
    lo, hi = DAY_YEARS
    if not lo <= d.year <= hi:
        raise argparse.ArgumentTypeError(f"{text!r} is out of range: expected a day in the years {lo}..{hi}")
    return d.isoformat()


def run_plant_step(run, out_h5, in_place: bool):
    """``run()`` (a read-compute step returning an object with ``.scenario``) and its plant written to ``out_h5``:
    in place under the plant's lock by its own atomic writer (:func:`heliotwin.workflows.update.locked_plant_write`),
    else staged to ``out_h5`` (none: no plant is written). Returns what ``run`` returned."""
    from ..io.scenario import write_scenario
    from ..workflows.update import locked_plant_write

    if in_place:
        return locked_plant_write(out_h5, run)
    result = run()
    if out_h5:
        write_scenario(result.scenario, out_h5)
    return result


def check_output_folder(path, flag: str) -> None:
    """Fail before a long run, not after it, when the folder of an output file does not exist.

    The rule of every command: an output's folder must exist (commands never create folders, except
    ``demo --out``, whose output is the folder itself).
    """
    if path is None:
        return
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    if not os.path.isdir(folder):
        raise HeliotwinError(f"{flag} {os.fspath(path)}: output folder {folder} does not exist (create it first)")
