"""Misuse cases of what the day's report claims (issue 41 items 5 and 8, issue 42 item 3): a limit held only by
sending heliostats to standby, a confidence that 50 draws cannot show, the pointing spread decades after the records,
and a plant whose records ended years before the wall clock. Each verdict is clean only when the fixed behaviour is
seen (exit 3 and the standby count; ``met: false`` with an exact bound; a spread that grows; the plant's own day)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from fuzz_daily import Case, Verdict, heliotwin


def _plant(ws, folder: Path) -> Path:
    plant = folder / "p.h5"
    shutil.copy(ws.small["cal"], plant)
    return plant


def _json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def standby_needs_a_person(ws, folder):
    plant = _plant(ws, folder)
    r = heliotwin("daily", "--plant", plant, "--paint", ws.small["base"], "--peak-limit", 1000, "--slots", 2,
                  "--json", folder / "d.json", cwd=folder, timeout=300)
    aim = _json(folder / "d.json").get("aimpoints", {})
    n = aim.get("standby_heliostats")
    ok = r.code == 3 and bool(n) and any("standby" in a for a in _json(folder / "d.json").get("attention", []))
    return Verdict(ok, f"exit {r.code}, {n} heliostat(s) on standby in the report; {r.out.strip()[-160:]}")


def _aim_confidence(ws, folder, time: str, confidence: str, draws: int) -> dict:
    plant = _plant(ws, folder)
    heliotwin("aimpoints", "--scenario", plant, "--time", time, "--peak-limit", 1e6, "--confidence", confidence,
              "--draws", draws, "--iterations", 40, "--no-baselines", "-o", folder / "a.h5", "--json",
              folder / f"a-{time[:4]}.json", cwd=folder, timeout=300)
    return _json(folder / f"a-{time[:4]}.json").get("robust") or {}


def confidence_honest_about_draws(ws, folder):
    rob = _aim_confidence(ws, folder, "2021-12-01T11:00Z", "0.9999999", 50)
    bound = (rob.get("robust") or {}).get("exceedance_upper_95")
    ok = rob.get("met") is False and bound is not None and bound > 0.05 and "why_not_met" in rob
    return Verdict(ok, f"met {rob.get('met')}, exact 95 % bound {bound}, {rob.get('why_not_met', '')[:120]}")


def spread_grows_with_time(ws, folder):
    near = _aim_confidence(ws, folder, "2021-09-01T11:00Z", "0.9", 40).get("pointing_sd_mrad", {})
    far = _aim_confidence(ws, folder, "2100-12-01T11:00Z", "0.9", 40).get("pointing_sd_mrad", {})
    ok = bool(near) and bool(far) and far.get("median", 0) > 2 * near.get("median", float("inf"))
    return Verdict(ok, f"median pointing spread {near.get('median')} mrad at the records' time, "
                       f"{far.get('median')} mrad in 2100")


def plans_the_plants_own_day(ws, folder):
    plant = _plant(ws, folder)
    r = heliotwin("daily", "--plant", plant, "--paint", ws.small["base"], "--no-aim", "--slots", 2, "--json",
                  folder / "d.json", cwd=folder, timeout=300)
    rep = _json(folder / "d.json")
    day = rep.get("day", "")
    ok = r.code in (0, 3) and day.startswith(("2021-", "2022-01")) and "latest record" in rep.get("day_reason", "")
    return Verdict(ok, f"exit {r.code}, planned {day or '-'}: {rep.get('day_reason', '')[:100]}")


CASES = [
    Case("daily-standby-exit-3", "high", "daily --peak-limit 1000: exit 3, standby heliostats counted",
         standby_needs_a_person),
    Case("confidence-50-draws", "medium", "--confidence 0.9999999 --draws 50: met false, exact bound ~0.058",
         confidence_honest_about_draws),
    Case("confidence-time-2100", "medium", "the pointing spread in 2100 grows by the stored walk",
         spread_grows_with_time),
    Case("daily-plant-clock", "medium", "daily without --day on a 2021 plant plans the day after its latest "
         "record and says so", plans_the_plants_own_day),
]
