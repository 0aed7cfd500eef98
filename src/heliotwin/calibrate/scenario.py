"""A calibration in the scenario file, and aiming with it.

``heliotwin calibrate -o plant.h5`` writes one scenario (:mod:`heliotwin.io.scenario`): the plant with the
calibrated static kinematics in ``/field/kinematics`` (so every reader traces the calibrated plant), and
under ``/learned/calibration`` what the plant geometry cannot hold — the deviations from the kinematics
they were fitted against, the networks of ``hybrid`` / ``mlp``, the field prior — plus a provenance step.
:func:`aim` answers "which motor steps put the sun's reflection on this point" from such a file.
"""
from __future__ import annotations

import json
from dataclasses import fields

import torch

from ..errors import HeliotwinError, InputFileError
from ..field import kinematics as K
from ..field.plant import Kinematics, Plant
from ..field.update import with_kinematics
from ..io.scenario import Scenario, next_scenario, provenance_entry, write_scenario
from ..sunangles import direction_from_paint_angles
from .methods.hybrid import aim_hybrid
from .methods.mlp import aim_mlp
from .params import STONE8, apply_deviations
from .priors import PlantPrior
from .twinstate import KEY
from .uncertainty import LEVEL, predictive

# KEY (the calibration's key under ``Scenario.learned``) is calibrate.twinstate's, imported above for the readers
# that take it from here.


def _calibrated_rows(model) -> list[int]:
    """Rows (heliostat axis of ``model``) of the heliostats that were calibrated."""
    return model.ok.nonzero().flatten().tolist()


def storable_choice(record: dict | None) -> dict | None:
    """The part of a run's ``settings_choice`` report that a later ``--settings stored`` run can reuse: a
    choice made by CV (``table`` present), or the stored choice a run used; None otherwise."""
    if not record:
        return None
    if "table" in record:
        return record
    return record.get("original") if record.get("used") else None


def calibration_state(model, *, focal_spot: str = "", prior=None, settings_choice: dict | None = None,
                      coverage: dict | None = None) -> dict:
    """The ``/learned/calibration`` entry of a calibrated model (calibrated heliostats only).

    Parameters
    ----------
    model : heliotwin.calibrate.model.Calibrated
        H heliostats, ``ok`` [H] says which were calibrated.
    focal_spot : str
        Centroid source the method was scored on.
    prior : (torch.Tensor [P], torch.Tensor [P]) or PlantPrior or None
        Field prior mean and standard deviation over ``model.names`` (rad, m, relative), when one was used, or
        a plant prior (:class:`~heliotwin.calibrate.priors.PlantPrior`: mean, sigma, covariance [P, P] and the
        heliostats it was learned from). A field prior of the run's own records lists the calibrated
        heliostats as its sources (so ``--prior-from`` refuses it for them).
    settings_choice : dict, optional
        The lm settings chosen by leave-heliostats-out CV
        (:func:`heliotwin.calibrate.protocol.selection.choose_for_run`'s record), stored as JSON text for
        ``--settings stored`` (:func:`heliotwin.calibrate.protocol.selection.stored_choice`).
    coverage : dict, optional
        What the run did with every heliostat (:func:`coverage_entry`'s input): ``expected_error_mrad``
        {id: float}, ``reduced`` {id: parameter set}, ``nominal`` {id: why}, ``residuals`` (per fitted record:
        ``record_id``, ``heliostat`` id list, ``time`` [s], ``error_mrad``). Stored as ``expected_error_mrad``
        [Hc] (NaN where unknown), ``coverage`` (JSON text) and ``residuals`` (arrays, ``heliostat`` indexing
        ``heliostats``): what ``scenario show``, ``score`` and ``report`` name and draw.

    Returns
    -------
    dict
        Encodable by :func:`heliotwin.io.scenario.save_scenario` (tensors, str, lists of str, dicts).
    """
    ok = _calibrated_rows(model)
    ids = [model.heliostat_ids[h] for h in ok]
    state = {"method": str(model.method), "focal_spot": str(focal_spot), "heliostats": ids,
             "parameter_names": [str(n) for n in model.names],
             "deviations": model.delta.detach()[ok].to(torch.float64).cpu(),
             "nominal": {f.name: getattr(model.nominal, f.name)[ok].detach().cpu() for f in fields(Kinematics)}}
    post = model.extras.get("posterior")
    if post:  # what aim needs for the expected error and its interval (Laplace posterior, see uncertainty.py)
        state["posterior"] = {"covariance": post["covariance"].detach()[ok].to(torch.float64).cpu(),
                              "noise_rad": post["noise_rad"].detach()[ok].to(torch.float64).cpu(),
                              "drift_rad": torch.tensor([float(post.get("drift_rad", 0.0))], dtype=torch.float64),
                              "walk_scale": torch.tensor([float(post.get("walk_scale", 1.0))], dtype=torch.float64)}
    ds = model.extras.get("drift_state")
    if ds:  # the random-walk offset (drift.py): already inside "deviations"; its state lets aim grow the
        # uncertainty with the time since the latest training record, and a later run start from it
        state["drift"] = {"model": "kalman",
                          "names": [STONE8[c] for c in ds["columns"].tolist()],
                          "offset": ds["offset"].detach()[ok].to(torch.float64).cpu(),
                          "covariance": ds["covariance"].detach()[ok].to(torch.float64).cpu(),
                          "time": ds["time"].detach()[ok].to(torch.float64).cpu(),
                          "process_noise_rad2_per_day": torch.tensor([float(ds["q"])], dtype=torch.float64),
                          **({"record_noise_rad": ds["record_noise"].detach()[ok].to(torch.float64).cpu(),
                              "filter_scale": torch.tensor([float(ds["filter_scale"])], dtype=torch.float64)}
                             if "record_noise" in ds else {}),
                          "static_deviations": ds["static_deviations"].detach()[ok].to(torch.float64).cpu()}
    networks = model.extras.get("networks") or {}
    if networks:
        state["networks"] = {hid: {"config": json.dumps(net["config"]),
                                   "state": {k: v.detach().cpu() for k, v in net["state"].items()}}
                             for hid, net in networks.items() if hid in ids}
    if settings_choice:
        state["settings_choice"] = json.dumps(settings_choice)
    if coverage:
        state.update(coverage_entry(coverage, ids))
    if isinstance(prior, PlantPrior):
        state["prior"] = prior.state()
    elif prior is not None:
        state["prior"] = {"names": [str(n) for n in model.names], "mean": torch.as_tensor(prior[0]).double(),
                          "sigma": torch.as_tensor(prior[1]).double(), "heliostats": list(ids)}
    return state


