"""Every calibration method under every split protocol on the real PAINT records (docs/methods.md).

For each method (``lm``, ``gradient``, ``hybrid``, ``mlp``; ``images`` where flux images exist), with and
without the plant prior (learned from the folder's other heliostats; methods without one say ``n/a``),
each split (chrono, online, isolation, region, random and PAINT's azimuth / solstice / balanced /
high-variance) and each training size: the median over heliostats of each heliostat's mean test error
[mrad], the networks kept (hybrid, mlp) and the fit time. Every setting a method uses is chosen inside the
records it may see (its validation records are carved out of ``--train``); the test records are scored
only.

Reference protocols, each network beside ``lm`` on the same records:

* MLP paper: ``random`` split, 200 training records per heliostat (every heliostat with >= 230 records);
* hybrid paper: ``isolation`` split, 20 training + 20 test records (every heliostat with >= 50 records);
* images (full run only): AA39 (the one heliostat with flux images), chrono, 10 + 8 records.

Usage::

    python benchmarks/bench_methods.py --quick            # a few splits and sizes (minutes on 2 cores)
    python benchmarks/bench_methods.py                    # everything (an idle machine; the lead runs it)
        [--paint ../shared/data/paint] [--out docs/methods] [--threads 2]

Writes ``<out>.json``, ``<out>.md`` (readable tables) and ``<out>.png`` (error vs training size per split).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_PAINT = ROOT.parent / "shared" / "data" / "paint"

FULL = {"methods": ["lm", "gradient", "hybrid", "mlp"], "priors": ["none", "plant"],
        "splits": ["chrono", "online", "isolation", "region", "random", "azimuth", "solstice", "balanced",
                   "high_variance"],
        "sizes": [10, 20, 30, 60]}
QUICK = {"methods": ["lm", "hybrid", "mlp"], "priors": ["none"], "splits": ["chrono", "random"], "sizes": [30]}
TEST = 30


def _row(rep: dict, model) -> dict:
    ov = rep["overall"]
    info = ov.get("method_info") or {}
    per = {h: r.get("mean_test_mrad") for h, r in rep["heliostats"].items() if r.get("status") == "ok"}
    nets = {h: r.get("method_info") for h, r in rep["heliostats"].items()
            if r.get("status") == "ok" and r.get("method_info")}
    return {"median_mrad": ov.get("median_of_mean_test_mrad"), "mean_mrad": ov.get("mean_of_mean_test_mrad"),
            "n_heliostats": ov.get("n_heliostats"), "fit_seconds": ov.get("fit_seconds"),
            "networks_kept": info.get("heliostats_using_network"), "per_heliostat_mean_test_mrad": per,
            "per_heliostat_method_info": nets}


def _supports_prior(base, method: str) -> bool:
    """Whether the run's own validation accepts a plant prior for ``method`` (the refusal is the one answer)."""
    from heliotwin.calibrate.protocol.config import validate_config
    from heliotwin.errors import HeliotwinError

    try:
        validate_config(replace(base, method=method, prior="plant"))
    except HeliotwinError:
        return False
    return True


def _run(base, ds, **changes) -> dict:
    from heliotwin.calibrate.protocol.pipeline import run_calibration

    t = time.perf_counter()
    rep, model, _ = run_calibration(replace(base, **changes), ds)
    out = _row(rep, model)
    out["seconds"] = time.perf_counter() - t
    return out


def _fmt(x, digits=2):
    return "-" if x is None else f"{x:.{digits}f}"


def _cell(r: dict | None) -> str:
    if r is None:
        return "-"
    if r.get("unsupported"):
        return "n/a"
    if r.get("error"):
        return "error"
    kept = r.get("networks_kept")
    extra = f" ({kept}/{r['n_heliostats']})" if kept is not None else ""
    return _fmt(r["median_mrad"]) + extra


