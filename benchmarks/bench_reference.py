"""Compare the Monte-Carlo tracer's speed of the working tree with reference commits, interleaved.

Usage::

    python benchmarks/bench_reference.py [--ref 4fce4ad^] [--ref ...] [--reps 5] [--json out.json]
                                         [--surface-points 10000] [--rays-per-point 100] [--resolution 256]
                                         [--threads 2]

Each reference commit is checked out with ``git worktree add`` into a temporary folder (removed afterwards).
Every repetition runs ``python -m heliotwin bench`` once per tree, each in a fresh process with
``PYTHONPATH=<tree>/src`` and ``OMP_NUM_THREADS=<threads>``, in a rotating order, so load from other
processes on the machine hits all trees alike. Prints and (with ``--json``) writes the per-run figures, the
medians of ``mc.forward_rays_per_s`` / ``mc.forward_backward_rays_per_s`` per tree, and the ratio of each
tree's median to the first reference's.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
KEYS = ("forward_rays_per_s", "forward_backward_rays_per_s")


def _git(*args: str, cwd: Path = ROOT) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def _env(tree: Path, threads: int) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(tree / "src")
    env["OMP_NUM_THREADS"] = str(threads)
    return env


def _check_import(tree: Path, threads: int) -> str:
    """The heliotwin package a run in ``tree`` imports (must be the tree's own)."""
    out = subprocess.run([sys.executable, "-c", "import heliotwin; print(heliotwin.__file__)"], env=_env(tree, threads),
                         cwd=tree, check=True, capture_output=True, text=True).stdout.strip()
    if not Path(out).resolve().is_relative_to((tree / "src").resolve()):
        raise RuntimeError(f"a run in {tree} imports {out}, not the tree's own package")
    return out


def _bench_once(tree: Path, args, json_path: Path) -> dict:
    cmd = [sys.executable, "-m", "heliotwin", "bench", "--surface-points", str(args.surface_points),
           "--rays-per-point", str(args.rays_per_point), "--resolution", str(args.resolution), "--json",
           str(json_path)]
    subprocess.run(cmd, env=_env(tree, args.threads), cwd=tree, check=True, capture_output=True, text=True,
                   timeout=args.timeout)
    mc = json.loads(json_path.read_text())["mc"]
    return {k: float(mc[k]) for k in KEYS}


def _summary(runs: list[dict]) -> dict:
    return {k: statistics.median(r[k] for r in runs) for k in KEYS}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ref", action="append", default=None,
                    help="reference commit (repeatable; default: 4fce4ad^); ratios are to the first")
    ap.add_argument("--reps", type=int, default=5, help="runs per tree (default: %(default)s)")
    ap.add_argument("--json", help="write the result here")
    ap.add_argument("--surface-points", type=int, default=10000)
    ap.add_argument("--rays-per-point", type=int, default=100)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2, help="OMP_NUM_THREADS of the runs (default: %(default)s)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per bench run (default: %(default)s)")
    args = ap.parse_args(argv)
    refs = args.ref or ["4fce4ad^"]
    if args.reps < 1:
        ap.error("--reps must be at least 1")

    head = _git("rev-parse", "--short", "HEAD")
    dirty = bool(_git("status", "--porcelain", "--untracked-files=no"))
    trees = [{"label": f"working tree ({head}{', modified' if dirty else ''})", "commit": head, "path": ROOT}]
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # e.g. `timeout`: still remove the worktrees
    tmp = Path(tempfile.mkdtemp(prefix="heliotwin-bench-ref-"))
    added: list[Path] = []
    try:
        for i, ref in enumerate(refs):
            commit = _git("rev-parse", "--short", f"{ref}^{{commit}}")
            path = tmp / f"ref{i}-{commit}"
            _git("worktree", "add", "--detach", str(path), commit)
            added.append(path)
            trees.append({"label": ref, "commit": commit, "path": path})
        for t in trees:
            t["imports"] = _check_import(t["path"], args.threads)
            t["runs"] = []
        order = list(range(len(trees)))
        for rep in range(args.reps):
            for j in order[rep % len(order):] + order[:rep % len(order)]:  # rotate who runs first
                t = trees[j]
                r = _bench_once(t["path"], args, tmp / "bench.json")
                t["runs"].append(r)
                print(f"rep {rep + 1}/{args.reps} {t['label']:>32}: forward {r[KEYS[0]] / 1e6:7.1f} M rays/s, "
                      f"forward+backward {r[KEYS[1]] / 1e6:7.1f} M rays/s", flush=True)
    finally:
        for path in added:
            subprocess.run(["git", "worktree", "remove", "--force", str(path)], cwd=ROOT, capture_output=True)
        subprocess.run(["git", "worktree", "prune"], cwd=ROOT, capture_output=True)
        for f in tmp.glob("*.json"):
            f.unlink()
        try:
            tmp.rmdir()
        except OSError:
            pass

    base = _summary(trees[1]["runs"])
    result = {
        "command": f"python -m heliotwin bench --surface-points {args.surface_points} --rays-per-point "
                   f"{args.rays_per_point} --resolution {args.resolution} (OMP_NUM_THREADS={args.threads})",
        "reps": args.reps,
        "ratio_to": trees[1]["label"],
        "trees": [],
    }
    print(f"\nmedians of {args.reps} interleaved runs; ratio to {trees[1]['label']} ({trees[1]['commit']})")
    for t in trees:
        med = _summary(t["runs"])
        ratio = {k: med[k] / base[k] for k in KEYS}
        result["trees"].append({"label": t["label"], "commit": t["commit"], "runs": t["runs"],
                                "median": med, "ratio": ratio})
        print(f"{t['label']:>32} ({t['commit']}): forward {med[KEYS[0]] / 1e6:7.1f} M rays/s (x{ratio[KEYS[0]]:.2f}), "
              f"forward+backward {med[KEYS[1]] / 1e6:7.1f} M rays/s (x{ratio[KEYS[1]]:.2f})")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