def coverage_entry(coverage: dict, ids: list) -> dict:
    """The stored form of a run's ``coverage`` (see :func:`calibration_state`) over the calibrated ``ids``."""
    expected = coverage.get("expected_error_mrad") or {}
    out = {"expected_error_mrad": torch.tensor([float(expected.get(h) if expected.get(h) is not None else "nan")
                                                for h in ids], dtype=torch.float64),
           "coverage": json.dumps({k: coverage.get(k) for k in ("reduced", "nominal", "min_records", "rule")})}
    res = coverage.get("residuals")
    if res and len(res.get("record_id", [])):
        where = {h: i for i, h in enumerate(ids)}
        rows = [i for i, h in enumerate(res["heliostat"]) if h in where]
        out["residuals"] = {
            "record_id": torch.as_tensor([int(res["record_id"][i]) for i in rows], dtype=torch.int64),
            "heliostat": torch.as_tensor([where[res["heliostat"][i]] for i in rows], dtype=torch.int64),
            "time": torch.as_tensor([float(res["time"][i]) for i in rows], dtype=torch.float64),
            "error_mrad": torch.as_tensor([float(res["error_mrad"][i]) for i in rows], dtype=torch.float64)}
    return out


def calibrated_plant(plant: Plant, model) -> Plant:
    """``plant`` with the calibrated static kinematics of every calibrated heliostat of ``model``."""
    ok = _calibrated_rows(model)
    if not ok:
        return plant
    return with_kinematics(plant, [model.heliostat_ids[h] for h in ok], model.kinematics.index(ok))


