"""Misuse campaign over the readers of a scenario's ``/learned`` group: every learned dataset damaged in turn.

A sibling of ``benchmarks/fuzz_field.py`` (same runner, same judging). The scenario is built in code
(``tests/helpers/learned.py``: 2 heliostats, ``/learned/calibration`` with its posterior and drift state,
``/learned/assimilation`` from one ``update``, ``/learned/surfaces/S1``). Each dataset is set to NaN, truncated,
given another shape, another dtype, deleted or made a scalar, and the commands that read its group run on it:

* calibration: ``scenario show``, ``aim``, ``plan``;
* assimilation: ``scenario show``, ``history``;
* surfaces: ``scenario show``, ``predict --every 31d``.

(``trace``, ``validate`` and ``update`` read the same groups through the same loader but need a PAINT folder
holding the heliostats; ``tests/test_fuzz_learned.py`` runs them on a few cases.)

Each run is judged like ``fuzz_field.py``: tracebacks, "internal error" lines, hangs, silent bad results (exit 0
with NaN or null in its JSON report or on the console), inputs modified, leftovers. A damage the readers may
accept (an optional dataset deleted, a record list shortened) is fine when the run stays clean.

Usage::

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/fuzz_learned.py [--cases 400] [--seed 0] [--show 25]
        [--group calibration|assimilation|surfaces ...]

Exit status 1 when any count is non-zero.
"""
from __future__ import annotations

import argparse
import random
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

import fuzz_field  # noqa: E402 -- the sibling campaign's runner and judge
from helpers.learned import DAMAGES, damage, learned_datasets, learned_scenario  # noqa: E402

SUN = ("--sun-azimuth", "10", "--sun-elevation", "40")
READERS = {
    "calibration": [("show", ["scenario", "show", "{d}/s.h5", "--json", "{d}/o.json"]),
                    ("aim", ["aim", "--scenario", "{d}/s.h5", "--heliostat", "S1", *SUN, "--aim", "0,0,50",
                             "--json", "{d}/o.json"]),
                    ("plan", ["plan", "--scenario", "{d}/s.h5", "--heliostat", "S1", "--quiet", "--no-plots", "--json",
                              "{d}/o.json"])],
    "assimilation": [("show", ["scenario", "show", "{d}/s.h5", "--json", "{d}/o.json"]),
                     ("history", ["history", "--scenario", "{d}/s.h5", "--heliostat", "S1", "--json",
                                  "{d}/o.json"])],
    "surfaces": [("show", ["scenario", "show", "{d}/s.h5", "--json", "{d}/o.json"]),
                 ("predict", ["predict", "--scenario", "{d}/s.h5", "--every", "31d", "--quiet", "--json",
                              "{d}/o.json"])],
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=400, help="at most this many runs (default %(default)s)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--show", type=int, default=25)
    ap.add_argument("--group", choices=sorted(READERS), action="append", help="only these learned groups")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fuzz-learned-") as tmp:
        root = Path(tmp)
        base = learned_scenario(root / "base.h5")
        runs = []
        for name in learned_datasets(base):
            group = name.split("/")[1]
            if args.group and group not in args.group:
                continue
            for how in DAMAGES:
                if damage(base, root / "probe.h5", name, how):
                    runs += [(f"{name} {how} -> {cmd}", name, how, argv) for cmd, argv in READERS.get(group, [])]
        random.Random(args.seed).shuffle(runs)
        runs = runs[:args.cases]
        c = fuzz_field.Campaign(root, args.show)
        for label, name, how, argv in runs:
            damage(base, root / "damaged.h5", name, how)
            c.case(label, argv, inputs={"s.h5": root / "damaged.h5"}, outputs=["{d}/o.json"], timeout=120)
    return c.report(f"{len(runs)} runs, {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    sys.exit(main())
