"""Aim points as learned state: the ``/learned/aimpoints`` group of a scenario, written and read here only.

Layout of the group (one dict in :attr:`heliotwin.io.scenario.Scenario.learned` under :data:`KEY`)::

    aim [H, 3] ENU [m], sun_direction [3], motor_steps [H, 2], reachable [H] (bool)   the first instant
    peak_limit_w_m2, method, target                                                 the run's settings
    flux_limit_w_m2 [rows, cols], flux_limit_source        an allowable-flux map's run only: every cell's own limit
    instants/<iNNN>/{instant, aim, sun_direction, motor_steps, reachable, power_w, peak_flux_w_m2}

The first instant is repeated at the top so that a reader of one instant needs no index. Motor steps come
from the plant's (possibly calibrated) kinematics (:func:`heliotwin.field.kinematics.inverse`); heliostats
that cannot reach their aim point keep the closest steps and are marked ``reachable = False``.
"""
from __future__ import annotations

import torch

from ..errors import HeliotwinError
from ..field.flux_limit import RANGE_W_M2
from ..field.kinematics import inverse
from ..field.plant import Plant
from .problem import FluxLimit

__all__ = ["KEY", "METHOD", "instant_state", "aimpoint_state", "stored_aimpoints", "stored_peak_limit",
           "stored_flux_limit",
           "PEAK_LIMIT_RANGE_W_M2", "check_peak_limit"]

#: Plausible receiver peak-flux limits [W/m^2]: below 1 kW/m^2 (the sun's own DNI) nothing is a limit the field could
#: hold but standby, above 100 MW/m^2 (about 100 times any receiver's rating) nothing binds; a value outside is a
#: typo or a unit slip (kW/m^2 given as W/m^2). Without the bound, 1e-300 made every ``peak / limit`` inf (the report's
#: JSON refused it at the very end) and the optimiser's margin grow without end.
PEAK_LIMIT_RANGE_W_M2 = RANGE_W_M2  # one range for a peak limit and every cell of an allowable-flux map


def check_peak_limit(limit, where: str = "--peak-limit") -> float:
    """``limit`` [W/m^2] as a float when it is a plausible receiver flux limit (:data:`PEAK_LIMIT_RANGE_W_M2`), else a
    one-line :class:`~heliotwin.errors.HeliotwinError` naming ``where`` (a flag, or a file and dataset)."""
    lo, hi = PEAK_LIMIT_RANGE_W_M2
    try:
        value = float(limit)
    except (TypeError, ValueError):
        value = float("nan")
    if isinstance(limit, bool) or not lo <= value <= hi:
        raise HeliotwinError(f"{where}: expected a receiver peak-flux limit between {lo:.0f} and {hi:.0f} W/m2 "
                             f"(1 kW/m2 .. 100 MW/m2), got {limit!r}")
    return value


#: Name of the learned group.
KEY = "aimpoints"
#: How the stored aim points were found.
METHOD = "augmented-lagrangian on the exact-corrected image model"


def instant_state(plant: Plant, label: str, aim: torch.Tensor, sun_direction: torch.Tensor, *,
                  power_w: float, peak_flux_w_m2: float) -> dict:
    """One instant's entry of the learned group, with the motor steps that realise ``aim``.

    Parameters
    ----------
    plant : Plant
        Its kinematics turn the aim points into motor steps.
    label : str
        The instant (an ISO time or a sun position in words).
    aim : torch.Tensor, [H, 3]
        Aim points, ENU [m].
    sun_direction : torch.Tensor, [3]
        Unit vector towards the sun (ENU).
    power_w, peak_flux_w_m2 : float
        Receiver power [W] and peak flux [W/m^2] at these aim points.

    Returns
    -------
    dict
        ``instant``, ``aim`` [H, 3], ``sun_direction`` [3], ``motor_steps`` [H, 2], ``reachable`` [H] (CPU,
        float64), ``power_w``, ``peak_flux_w_m2``.
    """
    aim = aim.to(torch.float64)
    steps, reachable = inverse(plant.field.kinematics, aim, sun_direction.to(aim.device, torch.float64)[None],
                               strict=False)
    return {"instant": label, "aim": aim.cpu(), "sun_direction": sun_direction.to(torch.float64).cpu(),
            "motor_steps": steps.cpu(), "reachable": reachable.cpu(), "power_w": power_w,
            "peak_flux_w_m2": peak_flux_w_m2}


