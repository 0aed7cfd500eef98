"""A small, self-contained, versioned HDF5 file for one learned heliostat surface.

Layout (``format = "heliotwin-learned-surface"``, ``version = 1``)::

    /                      attrs: format, version, heliostat_id, degree_u, degree_v, created_by,
                                  site_latitude, site_longitude, site_altitude (deg, deg, m),
                                  sun_* (SunSettings used in training), settings_json
    /surface/control_points   [1, F, nu, nv, 3] float64, heliostat frame [m]
    /surface/displacement     [1, F, nu, nv]    float64, learned offsets along the facet normals [m]
    /surface/weights          [1, F, nu, nv]    optional rational weights
    /facets/{translation,canting_e,canting_n}   [1, F, 3] float64 [m]
    /kinematics/<field>       one dataset per :class:`~heliotwin.field.plant.Kinematics` field ([1, ...])
    /targets/<name>           attrs: kind="planar", width, height; datasets center, normal, right, up (3,)

Everything needed to re-trace the heliostat (kinematics, facets, surface, targets, site, optics) is in the
file. Writes are atomic: a temp file in the same folder, then :func:`os.replace`.
"""
from __future__ import annotations

import dataclasses
import json
import os
import tempfile

import numpy as np
import torch

from ..errors import HeliotwinError, InputFileError
from ..io.hdf5 import open_for_reading
from ..field.plant import Facets, Kinematics, SunSettings, Surfaces
from ..field.targets import PlanarTarget

FORMAT = "heliotwin-learned-surface"
VERSION = 1

__all__ = ["LearnedHeliostat", "save_learned", "load_learned", "FORMAT", "VERSION"]


@dataclasses.dataclass
class LearnedHeliostat:
    """Contents of a learned-surface file.

    Attributes
    ----------
    heliostat_id : str
    surfaces : Surfaces
        ``[1, F, nu, nv, 3]``.
    displacement : torch.Tensor, [1, F, nu, nv]
        [m] along the facet normals.
    facets : Facets
    kinematics : Kinematics
        One heliostat.
    targets : dict of str -> PlanarTarget
    site : (float, float, float)
        Latitude, longitude [deg], altitude [m].
    sun : SunSettings
    settings : dict
        Training settings and provenance (free-form JSON).
    """

    heliostat_id: str
    surfaces: Surfaces
    displacement: torch.Tensor
    facets: Facets
    kinematics: Kinematics
    targets: dict
    site: tuple
    sun: SunSettings
    settings: dict = dataclasses.field(default_factory=dict)


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


def save_learned(path, item: LearnedHeliostat) -> None:
    """Write ``item`` to ``path`` atomically (temp file + ``os.replace``)."""
    import h5py

    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise InputFileError(path, "output folder does not exist")
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".h5", dir=directory)
    os.close(fd)
    try:
        with h5py.File(tmp, "w") as h5:
            h5.attrs["format"] = FORMAT
            h5.attrs["version"] = VERSION
            h5.attrs["heliostat_id"] = item.heliostat_id
            h5.attrs["degree_u"] = int(item.surfaces.degree_u)
            h5.attrs["degree_v"] = int(item.surfaces.degree_v)
            h5.attrs["created_by"] = "heliotwin.surfaces"
            for k, v in zip(("site_latitude", "site_longitude", "site_altitude"), item.site):
                h5.attrs[k] = float(v)
            for f in dataclasses.fields(SunSettings):
                h5.attrs[f"sun_{f.name}"] = getattr(item.sun, f.name)
            h5.attrs["settings_json"] = json.dumps(item.settings)
            g = h5.create_group("surface")
            g["control_points"] = _np(item.surfaces.control_points.to(torch.float64))
            g["displacement"] = _np(item.displacement.to(torch.float64))
            if item.surfaces.weights is not None:
                g["weights"] = _np(item.surfaces.weights.to(torch.float64))
            g = h5.create_group("facets")
            for name in ("translation", "canting_e", "canting_n"):
                g[name] = _np(getattr(item.facets, name))
            g = h5.create_group("kinematics")
            for f in dataclasses.fields(Kinematics):
                g[f.name] = _np(getattr(item.kinematics, f.name))
            g = h5.create_group("targets")
            for name, t in item.targets.items():
                if not isinstance(t, PlanarTarget):
                    continue  # the cylinder is not needed to re-trace on calibration targets
                tg = g.create_group(name)
                tg.attrs["kind"] = "planar"
                tg.attrs["width"] = float(t.width)
                tg.attrs["height"] = float(t.height)
                for k in ("center", "normal", "right", "up"):
                    tg[k] = _np(getattr(t, k))
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def load_learned(path) -> LearnedHeliostat:
    """Read a file written by :func:`save_learned`; one-line :class:`InputFileError` on any problem."""
    path = os.fspath(path)
    with open_for_reading(path) as h5:
        if h5.attrs.get("format") != FORMAT:
            raise InputFileError(path, f"not a learned-surface file (format {h5.attrs.get('format')!r})", field="format")
        if int(h5.attrs.get("version", -1)) != VERSION:
            raise InputFileError(path, f"unsupported version {h5.attrs.get('version')!r} (expected {VERSION})",
                                 field="version")

        def ds(name):
            if name not in h5:
                raise InputFileError(path, "missing dataset", field=name)
            return torch.from_numpy(np.asarray(h5[name][()]))

        try:
            cp = ds("surface/control_points")
            weights = ds("surface/weights") if "surface/weights" in h5 else None
            surfaces = Surfaces(cp, int(h5.attrs["degree_u"]), int(h5.attrs["degree_v"]), weights)
            facets = Facets(ds("facets/translation"), ds("facets/canting_e"), ds("facets/canting_n"))
            kin = Kinematics(**{f.name: ds(f"kinematics/{f.name}") for f in dataclasses.fields(Kinematics)})
            targets = {}
            for name, tg in h5["targets"].items():
                targets[name] = PlanarTarget(name, *(torch.from_numpy(np.asarray(tg[k][()])) for k in
                                                     ("center", "normal", "right", "up")),
                                             float(tg.attrs["width"]), float(tg.attrs["height"]))
            sun = SunSettings(**{f.name: type(f.default)(h5.attrs[f"sun_{f.name}"])
                                 for f in dataclasses.fields(SunSettings) if f"sun_{f.name}" in h5.attrs})
            site = tuple(float(h5.attrs[k]) for k in ("site_latitude", "site_longitude", "site_altitude"))
            settings = json.loads(h5.attrs.get("settings_json", "{}"))
            hid = str(h5.attrs["heliostat_id"])
            disp = ds("surface/displacement")
        except KeyError as exc:
            raise InputFileError(path, f"missing attribute or group {exc}") from None
    if cp.dim() != 5 or cp.shape[0] != 1 or cp.shape[-1] != 3:
        raise InputFileError(path, f"expected [1, F, nu, nv, 3], got {list(cp.shape)}", field="surface/control_points")
    if not targets:
        raise HeliotwinError(f"{path}: no planar targets stored")
    return LearnedHeliostat(hid, surfaces, disp, facets, kin, targets, site, sun, settings)
