"""The ``report`` workflow: the plant at a glance, one self-contained HTML page an operator opens each morning.

:func:`plant_report` reads what a scenario holds (and, when given, a PAINT folder's records) and gathers:

* the per-heliostat state (:func:`heliostat_state`): position, whether calibrated, the 95 % interval of the
  axis offsets from the stored posterior, the latest predicted pointing error and the step alarms of the
  update history (``heliotwin update``), days since the last record, learned surfaces;
* the alarms since the last report (the latest update's), sorted by their step statistic, with what to do;
* per-heliostat detail (state history across updates, residuals, the learned surface's tilt from the ideal
  facets) for the alarmed and the least certain heliostats with an update history or a learned surface, at
  most :attr:`ReportSettings.detail` of them, so that the page stays small at any plant size;
* tomorrow's calibration plan for the plant (:func:`heliotwin.calibrate.protocol.plan.plant_plan`, as
  ``heliotwin daily`` makes it: the alarmed heliostats first, then the largest predicted pointing spread
  (:mod:`heliotwin.calibrate.spread`), each with its time and sun position on the day after the latest record),
  and the sun-position coverage (the ``plan`` workflow's sky map, on the same day: the same spread) of the
  first of them;
* the receiver (the ``field`` workflow): equator aiming and the stored aim points on one colour scale, with
  the stored peak-flux limit;
* the plant's year, when ``heliotwin year`` stored one (``/learned/year``, :func:`year_state`): the field map
  coloured by annual energy and by the energy each heliostat loses to its tracking and to its mirror, the
  heliostats with the most energy at stake (what a crew fixes or washes first), the monthly energy, the weather
  file with its time convention and the interpolation check the year measured;
* provenance (:func:`heliotwin.workflows.show.describe_scenario`).

The page itself is drawn by :mod:`heliotwin.workflows.report_page` (Plotly, its JavaScript inlined). Like every
workflow this one writes no file: the report dict carries the page as ``html`` and the caller writes it.
Nothing here depends on the wall clock: "days since" and "tomorrow" are counted from the latest record time
the plant holds (``reference_time``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from ..calibrate.protocol.plan import plant_plan
from ..calibrate.twinstate import open_alarms, plant_clock
from ..errors import HeliotwinError, InputFileError
from ..field.facets import ideal_surfaces, surface_points
from ..field.plant import Facets, Surfaces
from ..field.targets import CylinderTarget
from ..geometry import angle_between
from ..io.records import parse_time
from ..io.scenario import Scenario
from ..optimise.aimstate import stored_peak_limit
from ..timefmt import utc_text
from .field import FieldRunSettings, field, sun_direction_at
from .plan import PlanSettings, plan
from .report_page import render_page
from .show import describe_scenario, nominal_heliostats
from .update import ASSIMILATION_KEY

__all__ = ["ReportSettings", "QUANTITIES", "YEAR_QUANTITIES", "heliostat_state", "alarm_rows", "open_alarm_rows",
            "heliostat_detail", "surface_deviation", "year_state", "year_ranking",
           "plant_report"]

#: Colour quantities of the field map: key -> (label with unit, higher is worse).
QUANTITIES = {
    "predicted_error_mrad": ("latest predicted pointing error [mrad]", True),
    "interval_mrad": ("95 % interval of the axis offsets [mrad]", True),
    "days_since_record": ("days since the last record [d]", True),
    "alarms": ("step alarms, all updates [-]", True),
    "alarms_latest": ("step alarms in the latest update [-]", True),
    "statistic_latest": ("largest alarm's step statistic, latest update [-]", True),
    "surface_learned": ("learned surface (1 = yes) [-]", False),
    "calibrated": ("calibrated kinematics (1 = yes) [-]", False),
}

#: The two encoder offsets whose posterior the interval is of (names of the calibration's parameters).
OFFSETS = ("initial_angle_1", "initial_angle_2")


@dataclass(frozen=True)
class ReportSettings:
    """Options of ``heliotwin report`` (same names and defaults).

    Attributes
    ----------
    colour : str
        The field map's initial colour quantity (a key of :data:`QUANTITIES`; the page switches between all).
    detail : int
        Most heliostats with their own section (alarmed first, then the widest intervals).
    plan_heliostats : int
        Heliostats with a sun-position coverage map (the ``plan`` workflow runs once for each).
    plan_slots : int
        Records in tomorrow's plan for the plant (one heliostat each).
    plan_count : int
        Sun positions proposed per planned heliostat.
    plan_every : str
        Spacing of the plan's candidate times over the year (``plan --every``; 2h halves the plan's time
        against 1h, and the sky map is binned anyway).
    time_utc : str or None
        Instant of the receiver map (ISO, UTC); None: the stored aim points' instant, else no receiver map.
    flux : bool
        Draw the receiver (runs the field model twice: equator and stored aim points).
    resolution : (int, int)
        Receiver map ``(rows, cols)``.
    year_rows : int
        Rows of the year's table of the heliostats with the most energy at stake (each gets a section of its own,
        beyond ``detail``); only when the plant file holds a year (``heliotwin year``).
    """

    colour: str = "predicted_error_mrad"
    detail: int = 40
    plan_heliostats: int = 10
    plan_slots: int = 20
    plan_count: int = 3
    plan_every: str = "2h"
    time_utc: str | None = None
    flux: bool = True
    resolution: tuple = (24, 64)
    year_rows: int = 20

    def __post_init__(self):
        if self.colour not in QUANTITIES:
            raise HeliotwinError(f"--colour {self.colour}: expected one of {', '.join(QUANTITIES)}")
        for name, lo in (("detail", 0), ("plan_heliostats", 0), ("plan_count", 1), ("plan_slots", 0), ("year_rows", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= 10000:
                raise HeliotwinError(f"--{name.replace('_', '-')}: expected an integer in {lo}..10000, got {v!r}")


# ------------------------------------------------------------------------------------------ per heliostat
def _history(scenario: Scenario) -> dict | None:
    """The update history as numpy arrays (``heliostat`` indexes ``ids``), or None."""
    st = scenario.learned.get(ASSIMILATION_KEY)
    if not isinstance(st, dict) or not isinstance(st.get("history"), dict):
        return None
    h = {k: np.asarray(v.detach().cpu() if torch.is_tensor(v) else v) for k, v in st["history"].items()}
    return {"ids": list(st["heliostats"]), "names": list(st.get("parameter_names") or []), "rows": h,
            "threshold": float(np.asarray(st.get("threshold", [math.nan])).reshape(-1)[0]),
            "updates": int(np.asarray(st.get("updates", [0])).reshape(-1)[0])}


def _per_heliostat_latest(ids: list, hist: dict | None) -> tuple[np.ndarray, ...]:
    """Latest record time [s], latest predicted error [rad], alarm counts (all, latest update) and the latest
    update's largest alarm statistic per heliostat (arrays [H])."""
    n = len(ids)
    last_t, last_err = np.full(n, np.nan), np.full(n, np.nan)
    alarms, latest, stat = np.zeros(n), np.zeros(n), np.zeros(n)
    if hist is None or not len(hist["rows"].get("time", [])):
        return last_t, last_err, alarms, latest, stat
    r = hist["rows"]
    where = {h: i for i, h in enumerate(ids)}
    to_plant = np.array([where.get(h, -1) for h in hist["ids"]])[r["heliostat"].astype(np.int64)]
    ok = to_plant >= 0
    order = np.argsort(r["time"][ok], kind="stable")
    rows, t, err = to_plant[ok][order], r["time"][ok][order], r["predicted_error"][ok][order]
    last_t[rows], last_err[rows] = t, err  # the latest row of each heliostat is written last
    alarm = r["alarm"][ok].astype(bool)
    np.add.at(alarms, to_plant[ok][alarm], 1)
    newest = alarm & (r["update"][ok] == r["update"].max())
    np.add.at(latest, to_plant[ok][newest], 1)
    np.maximum.at(stat, to_plant[ok][newest], r["statistic"][ok][newest].astype(np.float64))
    return last_t, last_err, alarms, latest, stat


