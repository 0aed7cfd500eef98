"""The plant's year (``heliotwin year``), measured as issue 43 asks.

1. **Weather formats x receivers** (generated radial fields of ``--heliostats`` with a cylinder, a flat and a
   tilted-flat receiver): per plant and weather file -- pvlib's clear sky, an EPW, a SAM CSV in both header
   layouts (``DNI`` and ``Beam``), an NSRDB PSM3 file and a plain ``time,dni`` CSV generated in code at the plant's
   site, and pvlib's own shipped TMY3 (``723170TYA.CSV``) and TMY2 (``12839.tm2``) at their sites -- the whole
   command's wall time and peak memory (summed over its processes), the share of the file's DNI energy below
   the horizon, and the interpolation's per-heliostat error against the field model evaluated directly at
   ``--check-hours`` drawn daylight hours (median, p95, field total).
2. **Simulated calibrated plants** (``heliotwin simulate`` + ``calibrate`` at each of ``--sizes``): the whole
   ``year`` command (time, memory), and on the first one the energy each heliostat loses to tracking -- the
   twin's expected loss over its posterior -- against the same figure with the simulator's true kinematics as the
   heliostat's motion (:func:`heliotwin.raytrace.annual.tracking_tables` with the truth as the variant).
3. **Against SolarPILOT** (``../shared/tools/solarpilot``, run as a separate program): its optical efficiency
   table of the reference layout (``../shared/data/solarpilot-reference/layout-500.csv``) interpolated over the
   daylight hours of the tools' own weather file, DNI-weighted, beside our year of the same plant and file.
   SolarPILOT azimuths (clockwise from north) are PAINT's as ``180 - az``.

Usage::

    python benchmarks/bench_year.py --out /tmp/year [--heliostats 200] [--check-hours 100] [--sizes 300,2000]

Writes ``<out>/year.json`` and prints the tables. Times depend on the machine and its load (recorded).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pvlib
import torch
from scipy.interpolate import RegularGridInterpolator

from heliotwin.field.layout import plant_from_layout
from heliotwin.io.report import write_json
from heliotwin.io.scenario import load_scenario, save_scenario
from heliotwin.io.weather import read_dni_series, weather_for_year
from heliotwin.optimise.testbed import generated_plant
from heliotwin.raytrace import annual as A
from heliotwin.site import Site
from heliotwin.sun import solar_position
from heliotwin.workflows.year import YearSettings, plant_year

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))
from helpers.field import PLANT_TOML  # noqa: E402
from helpers.weather import clear_dni, hour_means, write_epw, write_psm3, write_sam  # noqa: E402

SHARED = HERE.parents[1] / "shared"
TOOLS = SHARED / "tools" / "solarpilot"
REF = SHARED / "data" / "solarpilot-reference"
PVLIB_DATA = Path(pvlib.__file__).parent / "data"
JUELICH = {"name": "Juelich", "lat": 50.9134, "lon": 6.3878, "alt": 87.0, "tz": 1}


def run_measured(cmd: list[str]) -> dict:
    """Run ``cmd``; wall time [s] and the peak of its processes' summed resident memory [MB] (sampled every 0.25 s
    from /proc, no helper processes that would count as load)."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak = 0
    while p.poll() is None:
        peak = max(peak, _tree_rss(p.pid))
        time.sleep(0.25)
    out, err = p.communicate()
    return {"rc": p.returncode, "wall_s": time.perf_counter() - t0, "peak_mb": peak / 2 ** 20,
            "stderr_tail": err.strip().splitlines()[-1:] if p.returncode else []}


def _tree_rss(pid: int) -> int:
    kids: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as fh:
                    kids.setdefault(int(fh.read().rsplit(")", 1)[1].split()[1]), []).append(int(d))
            except OSError:
                pass
    total, todo = 0, [pid]
    while todo:
        q = todo.pop()
        try:
            with open(f"/proc/{q}/statm") as fh:
                total += int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except OSError:
            pass
        todo += kids.get(q, [])
    return total


def _year_cmd(scenario: Path, weather: Path | None, json_path: Path, check_hours: int) -> list[str]:
    cmd = ["heliotwin", "year", "--scenario", str(scenario), "--json", str(json_path), "--quiet",
           "--check-hours", str(check_hours)]
    return cmd + (["--weather", str(weather)] if weather else [])


