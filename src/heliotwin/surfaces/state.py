"""A learned mirror surface in the scenario file.

``heliotwin reconstruct -o plant.h5`` writes one scenario (:mod:`heliotwin.io.scenario`): the learned
control points go into the plant's ``/field/surfaces`` (so every reader traces the learned mirror), and
``/learned/surfaces/<HID>`` keeps what the geometry cannot hold — the learned displacement along the facet
normals, the optics chosen on the training images, the training records and settings, the target the
images were taken on. ``/learned/surface_prior`` holds the plant surface prior the latest reconstruction used
(:mod:`heliotwin.surfaces.plantprior`; a sibling of ``/learned/surfaces``, whose keys are heliostat ids).
"""
from __future__ import annotations

import dataclasses
import json

import torch

from ..errors import HeliotwinError, InputFileError
from ..field import facets as facet_ops
from ..field.plant import Plant, SunSettings, Surfaces
from ..field.update import with_surfaces
from ..io.scenario import Scenario, next_scenario, provenance_entry

__all__ = ["KEY", "PRIOR_KEY", "surface_state", "with_learned_surface", "learned_surface"]

#: The key of learned surfaces under ``Scenario.learned``.
KEY = "surfaces"
#: The ``Scenario.learned`` key of a stored plant surface prior (:mod:`heliotwin.surfaces.plantprior`).
PRIOR_KEY = "surface_prior"


def surface_state(displacement: torch.Tensor, optics: SunSettings, *, train_records, target: str,
                  settings: dict) -> dict:
    """The ``/learned/surfaces/<HID>`` entry of one learned heliostat.

    Parameters
    ----------
    displacement : torch.Tensor, [F, nu, nv]
        Learned offsets along the facet normals [m].
    optics : SunSettings
        Sunshape and slope error the surface was learned (and is to be traced) with.
    train_records : sequence of int
        Record ids of the training images.
    target : str
        Target the training images were taken on (the default for prediction).
    settings : dict
        Training settings (JSON values).
    """
    return {"displacement": displacement.detach().to(torch.float64).cpu(),
            "optics": json.dumps(dataclasses.asdict(optics)),
            "train_records": torch.as_tensor([int(r) for r in train_records], dtype=torch.long),
            "target": str(target), "settings": json.dumps(settings, allow_nan=False)}


def with_learned_surface(previous: Scenario | None, plant: Plant, heliostat_id: str, surfaces: Surfaces,
                         displacement: torch.Tensor, optics: SunSettings, *, train_records=(), target: str = "",
                         settings: dict | None = None, source: str = "",
                         surface_prior: dict | None = None) -> Scenario:
    """The scenario after one heliostat's surface was learned (plant″), in memory; the caller writes it
    (:func:`heliotwin.io.scenario.write_scenario`).

    Parameters
    ----------
    previous : heliotwin.io.scenario.Scenario or None
        The scenario ``plant`` came from (learned state and provenance kept), None for a PAINT folder's plant.
    plant : Plant
        The whole plant the step started from (a scenario's or the PAINT folder's).
    heliostat_id : str
    surfaces : Surfaces
        The learned surface, ``control_points`` [1, F, nu, nv, 3] [m], heliostat frame.
    displacement : torch.Tensor, [1, F, nu, nv] or [F, nu, nv]
        Learned offsets along the facet normals [m].
    optics : SunSettings
        Optics chosen for (and used in) the fit.
    train_records, target, settings, source
        Provenance: training record ids, their target, the fit settings (JSON values), the PAINT folder.
    surface_prior : dict, optional
        The plant surface prior used (:meth:`heliotwin.surfaces.plantprior.SurfacePrior.state`), stored under
        ``/learned/surface_prior`` (replacing one ``previous`` held); None keeps ``previous``'s.

    Returns
    -------
    heliotwin.io.scenario.Scenario
        With the learned control points in ``plant.field.surfaces``, the entry under
        ``learned["surfaces"][heliostat_id]`` and one ``"reconstruct"`` provenance step; not written.
    """
    learned = dict(previous.learned) if previous is not None else {}
    entries = dict(learned.get(KEY) or {})
    entries[heliostat_id] = surface_state(displacement.reshape(displacement.shape[-3:]), optics,
                                          train_records=train_records, target=target, settings=settings or {})
    learned[KEY] = entries
    if surface_prior is not None:
        learned[PRIOR_KEY] = surface_prior
    step = provenance_entry("reconstruct", heliostat=heliostat_id, source=str(source),
                            records=[int(r) for r in train_records], settings=settings or {})
    return next_scenario(previous, with_surfaces(plant, [heliostat_id], surfaces), learned=learned, step=step)


def learned_surface(scenario, heliostat_id: str) -> dict:
    """One heliostat's learned surface from a scenario, with its ideal counterpart on the same net.

    Returns
    -------
    dict
        ``surfaces`` and ``ideal`` (:class:`Surfaces`, 1 heliostat: control points ``[1, F, nu, nv, 3]`` [m],
        heliostat frame), ``facets`` (:class:`~heliotwin.field.plant.Facets`, ``[1, F, 3]`` [m]), ``optics``
        (:class:`SunSettings`), ``target`` (name), ``train_records`` (list of int), ``settings`` (dict).
    """
    plant: Plant = scenario.plant
    entries = scenario.learned.get(KEY) or {}
    if heliostat_id not in entries:
        have = ", ".join(sorted(entries)) or "none"
        raise HeliotwinError(f"{scenario.path}: no learned surface for heliostat {heliostat_id} (learned: {have}); "
                             f"run 'heliotwin reconstruct' first")
    e = entries[heliostat_id]
    where = f"/learned/{KEY}/{heliostat_id}"
    try:
        optics = SunSettings(**json.loads(e["optics"]))
        settings = json.loads(e["settings"])
        target = str(e["target"])
        train = [int(r) for r in torch.as_tensor(e["train_records"]).tolist()]
    except (KeyError, TypeError, ValueError) as exc:
        raise InputFileError(scenario.path, f"malformed learned-surface entry ({exc})", field=where) from None
    h = plant.field.index_of(heliostat_id)
    sf = plant.field.surfaces
    cp = sf.control_points[h:h + 1]
    facets = dataclasses.replace(plant.field.facets, **{f.name: getattr(plant.field.facets, f.name)[h:h + 1]
                                                        for f in dataclasses.fields(plant.field.facets)})
    ideal = facet_ops.ideal_surfaces(facets, (cp.shape[2], cp.shape[3]), (sf.degree_u, sf.degree_v))
    return {"surfaces": Surfaces(cp, sf.degree_u, sf.degree_v), "ideal": ideal, "facets": facets, "optics": optics,
            "target": target, "train_records": train, "settings": settings}