def calibrated_scenario(plant: Plant, model, *, previous: Scenario | None = None, focal_spot: str = "",
                        records: dict | None = None, settings: dict | None = None, source: str = "",
                        settings_choice: dict | None = None, coverage: dict | None = None) -> Scenario:
    """The calibrated plant as a scenario, in memory (plant′ = ``plant`` with the calibrated kinematics, the
    calibration under ``/learned/calibration`` and one ``calibrate`` provenance step).

    Parameters
    ----------
    plant : Plant
        The plant the calibration started from (nominal PAINT plant or a scenario's).
    model : heliotwin.calibrate.model.Calibrated
    previous : heliotwin.io.scenario.Scenario, optional
        The scenario ``plant`` came from: its learned state (surfaces, ...) and provenance are kept; its
        calibration is replaced.
    focal_spot : str
        Centroid source scored on.
    records : dict, optional
        Heliostat id -> record ids the method saw (training and validation), for the provenance.
    settings : dict, optional
        The run's settings (JSON values).
    source : str
        Where the records came from (the PAINT folder).
    settings_choice : dict, optional
        The run's ``settings_choice`` report; what :func:`storable_choice` keeps of it is stored.
    coverage : dict, optional
        What the run did with every heliostat (:func:`calibration_state`).

    Returns
    -------
    heliotwin.io.scenario.Scenario
        Not yet written (:func:`heliotwin.io.scenario.write_scenario` writes it).
    """
    prior = (model.extras.get("learned_plant_prior") or model.extras.get("plant_prior")
             or model.extras.get("field_prior"))
    prior = (prior["mean"], prior["sigma"]) if isinstance(prior, dict) and "mean" in prior else prior
    learned = dict(previous.learned) if previous is not None else {}
    learned[KEY] = calibration_state(model, focal_spot=focal_spot, prior=prior,
                                     settings_choice=storable_choice(settings_choice), coverage=coverage)
    step = provenance_entry("calibrate", method=str(model.method), source=str(source), records=records or {},
                            calibrated=list(learned[KEY]["heliostats"]), settings=settings or {})
    return next_scenario(previous, calibrated_plant(plant, model), learned=learned, step=step)


def save_calibration(path, plant: Plant, model, **options):
    """Write :func:`calibrated_scenario` (same ``options``) to ``path``; returns the path written."""
    return write_scenario(calibrated_scenario(plant, model, **options), path)


def network_entry(learned: dict, heliostat_id: str, path="") -> dict | None:
    """The stored network of one heliostat as ``{"config": dict, "state": dict}``, or None (rigid body)."""
    nets = (learned.get(KEY) or {}).get("networks") or {}
    entry = nets.get(heliostat_id)
    if entry is None:
        return None
    try:
        config = json.loads(entry["config"])
        state = dict(entry["state"])
    except (KeyError, TypeError, ValueError):
        raise InputFileError(path, "malformed network entry", field=f"/learned/{KEY}/networks/{heliostat_id}") from None
    return {"config": config, "state": state}


def aim(scenario, heliostat_id: str, sun_azimuth: float, sun_elevation: float, aim_point,
        time: float | None = None) -> dict:
    """Motor steps that put the sun's reflection on ``aim_point`` with the scenario's (calibrated) plant.

    Parameters
    ----------
    scenario : heliotwin.io.scenario.Scenario
        Any scenario: nominal kinematics when nothing was calibrated, plus the stored network of a
        ``hybrid`` / ``mlp`` calibration.
    heliostat_id : str
    sun_azimuth, sun_elevation : float
        [rad], PAINT convention (azimuth 0 = south, +pi/2 = east).
    aim_point : sequence of 3 float
        ENU [m].
    time : float, optional
        When: UTC POSIX seconds [s]. With a drift model (``--drift kalman``) the steps use the offset at the latest
        training time (its best prediction at any later time); its uncertainty grows by ``q (time - t_l)``
        (default: at ``t_l``). The answer then also has ``drift_days`` (time since that record).

    Returns
    -------
    dict
        ``motor_steps`` [2] (real-valued), ``reachable`` (bool), ``method`` (``nominal`` when uncalibrated);
        for a rigid-body calibration with a stored posterior also ``expected_error_mrad`` and
        ``error_interval_90_mrad`` (``[0, q_0.9]`` of the pointing error, :func:`expected_error`).
    """
    plant = scenario.plant
    h = plant.field.index_of(heliostat_id)
    kin = plant.field.kinematics.index([h])
    cal = scenario.learned.get(KEY) or {}
    ids = cal.get("heliostats") or []
    if not isinstance(ids, list) or not all(isinstance(i, str) for i in ids):
        raise InputFileError(scenario.path, "expected a list of heliostat ids", field=f"/learned/{KEY}/heliostats")
    calibrated = heliostat_id in ids
    sun = direction_from_paint_angles(torch.tensor([sun_azimuth]), torch.tensor([sun_elevation]))
    target = torch.as_tensor(aim_point, dtype=torch.float64).reshape(1, 3)
    if not bool(torch.isfinite(target).all()):
        raise HeliotwinError(f"aim point must be 3 finite numbers, got {list(aim_point)}")
    net = network_entry(scenario.learned, heliostat_id, scenario.path) if calibrated else None
    kind = (net or {}).get("config", {}).get("kind")
    if kind == "mlp":
        steps = aim_mlp(net, kin, sun, target)
    elif kind == "hybrid":
        steps = aim_hybrid(net, kin, sun, target)
    else:
        steps, _ = K.inverse(kin, target, sun, strict=False)
    steps = steps.reshape(-1, 2)[0]
    reachable = bool(((steps >= kin.min_steps[0]) & (steps <= kin.max_steps[0])).all())
    out = {"heliostat": heliostat_id, "motor_steps": [float(s) for s in steps], "reachable": reachable,
           "method": cal.get("method", "nominal") if calibrated else "nominal"}
    if calibrated and kind is None and cal.get("posterior"):
        out.update(expected_error(cal, heliostat_id, steps, scenario.path, time=time))
    return out