def recommend(out: dict, alpha: float = 0.05) -> list[dict]:
    """Per split and training size: the column the project recommends, by a rule fixed before the run.

    ``lm`` (no prior) is the default; another column replaces it only where it is better on the same heliostats
    by a one-sided Wilcoxon signed-rank test on the per-heliostat mean test errors (p < ``alpha``) and has the
    lower median; among several such, the lowest median. Nothing is chosen from the test records of one
    heliostat: the test compares whole-heliostat errors across the folder.
    """
    from scipy.stats import wilcoxon

    g = out["grid"]
    rows = []
    for split in g["splits"]:
        for n in g["sizes"]:
            ref = out["table"].get(f"lm/none/{split}/{n}") or {}
            base = ref.get("per_heliostat_mean_test_mrad") or {}
            if not base:
                continue
            best, why = "lm", "default"
            best_med = ref.get("median_mrad")
            for m in g["methods"]:
                for pr in g["priors"]:
                    key = f"{m}/{pr}/{split}/{n}"
                    cell = out["table"].get(key) or {}
                    per = cell.get("per_heliostat_mean_test_mrad") or {}
                    common = [h for h in base if h in per and base[h] is not None and per[h] is not None]
                    if (m, pr) == ("lm", "none") or len(common) < 6 or cell.get("median_mrad") is None:
                        continue
                    diff = [per[h] - base[h] for h in common]
                    if all(abs(d) < 1e-12 for d in diff):
                        continue
                    p_value = float(wilcoxon(diff, alternative="less").pvalue)
                    if p_value < alpha and cell["median_mrad"] < (best_med or float("inf")):
                        best = m + ("" if pr == "none" else " +prior")
                        best_med = cell["median_mrad"]
                        why = f"better than lm on {sum(d < 0 for d in diff)}/{len(diff)} heliostats, p={p_value:.3f}"
            rows.append({"split": split, "size": n, "recommended": best, "median_mrad": best_med, "why": why})
    return rows