def _interval_mrad(cal: dict, ids: list) -> np.ndarray:
    """95 % interval width [mrad] of the encoder offsets' combined angle, ``2 x 1.96 x sqrt(var_1 + var_2)``,
    from the stored posterior covariance [H, P, P] (NaN where none)."""
    out = np.full(len(ids), np.nan)
    post = cal.get("posterior") or {}
    names = list(cal.get("parameter_names") or [])
    if post.get("covariance") is None or not all(n in names for n in OFFSETS):
        return out
    cov = torch.as_tensor(post["covariance"], dtype=torch.float64)
    cols = [names.index(n) for n in OFFSETS]
    var = cov[:, cols, cols].sum(-1).clamp_min(0.0).numpy()
    where = {h: i for i, h in enumerate(ids)}
    rows = np.array([where.get(h, -1) for h in cal.get("heliostats", [])], dtype=np.int64)
    ok = rows >= 0
    out[rows[ok]] = 1e3 * 2 * 1.96 * np.sqrt(var[ok])
    return out


def _calibration_expected(cal: dict, ids: list) -> np.ndarray:
    """The calibration's expected pointing error [mrad] per plant heliostat [H] (``calibrate`` stores it: the
    validation inside the records for a fully calibrated heliostat, the Laplace posterior's for a reduced one);
    NaN where none is stored."""
    out = np.full(len(ids), np.nan)
    stored = cal.get("expected_error_mrad")
    if stored is None:
        return out
    values = np.asarray(torch.as_tensor(stored, dtype=torch.float64).reshape(-1))
    where = {h: i for i, h in enumerate(ids)}
    for h, v in zip(cal.get("heliostats") or [], values):
        if h in where:
            out[where[h]] = v
    return out


