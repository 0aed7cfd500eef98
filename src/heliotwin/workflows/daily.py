"""The daily workflow: a plant's day as one scheduled command (``heliotwin daily``).

It composes the workflows a plant engineer would otherwise run one by one every morning, on the plant file
and the PAINT folder that grew overnight:

1. **update** (:func:`heliotwin.workflows.update.update`): yesterday's records assimilated (only the new files
   are parsed: the folder's record index), step alarms raised;
2. **plan** (:func:`heliotwin.calibrate.protocol.plan.plant_plan`): the calibration slots of the planned day
   (default tomorrow, UTC), heliostats with an alarm first, then those whose pointing is least certain, each
   at the sun position that teaches most about it;
3. **aim points** (:func:`heliotwin.workflows.aimpoints.aimpoints`): for the planned day's instants (default
   the one nearest solar noon) under the peak-flux limit given or stored by an earlier ``aimpoints`` run;
   skipped, and said so, when the plant has neither a limit nor a receiver.

The result is one scenario with **one** ``daily`` provenance step (the records it assimilated, its alarms, the
plan and the aim points' summary), one report, and a status a scheduler can act on (:data:`OK`,
:data:`ATTENTION`). :func:`daily_plant_file` is the command on files: the plant is locked for the whole
read-update-write and replaced atomically, or not at all.
"""
from __future__ import annotations

import datetime as _dt
import math
import os
from dataclasses import dataclass, field, replace

from ..calibrate.clock import planned_day
from ..calibrate.protocol.plan import plant_plan
from ..errors import HeliotwinError
from ..io.scenario import Scenario, load_scenario, provenance_entry
from ..optimise.aimstate import stored_flux_limit, stored_peak_limit
from .aimpoints import AimpointSettings, aimpoints
from .field import sun_instants
from .update import UpdateSettings, locked_plant_write, update

__all__ = ["DailySettings", "Daily", "daily", "day_attention", "daily_plant_file", "OK", "ATTENTION"]

#: Exit status: the day ran and nothing needs a person.
OK = 0
#: Exit status: the day ran (the plant is written) and something needs a person: a step alarm raised or still
#: open (no later records have confirmed or cleared it), aim points that could not hold the peak limit, or
#: heliostats sent to standby to hold it.
ATTENTION = 3


@dataclass(frozen=True)
class DailySettings:
    """Options of ``heliotwin daily`` (same names and defaults).

    Attributes
    ----------
    update : UpdateSettings
        The update's options.
    day : str or None
        The planned day (UTC date); None: tomorrow by the wall clock, or the day after the plant's latest record
        when that is days behind (:func:`heliotwin.calibrate.clock.planned_day`).
    slots : int
        Calibration records to plan for the day.
    every : str
        Spacing of the candidate calibration times (pandas frequency).
    min_elevation : float
        Lowest sun elevation of a calibration candidate [deg].
    aim : bool
        Also optimise aim points for the day.
    peak_limit_w_m2 : float or None
        Peak-flux limit [W/m^2]; None: the one an earlier ``aimpoints`` run stored in the plant.
    aim_times : str or None
        Comma-separated UTC times of the day's aim points; None: the hour of the day with the highest sun.
    resolution : tuple of int
        Receiver map (rows, cols) of the aim points.
    flux_limit : str or None
        An allowable-flux map (``.csv``/``.toml``, :func:`heliotwin.optimise.fluxmap.load_flux_limit`). Given
        limits (this or ``peak_limit_w_m2``) replace the stored ones; none given: the map an earlier ``aimpoints``
        stored, else its peak limit.
    """

    update: UpdateSettings = field(default_factory=UpdateSettings)
    day: str | None = None
    slots: int = 20
    every: str = "30min"
    min_elevation: float = 15.0
    aim: bool = True
    peak_limit_w_m2: float | None = None
    aim_times: str | None = None
    resolution: tuple = (20, 48)
    flux_limit: str | None = None

    def __post_init__(self):
        if isinstance(self.slots, bool) or not isinstance(self.slots, int) or not 0 <= self.slots <= 100000:
            raise HeliotwinError(f"--slots: expected 0..100000 calibration records, got {self.slots!r}")
        e = self.min_elevation
        if not (isinstance(e, (int, float)) and math.isfinite(e) and 0 <= e <= 89):
            raise HeliotwinError(f"--min-elevation: expected an elevation in [0, 89] deg, got {e!r}")
        lim = self.peak_limit_w_m2
        if lim is not None and not (isinstance(lim, (int, float)) and math.isfinite(lim) and lim > 0):
            raise HeliotwinError(f"--peak-limit: expected a finite positive flux [W/m2], got {lim!r}")