def expected_error(cal: dict, heliostat_id: str, steps: torch.Tensor, path="", time: float | None = None) -> dict:
    """Expected pointing error and its 90 % interval ``[0, q_0.9]`` [mrad] at ``steps`` [2] (Laplace posterior).

    ``cal`` is the ``/learned/calibration`` entry; the normal's Jacobian w.r.t. the heliostat's deviations
    is taken at the stored fit (nominal kinematics + deviations), see :mod:`heliotwin.calibrate.uncertainty`.
    """
    where = f"/learned/{KEY}/posterior"
    try:
        j = list(cal["heliostats"]).index(heliostat_id)
        post = cal["posterior"]
        cov = torch.as_tensor(post["covariance"], dtype=torch.float64)[j]
        noise = torch.as_tensor(post["noise_rad"], dtype=torch.float64)[j]
        drift = float(torch.as_tensor(post["drift_rad"]).reshape(-1)[0])
        names = list(cal["parameter_names"])
        nominal = Kinematics(**{f.name: torch.as_tensor(cal["nominal"][f.name])[j:j + 1] for f in fields(Kinematics)})
        delta = torch.as_tensor(cal["deviations"], dtype=torch.float64)[j:j + 1]
    except (KeyError, IndexError, TypeError, ValueError, RuntimeError):
        raise InputFileError(path, "malformed calibration posterior", field=where) from None
    if cov.shape != (len(names), len(names)):
        raise InputFileError(path, f"posterior covariance must be [{len(names)}, {len(names)}]", field=where)
    extra = {}
    if cal.get("drift"):
        cov, extra = _with_drift(cal, j, names, cov, time, path)

    def normal(d):
        rot, _ = K.forward(apply_deviations(nominal, d, names), steps.reshape(1, 2).double())
        return K.mirror_normal(rot).reshape(3)

    jac = torch.autograd.functional.jacobian(normal, delta).reshape(3, len(names))
    with torch.no_grad():
        pred = predictive(jac[None], normal(delta)[None], cov[None], noise.reshape(1), drift=drift)
    return {"expected_error_mrad": float(1e3 * pred["expected"][0]),
            f"error_interval_{round(100 * LEVEL)}_mrad": [float(1e3 * pred["lower"][0]), float(1e3 * pred["upper"][0])],
            **extra}


def _with_drift(cal: dict, j: int, names: list, cov: torch.Tensor, time, path) -> tuple[torch.Tensor, dict]:
    """The posterior covariance [P, P] plus the drifting offset's covariance at ``time`` (drift.py)."""
    where = f"/learned/{KEY}/drift"
    try:
        d = cal["drift"]
        cols = [names.index(n) for n in d["names"]]
        p_l = torch.as_tensor(d["covariance"], dtype=torch.float64)[j]
        t_l = float(torch.as_tensor(d["time"], dtype=torch.float64)[j])
        q = float(torch.as_tensor(d["process_noise_rad2_per_day"]).reshape(-1)[0])
        scale = float(torch.as_tensor(cal["posterior"].get("walk_scale", 1.0)).reshape(-1)[0])
    except (KeyError, IndexError, TypeError, ValueError, RuntimeError):
        raise InputFileError(path, "malformed drift state", field=where) from None
    if p_l.shape != (len(cols), len(cols)):
        raise InputFileError(path, f"drift covariance must be [{len(cols)}, {len(cols)}]", field=where)
    days = 0.0
    if time is not None and torch.isfinite(torch.tensor(t_l)):
        days = max(0.0, (float(time) - t_l) / 86400.0)
    idx = torch.tensor(cols)
    cov = cov.clone()
    cov[idx[:, None], idx[None, :]] += scale * (p_l + q * days * torch.eye(len(cols), dtype=torch.float64))
    return cov, {"drift_days": days}