def heliostat_state(scenario: Scenario, records=None) -> dict:
    """Every heliostat's state for the field map.

    Parameters
    ----------
    scenario : Scenario
    records : heliotwin.io.records.RecordTable, optional
        A PAINT folder's records: their latest time per heliostat counts for "days since the last record".

    Returns
    -------
    dict
        ``ids`` [H], ``x_m``, ``y_m`` [H] (east, north [m]), one numpy array [H] per key of
        :data:`QUANTITIES` (NaN where unknown; ``predicted_error_mrad`` is the latest update's, else the
        calibration's expected error, flagged in ``predicted_from_calibration`` [H] bool), ``nominal`` [H] (1 =
        the plant's calibration left it at nominal kinematics), ``reference_time`` (POSIX s: the latest record
        time the plant holds, or NaN) and ``threshold`` (the update's step-alarm threshold, or NaN).
    """
    plant = scenario.plant
    ids = list(plant.field.ids)
    pos = plant.field.kinematics.position.detach().cpu().to(torch.float64).numpy()
    cal = scenario.learned.get("calibration") or {}
    hist = _history(scenario)
    last_t, last_err, alarms, latest, stat = _per_heliostat_latest(ids, hist)
    if records is not None and len(records):
        where = {h: i for i, h in enumerate(ids)}
        t = records.time.detach().cpu().numpy().astype(np.float64)
        per_id = np.array([where.get(h, -1) for h in records.heliostat_ids], dtype=np.int64)
        rows = per_id[records.heliostat_index.detach().cpu().numpy()]
        ok = (rows >= 0) & np.isfinite(t)
        folder_last = np.full(len(ids), -np.inf)
        np.maximum.at(folder_last, rows[ok], t[ok])
        last_t = np.where(np.isfinite(folder_last), np.fmax(last_t, folder_last), last_t)
    finite = last_t[np.isfinite(last_t)]
    reference = float(finite.max()) if len(finite) else math.nan
    calibrated = set(cal.get("heliostats") or [])
    surfaces = set((scenario.learned.get("surfaces") or {}).keys())
    # a heliostat no update touched: its calibration's expected error (every calibrated one has a value)
    from_cal = _calibration_expected(cal, ids)
    predicted = np.where(np.isfinite(last_err), 1e3 * last_err, from_cal)
    left = nominal_heliostats(scenario)
    nominal = np.array([1.0 if h in left else 0.0 for h in ids])
    return {"ids": ids, "x_m": pos[:, 0], "y_m": pos[:, 1],
            "predicted_error_mrad": predicted, "interval_mrad": _interval_mrad(cal, ids),
            "predicted_from_calibration": np.isfinite(from_cal) & ~np.isfinite(last_err), "nominal": nominal,
            "days_since_record": (reference - last_t) / 86400.0, "alarms": alarms, "alarms_latest": latest,
            "statistic_latest": stat,
            "surface_learned": np.array([1.0 if h in surfaces else 0.0 for h in ids]),
            "calibrated": np.array([1.0 if h in calibrated else 0.0 for h in ids]),
            "reference_time": reference, "threshold": hist["threshold"] if hist else math.nan}


def alarm_rows(scenario: Scenario, *, latest_only: bool = True) -> list[dict]:
    """The step alarms of the update history, largest step statistic first.

    Returns
    -------
    list of dict
        ``heliostat``, ``record_id``, ``time`` (UTC ISO), ``update``, ``statistic`` [-] (and ``threshold``),
        ``innovation_mrad`` (the record's miss before assimilation [mrad]) and ``action`` (what the operator
        should do). Only the latest update's alarms when ``latest_only``.
    """
    hist = _history(scenario)
    if hist is None or not len(hist["rows"].get("alarm", [])):
        return []
    r, thr = hist["rows"], hist["threshold"]
    pick = r["alarm"].astype(bool)
    if latest_only:
        pick &= r["update"] == r["update"].max()
    out = []
    for i in np.nonzero(pick)[0]:
        size = 1e3 * float(np.linalg.norm(r["innovation"][i]))
        big = math.isfinite(thr) and float(r["statistic"][i]) > 3 * thr
        action = ("inspect the drive and encoders (a step far above the threshold), then take a calibration record"
                  if big else "take a calibration record soon to confirm the step (the update re-opened the offset)")
        out.append({"heliostat": hist["ids"][int(r["heliostat"][i])], "record_id": int(r["record_id"][i]),
                    "time": utc_text(r["time"][i]), "update": int(r["update"][i]),
                    "statistic": float(r["statistic"][i]), "threshold": thr, "innovation_mrad": size,
                    "action": action})
    return sorted(out, key=lambda a: -a["statistic"])


def open_alarm_rows(scenario: Scenario) -> list[dict]:
    """Every open step alarm (no later record has confirmed or cleared it yet; oldest first), with its age in
    days on the plant's own clock (its latest record): :func:`heliotwin.calibrate.twinstate.open_alarms`.
    Nothing here reads the wall clock."""
    return open_alarms(scenario, now=plant_clock(scenario))