@dataclass(frozen=True)
class Daily:
    """What :func:`daily` returns; unpacks as ``scenario, report = daily(...)``.

    Attributes
    ----------
    scenario : Scenario
        The plant after the day (one ``daily`` provenance step).
    report : dict
        ``update`` (the update's report), ``plan``, ``aimpoints``, ``status`` and ``attention`` (why).
    status : int
        :data:`OK` or :data:`ATTENTION`.
    """

    scenario: Scenario
    report: dict
    status: int

    def __iter__(self):
        return iter((self.scenario, self.report))


#: Share of equator aiming's power below which aim points that hold the limit need a person: the field's light
#: is mostly sent off the receiver (spilled or on standby), which a limit set too low (or a wrong unit) does.
SPILL_ATTENTION = 0.5

def _aim(scenario: Scenario, day: str, settings: DailySettings) -> tuple[Scenario, dict]:
    """The day's aim points (or why there are none)."""
    if not settings.aim:
        return scenario, {"skipped": "not asked for (--no-aim)"}
    limit, flux = settings.peak_limit_w_m2, settings.flux_limit
    if limit is None and flux is None:  # the plant's own: its map if it keeps one, else its peak limit
        flux = stored_flux_limit(scenario)
        limit = stored_peak_limit(scenario) if flux is None else None
    if limit is None and flux is None:
        return scenario, {"skipped": "no peak-flux limit: give --peak-limit, or run 'heliotwin aimpoints' once "
                                     "(the plant keeps its limit)"}
    if "receiver" not in scenario.plant.targets:
        return scenario, {"skipped": "the plant has no receiver target"}
    if settings.aim_times:
        instants = sun_instants(scenario.plant, times=settings.aim_times)
    else:  # the hour with the highest sun: where the peak limit binds hardest
        hours = sun_instants(scenario.plant, day=day, every="1h")
        instants = [max(hours, key=lambda item: float(item[1][2]))]
    aim_settings = AimpointSettings(peak_limit_w_m2=None if limit is None else float(limit),
                                    resolution=tuple(settings.resolution), baselines=False, flux_limit=flux)
    aimed, report = aimpoints(scenario, instants, aim_settings)
    met = [e["optimised"]["peak_vs_limit"] <= 1 + 1e-6 for e in report["instants"]]
    # standby heliostats hold the limit by delivering nothing: what the limit costs is the power the field
    # loses against equator aiming with every heliostat on the receiver (the limit-free aim points)
    summary = {"peak_limit_w_m2": report["peak_limit_w_m2"], "instants": [
        {"instant": e["instant"], "power_w": e["optimised"].get("power_w"),
         "peak_flux_w_m2": e["optimised"]["peak_flux_w_m2"], "limit_met": ok,
         "standby_heliostats": int(e["optimised"].get("standby_heliostats", 0)),
         "equator_power_w": e["equator"].get("power_w"),
         "power_lost_w": (e["equator"]["power_w"] - e["optimised"]["power_w"]
                          if e["equator"].get("power_w") is not None and e["optimised"].get("power_w") is not None
                          else None)}
        for e, ok in zip(report["instants"], met)], "limit_met": all(met),
        "power_lost_means": "equator aiming's power (every heliostat on the receiver, no limit) less the "
                            "optimised aim points' [W]"}
    summary["standby_heliostats"] = max((e["standby_heliostats"] for e in summary["instants"]), default=0)
    if "flux_limit" in report:
        summary["flux_limit"] = report["flux_limit"]
        for row, e in zip(summary["instants"], report["instants"]):
            row.update(max_utilisation=e["optimised"]["max_utilisation"], binding_cells=e["optimised"]["binding_cells"])
    return aimed, summary


def _age(alarm: dict) -> str:
    days = alarm.get("age_days")
    return "age unknown" if days is None else f"{days:.1f} day(s) old"


