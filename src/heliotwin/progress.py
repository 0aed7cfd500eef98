"""Progress over named stages that reads well on a terminal and in a log.

On a terminal :class:`Stages` draws a tqdm bar on stderr (the stage's name beside it); when stderr is not a
terminal (a CI log, ``nohup``, a pipe) it writes plain lines to stdout instead of a bar's carriage returns,
one when a stage starts and one when it ends: ``heliotwin demo: 2/4 aim points done (12.3 s)``. Stdout, not
stderr: a failing command's stderr holds nothing but its one-line error. ``enabled=False`` (the commands'
``--quiet``) silences both.
"""
from __future__ import annotations

import sys
import time

from tqdm.auto import tqdm

__all__ = ["Stages"]


class Stages:
    """Progress of a run of ``total`` named stages.

    Parameters
    ----------
    total : int
    desc : str
        What runs (``"heliotwin demo"``).
    enabled : bool
        False: nothing is written.
    stream : file, optional
        The bar's stream (default ``sys.stderr``); is it a terminal decides bar or lines.
    lines : file, optional
        Where the plain lines go (default ``sys.stdout``).
    """

    def __init__(self, total: int, desc: str, *, enabled: bool = True, stream=None, lines=None):
        self.total, self.desc, self.enabled = int(total), desc, bool(enabled)
        self.stream = sys.stderr if stream is None else stream
        self.lines = sys.stdout if lines is None else lines
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.done = 0
        self.t0 = time.perf_counter()
        self.bar = tqdm(total=self.total, desc=desc, unit="stage", file=self.stream,
                        disable=not (self.enabled and self.tty))

    def start(self, name: str) -> None:
        """Say which stage is running now (the bar's label on a terminal; a line in a log)."""
        if not self.enabled:
            return
        if self.tty:
            self.bar.set_postfix_str(name)
        else:
            print(f"{self.desc}: {self.done + 1}/{self.total} {name} ...", file=self.lines, flush=True)

    def step(self, name: str = "") -> None:
        """One stage finished."""
        self.done += 1
        if not self.enabled:
            return
        if self.tty:
            self.bar.set_postfix_str(name)
            self.bar.update()
        else:
            print(f"{self.desc}: {self.done}/{self.total} {name} done ({time.perf_counter() - self.t0:.1f} s)",
                  file=self.lines, flush=True)

    def close(self) -> None:
        """End the bar (a terminal gets its final newline); the plain lines need no ending. Idempotent."""
        self.bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