def heliostat_detail(scenario: Scenario, heliostat: str) -> dict:
    """One heliostat's history across updates, for its page section.

    Returns
    -------
    dict
        ``heliostat``, ``time`` (UTC ISO) [n], ``offsets_mrad`` {name: mean [n]}, ``offsets_std_mrad``
        {name: std [n]} (the encoder offsets after each record), ``residual_mrad`` [n] (the record's miss
        before assimilation), ``predicted_error_mrad`` [n], ``alarm`` [n] (bool), ``update`` [n]. Empty lists
        for a heliostat without history.
    """
    hist = _history(scenario)
    empty = {"heliostat": heliostat, "time": [], "offsets_mrad": {}, "offsets_std_mrad": {}, "residual_mrad": [],
             "predicted_error_mrad": [], "alarm": [], "update": [],
             "calibration": calibration_history(scenario, heliostat)}
    if hist is None or heliostat not in hist["ids"]:
        return empty
    r = hist["rows"]
    rows = np.nonzero(r["heliostat"] == hist["ids"].index(heliostat))[0]
    rows = rows[np.argsort(r["time"][rows], kind="stable")]
    names = hist["names"]
    cols = {n: names.index(n) for n in OFFSETS if n in names}
    return {"heliostat": heliostat, "time": [utc_text(t) for t in r["time"][rows]],
            "offsets_mrad": {n: (1e3 * r["mean"][rows, c]).tolist() for n, c in cols.items()},
            "offsets_std_mrad": {n: (1e3 * np.sqrt(np.maximum(r["variance"][rows, c], 0))).tolist()
                                 for n, c in cols.items()},
            "residual_mrad": (1e3 * np.linalg.norm(r["innovation"][rows], axis=-1)).tolist(),
            "predicted_error_mrad": (1e3 * r["predicted_error"][rows]).tolist(),
            "alarm": r["alarm"][rows].astype(bool).tolist(), "update": r["update"][rows].astype(int).tolist(),
            "calibration": empty["calibration"]}


def calibration_history(scenario: Scenario, heliostat: str) -> dict:
    """What the calibration knew of ``heliostat``: the calibrated model's residual on every record it fitted
    (``calibrate`` stores them), and the encoder offsets it left with their posterior sigma at its latest record.

    Returns
    -------
    dict
        ``time`` (UTC ISO) [n], ``error_mrad`` [n] (pointing error of the calibrated kinematics on each record),
        ``record_id`` [n], ``offsets_mrad`` {name: value}, ``offsets_std_mrad`` {name: sigma}, ``at`` (UTC ISO
        of its latest fitted record or None), ``nominal`` (bool: the calibration left it at nominal kinematics),
        ``expected_error_mrad`` (or None). Empty lists and dicts where nothing is stored.
    """
    cal = scenario.learned.get("calibration") or {}
    ids = list(cal.get("heliostats") or [])
    out = {"time": [], "error_mrad": [], "record_id": [], "offsets_mrad": {}, "offsets_std_mrad": {}, "at": None,
           "nominal": bool(cal) and heliostat not in ids, "expected_error_mrad": None}
    if heliostat not in ids:
        return out
    j = ids.index(heliostat)
    res = cal.get("residuals") or {}
    times = np.array([], dtype=np.float64)
    if res.get("heliostat") is not None:
        mine = np.nonzero(np.asarray(res["heliostat"]).reshape(-1) == j)[0]
        t = np.asarray(res["time"], dtype=np.float64).reshape(-1)[mine]
        order = mine[np.argsort(np.where(np.isfinite(t), t, -np.inf), kind="stable")]
        times = np.asarray(res["time"], dtype=np.float64).reshape(-1)[order]
        keep = np.isfinite(times)  # a record without a time has no place on a time axis
        out.update(time=[utc_text(x) for x in times[keep]],
                   error_mrad=np.asarray(res["error_mrad"], dtype=np.float64).reshape(-1)[order][keep].tolist(),
                   record_id=np.asarray(res["record_id"]).reshape(-1)[order][keep].astype(int).tolist())
    finite = times[np.isfinite(times)]
    out["at"] = utc_text(finite.max()) if len(finite) else None
    names = list(cal.get("parameter_names") or [])
    delta = cal.get("deviations")
    cov = (cal.get("posterior") or {}).get("covariance")
    if delta is not None and cov is not None:
        d, c = np.asarray(delta, dtype=np.float64), np.asarray(cov, dtype=np.float64)
        for n in OFFSETS:
            if n in names:
                k = names.index(n)
                out["offsets_mrad"][n] = 1e3 * float(d[j, k])
                out["offsets_std_mrad"][n] = 1e3 * float(np.sqrt(max(c[j, k, k], 0.0)))
    expected = _calibration_expected(cal, ids)[j]
    out["expected_error_mrad"] = float(expected) if np.isfinite(expected) else None
    return out


