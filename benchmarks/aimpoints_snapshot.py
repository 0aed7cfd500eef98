"""The aim points of a reduced test bed, saved to (or compared with) an ``.npz``: proof that a change of the aim-point
code keeps its results bit for bit.

Every (layout, receiver) pair of ``bench_aimpoints.PAIRS`` at ``--heliostats`` (60) on ``--towers`` (30, 55, 120 m),
the test bed's three suns and limit fractions (0.6, 0.75, 0.9 x the equator peak): the optimised aim points
(:func:`heliotwin.optimise.aimpoints.optimise_aimpoints`, cold), their power and peak; on the first plant of each
receiver also a warm start from the previous sun's result (``start_aim``, multipliers, margin, predicted start), a
target shape, the field-gradient correction and both baselines. ::

    OMP_NUM_THREADS=1 python benchmarks/aimpoints_snapshot.py --save /tmp/aim_base.npz      # at the old commit
    OMP_NUM_THREADS=1 python benchmarks/aimpoints_snapshot.py --compare /tmp/aim_base.npz   # after the change

``--compare`` prints every case that differs (``torch.equal`` on the aim points, equality of power and peak) and
exits 1 if any does.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_aimpoints import PAIRS, TESTBED_TIMES  # noqa: E402

from heliotwin.optimise.aimpoints import (  # noqa: E402
    AimSettings,
    aiming_factor,
    calibrate_images,
    image_size_priority,
    optimise_aimpoints,
    uniform_target,
)
from heliotwin.optimise.testbed import generated_plant  # noqa: E402
from heliotwin.sun import direction_from_time  # noqa: E402


def _sun(plant, text):
    s = plant.site
    return direction_from_time(pd.DatetimeIndex([pd.Timestamp(text)]), s.latitude_deg, s.longitude_deg,
                               s.altitude_m)[0]


def snapshot(heliostats: int, towers, fractions) -> dict:
    """``{case name: array}``: aim points [H, 3] and ``[power, peak]`` per case."""
    out = {}

    def keep(name, r):
        out[f"{name}/aim"] = r.aim.detach().cpu().numpy()
        out[f"{name}/power_peak"] = np.array([r.power_w, r.peak_flux_w_m2])
        print(f"{name}: power {r.power_w:.6f} W, peak {r.peak_flux_w_m2:.6f} W/m2", flush=True)

    extras_done = set()
    for tower in towers:
        for layout, receiver in PAIRS:
            plant, atm = generated_plant(layout, heliostats, receiver, tower=tower)
            label = f"{layout}/{receiver}/{tower:g}"
            prev = None
            for text in TESTBED_TIMES.split(","):
                sun = _sun(plant, text)
                if float(sun[2]) < np.sin(np.radians(5.0)):
                    continue
                model, eq = calibrate_images(plant, sun, atm, (20, 48))
                for f in fractions:
                    limit = f * float(eq.flux.max())
                    best = optimise_aimpoints(plant, sun, limit, AimSettings(), atmosphere=atm, equator=eq,
                                              model=model)
                    keep(f"{label}/{text}/{f}", best)
                if receiver in extras_done:
                    continue
                limit = 0.75 * float(eq.flux.max())
                if prev is not None:
                    warm = optimise_aimpoints(plant, sun, limit, atmosphere=atm, start_aim=prev.aim,
                                              start_multipliers=prev.multipliers, start_margin=prev.parameter)
                    keep(f"{label}/{text}/warm", warm)
                    pred = optimise_aimpoints(plant, sun, limit, atmosphere=atm, start_aim=prev.aim,
                                              start_multipliers=prev.multipliers, start_margin=prev.parameter,
                                              start_field=prev.exact)
                    keep(f"{label}/{text}/warm-predicted", pred)
                    keep(f"{label}/{text}/target", optimise_aimpoints(
                        plant, sun, limit, AimSettings(iterations=100, rounds=3), atmosphere=atm,
                        target=uniform_target(eq.flux), equator=eq, model=model))
                    keep(f"{label}/{text}/field-gradient", optimise_aimpoints(
                        plant, sun, limit, AimSettings(field_gradient=True, iterations=100, rounds=3),
                        atmosphere=atm, equator=eq, model=model))
                    keep(f"{label}/{text}/aiming-factor", aiming_factor(plant, sun, limit, atmosphere=atm,
                                                                        model=model, steps=4))
                    keep(f"{label}/{text}/image-size-priority", image_size_priority(plant, sun, limit,
                                                                                    atmosphere=atm, model=model,
                                                                                    steps=4))
                    keep(f"{label}/{text}/standby", optimise_aimpoints(
                        plant, sun, 0.2 * float(eq.flux.max()), AimSettings(iterations=60, rounds=2),
                        atmosphere=atm, equator=eq, model=model))
                    extras_done.add(receiver)
                prev = optimise_aimpoints(plant, sun, limit, atmosphere=atm, equator=eq, model=model)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--save")
    ap.add_argument("--compare")
    ap.add_argument("--heliostats", type=int, default=60)
    ap.add_argument("--towers", default="30,55,120")
    ap.add_argument("--fractions", default="0.6,0.75,0.9")
    args = ap.parse_args(argv)
    snap = snapshot(args.heliostats, [float(t) for t in args.towers.split(",")],
                    [float(f) for f in args.fractions.split(",")])
    if args.save:
        np.savez(args.save, **snap)
        print(f"saved {len(snap) // 2} cases to {args.save}")
    if args.compare:
        ref = dict(np.load(args.compare))
        bad = [k for k in ref if k not in snap or not torch.equal(torch.as_tensor(ref[k]), torch.as_tensor(snap[k]))]
        bad += [k for k in snap if k not in ref]
        for k in bad:
            print(f"DIFFERS: {k}")
        print(f"compared {len(ref) // 2} cases: {len(ref) // 2 - len({k.rsplit('/', 1)[0] for k in bad})} equal "
              f"bit for bit, {len({k.rsplit('/', 1)[0] for k in bad})} differ")
        return 1 if bad else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