def day_attention(alarms: list, aim: dict, still_open: list = ()) -> list[str]:
    """Why the day needs a person (empty: nothing): step alarms raised today or still open, a peak limit not
    held, the field's light sent off the receiver (below :data:`SPILL_ATTENTION` of equator aiming's power [W]),
    heliostats on standby.

    ``alarms``: the update's new alarms; ``aim``: the day's aim-point summary (:func:`_aim`); ``still_open``:
    :func:`heliotwin.calibrate.twinstate.open_alarms`."""
    attention = [f"{len(alarms)} step alarm(s)"] if alarms else []
    if still_open:
        attention.append(f"{len(still_open)} open step alarm(s): " + ", ".join(
            f"{a['heliostat']} (record {a['record_id']}, opened {a['opened_utc']}, {_age(a)}, {a['records']} of "
            f"{a['records_to_settle']} records to settle it)" for a in still_open))
    if aim.get("limit_met") is False:
        attention.append("aim points could not hold the peak limit at every instant")
    spilled = [e for e in aim.get("instants", []) if e.get("equator_power_w") and e.get("power_w") is not None
               and e["power_w"] < SPILL_ATTENTION * e["equator_power_w"]]
    standby = max((e.get("standby_heliostats", 0) for e in aim.get("instants", [])), default=0)
    if spilled and not standby:
        worst = min(spilled, key=lambda e: e["power_w"] / e["equator_power_w"])
        attention.append(f"aim points at {worst['instant']} deliver {worst['power_w'] / 1e3:.3g} kW of equator "
                         f"aiming's {worst['equator_power_w'] / 1e3:.3g} kW "
                         f"({worst['power_w'] / worst['equator_power_w']:.1%}): the peak limit is held by sending "
                         "the field's light off the receiver")
    if standby:
        worst = max(aim["instants"], key=lambda e: e["standby_heliostats"])
        lost = worst.get("power_lost_w")
        attention.append(f"{worst['standby_heliostats']} heliostat(s) on standby to hold the peak limit at "
                         f"{worst['instant']}" + (f" ({worst['power_w'] / 1e3:.3g} kW of equator aiming's "
                                                  f"{worst['equator_power_w'] / 1e3:.3g} kW delivered)"
                                                  if lost is not None else ""))
    return attention


def daily(scenario, paint, settings: DailySettings = DailySettings(), *, device: str = "cpu",
          now: float | None = None) -> Daily:
    """The plant's day (module docstring): update with the folder's new records, plan the next calibrations,
    aim the field; one provenance step.

    Parameters
    ----------
    scenario : Scenario, str or os.PathLike
        A calibrated plant (``calibrate --method lm -o``, or an earlier update or day).
    paint : str or os.PathLike
        The plant's PAINT folder (it grows every day; seen records are recognised).
    settings : DailySettings
    device : str
        Where the update computes.
    now : float, optional
        The wall clock [POSIX s] (default: the system's; tests give it).
    """
    previous = load_scenario(scenario) if isinstance(scenario, (str, os.PathLike)) else scenario
    updated = update(previous, paint, settings.update, device=device)
    alarms = updated.report["alarms"]
    wall = None if now is None else _dt.datetime.fromtimestamp(float(now), _dt.timezone.utc)
    day, day_why = planned_day(updated.scenario.learned, settings.day, wall)
    # an alarm is open until records settle it; the update lists them, aged on the plant's own clock
    still_open = updated.report["open_alarms"]
    urgent = [a["heliostat"] for a in still_open] + [a["heliostat"] for a in alarms]
    plan = plant_plan(updated.scenario, day=day, slots=settings.slots, every=settings.every,
                      min_elevation_deg=settings.min_elevation, urgent=list(dict.fromkeys(urgent)))

    final, aim = _aim(updated.scenario, day, settings)
    update_step = updated.scenario.provenance[-1]
    step = provenance_entry("daily", source=update_step.get("source"), records=update_step.get("records", {}),
                            alarms=alarms, threshold=update_step.get("threshold"), day=day,
                            plan=[{k: p[k] for k in ("heliostat", "time")} for p in plan["proposals"]],
                            aimpoints={k: v for k, v in aim.items() if k != "instants"},
                            settings={"update": update_step.get("settings"), "slots": settings.slots,
                                      "every": settings.every})
    final = replace(final, provenance=list(previous.provenance or []) + [step])
    attention = day_attention(alarms, aim, still_open)
    status = ATTENTION if attention else OK
    report = {"day": day, "day_reason": day_why, "status": status, "attention": attention, "update": updated.report,
              "plan": plan, "aimpoints": aim, "open_alarms": still_open}
    return Daily(final, report, status)


def daily_plant_file(plant_path, paint, output=None, settings: DailySettings = DailySettings(), *,
                     device: str = "cpu", timeout: float | None = None, now: float | None = None) -> Daily:
    """:func:`daily` on files: ``output`` (default: the plant file itself) is locked for the whole day's
    read-update-write, not replaced when another process changed it meanwhile, and written atomically."""
    output = plant_path if output is None else output
    return locked_plant_write(output, lambda: daily(plant_path, paint, settings, device=device, now=now), timeout)