def markdown(out: dict) -> str:
    """The readable tables of a benchmark result."""
    g = out["grid"]
    cols = [(m, p) for m in g["methods"] for p in g["priors"]]
    lines = ["# Calibration methods on the real PAINT records", "",
             f"Generated by `python benchmarks/bench_methods.py {out.get('argv', '--quick' if out['quick'] else '')}`"
             " "
             f"on `{out['paint']}` ({out['threads']} threads, {out['seconds']:.0f} s). Median over heliostats of "
             f"each heliostat's mean test error [mrad], {TEST} test records per heliostat (fewer where a heliostat "
             "has fewer); for networks, `(k/H)` = heliostats that kept their network (validation inside the "
             "training records decides). `n/a`: the method has no plant prior; `-`: not run.", "",
             "## Every method, split and training size", "",
             "| split | N | " + " | ".join(f"{m}{'' if p == 'none' else ' +prior'}" for m, p in cols) + " |",
             "|---|---|" + "---|" * len(cols)]
    for split in g["splits"]:
        for n in g["sizes"]:
            cells = [_cell(out["table"].get(f"{m}/{p}/{split}/{n}")) for m, p in cols]
            lines.append(f"| {split} | {n} | " + " | ".join(cells) + " |")
    lines += ["", "## Reference protocols (each network beside lm on the same records)", "",
              "| protocol | heliostats | lm [mrad] | network [mrad] | kept | per heliostat (lm / network) |",
              "|---|---|---|---|---|---|"]
    for name, ref in out["reference"].items():
        if ref.get("skipped"):
            lines.append(f"| {name} | - | - | - | - | {ref['skipped']} |")
            continue
        a, b = ref["lm"], ref["network"]
        per = ", ".join(f"{h} {_fmt(a['per_heliostat_mean_test_mrad'].get(h))}/"
                        f"{_fmt(b['per_heliostat_mean_test_mrad'].get(h))}" for h in a["per_heliostat_mean_test_mrad"])
        kept = "-" if b.get("networks_kept") is None else f"{b['networks_kept']}/{b['n_heliostats']}"
        lines.append(f"| {name} | {a['n_heliostats']} | {_fmt(a['median_mrad'])} | {_fmt(b['median_mrad'])} | "
                     f"{kept} | {per} |")
    nets = out.get("networks", {})
    if nets:
        lines += ["", "## Networks: validation error before / after fine-tuning (mlp, chrono)", "",
                  "| heliostat | rigid validation | after pretraining | after fine-tuning | kept |",
                  "|---|---|---|---|---|"]
        for h, r in nets.items():
            lines.append(f"| {h} | {_fmt(r.get('rigid_validation_mrad'))} | "
                         f"{_fmt(r.get('validation_after_pretraining_mrad'))} | "
                         f"{_fmt(r.get('validation_after_finetuning_mrad'))} | {r.get('uses_network')} |")
    rec = recommend(out)
    if rec:
        lines += ["", "## Recommended method per situation", "",
                  "Rule (fixed before the run, :func:`recommend`): `lm` unless another column beats it on the same "
                  "heliostats (one-sided Wilcoxon signed-rank on per-heliostat mean test errors, p < 0.05) with a "
                  "lower median.", "", "| split | N | recommended | median [mrad] | why |", "|---|---|---|---|---|"]
        lines += [f"| {r['split']} | {r['size']} | {r['recommended']} | {_fmt(r['median_mrad'])} | {r['why']} |"
                  for r in rec]
    lines += ["", "## Notes", "",
              "* `mlp`'s first version failed on real records (412 mrad validation error after pretraining) because "
              "its network output the motor steps as a fraction of the actuator range (~10^4-10^5 increments, one "
              "increment ~0.02 mrad of axis rotation): useful answers need a relative precision of ~10^-5, a small "
              "net trained a few hundred steps reaches ~10^-2. Learning the rigid body on top of the nominal "
              "geometry (`base=\"nominal\"`, affine skip connection) still left 100-270 increments at the range's "
              "edges (0.3-1.4 mrad worse than its rigid body on validation). The default network adds its steps to "
              "the heliostat's own rigid body (`base=\"rigid\"`): pretraining on that rigid body's samples is exact "
              "(the 'after pretraining' column equals the rigid one), fine-tuning runs in growing cycles with "
              "rehearsal of the pretraining samples.",
              "* `mlp` and `hybrid` fall back to exactly `lm` (bagged, train + validation) wherever their network "
              "does not beat the rigid body significantly on the validation records inside `--train`.",
              "* Timings come from the machine named above; on a shared machine they are upper bounds.",
              "", "![error vs training size](methods.png)", ""]
    return "\n".join(lines)