def surface_deviation(scenario: Scenario, heliostat: str, samples: tuple = (12, 12)) -> dict:
    """How far ``heliostat``'s surface in the plant (learned, if a step learned one) tilts from its ideal canted
    facets: the angle between the two normals at the same facet samples.

    Returns
    -------
    dict
        ``deviation_mrad`` [F][su][sv] (nested lists; u along the facet's ``canting_e``), ``rms_mrad``
        (area-weighted over the mirror) and ``facets`` (F).
    """
    f = scenario.plant.field
    i = list(f.ids).index(heliostat)
    s = f.surfaces
    cp = s.control_points[i:i + 1].detach().cpu().double()
    learned = Surfaces(cp, s.degree_u, s.degree_v, None if s.weights is None else s.weights[i:i + 1].detach().cpu())
    facets = Facets(*(getattr(f.facets, k)[i:i + 1].detach().cpu().double()
                      for k in ("translation", "canting_e", "canting_n")))
    ideal = ideal_surfaces(facets, num_control_points=tuple(cp.shape[2:4]), degree=(s.degree_u, s.degree_v))
    with torch.no_grad():
        _, n_learned, area = surface_points(learned, samples)
        _, n_ideal, _ = surface_points(ideal, samples)
        angle = 1e3 * angle_between(n_learned, n_ideal.to(n_learned))[0]  # [F * su * sv] [mrad]
    rms = float(torch.sqrt((area[0] * angle ** 2).sum() / area[0].sum()))
    n_facets = cp.shape[1]
    return {"facets": n_facets, "rms_mrad": rms,
            "deviation_mrad": angle.reshape(n_facets, samples[0], samples[1]).numpy().round(4).tolist()}


# ------------------------------------------------------------------------------------------------ choices
def _ranked(state: dict, count: int) -> list[int]:
    """Heliostat indices that need attention most: alarmed in the latest update (largest step statistic first),
    then the widest interval, then the longest without a record; at most ``count``."""
    key_alarm = np.nan_to_num(state["statistic_latest"], nan=0.0)
    key_width = np.nan_to_num(state["interval_mrad"], nan=-1.0)
    key_days = np.nan_to_num(state["days_since_record"], nan=-1.0)
    order = np.lexsort((-key_days, -key_width, -key_alarm))
    return [int(i) for i in order[:count]]


def _coverage_order(state: dict, tomorrow: dict) -> list[int]:
    """The heliostats (indices into ``state["ids"]``) of the sun-position coverage section, in the order tomorrow's
    plan ranks them (its planned heliostats first, then the others by the same predicted pointing spread), else
    (no plan) :func:`_ranked`'s; calibrated ones only."""
    where = {h: i for i, h in enumerate(state["ids"])}
    spread = tomorrow.get("spread_mrad") or {}
    if spread:
        planned = [p["heliostat"] for p in tomorrow.get("proposals") or []]
        rest = sorted((h for h in spread if h not in set(planned)), key=lambda h: -spread[h])
        return [where[h] for h in planned + rest if h in where]
    return [i for i in _ranked(state, len(state["ids"])) if state["calibrated"][i]]


def _plan_rows(scenario: Scenario, state: dict, settings: ReportSettings, tomorrow: dict) -> list[dict]:
    """The ``plan`` workflow for the heliostats tomorrow's plan puts first (:func:`_coverage_order`), on the plan's
    day, so that the spread each row shows is the one the plan ranked by."""
    if not settings.plan_heliostats or not (scenario.learned.get("calibration") or {}).get("posterior"):
        return []
    ref = state["reference_time"]
    day = tomorrow.get("day") or (utc_text(ref + 86400.0)[:10] if math.isfinite(ref) else None)
    out = []
    for i in _coverage_order(state, tomorrow)[:settings.plan_heliostats]:
        hid = state["ids"][i]
        try:
            _, ans = plan(scenario, hid, PlanSettings(day=day, year=None if day else 2030, every=settings.plan_every,
                                                    count=settings.plan_count, sky=True))
        except HeliotwinError as exc:
            out.append({"heliostat": hid, "error": str(exc)})
            continue
        out.append({"heliostat": hid, "spread_now_mrad": ans["spread_now_mrad"], "spread_day": ans["spread_day"],
                    "target": ans["target"], "proposals": ans["proposals"],
                    "sky": {k: np.asarray(v).tolist() for k, v in ans["sky"].items()},
                    "interval_mrad": float(state["interval_mrad"][i]),
                    "alarms_latest": int(state["alarms_latest"][i])})
    return out


