"""CPU time per test and per test file, for keeping the default suite's time in check on a shared machine.

Wall times mean little while other processes share the cores; the CPU time a test costs (this process's user +
system time, plus that of the child processes it waited for: subprocess CLIs, spawned ranks) does not depend on
them. Use as a plugin: ``python -m pytest -q -p helpers.cputime`` prints the files that cost the most CPU at the
end, and with ``HELIOTWIN_CPU_LOG=FILE`` writes one JSON line per test (``id``, ``self_s``, ``children_s``,
``wall_s``; setup and teardown included: a module fixture counts in the first test that uses it), so that two
checkouts' runs can be compared test by test.
"""
from __future__ import annotations

import collections
import json
import os
import resource
import time

import pytest

_ROWS: list = []


def _cpu() -> tuple[float, float]:
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime, kids.ru_utime + kids.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    (me, kids), wall = _cpu(), time.perf_counter()
    yield
    me2, kids2 = _cpu()
    _ROWS.append({"id": item.nodeid, "self_s": me2 - me, "children_s": kids2 - kids,
                  "wall_s": time.perf_counter() - wall})


def pytest_terminal_summary(terminalreporter):
    if not _ROWS:
        return
    path = os.environ.get("HELIOTWIN_CPU_LOG")
    if path:
        with open(path, "w", encoding="utf-8") as fh:
            fh.writelines(json.dumps(r) + "\n" for r in _ROWS)
    per_file = collections.Counter()
    for r in _ROWS:
        per_file[r["id"].split("::")[0]] += r["self_s"] + r["children_s"]
    total = sum(per_file.values())
    terminalreporter.write_sep("-", f"CPU time of the tests: {total:.1f} s (user + system, waited children included)")
    for name, seconds in per_file.most_common(15):
        terminalreporter.write_line(f"{seconds:8.1f} s  {name}")