# --------------------------------------------------------------------------------------------- 1. formats
def weather_files(folder: Path) -> list[tuple[str, Path | None, dict]]:
    """(name, file or None for clear sky, site) of every format the year reads."""
    starts = pd.date_range("2001-01-01", periods=8760, freq="1h")
    means, at30 = hour_means(JUELICH, starts)
    plain = folder / "plain.csv"
    utc = pd.date_range("2023-01-01", periods=8760, freq="1h", tz="UTC")
    pd.DataFrame({"time": utc.strftime("%Y-%m-%dT%H:%M:%SZ"), "dni": clear_dni(JUELICH, utc).round(1)}).to_csv(
        plain, index=False)
    tmy3 = pvlib.iotools.read_tmy3(str(PVLIB_DATA / "723170TYA.CSV"), map_variables=True)[1]
    tmy2 = pvlib.iotools.read_tmy2(str(PVLIB_DATA / "12839.tm2"))[1]
    return [
        ("clear sky", None, JUELICH),
        ("EPW", write_epw(folder / "w.epw", JUELICH, starts, means), JUELICH),
        ("SAM CSV (Source, DNI)", write_sam(folder / "sam.csv", JUELICH, starts, means), JUELICH),
        ("SAM CSV (Location, Beam)", write_sam(folder / "sam_beam.csv", JUELICH, starts, means, "location", "Beam"),
         JUELICH),
        ("NSRDB PSM3", write_psm3(folder / "psm3.csv", JUELICH, starts, at30), JUELICH),
        ("time,dni CSV (UTC)", plain, JUELICH),
        ("TMY3 (pvlib 723170TYA)", PVLIB_DATA / "723170TYA.CSV",
         {"lat": tmy3["latitude"], "lon": tmy3["longitude"], "alt": tmy3["altitude"]}),
        ("TMY2 (pvlib 12839)", PVLIB_DATA / "12839.tm2",
         {"lat": tmy2["latitude"], "lon": tmy2["longitude"], "alt": tmy2["altitude"]}),
    ]


def formats(out: Path, heliostats: int, check_hours: int) -> list[dict]:
    """Part 1: every weather file on the cylinder plant, clear sky and the EPW on the flat and tilted ones."""
    rows = []
    for receiver in ("cylinder", "flat", "tilted-flat"):
        plant, atm = generated_plant("radial", heliostats, receiver)
        for name, weather, site in weather_files(out):
            if receiver != "cylinder" and name not in ("clear sky", "EPW"):
                continue
            sited = replace(plant, site=Site(float(site["lat"]), float(site["lon"]), float(site["alt"]), "bench"))
            tag = f"{receiver}-{len(rows)}"
            path = save_scenario(sited, out / f"{tag}.h5", extras=atm.to_extras())
            m = run_measured(_year_cmd(path, weather, out / f"{tag}.json", check_hours))
            rep = json.loads((out / f"{tag}.json").read_text()) if m["rc"] == 0 else {}
            check = rep.get("interpolation") or {}
            rows.append({"receiver": receiver, "weather": name, "heliostats": heliostats, **m,
                         "annual_energy_mwh": rep.get("annual_energy_mwh"),
                         "field_efficiency": rep.get("field_efficiency"),
                         "dni_share_below_horizon": rep.get("dni_share_below_horizon"),
                         "site_offset_km": (rep.get("weather") or {}).get("site_offset_km"),
                         "convention": rep.get("time_convention"), "checked_hours": check.get("checked_hours"),
                         "median_error": check.get("median_error"), "p95_error": check.get("p95_error"),
                         "field_error": check.get("field_error")})
            _print_format(rows[-1])
    return rows


def _pct(v) -> str:
    return "   -  " if v is None else f"{100 * v:6.2f}"


def _print_format(r: dict) -> None:
    pct = _pct
    print(f"{r['receiver']:12s} {r['weather']:26s} rc {r['rc']} {r['wall_s']:6.1f} s {r['peak_mb']:6.0f} MB | "
          f"below horizon {pct(r['dni_share_below_horizon'])} % | interp median {pct(r['median_error'])} % p95 "
          f"{pct(r['p95_error'])} % field {pct(r['field_error'])} % | eff {r['field_efficiency'] or 0:.4f}",
          flush=True)