def figure(out: dict, path: str) -> None:
    """Median test error vs training size, one panel per split, one line per method (+prior dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    g = out["grid"]
    n = len(g["splits"])
    cols = min(n, 3)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3 * rows), squeeze=False)
    for ax, split in zip(axes.flat, g["splits"]):
        for m in g["methods"]:
            for p in g["priors"]:
                pts = [(s, out["table"].get(f"{m}/{p}/{split}/{s}", {}).get("median_mrad")) for s in g["sizes"]]
                pts = [(s, v) for s, v in pts if v is not None]
                if pts:
                    ax.plot(*zip(*pts), marker="o", ls="-" if p == "none" else "--",
                            label=m + ("" if p == "none" else " +prior"))
        ax.set_title(split)
        ax.set_xlabel("training records N")
        ax.set_ylabel("median test error [mrad]")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def reference(base, ds, quick: bool) -> dict:
    """The papers' protocols: each network beside lm on the same records."""
    counts = ds.records.counts()
    ids = list(ds.records.heliostat_ids)
    out = {}
    many = [h for h, c in zip(ids, counts.tolist()) if c >= 230]
    if many:
        cfg = dict(split="random", train=200, test=None, heliostats=many, min_records=230)
        out["mlp: random, 200 train"] = {"heliostats": many, "lm": _run(base, ds, method="lm", **cfg),
                                         "network": _run(base, ds, method="mlp", **cfg)}
    else:
        out["mlp: random, 200 train"] = {"skipped": "no heliostat with >= 230 records"}
    cfg = dict(split="isolation", train=20, test=20, min_records=50)
    out["hybrid: isolation, 20 + 20"] = {"lm": _run(base, ds, method="lm", **cfg),
                                         "network": _run(base, ds, method="hybrid", **cfg)}
    if not quick:
        out["mlp: isolation, 20 + 20"] = {"lm": out["hybrid: isolation, 20 + 20"]["lm"],
                                          "network": _run(base, ds, method="mlp", **cfg)}
    if not quick:
        cfg = dict(split="chrono", train=10, test=8, heliostats=["AA39"], min_records=10)
        out["images: AA39, chrono 10 + 8"] = {"lm": _run(base, ds, method="lm", **cfg),
                                              "network": _run(base, ds, method="images", **cfg)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paint", default=str(DEFAULT_PAINT))
    ap.add_argument("--out", default=str(ROOT / "docs" / "methods"), help="path stem of the .json/.md/.png")
    ap.add_argument("--quick", action="store_true", help="a few splits and sizes (minutes on 2 cores)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--methods", help="comma-separated subset of the grid's methods")
    ap.add_argument("--splits", help="comma-separated subset of the grid's splits")
    ap.add_argument("--sizes", help="comma-separated training sizes")
    ap.add_argument("--no-reference", action="store_true", help="skip the reference protocols")
    ap.add_argument("--resume", action="store_true",
                    help="keep the cells <out>.json already holds (same grid cell keys) and run only the others; "
                         "the JSON is rewritten after every cell, so an interrupted run loses at most one cell")
    args = ap.parse_args(argv)
    import torch

    from heliotwin.calibrate.protocol.pipeline import RunConfig
    from heliotwin.io.paint import load_paint
    from heliotwin.io.report import write_json

    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    ds = load_paint(args.paint)
    grid = dict(QUICK if args.quick else FULL)
    for key in ("methods", "splits", "sizes"):
        if getattr(args, key):
            grid[key] = [int(v) if key == "sizes" else v for v in getattr(args, key).split(",")]
    base = RunConfig(paint=args.paint, test=TEST, min_records=50)
    out = {"paint": args.paint, "quick": args.quick, "threads": args.threads, "grid": grid, "table": {},
           "argv": " ".join(sys.argv[1:] if argv is None else argv)}
    done = {}
    if args.resume and Path(args.out + ".json").exists():
        old = json.loads(Path(args.out + ".json").read_text())
        done = {k: v for k, v in old.get("table", {}).items() if not v.get("error")}
        out["seconds_before"] = old.get("seconds", 0.0) + old.get("seconds_before", 0.0)
    for split in grid["splits"]:
        for n in grid["sizes"]:
            for m in grid["methods"]:
                for p in grid["priors"]:
                    key = f"{m}/{p}/{split}/{n}"
                    if key in done:
                        out["table"][key] = done[key]
                        continue
                    if p == "plant" and not _supports_prior(base, m):
                        out["table"][key] = {"unsupported": True}
                        continue
                    try:
                        out["table"][key] = _run(base, ds, method=m, split=split, train=n, prior="run" if p == "none"
                                                 else "plant")
                    except Exception as exc:  # one failing cell must not lose the others
                        out["table"][key] = {"error": f"{type(exc).__name__}: {exc}"}
                    print(key, _cell(out["table"][key]), flush=True)
                    write_json(args.out + ".json", dict(out, seconds=time.perf_counter() - t0))
    mlp_chrono = out["table"].get(f"mlp/none/chrono/{grid['sizes'][-1]}", {})
    out["networks"] = mlp_chrono.get("per_heliostat_method_info", {})
    out["reference"] = {} if args.no_reference else reference(base, ds, args.quick)
    for name, ref in out["reference"].items():
        if not ref.get("skipped"):
            print(name, "lm", _fmt(ref["lm"]["median_mrad"]), "network", _cell(ref["network"]), flush=True)
    out["seconds"] = time.perf_counter() - t0
    write_json(args.out + ".json", out)
    Path(args.out + ".md").write_text(markdown(out))
    figure(out, args.out + ".png")
    print(f"wrote {args.out}.json/.md/.png ({out['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