def _tomorrow(scenario: Scenario, state: dict, alarms: list, settings: ReportSettings) -> dict:
    """Tomorrow's plan for the plant (``plant_plan`` on the day after the latest record, the latest update's
    alarmed heliostats first), or ``{"note": why not}``."""
    ref = state["reference_time"]
    if not settings.plan_slots:
        return {"note": "no plan asked for (--slots 0)"}
    if not math.isfinite(ref):
        return {"note": "no record times in the plant: no day to plan"}
    day = utc_text(ref + 86400.0)[:10]
    urgent = list(dict.fromkeys(a["heliostat"] for a in alarms))
    try:
        return plant_plan(scenario, day=day, slots=settings.plan_slots, urgent=urgent)
    except HeliotwinError as exc:
        return {"note": str(exc)}


def _receiver(scenario: Scenario, settings: ReportSettings) -> dict | None:
    """Equator aiming and (if stored) the stored aim points at one instant, for the receiver section."""
    plant = scenario.plant
    if not settings.flux or "receiver" not in plant.targets:
        return None
    group = scenario.learned.get("aimpoints") or {}
    when = settings.time_utc
    if when is None and group.get("aim") is not None:
        label = str(next(iter((group.get("instants") or {}).values()), {}).get("instant", ""))
        try:
            when = label if math.isfinite(parse_time(label)) else None
        except ValueError:
            when = None
        sun = torch.as_tensor(group["sun_direction"], dtype=torch.float64) if when is None else None
    else:
        sun = None
    if when is None and sun is None:
        return {"note": "no stored aim points and no --time: no receiver map (give --time)"}
    if sun is None:
        sun = sun_direction_at(plant, time_utc=when)
    maps, aims = {}, None
    for aim in ("equator", "scenario") if group.get("aim") is not None else ("equator",):
        rep, result = field(scenario, sun, FieldRunSettings(resolution=tuple(settings.resolution), aim=aim))
        label = "equator aiming" if aim == "equator" else "stored aim points"
        maps[label] = {"flux_w_m2": result.flux.detach().cpu().double().numpy(), "power_w": rep["receiver"]["power_w"],
                       "peak_w_m2": rep["receiver"]["peak_flux_w_m2"]}
        if aim == "scenario":
            aims = plant.targets["receiver"].to_local(result.aim.detach().cpu().double()).numpy()
    rec = plant.targets["receiver"]
    extent = [float(v) for v in result.extent.detach().cpu()]
    limit = stored_peak_limit(scenario)
    return {"time_utc": when, "sun_enu": [float(v) for v in sun.detach().cpu()], "maps": maps, "extent_m": extent,
            "aim_local_m": aims, "limit_w_m2": limit,
            "cylinder": isinstance(rec, CylinderTarget), "radius_m": float(getattr(rec, "radius", 0.0)),
            "receiver": rec}


# -------------------------------------------------------------------------------------------------- year
#: The plant file's year (``heliotwin year`` writes it): ``/learned/year``.
YEAR_KEY = "year"

#: Colourings of the year's field map: key -> (label with unit, higher is worse).
YEAR_QUANTITIES = {
    "energy_mwh": ("annual energy on the receiver [MWh]", False),
    "tracking_loss_mwh": ("energy lost to its tracking error [MWh/year]", True),
    "surface_loss_mwh": ("energy lost to its mirror surface [MWh/year]", True),
    "at_stake_mwh": ("energy at stake, tracking + mirror [MWh/year]", True),
    "efficiency": ("DNI-weighted annual efficiency [-]", False),
}

#: Per-heliostat arrays the report needs (the others of the stored year are shown where present).
_YEAR_REQUIRED = ("energy_mwh", "tracking_loss_mwh", "surface_loss_mwh")
_YEAR_OPTIONAL = ("tracking_loss_low_mwh", "tracking_loss_high_mwh", "surface_loss_low_mwh", "surface_loss_high_mwh",
                  "efficiency", "cosine", "shading", "blocking", "attenuation", "intercept", "reflectance")