# ------------------------------------------------------------------------------------ 2. simulated plants
def simulated(out: Path, sizes: list[int], check_hours: int) -> dict:
    """Part 2: simulate + calibrate + year per size; the tracking loss against the truth on the first."""
    runs, truth = [], None
    for n in sizes:
        folder, cal = out / f"sim{n}", out / f"sim{n}.h5"
        subprocess.run(["heliotwin", "simulate", "--heliostats", str(n), "--years", "2", "--seed", "5", "--out",
                        str(folder), "--quiet"], check=True)
        subprocess.run(["heliotwin", "calibrate", "--paint", str(folder), "-o", str(cal), "--quiet"], check=True)
        m = run_measured(_year_cmd(cal, None, out / f"sim{n}.json", check_hours if n == sizes[0] else 0))
        rep = json.loads((out / f"sim{n}.json").read_text()) if m["rc"] == 0 else {}
        runs.append({"heliostats": n, **m, "annual_energy_mwh": rep.get("annual_energy_mwh"),
                     "tracking_loss_mwh": rep.get("tracking_loss_mwh"), "interpolation": rep.get("interpolation"),
                     "tables_processes": rep.get("tables_processes")})
        print(f"simulated {n}: year {m['wall_s']:.1f} s, {m['peak_mb']:.0f} MB, energy "
              f"{rep.get('annual_energy_mwh', float('nan')):.1f} MWh, tracking loss "
              f"{rep.get('tracking_loss_mwh', float('nan')):.1f} MWh", flush=True)
        if truth is None:
            truth = tracking_against_truth(cal, folder / "truth.h5")
    return {"runs": runs, "tracking_vs_truth": truth}


def tracking_against_truth(cal: Path, truth_path: Path) -> dict:
    """Per calibrated heliostat: the twin's expected tracking loss (posterior) and the loss with the simulator's
    true kinematics moving on the learned kinematics' motor steps, same tables and hours."""
    sc = load_scenario(cal)
    res = plant_year(sc, settings=YearSettings(nproc=1))
    t = res.tables
    rows = t["calibrated_rows"]
    plant = sc.plant
    index = {h: i for i, h in enumerate(load_scenario(truth_path).plant.field.ids)}
    true_kin = load_scenario(truth_path).plant.field.kinematics.index(
        torch.tensor([index[plant.field.ids[int(r)]] for r in rows])).to(dtype=torch.float64)
    learned = plant.field.kinematics.index(rows).to(dtype=torch.float64)
    ratio = A.tracking_tables(plant, t["suns"], t["aim"], rows, learned, [true_kin])[0]  # [h, S]
    over_cos = t["efficiency"] / t["cosine"].clamp_min(1e-12)
    true_loss = (t["mirror_area"][rows] * t["hours"].sums(rows, over_cos[rows] * (1.0 - ratio)) / 1e6).numpy()
    hel = res.scenario.learned["year"]["heliostats"]
    expected = np.asarray(hel["tracking_loss_mwh"])[rows.numpy()]
    energy = np.asarray(hel["energy_mwh"])[rows.numpy()]
    diff = expected - true_loss
    out = {"heliostats": int(rows.numel()), "expected_total_mwh": float(expected.sum()),
           "truth_total_mwh": float(true_loss.sum()), "energy_total_mwh": float(energy.sum()),
           "median_abs_difference_mwh": float(np.median(np.abs(diff))),
           "p95_abs_difference_mwh": float(np.quantile(np.abs(diff), 0.95)),
           "median_difference_mwh": float(np.median(diff)),
           "median_truth_loss_share": float(np.median(true_loss / np.maximum(energy, 1e-12))),
           "median_expected_loss_share": float(np.median(expected / np.maximum(energy, 1e-12))),
           "spearman": float(pd.Series(expected).corr(pd.Series(true_loss), method="spearman"))}
    print("tracking loss, expected (posterior) vs truth:", json.dumps(out), flush=True)
    return out


# ------------------------------------------------------------------------------------------ 3. SolarPILOT
_SOLARPILOT_TABLE = """
import json, sys
sys.path.insert(0, {tools!r})
import common, solarpilot_reference as R
cfg = dict(lat=common.SITE["lat"], lon=common.SITE["lon"], tz=common.SITE["tz"], elev=common.SITE["elev_m"],
           h_tower=common.TOWER["h_tower"], rec_radius=common.RECEIVER["radius"],
           rec_height=common.RECEIVER["height"], absorptance=1.0, helio_width=common.HELIO["width"],
           helio_height=common.HELIO["height"], slope_error=common.HELIO["slope_error_rad"],
           reflectance=common.HELIO["reflectance"], c_atm=common.ATM["c_atm"], dni=common.DNI)
c = R.copilot_setup(cfg)
c.assign_layout(common.load_layout_csv({layout!r}), 1)
az, el, eff = c.efficiency_table({n_az}, {n_el})
print(json.dumps({{"azimuth_deg": az.tolist(), "elevation_deg": el.tolist(), "efficiency": eff.tolist()}}))
"""


