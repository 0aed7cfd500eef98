"""Progress over named stages that reads well on a terminal and in a log.

On a terminal :class:`Stages` draws a tqdm bar on stderr (the stage's name beside it); when stderr is not a
terminal (a CI log, ``nohup``, a pipe) it writes plain lines to stdout instead of a bar's carriage returns,
one when a stage starts and one when it ends: ``heliotwin demo: 2/4 aim points done (12.3 s)``. Stdout, not
stderr: a failing command's stderr holds nothing but its one-line error. ``enabled=False`` (the commands'
``--quiet``) silences both. :class:`Progress` does the same for a count of work items (chunks, records, fits):
a bar on a terminal, otherwise one line each time another ``every`` percent is done.
"""
from __future__ import annotations

import sys
import time

from tqdm.auto import tqdm

__all__ = ["Stages", "Progress", "iterate"]


class _Reporter:
    """What :class:`Stages` and :class:`Progress` share: where the bar and the plain lines go, whether the
    stream is a terminal (bar) or a log (lines), the start time, and the bar's lifetime."""

    def __init__(self, total: int, desc: str, *, unit: str, enabled: bool, stream, lines, leave: bool):
        self.total, self.desc, self.enabled = int(total), desc, bool(enabled)
        self.stream = sys.stderr if stream is None else stream
        self.lines = sys.stdout if lines is None else lines
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.done = 0
        self.t0 = time.perf_counter()
        self.bar = tqdm(total=self.total, desc=desc, unit=unit, file=self.stream, leave=leave,
                        disable=not (self.enabled and self.tty))

    def close(self) -> None:
        """End the bar (a terminal gets its final newline); the plain lines need no ending. Idempotent."""
        self.bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Stages(_Reporter):
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
        super().__init__(total, desc, unit="stage", enabled=enabled, stream=stream, lines=lines, leave=True)

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


class Progress(_Reporter):
    """Progress over ``total`` work items: a tqdm bar on a terminal, a plain line every ``every`` percent in a log.

    Parameters
    ----------
    total : int
    desc : str
        What runs (``"heliotwin predict: year"``).
    unit : str
        The items' name (``"chunk"``, ``"record"``).
    enabled : bool
        False: nothing is written.
    every : float
        Percent between two plain lines (the last item always gets one).
    stream, lines : file, optional
        As for :class:`Stages`.
    """

    def __init__(self, total: int, desc: str, *, unit: str = "it", enabled: bool = True, every: float = 10.0,
                 stream=None, lines=None):
        super().__init__(max(0, int(total)), desc, unit=unit, enabled=enabled, stream=stream, lines=lines,
                         leave=False)
        self.unit, self.every, self.said = unit, float(every), -1.0

    def update(self, n: int = 1) -> None:
        """``n`` more items done."""
        self.done += int(n)
        if not self.enabled:
            return
        if self.tty:
            self.bar.update(n)
            return
        pct = 100.0 * self.done / self.total if self.total else 100.0
        if pct >= self.said + self.every or (self.done >= self.total and self.said < 100.0):
            self.said = pct if self.done < self.total else 100.0
            print(f"{self.desc}: {pct:.0f}% ({self.done}/{self.total} {self.unit}s, "
                  f"{time.perf_counter() - self.t0:.1f} s)", file=self.lines, flush=True)


def iterate(items, desc: str, *, unit: str = "it", enabled: bool = True, every: float = 10.0, total=None):
    """Yield ``items`` while :class:`Progress` reports them (``total`` defaults to ``len(items)``)."""
    with Progress(len(items) if total is None else total, desc, unit=unit, enabled=enabled, every=every) as bar:
        for item in items:
            yield item
            bar.update()
