"""A small scenario holding every learned group heliotwin writes (calibration with its posterior and drift
state, an update's assimilation history, a learned surface), and damaged copies of it: what the misuse tests
and ``benchmarks/fuzz_learned.py`` feed the readers of ``/learned``."""
from __future__ import annotations

import shutil
from dataclasses import fields, replace
from pathlib import Path

import h5py
import numpy as np
import torch

from .calibrate import F64, TRUE, jueliche_like, plant_of, simulate

#: Ways one dataset is damaged.
DAMAGES = ("nan", "truncated", "wrong_shape", "wrong_dtype", "missing", "scalar")
DAY = 86400.0


def calibrated_scenario_of(kin, truth: torch.Tensor, train, post: dict):
    """The scenario of an ``lm`` calibration of heliostats ``S0..S{H-1}`` with deviations ``truth`` [H, 8] and
    Laplace posterior ``post``, having seen ``train``'s records (their ids are set to the names); (scenario, ids)."""
    from heliotwin.calibrate.model import Calibrated
    from heliotwin.calibrate.params import STONE8
    from heliotwin.calibrate.scenario import calibrated_scenario

    h = truth.shape[0]
    ids = [f"S{i}" for i in range(h)]
    train.heliostat_ids = ids
    model = Calibrated("lm", ids, kin, STONE8, truth.clone(), torch.ones(h, dtype=torch.bool),
                       extras={"posterior": dict(post, walk_scale=1.0)})
    seen = {ids[j]: train.record_id[train.heliostat_index == j].tolist() for j in range(h)}
    return calibrated_scenario(plant_of(kin, ids), model, records=seen, source="synthetic"), ids


def learned_scenario(path: Path) -> Path:
    """Write a 2-heliostat scenario (``S0``, ``S1``) with ``/learned/{calibration, assimilation, surfaces/S1}``."""
    from heliotwin.calibrate import priors
    from heliotwin.calibrate.methods.lm import laplace
    from heliotwin.calibrate.params import STONE8, apply_deviations
    from heliotwin.field.plant import SunSettings
    from heliotwin.io.records import RecordTable
    from heliotwin.io.scenario import write_scenario
    from heliotwin.surfaces.learning import LearnableSurface
    from heliotwin.surfaces.state import with_learned_surface
    from heliotwin.workflows.update import update

    h, n = 2, 20
    kin = jueliche_like(h)
    truth = torch.tensor([TRUE[k] for k in STONE8], dtype=F64).expand(h, 8).clone()
    train = simulate(apply_deviations(kin, truth, STONE8), n, seed=0, noise=5e-4)
    train.time = 1.6e9 - (n - torch.arange(len(train), dtype=F64) % n) * 7 * DAY
    post = laplace(kin, train, truth, torch.diag(1.0 / priors.sigma_vector(STONE8, priors.STONE8_SIGMA) ** 2))
    sc, ids = calibrated_scenario_of(kin, truth, train, post)
    new = simulate(apply_deviations(kin, truth, STONE8), 4, seed=5, noise=5e-4)
    new.heliostat_ids = ids
    new.record_id = 10 ** 6 + torch.arange(len(new))
    new.time = 1.6e9 + (1 + torch.arange(len(new), dtype=F64)) * DAY
    sc, _ = update(sc, RecordTable.concatenate([train, new]))
    plant = sc.plant
    fac = plant.field.facets
    one = replace(fac, **{f.name: getattr(fac, f.name)[1:2] for f in fields(fac)})
    sf = plant.field.surfaces
    surface = LearnableSurface(one, tuple(sf.control_points.shape[2:4]), (sf.degree_u, sf.degree_v))
    with torch.no_grad():
        surface.displacement_mm.normal_(0.0, 0.3, generator=torch.Generator().manual_seed(1))
    sc = with_learned_surface(sc, plant, "S1", surface.surfaces(), surface.displacement.detach(), SunSettings(),
                              train_records=[1, 2], target=next(iter(plant.targets)), settings={"loss": "kl"})
    return write_scenario(sc, path)


def learned_datasets(path: Path) -> list[str]:
    """Every dataset under ``/learned`` of a scenario file (HDF5 names without the leading slash)."""
    names = []
    with h5py.File(path, "r") as h5:
        h5["learned"].visititems(lambda n, o: names.append(f"learned/{n}") if isinstance(o, h5py.Dataset) else None)
    return names


def damage(src: Path, dst: Path, name: str, how: str) -> bool:
    """Copy ``src`` to ``dst`` with dataset ``name`` damaged ``how`` (one of :data:`DAMAGES`); False when that
    damage does not apply (NaN in an integer or text dataset)."""
    shutil.copyfile(src, dst)
    with h5py.File(dst, "a") as h5:
        ds = h5[name]
        attrs, data = dict(ds.attrs), ds[()]
        text = h5py.check_string_dtype(ds.dtype) is not None
        if how == "nan":
            if text or data.dtype.kind != "f":
                return False
            data = np.array(data, copy=True)
            data.reshape(-1)[0] = np.nan if data.size else np.nan
            if not data.size:
                return False
        elif how == "truncated":
            if np.ndim(data) == 0 or len(data) == 0:
                return False
            data = data[:-1]
        elif how == "wrong_shape":
            data = np.stack([data, data], axis=-1) if np.ndim(data) else np.array([data, data])
        elif how == "wrong_dtype":
            data = np.array(1.5) if text else np.array("text", dtype=object)
        elif how == "scalar":
            if np.ndim(data) == 0:
                return False
            data = np.array(data.reshape(-1)[0]) if data.size else np.array(0.0)
        del h5[name]
        if how == "missing":
            return True
        if data.dtype == object or (how == "wrong_dtype" and not text):
            new = h5.create_dataset(name, data=data, dtype=h5py.string_dtype("utf-8"))
        else:
            new = h5.create_dataset(name, data=data)
        for k, v in attrs.items():
            new.attrs[k] = v
    return True