def aimpoint_state(instants: dict, *, peak_limit_w_m2: float, target: str = "max-power",
                   method: str = METHOD, flux_limit=None) -> dict:
    """The ``/learned/aimpoints`` group from per-instant entries (:func:`instant_state`), keyed ``iNNN``.

    Parameters
    ----------
    instants : dict
        ``{"i000": entry, "i001": ...}`` in time order (at least one).
    peak_limit_w_m2 : float
        The limit every map cell was held to [W/m^2].
    target : str
        ``"max-power"``, ``"uniform"`` or the target map's file.
    method : str
    flux_limit : (torch.Tensor [rows, cols], str), optional
        The allowable-flux map every cell was held under [W/m^2] and where it came from (``peak_limit_w_m2`` is then
        its highest cell).

    Returns
    -------
    dict
        The group (store it as ``learned[KEY]``).
    """
    if not instants:
        raise HeliotwinError("aimpoint_state: no instant to store")
    first = next(iter(instants.values()))
    out = {"aim": first["aim"], "peak_limit_w_m2": float(peak_limit_w_m2), "sun_direction": first["sun_direction"],
           "method": method, "motor_steps": first["motor_steps"], "reachable": first["reachable"],
           "target": target, "instants": instants}
    if flux_limit is not None:
        out["flux_limit_w_m2"] = torch.as_tensor(flux_limit[0], dtype=torch.float64).cpu()
        out["flux_limit_source"] = str(flux_limit[1])
    return out


def stored_peak_limit(scenario) -> float | None:
    """The peak-flux limit [W/m^2] the scenario's stored aim points were optimised under (None: none stored)."""
    state = (scenario.learned or {}).get(KEY)
    if not isinstance(state, dict) or state.get("peak_limit_w_m2") is None:
        return None
    value = torch.as_tensor(state["peak_limit_w_m2"], dtype=torch.float64).reshape(-1)
    where = f"{getattr(scenario, 'path', None) or 'scenario'} [/learned/{KEY}/peak_limit_w_m2]"
    if value.numel() != 1:
        raise HeliotwinError(f"{where}: expected one number, got {value.numel()}")
    return check_peak_limit(float(value[0]), where)


def stored_flux_limit(scenario):
    """The allowable-flux map the scenario's stored aim points were optimised under, a
    :class:`~heliotwin.optimise.problem.FluxLimit` on the stored grid (None: none stored, a peak limit alone)."""
    state = (scenario.learned or {}).get(KEY)
    if not isinstance(state, dict) or state.get("flux_limit_w_m2") is None:
        return None
    where = f"{getattr(scenario, 'path', None) or 'scenario'} [/learned/{KEY}/flux_limit_w_m2]"
    try:
        cells = torch.as_tensor(state["flux_limit_w_m2"], dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise HeliotwinError(f"{where}: expected a numeric map") from None
    if cells.ndim != 2 or not cells.numel():
        raise HeliotwinError(f"{where}: expected a [rows, cols] map, got shape {list(cells.shape)}")
    lo, hi = PEAK_LIMIT_RANGE_W_M2
    if not bool(torch.isfinite(cells).all()) or float(cells.min()) < lo or float(cells.max()) > hi:
        raise HeliotwinError(f"{where}: every cell's limit must be finite, within {lo:.0f}..{hi:.0f} W/m2")
    return FluxLimit(cells, str(state.get("flux_limit_source") or "stored map"))


def stored_aimpoints(scenario, sun_direction: torch.Tensor) -> torch.Tensor:
    """The scenario's aim points for the stored instant whose sun is nearest ``sun_direction``.

    Parameters
    ----------
    scenario : heliotwin.io.scenario.Scenario
    sun_direction : torch.Tensor, [3]
        Unit vector towards the sun (ENU); the result is on its device.

    Returns
    -------
    torch.Tensor, [H, 3], float64
        Aim points, ENU [m] (a scenario with one instant: those, whatever the sun).

    Raises
    ------
    HeliotwinError
        The scenario holds no aim points.
    """
    group = scenario.learned.get(KEY) or {}
    if group.get("aim") is None:
        raise HeliotwinError(f"{scenario.path} [/learned/aimpoints/aim]: no aim points in this scenario "
                             "(use --aim equator)")
    choices = list((group.get("instants") or {}).values()) or [group]
    s = sun_direction.detach().cpu().to(torch.float64)
    best = max(choices, key=lambda c: float(torch.as_tensor(c["sun_direction"], dtype=torch.float64) @ s))
    return torch.as_tensor(best["aim"], dtype=torch.float64, device=sun_direction.device)