def _year_numbers(value, path, field: str, n: int | None) -> np.ndarray:
    """``value`` (tensor, array, list or number) as a float64 array [n]; a one-line error naming the field."""
    try:
        a = np.asarray(value.detach().cpu() if torch.is_tensor(value) else value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputFileError(path, "expected numbers", field=field) from None
    if n is not None and a.shape != (n,):
        raise InputFileError(path, f"expected {n} values (one per heliostat of the plant), found {a.size}",
                             field=field)
    return a


def _year_scalar(group: dict, key: str, path, where: str) -> float:
    v = group.get(key)
    return math.nan if v is None else float(_year_numbers(v, path, f"{where}/{key}", 1)[0])


def year_state(scenario: Scenario) -> dict | None:
    """The plant's year as the report shows it, from ``learned["year"]`` (written by ``heliotwin year``), or
    None when the plant file holds no year.

    Returns
    -------
    dict
        ``year``, ``aim``, ``ids`` [H], ``x_m``, ``y_m`` [H] (east, north [m]), per heliostat [H] (numpy, NaN
        where not stored): ``energy_mwh``, ``tracking_loss_mwh`` / ``_low_mwh`` / ``_high_mwh``,
        ``surface_loss_mwh`` / ``_low_mwh`` / ``_high_mwh``, ``surface_learned`` (bool), the factors
        (``efficiency``, ``cosine``, ..., ``reflectance`` [-]) and ``at_stake_mwh`` (tracking + mirror loss
        [MWh/year]; a mirror that was never learned counts 0, as ideal) with ``at_stake_low_mwh`` /
        ``at_stake_high_mwh`` (the bounds added); ``annual_energy_mwh``, ``annual_dni_energy_on_mirrors_mwh``,
        ``rows_sum_mwh`` (the heliostats' sum), ``monthly_energy_mwh`` [12], ``weather`` (dict: ``file``,
        ``kind``, ``annual``, ...), ``time_convention`` (str), ``dni_share_below_horizon`` [-] and
        ``interpolation`` (``median_error``, ``p95_error``, ``field_error`` [-, relative], ``checked_hours``)
        or None when the year was not checked.

    Raises
    ------
    InputFileError
        A stored array does not have one value per heliostat, or a value is not a number (the field named).
    """
    y = scenario.learned.get(YEAR_KEY)
    if y is None:
        return None
    path, where = scenario.path or "scenario", f"/learned/{YEAR_KEY}"
    if not isinstance(y, dict) or not isinstance(y.get("heliostats"), dict):
        raise InputFileError(path, "expected a group with a 'heliostats' group (heliotwin year writes it)",
                             field=where if not isinstance(y, dict) else f"{where}/heliostats")
    plant = scenario.plant
    n = len(plant.field.ids)
    per = y["heliostats"]
    out = {}
    for key in _YEAR_REQUIRED + _YEAR_OPTIONAL:
        v = per.get(key)
        if v is None and key in _YEAR_REQUIRED:
            raise InputFileError(path, "missing (heliotwin year writes it)", field=f"{where}/heliostats/{key}")
        out[key] = np.full(n, np.nan) if v is None else _year_numbers(v, path, f"{where}/heliostats/{key}", n)
    learned_surface = per.get("surface_learned")
    out["surface_learned"] = np.zeros(n, dtype=bool) if learned_surface is None else \
        _year_numbers(learned_surface, path, f"{where}/heliostats/surface_learned", n) > 0.5
    surface = np.where(np.isfinite(out["surface_loss_mwh"]), out["surface_loss_mwh"], 0.0)
    out["at_stake_mwh"] = out["tracking_loss_mwh"] + surface
    for b in ("low", "high"):  # the bounds added: an interval at least as wide as the sum's
        t, s = out[f"tracking_loss_{b}_mwh"], out[f"surface_loss_{b}_mwh"]
        out[f"at_stake_{b}_mwh"] = np.where(np.isfinite(t), t, out["tracking_loss_mwh"]) \
            + np.where(np.isfinite(s), s, surface)
    monthly = y.get("monthly_energy_mwh")
    out["monthly_energy_mwh"] = np.full(12, np.nan) if monthly is None else \
        _year_numbers(monthly, path, f"{where}/monthly_energy_mwh", 12)
    weather = y.get("weather") if isinstance(y.get("weather"), dict) else {}
    share = weather.get("dni_share_below_horizon", y.get("dni_share_below_horizon"))
    interp = y.get("interpolation")
    if isinstance(interp, dict) and interp:
        interp = {k: _year_scalar(interp, k, path, f"{where}/interpolation")
                  for k in ("median_error", "p95_error", "field_error", "checked_hours")}
    else:
        interp = None
    pos = plant.field.kinematics.position.detach().cpu().to(torch.float64).numpy()
    year = y.get("year")
    out.update(ids=list(plant.field.ids), x_m=pos[:, 0], y_m=pos[:, 1],
               year=None if year is None else int(_year_scalar(y, "year", path, where)),
               aim=str(y.get("aim") or "?"), weather={k: v for k, v in weather.items() if not isinstance(v, dict)},
               time_convention=str(y.get("time_convention") or "not stated"),
               dni_share_below_horizon=math.nan if share is None else
               float(_year_numbers(share, path, f"{where}/weather/dni_share_below_horizon", 1)[0]),
               annual_energy_mwh=_year_scalar(y, "annual_energy_mwh", path, where),
               annual_dni_energy_on_mirrors_mwh=_year_scalar(y, "annual_dni_energy_on_mirrors_mwh", path, where),
               rows_sum_mwh=float(np.nansum(out["energy_mwh"])), interpolation=interp)
    return out


def year_ranking(year: dict, count: int | None = None) -> list[int]:
    """Heliostat indices by the energy at stake (tracking + mirror loss [MWh/year]), largest first (ties in plant
    order; no value last); at most ``count``."""
    key = np.nan_to_num(year["at_stake_mwh"], nan=-np.inf)
    order = np.argsort(-key, kind="stable")
    return [int(i) for i in order[:count]]


def year_row(year: dict, i: int, rank: int | None = None) -> dict:
    """Heliostat ``i``'s year as JSON-ready numbers (NaN -> None): energy, losses with bounds, factors, and its
    ``rank`` by the energy at stake (1 = the most)."""
    keys = ("energy_mwh", "at_stake_mwh", "at_stake_low_mwh", "at_stake_high_mwh") + _YEAR_REQUIRED[1:] \
        + _YEAR_OPTIONAL
    row = {k: (float(year[k][i]) if np.isfinite(year[k][i]) else None) for k in dict.fromkeys(keys)}
    row.update(heliostat=year["ids"][i], surface_learned=bool(year["surface_learned"][i]), rank=rank)
    return row


# ---------------------------------------------------------------------------------------------- workflow
def plant_report(scenario: Scenario, records=None, settings: ReportSettings = ReportSettings()
                 ) -> tuple[Scenario, dict]:
    """The plant page of ``scenario`` (module docstring).

    Parameters
    ----------
    scenario : Scenario
    records : heliotwin.io.records.RecordTable, optional
        Records of a PAINT folder (``--paint``): their times count for "days since the last record".
    settings : ReportSettings

    Returns
    -------
    scenario : Scenario
        Unchanged (a report learns nothing).
    report : dict
        ``html`` (the page, str), ``heliostats``, ``alarms`` (the latest update's, sorted), ``detail`` (ids
        with a section), ``plan`` (heliostat ids planned), ``receiver`` (bool), ``reference_time`` (UTC ISO or
        None), ``tomorrow`` (the plan's day and planned heliostat ids, or its note), ``year`` (None without a
        stored year; else ``year``, ``annual_energy_mwh``, ``top``: the table's ids, most energy at stake first,
        and ``at_stake_mwh``: the plant's sum) and ``seconds`` {state, plan, receiver, page} [s].
    """
    seconds = {}
    t0 = time.perf_counter()
    state = heliostat_state(scenario, records)
    alarms = alarm_rows(scenario)
    with_history = np.isfinite(state["predicted_error_mrad"]) | (state["alarms"] > 0) | (state["surface_learned"] > 0) \
        | (state["nominal"] > 0)
    detail_ids = [state["ids"][i] for i in _ranked(state, len(state["ids"])) if with_history[i]][:settings.detail]
    year = year_state(scenario)
    year_top = [] if year is None else year_ranking(year, settings.year_rows)
    # the heliostats with the most energy at stake get a section too: the year's table links to it
    detail_ids += [year["ids"][i] for i in year_top if year["ids"][i] not in detail_ids]
    details = [heliostat_detail(scenario, h) for h in detail_ids]
    if year is not None:
        where = {h: i for i, h in enumerate(year["ids"])}
        rank = {i: r for r, i in enumerate(year_ranking(year), 1)}
        for d in details:
            d["year"] = year_row(year, where[d["heliostat"]], rank[where[d["heliostat"]]])
        year["top"] = [year_row(year, i, r) for r, i in enumerate(year_top, 1)]
    learned_surfaces = set((scenario.learned.get("surfaces") or {}).keys())
    for d in details:
        if d["heliostat"] in learned_surfaces:
            d["surface"] = surface_deviation(scenario, d["heliostat"])
    seconds["state"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    tomorrow = _tomorrow(scenario, state, alarms, settings)
    plans = _plan_rows(scenario, state, settings, tomorrow)
    seconds["plan"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    receiver = _receiver(scenario, settings)
    seconds["receiver"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    described = describe_scenario(scenario)
    colour = settings.colour  # the chosen one, else the first quantity the plant has values of
    if not np.isfinite(state[colour]).any():
        colour = next((k for k in QUANTITIES if np.isfinite(state[k]).any() and np.nanmax(state[k]) > 0), colour)
    html = render_page(described=described, state=state, quantities=QUANTITIES, colour=colour,
                       alarms=alarms, details=details, plans=plans, receiver=receiver, tomorrow=tomorrow,
                       year=year, year_quantities=YEAR_QUANTITIES)
    seconds["page"] = time.perf_counter() - t0
    ref = state["reference_time"]
    return scenario, {"html": html, "heliostats": len(state["ids"]), "alarms": alarms, "detail": detail_ids,
                      "plan": [p["heliostat"] for p in plans], "receiver": bool(receiver and "maps" in receiver),
                      "reference_time": utc_text(ref) if math.isfinite(ref) else None, "seconds": seconds,
                      "tomorrow": {"day": tomorrow.get("day"), "heliostats": [p["heliostat"] for p in
                                                                             tomorrow.get("proposals", [])],
                                   "note": tomorrow.get("note")},
                      "year": None if year is None else {
                          "year": year["year"], "annual_energy_mwh": year["annual_energy_mwh"],
                          "top": [r["heliostat"] for r in year["top"]],
                          "at_stake_mwh": float(np.nansum(year["at_stake_mwh"]))}}
