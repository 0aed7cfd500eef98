"""Benchmark the Monte-Carlo tracer (forward, forward+backward) and the gaussian (Gaussian-footprint) integrator.

Usage::

    python benchmarks/bench_forward.py [--points 10000] [--rays 10 100] [--resolution 256] [--seed 0]
                                       [--threads 2] [--out bench_forward.json]

Prints a summary and writes the full result (see :func:`heliotwin.workflows.bench.run_benchmark`) as JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile

from heliotwin.workflows.bench import run_benchmark


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=10000, help="mirror surface points")
    ap.add_argument("--rays", type=int, nargs="+", default=[10, 100], help="rays per point to time")
    ap.add_argument("--resolution", type=int, default=256, help="bitmap side [px]")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--no-accuracy", action="store_true", help="skip the time-to-accuracy study")
    ap.add_argument("--out", default="bench_forward.json", help="JSON output path")
    args = ap.parse_args(argv)
    res = run_benchmark(surface_points=args.points, rays_per_point=tuple(args.rays), resolution=args.resolution,
                        seed=args.seed, threads=args.threads, repeats=args.repeats,
                        time_to_accuracy=not args.no_accuracy)
    print(f"torch {res['torch']}, {res['threads']} threads, {res['surface_points']} points, "
          f"{res['resolution']}^2 bitmap, {res['sunshape']} sun")
    for k, r in res["mc"]["per_k"].items():
        print(f"  K={k:>5}: forward {r['forward_rays_per_s'] / 1e6:7.1f} M rays/s ({r['forward_s'] * 1e3:7.2f} ms)  "
              f"forward+backward {r['forward_backward_rays_per_s'] / 1e6:7.1f} M rays/s "
              f"({r['forward_backward_s'] * 1e3:7.2f} ms)")
    tta = res.get("time_to_accuracy")
    if tta:
        an = tta["gaussian"]
        print(f"  reference (gaussian sun): {tta['reference']['rays'] / 1e6:.0f} M rays in "
              f"{tta['reference']['time_s']:.2f} s, noise L1 ~{tta['reference']['noise_l1']:.4f}")
        print(f"  gaussian integrator: {an['time_s'] * 1e3:.1f} ms, L1 vs reference {an['l1_vs_reference']:.4f}")
        reached = tta["mc_to_same_l1"]
        if reached:
            print(f"  MC reaches that L1 with K={reached['rays_per_point']} ({reached['rays'] / 1e6:.1f} M rays) "
                  f"in {reached['time_s'] * 1e3:.1f} ms")
        else:
            last = tta["mc_curve"][-1]
            print(f"  MC did not reach it up to K={last['rays_per_point']} (L1 {last['l1']:.4f})")
            est = tta.get("mc_to_same_l1_estimate")
            if est:
                print(f"  MC would need ~{est['rays'] / 1e6:.0f} M rays, ~{est['time_s']:.1f} s (extrapolated)")
    print(f"  peak RSS {res['peak_rss_mb']:.0f} MB")
    out = os.path.abspath(args.out)
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(out), suffix=".json")
    with os.fdopen(fd, "w") as fh:
        json.dump(res, fh, indent=2)
    os.replace(tmp, out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