def against_solarpilot(out: Path, n_az: int = 24, n_el: int = 10) -> dict | None:
    """Part 3: SolarPILOT's annual optical efficiency (its table over the weather's hours) beside ours."""
    weather = TOOLS / "weather_50.9134_6.3878_+1.0.csv"
    if not (TOOLS / "spcopilot.py").exists() or not weather.exists():
        print("SolarPILOT tools not found: part 3 skipped", flush=True)
        return None
    toml = out / "sp-plant.toml"
    toml.write_text(PLANT_TOML)
    plant, atm = plant_from_layout(REF / "layout-500.csv", toml)
    path = save_scenario(plant, out / "sp.h5", extras=atm.to_extras())
    m = run_measured(_year_cmd(path, weather, out / "sp.json", 0))
    ours = json.loads((out / "sp.json").read_text())
    t0 = time.perf_counter()
    script = _SOLARPILOT_TABLE.format(tools=str(TOOLS), layout=str(REF / "layout-500.csv"), n_az=n_az, n_el=n_el)
    table = json.loads(subprocess.run([sys.executable, "-c", script], check=True, capture_output=True,
                                      text=True).stdout.strip().splitlines()[-1])
    sp_seconds = time.perf_counter() - t0
    wy = weather_for_year(read_dni_series(str(weather)), int(ours["year"]))
    s = plant.site
    az, el = solar_position(wy.times, s.latitude_deg, s.longitude_deg, s.altitude_m)
    up = (el > 0).numpy() & (np.asarray(wy.dni) > 0)
    q = (np.asarray(wy.dni) * np.asarray(wy.hours))[up]
    sp_az = (180.0 - np.degrees(az.numpy()[up])) % 360.0
    sp_el = np.degrees(el.numpy()[up])
    taz, tel = np.asarray(table["azimuth_deg"]), np.asarray(table["elevation_deg"])
    eff = np.asarray(table["efficiency"])
    order = np.argsort(taz)  # periodic in azimuth: one column repeated on each side
    taz, eff = taz[order], eff[order]
    taz = np.concatenate([taz[-1:] - 360.0, taz, taz[:1] + 360.0])
    eff = np.concatenate([eff[-1:], eff, eff[:1]])
    f = RegularGridInterpolator((taz, tel), eff, bounds_error=False, fill_value=None)
    sp_eff = f(np.stack([sp_az, np.clip(sp_el, tel.min(), tel.max())], -1))
    sp_annual = float((sp_eff * q).sum() / q.sum())
    res = {"layout": "layout-500.csv", "weather": weather.name, "ours_field_efficiency": ours["field_efficiency"],
           "solarpilot_field_efficiency": sp_annual, "relative_difference": ours["field_efficiency"] / sp_annual - 1,
           "ours_wall_s": m["wall_s"], "solarpilot_table_s": sp_seconds, "table": f"{n_az} x {n_el}",
           "below_table_elevation_share": float(q[sp_el < tel.min()].sum() / q.sum())}
    print("against SolarPILOT:", json.dumps(res), flush=True)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--heliostats", type=int, default=200)
    ap.add_argument("--check-hours", type=int, default=100)
    ap.add_argument("--sizes", default="300,2000", help="simulated calibrated plants (comma list; '' to skip)")
    ap.add_argument("--skip", default="", help="parts to skip: formats, simulated, solarpilot (comma list)")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    skip = set(filter(None, a.skip.split(",")))
    result = {"machine": {"cpus": os.cpu_count(), "load_average": os.getloadavg()}}
    if "formats" not in skip:
        result["formats"] = formats(out, a.heliostats, a.check_hours)
    sizes = [int(s) for s in a.sizes.split(",") if s.strip()]
    if sizes and "simulated" not in skip:
        result["simulated"] = simulated(out, sizes, a.check_hours)
    if "solarpilot" not in skip:
        result["solarpilot"] = against_solarpilot(out)
    write_json(out / "year.json", result)
    print(f"wrote {out / 'year.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
