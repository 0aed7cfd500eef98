"""Misuse cases of the daily loop's outputs that the "loop" helper owns (issue 41 items 5 and 8, issue 42 items 2
and 3): standby aim points reported and acted on, an honest --confidence, open alarms that persist, and the
plant's own clock. Each case is clean only when the fixed behaviour is seen."""
from __future__ import annotations

import json
import shutil

from fuzz_daily import Case, Verdict, heliotwin


def _plant(ws, folder):
    plant = folder / "p.h5"
    shutil.copy(ws.small["cal"], plant)
    return plant


def _daily(ws, folder, *extra):
    plant = _plant(ws, folder)
    out = folder / "day.json"
    r = heliotwin("daily", "--plant", plant, "--paint", ws.small["base"], "--json", out, *extra, cwd=folder,
                  timeout=600)
    report = json.loads(out.read_text()) if out.exists() else {}
    return r, report, plant


def standby_needs_a_person(ws, folder) -> Verdict:
    r, rep, _ = _daily(ws, folder, "--day", "2021-12-01", "--peak-limit", 1000)
    aim = rep.get("aimpoints") or {}
    standby = aim.get("standby_heliostats")
    # the optimiser holds 1 kW/m2 by aiming the light off the receiver (standby or spilled): either is said
    said = any("standby" in why or "off the receiver" in why for why in rep.get("attention", []))
    clean = r.code == 3 and said
    return Verdict(clean, f"exit {r.code}, standby {standby}, attention {rep.get('attention')}")


def confidence_honest_about_draws(ws, folder) -> Verdict:
    out = folder / "aim.json"
    r = heliotwin("aimpoints", "--scenario", ws.small["cal"], "--time", "2021-06-21T12:00:00Z", "--peak-limit", 2e5,
                  "--confidence", 0.9999999, "--draws", 50, "--no-baselines", "--output", folder / "aimed.h5",
                  "--json", out, cwd=folder, timeout=600)
    rep = json.loads(out.read_text()) if out.exists() else {}
    rob = rep.get("robust") or (rep.get("instants") or [{}])[0].get("robust") or {}
    bound = rob.get("exceedance_upper_95")
    clean = r.code in (0, 3) and rob.get("met") is False and bound is not None and bound > 0.05
    return Verdict(clean, f"exit {r.code}, met {rob.get('met')}, exact bound {bound}, {rob.get('met_reason')}")


def confidence_spread_grows_with_time(ws, folder) -> Verdict:
    sds = {}
    for when in ("2021-09-01T12:00:00Z", "2100-12-01T12:00:00Z"):
        out = folder / f"aim-{when[:4]}.json"
        heliotwin("aimpoints", "--scenario", ws.small["cal"], "--time", when, "--peak-limit", 2e5, "--confidence",
                  0.9, "--draws", 50, "--no-baselines", "--output", folder / "aimed.h5", "--json", out, cwd=folder,
                  timeout=600)
        rep = json.loads(out.read_text()) if out.exists() else {}
        rob = rep.get("robust") or {}
        sds[when[:4]] = (rob.get("pointing_sd_mrad") or {}).get("median")
    clean = None not in sds.values() and sds["2100"] > 1.5 * sds["2021"]
    return Verdict(clean, f"median pointing sd [mrad] {sds}")


def alarms_persist_over_reruns(ws, folder) -> Verdict:
    r1, rep1, plant = _daily(ws, folder, "--day", "2022-01-02", "--no-aim")
    if "open_alarms" not in rep1:
        return Verdict(False, f"exit {r1.code}: the day's report has no open alarms (alarms are forgotten)")
    out = folder / "again.json"
    r2 = heliotwin("daily", "--plant", plant, "--paint", ws.small["base"], "--json", out, "--day", "2022-01-02",
                   "--no-aim", cwd=folder, timeout=600)
    rep2 = json.loads(out.read_text()) if out.exists() else {}
    first = {(a["heliostat"], a["record_id"]) for a in rep1["open_alarms"]}
    second = {(a["heliostat"], a["record_id"]) for a in rep2.get("open_alarms", [])}
    kept = first == second and (r2.code == 3) == bool(second)
    return Verdict(kept, f"exit {r1.code} then {r2.code} (no new record); open {sorted(first)} then {sorted(second)}")


def plans_the_plants_own_tomorrow(ws, folder) -> Verdict:
    r, rep, _ = _daily(ws, folder, "--no-aim")
    day, why = rep.get("day"), rep.get("day_reason", "")
    clean = r.code in (0, 3) and day is not None and day < "2023-01-01" and "latest record" in why
    return Verdict(clean, f"exit {r.code}, planned {day}: {why}")


CASES = [
    Case("daily-peak-limit-standby", "high", "exit 3, the standby heliostats and the power they cost in the report",
         standby_needs_a_person),
    Case("aimpoints-confidence-few-draws", "medium", "met false with the exact bound (0 of 50: below ~6 %)",
         confidence_honest_about_draws),
    Case("aimpoints-confidence-far-time", "medium", "the pointing spread in 2100 wider than at the records' time",
         confidence_spread_grows_with_time),
    Case("daily-alarms-persist", "high", "open alarms kept over a rerun with no new record (exit 3 while open)",
         alarms_persist_over_reruns),
    Case("daily-plant-clock", "medium", "without --day: the day after the plant's latest record, said why",
         plans_the_plants_own_tomorrow),
]
