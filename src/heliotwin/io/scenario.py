"""Scenario files: the plant and everything heliotwin learned about it, in one versioned HDF5 file.

The scenario is the one currency between steps: ``scenario from-paint`` writes the nominal plant,
``calibrate`` writes it back with calibrated kinematics, ``reconstruct`` with learned surfaces, and
``trace`` / ``validate`` / ``aim`` / ``predict`` read whatever the last step wrote. It holds the site,
the tower targets, the heliostat field (kinematics, facets, NURBS surfaces), the sun/optics settings,
the ``learned`` state that is not plain plant geometry (calibration deviations, networks, field prior,
surface-learning settings), the ``provenance`` of every step, free-form ``extras`` and ``metadata``.

The plant in the file is always the *current best* plant: ``/field/kinematics`` are the calibrated
kinematics once a calibration ran and ``/field/surfaces`` the learned control points once a surface was
learned, so a reader that knows nothing about learning still traces the learned plant.

Layout (format ``"heliotwin-scenario"``, version 2; version 1 is version 2 without ``/learned`` and
``/provenance`` and still loads)::

    /                       attrs: format = "heliotwin-scenario", version = 2
    /metadata               attrs: one per metadata key (str, int, float, bool stored natively; lists,
                            dicts and None as JSON text, their keys listed in the attr "_json_keys")
    /site                   attrs: latitude_deg, longitude_deg, altitude_m, name
    /targets/<name>         one group per target, in insertion order; attrs: kind ("planar" |
                            "cylinder"), name, width, height (planar) or radius, height, opening_angle
                            (cylinder); datasets center, normal, right, up, shape (3,) float64
    /field                  datasets: ids [H] (UTF-8), width [H], height [H], renovation [H or 0] (UTF-8)
    /field/kinematics       one dataset per Kinematics attribute, [H, ...]; bool ones stay bool
    /field/facets           translation, canting_e, canting_n, [H, F, 3]
    /field/surfaces         control_points [H, F, nu, nv, 3], optional weights [H, F, nu, nv];
                            attrs degree_u, degree_v
    /sun                    attrs: one per SunSettings attribute
    /extras                 optional: one dataset per entry (attr "type": "torch", "numpy", "scalar",
                            "str", "strs" for a list of str); nested dicts become sub-groups
    /learned                optional, same encoding as /extras; the keys heliotwin writes:
        calibration/        method, focal_spot, heliostats [Hc] (strs), parameter_names [P] (strs),
                            deviations [Hc, P] (rad, m, relative increments; from the nominal
                            kinematics), nominal/<Kinematics field> [Hc, ...] (the kinematics the
                            deviations are relative to), networks/<HID>/{config (JSON str), state/...}
                            for ``hybrid`` / ``mlp``, prior/{names, mean [P], sigma [P], and for a
                            plant prior covariance [P, P], heliostats (its sources), settings},
                            posterior/{covariance [Hc, P, P], noise_rad [Hc], drift_rad [1]} (the
                            Laplace predictive error ``aim`` reports; method lm)
        surfaces/<HID>/     settings (JSON str), displacement [F, nu, nv] (learned offsets along the
                            facet normals [m]), optics (JSON str), train_records [n] (record ids), target
        surface_prior/      the plant surface prior a reconstruction used (``reconstruct
                            --surface-prior-from``; :mod:`heliotwin.surfaces.plantprior`): per-facet
                            low-order shape mean [F, K] (rad) and covariance [F K, F K], its source
                            heliostats and settings
        aimpoints/          aim points and their motor steps (``heliotwin aimpoints``; see
                            :mod:`heliotwin.optimise.aimpoints`)
        year/               the plant's year heliostat by heliostat (``heliotwin year``; see
                            :func:`heliotwin.workflows.year.year_state`)
    /extras/atmosphere      optional: the attenuation model of a layout-built plant
                            (:mod:`heliotwin.atmosphere`)
    /provenance             optional: one UTF-8 JSON string, a list of steps, each
                            {"step", "utc", "heliotwin", ...} (method, records, settings, source)

Every array keeps its dtype (float64 stays float64, bit for bit; bool stays bool). Writing is atomic: the
file is written to a temporary file in the destination folder and moved into place with
:func:`os.replace`, so an error never leaves a half-written scenario (an existing file is kept intact).
Reading validates everything and raises :class:`~heliotwin.errors.InputFileError` (or
:class:`~heliotwin.errors.ScenarioVersionError` for another format or version) with a one-line message
naming the file and the HDF5 object (``/field/kinematics/position``, ``/site@latitude_deg``).

Changing the layout means bumping :data:`VERSION` and teaching :func:`load_scenario` to read (migrate)
the older versions it still supports.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import io
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
import torch

from .. import __version__
from ..atmosphere import ATMOSPHERE_MODELS, Atmosphere
from ..errors import HeliotwinError, InputFileError, ScenarioVersionError
from ..field.layout import MAX_DISTANCE_M, MAX_MIRROR_M, MIN_MIRROR_M, check_attenuation, require_regular_file
from ..field.plant import Facets, Field, Kinematics, Plant, SunSettings, Surfaces
from ..field.targets import CylinderTarget, PlanarTarget
from ..field.update import select_heliostats
from ..site import Site, site_problem
from .paint import list_heliostats, load_paint
from .report import atomic_path

#: Root attribute ``format`` of every scenario file.
FORMAT = "heliotwin-scenario"
#: Layout version written by this heliotwin.
VERSION = 2
#: Versions this heliotwin reads (1: no learned state, no provenance).
READABLE_VERSIONS = (1, 2)

_TARGET_CLASSES = {"planar": PlanarTarget, "cylinder": CylinderTarget}
#: Trailing shapes of the Kinematics tensors (after the heliostat axis); unlisted ones are not checked.
_KINEMATICS_TRAILING = {"position": (3,), "joint_translation": (2, 3), "concentrator_translation": (3,),
                        "joint_tilt": (2, 3), "concentrator_tilt": (3,)}
_KINEMATICS_BOOL = ("clockwise", "linear")
#: Kinematics fields that may hold NaN (limits a PAINT file does not give).
_KINEMATICS_OPTIONAL = ("min_angle", "max_angle")
_STR = h5py.string_dtype("utf-8")


@dataclass
class Scenario:
    """What :func:`load_scenario` returns; unpacks as ``plant, extras, metadata = load_scenario(path)``.

    Attributes
    ----------
    plant : Plant
        Tensors on the CPU, dtypes as stored.
    extras : dict
        Name -> torch.Tensor / numpy.ndarray / Python scalar / str / list of str / nested dict, as saved.
    metadata : dict
        Name -> str / int / float / bool / JSON value; always has ``created_by`` and ``created_utc``.
    version : int
        Format version of the file.
    path : str
    learned : dict
        The learned state (see the module docstring); ``{}`` for a nominal plant or a version-1 file.
    provenance : list of dict
        One entry per step that wrote the file, oldest first (see :func:`provenance_entry`).
    """

    plant: Plant
    extras: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    version: int = VERSION
    path: str = ""
    learned: dict = field(default_factory=dict)
    provenance: list = field(default_factory=list)

    def __iter__(self):
        return iter((self.plant, self.extras, self.metadata))


# ============================================================================================ writing
def _one_line(text) -> str:
    return " ".join(str(text).split())


def _fail_write(path, name: str, message: str):
    raise HeliotwinError(f"{path} [{name}]: {message}")


def _to_numpy(t, path, name: str) -> np.ndarray:
    if isinstance(t, torch.Tensor):
        try:
            return t.detach().cpu().resolve_conj().resolve_neg().numpy()
        except (TypeError, RuntimeError):
            _fail_write(path, name, f"dtype {t.dtype} has no numpy/HDF5 equivalent; convert it first")
    if isinstance(t, np.ndarray):
        if t.dtype.kind not in "biufc":
            _fail_write(path, name, f"numpy dtype {t.dtype} is not numeric/bool")
        return t
    _fail_write(path, name, f"expected a tensor, got {type(t).__name__}")


def _check_name(path, where: str, name) -> str:
    if not isinstance(name, str) or not name or "/" in name or name in (".", ".."):
        _fail_write(path, where, f"name {name!r} must be a non-empty string without '/'")
    return name


def _is_tensor_field(f: dataclasses.Field) -> bool:
    return "Tensor" in str(f.type)


def _write_dataclass(group: h5py.Group, obj, path, where: str) -> None:
    """Tensor attributes -> datasets, str/int/float/bool -> attrs, None -> omitted."""
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        name = f"{where}/{f.name}"
        if v is None:
            continue
        if _is_tensor_field(f) or isinstance(v, (torch.Tensor, np.ndarray)):
            group.create_dataset(f.name, data=_to_numpy(v, path, name))
        elif isinstance(v, (bool, int, float, str, np.generic)):
            group.attrs[f.name] = v
        else:
            _fail_write(path, name, f"cannot store a {type(v).__name__}")


def _write_metadata(group: h5py.Group, metadata: dict, path) -> None:
    json_keys = []
    for key, value in metadata.items():
        _check_name(path, "/metadata", key)
        if key == "_json_keys":
            _fail_write(path, "/metadata", "the key '_json_keys' is reserved")
        if isinstance(value, os.PathLike):
            value = os.fspath(value)
        if isinstance(value, (str, bool, int, float, np.bool_, np.integer, np.floating)):
            group.attrs[key] = value
        else:
            try:
                group.attrs[key] = json.dumps(value)
            except (TypeError, ValueError) as exc:
                _fail_write(path, f"/metadata@{key}", f"not a str/number/bool or JSON value ({_one_line(exc)})")
            json_keys.append(key)
    group.attrs["_json_keys"] = json.dumps(json_keys)


#: Numeric arrays of ``/learned`` this large [bytes] or larger are stored chunked and compressed (byte shuffle +
#: gzip: lossless, read back unchanged); smaller ones contiguous, where a chunk index would cost more than it saves.
COMPRESS_BYTES = 16 * 1024


def _array_dataset(group: h5py.Group, key: str, data: np.ndarray) -> h5py.Dataset:
    """``data`` as the dataset ``key`` of ``group``: compressed when large and numeric (:data:`COMPRESS_BYTES`)."""
    if data.nbytes >= COMPRESS_BYTES and data.ndim >= 1 and data.dtype.kind in "biuf":
        return group.create_dataset(key, data=data, chunks=True, shuffle=True, compression="gzip",
                                    compression_opts=4)
    return group.create_dataset(key, data=data)


def _write_extras(group: h5py.Group, extras: dict, path, where: str) -> None:
    if not isinstance(extras, dict):
        _fail_write(path, where, f"extras must be a dict, got {type(extras).__name__}")
    for key, value in extras.items():
        _check_name(path, where, key)
        name = f"{where}/{key}"
        if isinstance(value, dict):
            _write_extras(group.create_group(key, track_order=True), value, path, name)
            continue
        if isinstance(value, torch.Tensor):
            ds, kind = _array_dataset(group, key, _to_numpy(value, path, name)), "torch"
        elif isinstance(value, np.ndarray):
            ds, kind = _array_dataset(group, key, _to_numpy(value, path, name)), "numpy"
        elif isinstance(value, (bool, int, float, np.bool_, np.integer, np.floating)):
            ds, kind = group.create_dataset(key, data=np.asarray(value)), "scalar"
        elif isinstance(value, str):
            ds, kind = group.create_dataset(key, data=value, dtype=_STR), "str"
        elif isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
            ds, kind = group.create_dataset(key, data=np.array(list(value), dtype=object), dtype=_STR), "strs"
        else:
            _fail_write(path, name, f"values must be tensors, arrays, numbers, str, lists of str or dicts, got "
                                    f"{type(value).__name__}")
        ds.attrs["type"] = kind


def _write_plant(h5: h5py.File, plant: Plant, path) -> None:
    s = plant.site
    g = h5.create_group("site")
    g.attrs.update({"latitude_deg": float(s.latitude_deg), "longitude_deg": float(s.longitude_deg),
                    "altitude_m": float(s.altitude_m), "name": str(s.name)})

    tg = h5.create_group("targets", track_order=True)
    for key, target in plant.targets.items():
        _check_name(path, "/targets", key)
        if target.kind not in _TARGET_CLASSES or not isinstance(target, _TARGET_CLASSES[target.kind]):
            _fail_write(path, f"/targets/{key}", f"unknown target type {type(target).__name__} (kind {target.kind!r})")
        if target.name != key:
            _fail_write(path, f"/targets/{key}", f"target is stored under {key!r} but named {target.name!r}")
        _write_dataclass(tg.create_group(key), target, path, f"/targets/{key}")

    fl = plant.field
    fg = h5.create_group("field")
    fg.create_dataset("ids", data=np.array(list(fl.ids), dtype=object), dtype=_STR)
    fg.create_dataset("width", data=_to_numpy(fl.width, path, "/field/width"))
    fg.create_dataset("height", data=_to_numpy(fl.height, path, "/field/height"))
    fg.create_dataset("renovation", data=np.array(list(fl.renovation), dtype=object), dtype=_STR)
    _write_dataclass(fg.create_group("kinematics"), fl.kinematics, path, "/field/kinematics")
    _write_dataclass(fg.create_group("facets"), fl.facets, path, "/field/facets")
    sg = fg.create_group("surfaces")
    sg.create_dataset("control_points",
                      data=_to_numpy(fl.surfaces.control_points, path, "/field/surfaces/control_points"))
    if fl.surfaces.weights is not None:
        sg.create_dataset("weights", data=_to_numpy(fl.surfaces.weights, path, "/field/surfaces/weights"))
    sg.attrs["degree_u"] = int(fl.surfaces.degree_u)
    sg.attrs["degree_v"] = int(fl.surfaces.degree_v)

    _write_dataclass(h5.create_group("sun"), plant.sun, path, "/sun")


def save_scenario(plant: Plant, path, extras: dict | None = None, metadata: dict | None = None, *,
                  learned: dict | None = None, provenance: list | None = None) -> Path:
    """Write a plant (and learned state, provenance, extras, metadata) to a scenario file, atomically.

    Parameters
    ----------
    plant : Plant
        Any dtypes/devices; tensors are detached and copied to the CPU. Shapes must be consistent
        (``[H, ...]`` kinematics, ``[H, F, 3]`` facets, ``[H, F, nu, nv, 3]`` control points).
    path : str or Path
        Destination (conventionally ``*.h5``); an existing file is replaced only once the new one is
        complete.
    extras : dict, optional
        Name -> torch.Tensor, numpy.ndarray, Python/numpy scalar, str or nested dict of those (names
        without ``/``). Read back as the same types (tensors as CPU tensors without grad).
    metadata : dict, optional
        Name -> str / int / float / bool, or anything JSON-serialisable. ``created_by`` (heliotwin
        version) and ``created_utc`` (ISO time) are added unless given; e.g. ``{"source": paint_dir}``.
    learned : dict, optional
        The learned state (module docstring), encoded like ``extras``.
    provenance : list of dict, optional
        JSON-serialisable steps, oldest first (:func:`provenance_entry` builds one).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    HeliotwinError
        Inconsistent plant, unsupported extras/metadata (names the field); no file is written.
    InputFileError
        The destination cannot be written (missing folder, permissions, disk full, a file-size limit): one
        line naming ``path``; an existing file is left untouched and no temporary file is left behind.
    """
    path = Path(path)
    _validate_plant(plant, path, writing=True)
    provenance_json = _provenance_json(provenance or [], path)
    meta = {"created_by": f"heliotwin {__version__}",
            "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}
    meta.update(metadata or {})
    # The file is built in memory and written with one plain write: HDF5 writing to disk itself meets a full
    # disk (ENOSPC, or EFBIG under ``ulimit -f``) in its metadata cache, where the error cannot be raised and
    # the process crashes; a plain write raises an OSError that ``atomic_path`` turns into one line.
    image = io.BytesIO()
    with h5py.File(image, "w") as h5:
        h5.attrs["format"] = FORMAT
        h5.attrs["version"] = VERSION
        _write_metadata(h5.create_group("metadata"), meta, path)
        _write_plant(h5, plant, path)
        if extras:
            _write_extras(h5.create_group("extras", track_order=True), extras, path, "/extras")
        if learned:
            _write_extras(h5.create_group("learned", track_order=True), learned, path, "/learned")
        if provenance:
            h5.create_dataset("provenance", data=provenance_json, dtype=_STR)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(image.getbuffer())
    return path


def next_scenario(previous: Scenario | None, plant: Plant, *, learned: dict, step: dict,
                  metadata: dict | None = None) -> Scenario:
    """What one step makes of a scenario, in memory: the new plant, its learned state and one more provenance
    step. The one place where a step's provenance is appended (:func:`write_scenario` writes the result).

    Parameters
    ----------
    previous : Scenario or None
        The scenario the step started from (its extras, metadata and provenance are carried over), or
        None when it started from a PAINT folder.
    plant : Plant
        The plant after the step (e.g. with calibrated kinematics).
    learned : dict
        The complete learned state after the step (the caller merges ``previous.learned``).
    step : dict
        From :func:`provenance_entry`.
    metadata : dict, optional
        Added to (and overriding) the previous metadata.

    Returns
    -------
    Scenario
        Not yet written (``path`` empty); :func:`write_scenario` writes it.

    Examples
    --------
    Each step appends one provenance entry to what the previous scenario carried:

    >>> from heliotwin.field.demo import demo_field_plant
    >>> plant, _ = demo_field_plant(4)
    >>> calibrated = next_scenario(None, plant, learned={}, step=provenance_entry("calibrate", method="lm"))
    >>> learned = next_scenario(calibrated, plant, learned={}, step=provenance_entry("reconstruct"))
    >>> [(p["step"], p.get("method")) for p in learned.provenance]
    [('calibrate', 'lm'), ('reconstruct', None)]
    """
    meta = {k: v for k, v in (previous.metadata if previous else {}).items() if k not in ("created_by", "created_utc")}
    meta.update(metadata or {})
    provenance = list(previous.provenance if previous else []) + [step]
    return Scenario(plant=plant, extras=dict(previous.extras) if previous else {}, metadata=meta, learned=learned,
                    provenance=provenance)


def write_scenario(scenario: Scenario, path) -> Path:
    """Write an in-memory :class:`Scenario` (e.g. from :func:`next_scenario`) to ``path``, atomically."""
    return save_scenario(scenario.plant, path, extras=scenario.extras or None, metadata=scenario.metadata,
                         learned=scenario.learned, provenance=scenario.provenance)


def _provenance_json(provenance: list, path) -> str:
    if not isinstance(provenance, list) or not all(isinstance(p, dict) for p in provenance):
        _fail_write(path, "/provenance", "expected a list of dicts")
    try:
        return json.dumps(provenance, allow_nan=False, sort_keys=False)
    except (TypeError, ValueError) as exc:
        _fail_write(path, "/provenance", f"not strict JSON ({_one_line(exc)})")


def provenance_entry(step: str, **fields) -> dict:
    """One provenance step: ``{"step", "utc", "heliotwin", **fields}`` (fields must be JSON values).

    Parameters
    ----------
    step : str
        ``"from-paint"``, ``"calibrate"``, ``"reconstruct"``, ...
    **fields
        What a reader needs to reproduce the step: ``method``, ``source`` (PAINT folder), ``records``
        (ids used for training), ``settings``.
    """
    return {"step": step, "utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "heliotwin": __version__, **fields}


# ============================================================================================ reading
#: Datasets up to this size [bytes] are read without looking at their storage (a small table, an attribute-like
#: array).
SMALL_DATASET_BYTES = 1 << 20
#: Largest numeric dataset a scenario may hold [bytes]: a 100,000-heliostat plant's control points are ~0.5 GiB.
MAX_DATASET_BYTES = 8 << 30
#: Largest ratio of a dataset's size to the bytes the file stores for it: gzip at its best packs about 1032:1, so a
#: dataset claiming more than that over its storage (an unwritten dataset, one stored elsewhere) is not the writer's.
MAX_COMPRESSION_RATIO = 1100


def check_dataset_size(obj: h5py.Dataset, path) -> None:
    """Refuse, before reading, an HDF5 dataset whose shape claims more than the file holds for it (a 69 KB file whose
    datasets claim 22-29 GiB was allocated in full before any shape check) or more than :data:`MAX_DATASET_BYTES`.

    Raises
    ------
    InputFileError
        One line naming the file and the dataset, its shape, dtype and claimed and stored sizes.
    """
    claimed = int(obj.size) * int(obj.dtype.itemsize)
    if claimed <= SMALL_DATASET_BYTES:
        return
    try:
        stored = int(obj.id.get_storage_size())
    except (OSError, RuntimeError, ValueError):
        stored = 0
    if claimed > MAX_DATASET_BYTES or claimed > MAX_COMPRESSION_RATIO * stored:
        raise InputFileError(path, f"shape {list(obj.shape)} of {obj.dtype} claims {claimed / 2**30:.2f} GiB but the "
                                   f"file stores {stored} bytes of it (at most {MAX_DATASET_BYTES / 2**30:.0f} GiB, "
                                   f"{MAX_COMPRESSION_RATIO}:1 compressed); not read: a damaged or foreign file",
                             field=obj.name)


class _Reader:
    """Validating accessors that raise one-line :class:`InputFileError` naming the HDF5 object."""

    def __init__(self, path):
        self.path = str(path)

    def fail(self, where: str, message: str, cls=InputFileError):
        raise cls(self.path, message, field=where)

    def group(self, parent: h5py.Group, name: str) -> h5py.Group:
        where = f"{parent.name.rstrip('/')}/{name}"
        if name not in parent:
            self.fail(where, "missing group (not a complete heliotwin scenario)")
        obj = parent[name]
        if not isinstance(obj, h5py.Group):
            self.fail(where, "expected a group, found a dataset")
        return obj

    def sized(self, obj: h5py.Dataset, lead: int | None = None) -> h5py.Dataset:
        """``obj`` when its shape and storage are plausible, checked before a byte of it is read: the first dimension
        ``lead`` when given (one row per heliostat), and a size the file actually holds (:func:`check_dataset_size`)."""
        if lead is not None and (obj.ndim < 1 or obj.shape[0] != lead):
            self.fail(obj.name, f"expected {lead} rows (one per heliostat), got shape {list(obj.shape)}; not read")
        check_dataset_size(obj, self.path)
        return obj

    def array(self, parent: h5py.Group, name: str, lead: int | None = None) -> np.ndarray:
        where = f"{parent.name.rstrip('/')}/{name}"
        if name not in parent:
            self.fail(where, "missing dataset")
        obj = parent[name]
        if not isinstance(obj, h5py.Dataset):
            self.fail(where, "expected a dataset, found a group")
        if h5py.check_string_dtype(obj.dtype) is not None:
            self.fail(where, "expected a numeric dataset, found text")
        if obj.dtype.kind not in "biufc":
            self.fail(where, f"expected a numeric array, found dtype {obj.dtype}")
        data = np.asarray(self.sized(obj, lead)[()])
        if data.dtype.kind not in "biufc":
            self.fail(where, f"expected a numeric array, found dtype {obj.dtype}")
        return data

    def tensor(self, parent: h5py.Group, name: str, lead: int | None = None) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(self.array(parent, name, lead)))

    def strings(self, parent: h5py.Group, name: str, lead: int | None = None) -> list[str]:
        where = f"{parent.name.rstrip('/')}/{name}"
        if name not in parent:
            self.fail(where, "missing dataset")
        obj = parent[name]
        if not isinstance(obj, h5py.Dataset) or h5py.check_string_dtype(obj.dtype) is None or obj.ndim != 1:
            self.fail(where, "expected a 1-D dataset of strings")
        return [str(s) for s in self.sized(obj, lead).asstr()[()]]

    def attr(self, obj, name: str, kind: type):
        where = f"{obj.name}@{name}" if obj.name != "/" else f"/@{name}"
        if name not in obj.attrs:
            self.fail(where, "missing attribute")
        v = _py(obj.attrs[name])
        if kind is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if kind is int and isinstance(v, float) and v.is_integer():
            v = int(v)
        if not isinstance(v, kind) or (kind is not bool and isinstance(v, bool)):
            self.fail(where, f"expected {kind.__name__}, got {v!r}")
        return v


def _py(v):
    """numpy / bytes attribute value -> plain Python."""
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    if isinstance(v, np.ndarray) and v.ndim == 0:
        return _py(v[()])
    return v


def _scalar_kind(f: dataclasses.Field) -> type:
    t = str(f.type)
    return {"float": float, "int": int, "str": str, "bool": bool}.get(t.split("|")[0].strip(), object)


def _read_dataclass(r: _Reader, group: h5py.Group, cls, optional=(), lead: int | None = None):
    kwargs = {}
    for f in dataclasses.fields(cls):
        if _is_tensor_field(f):
            if f.name in optional and f.name not in group:
                kwargs[f.name] = None
            else:
                kwargs[f.name] = r.tensor(group, f.name, lead)
        else:
            kwargs[f.name] = r.attr(group, f.name, _scalar_kind(f))
    return cls(**kwargs)


def _read_metadata(r: _Reader, group: h5py.Group) -> dict:
    try:
        json_keys = set(json.loads(r.attr(group, "_json_keys", str))) if "_json_keys" in group.attrs else set()
    except (TypeError, ValueError):
        r.fail("/metadata@_json_keys", "expected a JSON list of attribute names")
    out = {}
    for key, value in group.attrs.items():
        if key == "_json_keys":
            continue
        value = _py(value)
        if key in json_keys:
            try:
                value = json.loads(value)
            except (TypeError, ValueError):
                r.fail(f"/metadata@{key}", "malformed JSON value")
        elif isinstance(value, np.ndarray):
            value = value.tolist()
        out[key] = value
    return out


def _read_extras(r: _Reader, group: h5py.Group) -> dict:
    out = {}
    for key, obj in group.items():
        where = obj.name
        if isinstance(obj, h5py.Group):
            out[key] = _read_extras(r, obj)
            continue
        kind = _py(obj.attrs.get("type", "numpy"))
        if kind == "strs":
            out[key] = r.strings(group, key)
            continue
        if kind == "str":
            if h5py.check_string_dtype(obj.dtype) is None:
                r.fail(where, "expected a string dataset")
            out[key] = r.sized(obj).asstr()[()]
            continue
        data = r.array(group, key)
        if kind == "torch":
            out[key] = torch.from_numpy(np.ascontiguousarray(data))
        elif kind == "numpy":
            out[key] = data
        elif kind == "scalar":
            out[key] = _py(data)
        else:
            r.fail(where, f"unknown value type {kind!r} (known: torch, numpy, scalar, str, strs)")
    return out


def _read_plant(r: _Reader, h5: h5py.File) -> Plant:
    sg = r.group(h5, "site")
    site = Site(r.attr(sg, "latitude_deg", float), r.attr(sg, "longitude_deg", float),
                r.attr(sg, "altitude_m", float), r.attr(sg, "name", str))

    targets = {}
    for key, tg in r.group(h5, "targets").items():
        if not isinstance(tg, h5py.Group):
            r.fail(tg.name, "expected a target group, found a dataset")
        kind = r.attr(tg, "kind", str)
        if kind not in _TARGET_CLASSES:
            r.fail(f"{tg.name}@kind", f"unknown target kind {kind!r} (known: {', '.join(_TARGET_CLASSES)})")
        targets[key] = _read_dataclass(r, tg, _TARGET_CLASSES[kind])

    fg = r.group(h5, "field")
    ids = r.strings(fg, "ids")
    h = len(ids)  # every per-heliostat dataset is checked to have h rows before it is read
    sfg = r.group(fg, "surfaces")
    surfaces = Surfaces(r.tensor(sfg, "control_points", h), r.attr(sfg, "degree_u", int),
                        r.attr(sfg, "degree_v", int), r.tensor(sfg, "weights", h) if "weights" in sfg else None)
    fld = Field(ids=ids,
                kinematics=_read_dataclass(r, r.group(fg, "kinematics"), Kinematics, lead=h),
                facets=_read_dataclass(r, r.group(fg, "facets"), Facets, lead=h),
                surfaces=surfaces,
                width=r.tensor(fg, "width", h), height=r.tensor(fg, "height", h),
                renovation=r.strings(fg, "renovation", h))
    sun = _read_dataclass(r, r.group(h5, "sun"), SunSettings)
    return Plant(site, targets, fld, sun)


def _check_version(r: _Reader, h5: h5py.File) -> int:
    fmt = _py(h5.attrs.get("format"))
    if fmt != FORMAT:
        what = "no 'format' attribute" if fmt is None else f"format {fmt!r}"
        r.fail("/@format", f"not a heliotwin scenario ({what}; expected {FORMAT!r})", ScenarioVersionError)
    version = _py(h5.attrs.get("version"))
    if isinstance(version, bool) or not isinstance(version, int):
        r.fail("/@version", f"missing or non-integer format version {version!r}", ScenarioVersionError)
    if version > VERSION:
        r.fail("/@version", f"written by a newer heliotwin (format version {version}; this heliotwin reads "
                            f"versions {', '.join(map(str, READABLE_VERSIONS))}); upgrade heliotwin",
               ScenarioVersionError)
    if version not in READABLE_VERSIONS:
        r.fail("/@version", f"format version {version} is older than the supported versions "
                            f"{', '.join(map(str, READABLE_VERSIONS))} and has no migration; re-create the scenario",
               ScenarioVersionError)
    return version


def _read_provenance(r: _Reader, h5: h5py.File) -> list:
    if "provenance" not in h5:
        return []
    obj = h5["provenance"]
    if not isinstance(obj, h5py.Dataset) or h5py.check_string_dtype(obj.dtype) is None or obj.ndim != 0:
        r.fail("/provenance", "expected one JSON string")
    try:
        value = json.loads(r.sized(obj).asstr()[()])
    except ValueError:
        r.fail("/provenance", "malformed JSON")
    if not isinstance(value, list) or not all(isinstance(p, dict) for p in value):
        r.fail("/provenance", "expected a JSON list of objects")
    return value


def load_scenario(path) -> Scenario:
    """Read a scenario file written by :func:`save_scenario`.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Scenario
        ``plant``, ``extras``, ``metadata`` (unpackable as a 3-tuple), ``version``, ``path``, ``learned``,
        ``provenance``.

    Raises
    ------
    InputFileError
        Missing file, not HDF5, missing/mistyped group, dataset or attribute, inconsistent shapes.
    ScenarioVersionError
        Another format, or a format version this heliotwin cannot read.
    """
    path = Path(path)
    r = _Reader(path)
    if not path.exists():
        raise InputFileError(path, "file not found")
    if path.is_dir():
        raise InputFileError(path, "is a folder, expected a scenario file (.h5)")
    require_regular_file(path, "scenario file (.h5)")
    try:
        is_hdf5 = h5py.is_hdf5(path)
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({_one_line(exc)})") from None
    if not is_hdf5:
        raise InputFileError(path, "not an HDF5 file (expected a heliotwin scenario)")
    try:
        with h5py.File(path, "r") as h5:
            version = _check_version(r, h5)
            metadata = _read_metadata(r, r.group(h5, "metadata"))
            plant = _read_plant(r, h5)
            extras = _read_extras(r, r.group(h5, "extras")) if "extras" in h5 else {}
            learned = _read_extras(r, r.group(h5, "learned")) if "learned" in h5 else {}
            provenance = _read_provenance(r, h5)
    except (OSError, KeyError, RuntimeError) as exc:  # h5py's low-level failures (corrupt/truncated file)
        raise InputFileError(path, f"cannot read HDF5 ({_one_line(exc)})") from None
    _validate_plant(plant, path)
    _validate_extras(extras, plant, path)
    _validate_learned(learned, len(plant.field.ids), path)
    _validate_learned_state(learned, plant, path)
    return Scenario(plant, extras, metadata, version, str(path), learned, provenance)


# ========================================================================================= validation
class _PlantCheck:
    """Failing checks of :func:`_validate_plant`, each naming the HDF5 object the problem maps to."""

    def __init__(self, path, writing: bool):
        self.path, self.writing = path, writing

    def fail(self, where: str, message: str):
        if self.writing:
            _fail_write(self.path, where, message)
        raise InputFileError(self.path, message, field=where)

    def tensor(self, where: str, t, shape: tuple, *, floating: bool = True, finite: bool = False):
        if not isinstance(t, torch.Tensor):
            self.fail(where, f"expected a tensor, got {type(t).__name__}")
        ok = t.dim() == len(shape) and all(s is None or s == n for s, n in zip(shape, t.shape))
        if not ok:
            want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
            self.fail(where, f"expected shape {want}, got {list(t.shape)}")
        if floating and not t.dtype.is_floating_point:
            self.fail(where, f"expected a floating-point tensor, got {t.dtype}")
        if finite and not bool(torch.isfinite(t).all()):
            self.fail(where, "contains NaN/inf")


def _validate_plant(plant: Plant, path, *, writing: bool = False) -> None:
    """Shape/dtype/finiteness consistency of a plant; raises naming the HDF5 object the problem maps to."""
    c = _PlantCheck(path, writing)
    if not isinstance(plant, Plant):
        c.fail("/", f"expected a Plant, got {type(plant).__name__}")
    s = plant.site
    for name in ("latitude_deg", "longitude_deg", "altitude_m"):
        v = getattr(s, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            c.fail(f"/site@{name}", f"expected a finite number, got {v!r}")
        problem = site_problem(name, v)
        if problem:
            c.fail(f"/site@{name}", problem)
    for key, t in plant.targets.items():
        for name in ("center", "normal", "right", "up"):
            c.tensor(f"/targets/{key}/{name}", getattr(t, name), (3,), finite=True)
            norm = float(torch.linalg.vector_norm(getattr(t, name).to(torch.float64)))
            if name != "center" and abs(norm - 1.0) > 1e-6:
                c.fail(f"/targets/{key}/{name}", f"expected a unit vector, got length {norm:.6g}")
            if name == "center" and norm > MAX_DISTANCE_M:
                c.fail(f"/targets/{key}/{name}", f"expected a point within {MAX_DISTANCE_M:g} m, got {norm:.3g} m away")
        stored = {f.name for f in dataclasses.fields(t)} if dataclasses.is_dataclass(t) else set()
        for name in ("width", "height", "radius", "opening_angle"):
            v = getattr(t, name, None) if name in stored else None
            hi = 2 * math.pi + 1e-9 if name == "opening_angle" else 1e4
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= hi):
                c.fail(f"/targets/{key}@{name}", f"expected a finite value in (0, {hi:g}], got {v!r}")
    _validate_sun(c, plant.sun)
    fl = plant.field
    if not isinstance(fl.ids, (list, tuple)) or not all(isinstance(i, str) for i in fl.ids):
        c.fail("/field/ids", "expected a list of str")
    if len(set(fl.ids)) != len(fl.ids):
        c.fail("/field/ids", "duplicate heliostat ids")
    h = len(fl.ids)
    c.tensor("/field/width", fl.width, (h,), finite=True)
    c.tensor("/field/height", fl.height, (h,), finite=True)
    for name, t in (("width", fl.width), ("height", fl.height)):
        if h and not bool(((t >= MIN_MIRROR_M) & (t <= MAX_MIRROR_M)).all()):
            c.fail(f"/field/{name}", f"expected mirror sizes in [{MIN_MIRROR_M:g}, {MAX_MIRROR_M:g}] m")
    if len(fl.renovation) not in (0, h) or not all(isinstance(x, str) for x in fl.renovation):
        c.fail("/field/renovation", f"expected 0 or {h} strings, got {len(fl.renovation)} entries")
    _validate_kinematics(c, fl.kinematics, h)
    _validate_positions(c, fl.kinematics.position, fl.ids)
    _validate_mirrors(c, fl, h)


def _validate_positions(c: _PlantCheck, position: torch.Tensor, ids) -> None:
    """Heliostat positions [H, 3] ENU [m] within :data:`~heliotwin.field.layout.MAX_DISTANCE_M` of the ENU origin
    (the tower base), naming the first heliostat outside (1e300 m was accepted, then blamed on the atmosphere)."""
    if not len(ids):
        return
    far = torch.nonzero(torch.linalg.vector_norm(position.to(torch.float64), dim=-1) > MAX_DISTANCE_M).flatten()
    if len(far):
        i = int(far[0])
        xyz = ", ".join(f"{float(v):.4g}" for v in position[i])
        more = f" (and {len(far) - 1} more)" if len(far) > 1 else ""
        c.fail("/field/kinematics/position", f"heliostat {ids[i]} at ({xyz}) m is farther than {MAX_DISTANCE_M:g} m "
                                             f"from the tower base{more}")


#: Physical ranges of the sun and mirror optics: (low, high, low excluded).
_SUN_RANGES = {"sigma": (0.0, 0.1, True), "radius": (0.0, 0.1, True), "csr": (0.0, 1.0, False),
               "slope_error": (0.0, 0.1, False), "dni": (0.0, 1500.0, False), "reflectivity": (0.0, 1.0, False)}


def _validate_sun(c: _PlantCheck, sun) -> None:
    for name, (lo, hi, lo_open) in _SUN_RANGES.items():
        v = getattr(sun, name, None)
        bad = isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v > hi or \
            (v <= lo if lo_open else v < lo)
        if bad:
            c.fail(f"/sun@{name}", f"expected a value in {'(' if lo_open else '['}{lo:g}, {hi:g}], got {v!r}")


def _validate_extras(extras: dict, plant: Plant, path) -> None:
    """The atmosphere of ``/extras/atmosphere``: finite coefficients whose transmitted fraction stays in [0, 1]
    at every heliostat's slant range to every target."""
    entry = extras.get("atmosphere")
    if not entry:
        return
    where = "/extras/atmosphere/coefficients"
    try:
        atm = Atmosphere.from_extras(extras)
    except (TypeError, ValueError, KeyError, AttributeError):
        raise InputFileError(path, "expected a model name and a list of numbers", field="/extras/atmosphere") \
            from None
    if atm.model not in ATMOSPHERE_MODELS:
        raise InputFileError(path, f"unknown model {atm.model!r} (known: {', '.join(ATMOSPHERE_MODELS)})",
                             field="/extras/atmosphere/model")
    if not atm.coefficients or len(atm.coefficients) > 8 or not all(math.isfinite(c) for c in atm.coefficients):
        raise InputFileError(path, f"expected 1 to 8 finite numbers, got {list(atm.coefficients)}", field=where)
    pos = plant.field.kinematics.position.to(torch.float64)
    for t in plant.targets.values():
        slant = torch.linalg.vector_norm(t.center.to(torch.float64) - pos, dim=-1)
        check_attenuation(atm, slant, path, where, plant.field.ids)


def _validate_learned(learned: dict, h: int, path) -> None:
    """The learned groups this floor knows the layout of; ``/learned/aimpoints`` (written by
    :mod:`heliotwin.optimise.aimstate`): per instant ``aim`` [H, 3] and ``motor_steps`` [H, 2] finite,
    ``sun_direction`` [3] a finite direction above the horizon, ``reachable`` [H]; a positive finite limit."""
    group = learned.get("aimpoints")
    if group is None:
        return
    where = "/learned/aimpoints"
    if not isinstance(group, dict):
        raise InputFileError(path, "expected a group", field=where)
    instants = group.get("instants")
    if instants is not None and (not isinstance(instants, dict) or not instants):
        raise InputFileError(path, "expected a group of instants", field=f"{where}/instants")
    entries = [(where, group)] + [(f"{where}/instants/{k}", v) for k, v in sorted((instants or {}).items())]
    for at, entry in entries:
        if not isinstance(entry, dict):
            raise InputFileError(path, "expected a group", field=at)
        for name, shape in (("aim", (h, 3)), ("sun_direction", (3,)), ("motor_steps", (h, 2)), ("reachable", (h,))):
            v = entry.get(name)
            if v is None:
                raise InputFileError(path, "missing dataset", field=f"{at}/{name}")
            try:
                t = torch.as_tensor(v, dtype=torch.float64)
            except (TypeError, ValueError, RuntimeError):
                raise InputFileError(path, "expected a numeric array", field=f"{at}/{name}") from None
            if tuple(t.shape) != shape:
                raise InputFileError(path, f"expected shape {list(shape)}, got {list(t.shape)}", field=f"{at}/{name}")
            if not bool(torch.isfinite(t).all()):
                raise InputFileError(path, "contains NaN/inf", field=f"{at}/{name}")
            if name == "sun_direction" and not (abs(float(t.norm()) - 1.0) < 1e-6 and float(t[2]) > 0):
                raise InputFileError(path, "expected a unit vector towards a sun above the horizon",
                                     field=f"{at}/{name}")
        if at == where:
            v = entry.get("peak_limit_w_m2")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise InputFileError(path, f"expected a positive finite flux [W/m2], got {v!r}",
                                     field=f"{where}@peak_limit_w_m2")


# ===================================================================== learned calibration, surfaces, updates
class _LearnedCheck:
    """Checks of one learned group's entries, each failing with a one-line :class:`InputFileError` naming the
    file and the HDF5 object; readers downstream then index and do arithmetic on them without surprises."""

    def __init__(self, path):
        self.path = path

    def fail(self, where: str, message: str):
        raise InputFileError(self.path, message, field=where)

    def group(self, parent: dict, name: str, where: str, *, required: bool = True) -> dict | None:
        v = parent.get(name)
        if v is None and not required:
            return None
        if not isinstance(v, dict):
            self.fail(f"{where}/{name}", "missing group" if v is None else "expected a group, found a dataset")
        return v

    def names(self, parent: dict, name: str, where: str, *, required: bool = True, n: int | None = None):
        v = parent.get(name)
        if v is None and not required:
            return None
        if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
            self.fail(f"{where}/{name}", "missing dataset" if v is None else "expected a 1-D dataset of strings")
        if len(set(v)) != len(v):
            self.fail(f"{where}/{name}", "duplicate entries")
        if n is not None and len(v) != n:
            self.fail(f"{where}/{name}", f"expected {n} entries, got {len(v)}")
        return v

    def text(self, parent: dict, name: str, where: str, *, required: bool = True, json_value: bool = False):
        v = parent.get(name)
        if v is None and not required:
            return None
        if not isinstance(v, str):
            self.fail(f"{where}/{name}", "missing dataset" if v is None else "expected a string dataset")
        if json_value:
            try:
                return json.loads(v)
            except ValueError:
                self.fail(f"{where}/{name}", "malformed JSON text")
        return v

    def array(self, parent: dict, name: str, where: str, shape: tuple, *, required: bool = True,
              kind: str = "float", finite: bool = True, low: float | None = None) -> torch.Tensor | None:
        """``shape``: ints, None for any size; ``kind``: "float" (int accepted), "int", "bool", "any"."""
        at = f"{where}/{name}"
        v = parent.get(name)
        if v is None and not required:
            return None
        if v is None:
            self.fail(at, "missing dataset")
        if isinstance(v, np.ndarray):
            v = torch.from_numpy(np.ascontiguousarray(v))
        if not isinstance(v, torch.Tensor):
            self.fail(at, f"expected a numeric dataset, found {type(v).__name__}")
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        if v.dim() != len(shape) or not all(s is None or s == n for s, n in zip(shape, v.shape)):
            self.fail(at, f"expected shape {want}, got {list(v.shape)}")
        ok = {"float": v.dtype.is_floating_point or (v.dtype != torch.bool and not v.dtype.is_complex),
              "int": not v.dtype.is_floating_point and not v.dtype.is_complex and v.dtype != torch.bool,
              "bool": v.dtype == torch.bool, "any": not v.dtype.is_complex}[kind]
        if not ok:
            self.fail(at, f"expected a {kind} dataset, got {str(v.dtype).replace('torch.', '')}")
        if finite and v.dtype.is_floating_point and not bool(torch.isfinite(v).all()):
            self.fail(at, "contains NaN/inf")
        if low is not None and v.numel() and not bool((v >= low).all()):
            self.fail(at, f"expected values >= {low:g}")
        return v


def _validate_learned_calibration(c: _LearnedCheck, cal) -> None:
    """``/learned/calibration`` (:mod:`heliotwin.calibrate.scenario`): heliostats [Hc] and parameter names [P]
    index deviations [Hc, P]; nominal kinematics [Hc, ...]; the posterior, drift, prior and networks when
    present. Keys this floor does not know are left to their readers."""
    where = "/learned/calibration"
    if not isinstance(cal, dict):
        c.fail(where, "expected a group")
    for name in ("method", "focal_spot"):
        c.text(cal, name, where, required=False)
    c.text(cal, "settings_choice", where, required=False, json_value=True)
    ids = c.names(cal, "heliostats", where)
    names = c.names(cal, "parameter_names", where)
    hc, p = len(ids), len(names)
    c.array(cal, "deviations", where, (hc, p))
    nominal = c.group(cal, "nominal", where, required=False)
    if nominal is not None:
        for f in dataclasses.fields(Kinematics):
            boolean = f.name in _KINEMATICS_BOOL
            c.array(nominal, f.name, f"{where}/nominal", (hc, *_KINEMATICS_TRAILING.get(f.name, (2,))),
                    kind="bool" if boolean else "float", finite=f.name not in _KINEMATICS_OPTIONAL)
    post = c.group(cal, "posterior", where, required=False)
    if post is not None:
        at = f"{where}/posterior"
        c.array(post, "covariance", at, (hc, p, p))
        c.array(post, "noise_rad", at, (hc,), low=0.0)
        c.array(post, "drift_rad", at, (1,), required=False, low=0.0)
        c.array(post, "walk_scale", at, (1,), required=False, low=0.0)
    drift = c.group(cal, "drift", where, required=False)
    if drift is not None:
        at = f"{where}/drift"
        c.text(drift, "model", at, required=False)
        d = len(c.names(drift, "names", at))
        if any(n not in names for n in drift["names"]):
            c.fail(f"{at}/names", "expected names among the parameter names")
        c.array(drift, "offset", at, (hc, d), required=False)
        c.array(drift, "covariance", at, (hc, d, d))
        c.array(drift, "time", at, (hc,), finite=False)  # NaN: no record seen yet
        c.array(drift, "process_noise_rad2_per_day", at, (1,), low=0.0)
        c.array(drift, "record_noise_rad", at, (hc,), required=False, low=0.0)
        c.array(drift, "filter_scale", at, (1,), required=False, low=0.0)
        c.array(drift, "static_deviations", at, (hc, p), required=False)
    prior = c.group(cal, "prior", where, required=False)
    if prior is not None:
        at = f"{where}/prior"
        k = len(c.names(prior, "names", at))
        c.array(prior, "mean", at, (k,))
        c.array(prior, "sigma", at, (k,), low=0.0)
        c.array(prior, "covariance", at, (k, k), required=False)
        c.names(prior, "heliostats", at, required=False)
    choice = c.group(cal, "process_noise_choice", where, required=False)
    if choice is not None:  # the update's random-walk q chosen on the plant's records (workflows.update)
        at = f"{where}/process_noise_choice"
        c.array(choice, "process_noise_mrad2_per_day", at, (1,), low=0.0)
        g = c.array(choice, "grid_mrad2_per_day", at, (None,), low=0.0)
        c.array(choice, "validation_error_mrad", at, (len(g),), finite=False)  # inf: a grid value that diverged
        c.array(choice, "validation_records", at, (1,), kind="int", low=0)
        c.array(choice, "validation_heliostats", at, (1,), kind="int", low=0)
        c.array(choice, "share", at, (1,), low=0.0)
        c.text(choice, "method", at)
    alarm = c.group(cal, "alarm_threshold", where, required=False)
    if alarm is not None:  # the updates' step-alarm threshold chosen on the calibration's records (twinstate)
        at = f"{where}/alarm_threshold"
        c.array(alarm, "threshold", at, (1,), low=0.0)
        c.array(alarm, "kappa", at, (1,), low=1.0)
        c.array(alarm, "false_alarm_rate", at, (1,), low=0.0)
        c.array(alarm, "tests", at, (1,), kind="int", low=1)
        c.array(alarm, "validation_records", at, (1,), kind="int", low=0)
        c.text(alarm, "method", at)
        c.text(alarm, "rate_rule", at, required=False)
        c.array(alarm, "records_per_heliostat_year", at, (1,), required=False, low=0.0)
        c.array(alarm, "false_alarms_per_heliostat_year", at, (1,), required=False, low=0.0)
    nets = c.group(cal, "networks", where, required=False)
    for hid, net in (nets or {}).items():
        at = f"{where}/networks/{hid}"
        if not isinstance(net, dict):
            c.fail(at, "expected a group")
        c.text(net, "config", at, json_value=True)
        state = c.group(net, "state", at)
        for key, t in state.items():
            c.array(state, key, f"{at}/state", (None,) * getattr(t, "ndim", 0), kind="any")


def _validate_learned_surfaces(c: _LearnedCheck, entries, plant: Plant) -> None:
    """``/learned/surfaces/<HID>`` (:mod:`heliotwin.surfaces.state`): a heliostat of the plant, displacement
    [F, nu, nv] on its control net, optics a physical sun, settings JSON, train_records [n] ints, target."""
    where = "/learned/surfaces"
    if not isinstance(entries, dict):
        c.fail(where, "expected a group")
    cp = plant.field.surfaces.control_points
    for hid, e in entries.items():
        at = f"{where}/{hid}"
        if hid not in plant.field.ids:
            c.fail(at, "not a heliostat of this scenario's field")
        if not isinstance(e, dict):
            c.fail(at, "expected a group")
        c.array(e, "displacement", at, tuple(cp.shape[1:4]))
        c.array(e, "train_records", at, (None,), kind="int")
        c.text(e, "target", at)
        c.text(e, "settings", at, json_value=True)
        optics = c.text(e, "optics", at, json_value=True)
        try:
            sun = SunSettings(**optics)
        except TypeError:
            c.fail(f"{at}/optics", "expected the sun settings as a JSON object")
        check = _PlantCheck(c.path, False)
        check.fail = lambda _w, message: c.fail(f"{at}/optics", message)
        _validate_sun(check, sun)


def _validate_learned_assimilation(c: _LearnedCheck, st) -> None:
    """``/learned/assimilation`` (:mod:`heliotwin.workflows.update`): scalars [1], heliostats [Hs], parameter
    names [P], the history's rows [n, ...] (heliostat indices into heliostats), the step-test window."""
    where = "/learned/assimilation"
    if not isinstance(st, dict):
        c.fail(where, "expected a group")
    for name in ("version", "updates", "calibrations"):
        c.array(st, name, where, (1,), kind="int", required=name != "version")
    for name in ("threshold", "kappa", "false_alarm_rate"):
        c.array(st, name, where, (1,), low=0.0)
    p = len(c.names(st, "parameter_names", where))
    ids = c.names(st, "heliostats", where)
    hist = c.group(st, "history", where)
    at = f"{where}/history"
    n = c.array(hist, "heliostat", at, (None,), kind="int").shape[0]
    if n and not bool(((hist["heliostat"] >= 0) & (hist["heliostat"] < len(ids))).all()):
        c.fail(f"{at}/heliostat", f"expected indices into the {len(ids)} heliostats")
    for name, trailing, kind in (("record_id", (), "int"), ("time", (), "float"), ("update", (), "int"),
                                 ("mean", (p,), "float"), ("variance", (p,), "float"), ("innovation", (2,), "float"),
                                 ("d2", (), "float"), ("statistic", (), "float"), ("window", (), "int"),
                                 ("alarm", (), "bool"), ("predicted_error", (), "float")):
        c.array(hist, name, at, (n, *trailing), kind=kind)
    _validate_alarm_tables(c, st, where, len(ids), p)
    window = c.group(st, "window", where, required=False)
    if window is not None:
        hw = len(c.names(window, "heliostats", f"{where}/window"))
        g = c.array(window, "g", f"{where}/window", (hw, None, None))
        c.array(window, "f", f"{where}/window", (hw, g.shape[1], g.shape[2], g.shape[2]))


def _validate_alarm_tables(c: _LearnedCheck, st: dict, where: str, hs: int, p: int) -> None:
    """``open_alarms`` and ``closed_alarms`` (layout version 2, :mod:`heliotwin.calibrate.twinstate`; optional:
    older files have none): rows [A] / [C], heliostats indices into the assimilation's ``hs`` heliostats."""
    for name, floats, wide in (("open_alarms", ("time", "statistic"), True),
                               ("closed_alarms", ("opened", "statistic", "closed_at", "evidence"), False)):
        table = c.group(st, name, where, required=False)
        if table is None:
            continue
        at = f"{where}/{name}"
        n = c.array(table, "heliostat", at, (None,), kind="int").shape[0]
        if n and not bool(((table["heliostat"] >= 0) & (table["heliostat"] < hs)).all()):
            c.fail(f"{at}/heliostat", f"expected indices into the {hs} heliostats")
        ints = ("record_id", "window", "records") + (() if wide else ("closed_by", "outcome", "update"))
        for key in ints:
            c.array(table, key, at, (n,), kind="int")
        for key in floats:
            c.array(table, key, at, (n,), finite=key != "closed_at" and key != "opened" and key != "time")
        if wide:
            b = c.array(table, "g", at, (n, None)).shape[1]
            c.array(table, "mean", at, (n, p))
            c.array(table, "covariance", at, (n, p, p))
            c.array(table, "f", at, (n, b, b))


def _validate_learned_state(learned: dict, plant: Plant, path) -> None:
    """The calibration, surfaces, surface prior and update groups of ``/learned`` (see the helpers above)."""
    c = _LearnedCheck(path)
    if "calibration" in learned:
        _validate_learned_calibration(c, learned["calibration"])
    if "surfaces" in learned:
        _validate_learned_surfaces(c, learned["surfaces"], plant)
    if "surface_prior" in learned:
        prior = learned["surface_prior"]
        where = "/learned/surface_prior"
        if not isinstance(prior, dict):
            c.fail(where, "expected a group")
        # Its facet count may differ from this plant's (a prior of another design): the reconstruction says so.
        f, k = c.array(prior, "mean", where, (None, None)).shape
        c.array(prior, "covariance", where, (f * k, f * k))
    if "assimilation" in learned:
        _validate_learned_assimilation(c, learned["assimilation"])
    if "year" in learned:
        _validate_learned_year(c, learned["year"], len(plant.field.ids))


#: Per-heliostat arrays of ``/learned/year/heliostats`` (:mod:`heliotwin.workflows.year`); the tracking loss may be
#: NaN (a heliostat on nominal kinematics: unknown).
_YEAR_ARRAYS = ("energy_mwh", "efficiency", "cosine", "shading", "blocking", "attenuation", "intercept",
                "reflectance", "surface_loss_mwh", "surface_loss_low_mwh", "surface_loss_high_mwh")
_YEAR_NAN = ("tracking_loss_mwh", "tracking_loss_low_mwh", "tracking_loss_high_mwh")


def _validate_learned_year(c: _LearnedCheck, st, h: int) -> None:
    """``/learned/year`` (:func:`heliotwin.workflows.year.year_state`): scalars, ``monthly_energy_mwh`` [12], the
    weather group, per heliostat [H] energies, factors in [0, 1] and losses; the interpolation check if any."""
    where = "/learned/year"
    if not isinstance(st, dict):
        c.fail(where, "expected a group")
    for name in ("version", "year", "annual_energy_mwh", "annual_dni_energy_on_mirrors_mwh"):
        v = st.get(name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            c.fail(f"{where}/{name}", "missing dataset" if v is None else "expected a finite number")
    c.text(st, "aim", where)
    c.text(st, "time_convention", where)
    c.array(st, "monthly_energy_mwh", where, (12,))
    c.group(st, "weather", where)
    hel = c.group(st, "heliostats", where)
    at = f"{where}/heliostats"
    for name in _YEAR_ARRAYS:
        v = c.array(hel, name, at, (h,))
        if name in ("efficiency", "cosine", "shading", "blocking", "attenuation", "intercept", "reflectance") and \
                v.numel() and not bool(((v >= -1e-9) & (v <= 1 + 1e-9)).all()):
            c.fail(f"{at}/{name}", "expected values in [0, 1]")
    for name in _YEAR_NAN:
        c.array(hel, name, at, (h,), finite=False)
    c.array(hel, "surface_learned", at, (h,), kind="bool")
    check = c.group(st, "interpolation", where, required=False)
    if check is not None:
        for name in ("median_error", "p95_error", "field_error", "checked_hours"):
            v = check.get(name)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                c.fail(f"{where}/interpolation/{name}", "expected a number")


def _validate_kinematics(c: _PlantCheck, kin: Kinematics, h: int) -> None:
    for f in dataclasses.fields(Kinematics):
        t = getattr(kin, f.name)
        where = f"/field/kinematics/{f.name}"
        trailing = _KINEMATICS_TRAILING.get(f.name, (2,))
        # Movement-angle limits are optional in PAINT (NaN = not given); every other value must be finite.
        c.tensor(where, t, (h, *trailing), floating=f.name not in _KINEMATICS_BOOL,
                 finite=f.name not in _KINEMATICS_BOOL + _KINEMATICS_OPTIONAL)
        if f.name in _KINEMATICS_BOOL and t.dtype != torch.bool:
            c.fail(where, f"expected a bool tensor, got {t.dtype}")


def _validate_mirrors(c: _PlantCheck, fl: Field, h: int) -> None:
    """Facets [H, F, 3] and their NURBS surfaces [H, F, nu, nv, 3] (degrees below the net size)."""
    fac = fl.facets
    c.tensor("/field/facets/translation", fac.translation, (h, None, 3), finite=True)
    nf = fac.translation.shape[1]
    c.tensor("/field/facets/canting_e", fac.canting_e, (h, nf, 3), finite=True)
    c.tensor("/field/facets/canting_n", fac.canting_n, (h, nf, 3), finite=True)
    sf = fl.surfaces
    c.tensor("/field/surfaces/control_points", sf.control_points, (h, nf, None, None, 3), finite=True)
    cp = sf.control_points.shape
    for name, n in (("degree_u", cp[2]), ("degree_v", cp[3])):
        d = getattr(sf, name)
        if isinstance(d, bool) or not isinstance(d, int) or not 1 <= d < n:
            c.fail(f"/field/surfaces@{name}", f"expected an int in [1, {n - 1}] for {n} control points, got {d!r}")
    if sf.weights is not None:
        c.tensor("/field/surfaces/weights", sf.weights, tuple(cp[:-1]), finite=True)
        if sf.weights.numel() and not bool((sf.weights > 0).all()):
            c.fail("/field/surfaces/weights", "expected positive NURBS weights")
    # Each facet's control net spans a real surface: not collapsed to a point, not larger than a mirror.
    if sf.control_points.numel():
        net = sf.control_points.detach().to(torch.float64).flatten(2, 3)  # [H, F, nu*nv, 3]
        extent = (net.amax(2) - net.amin(2))[..., :2].amax(-1)  # [H, F] largest in-plane side [m]
        if not bool(((extent > 1e-4) & (extent <= 2 * MAX_MIRROR_M)).all()):
            c.fail("/field/surfaces/control_points", "expected every facet's control net to span between 0.1 mm "
                   f"and {2 * MAX_MIRROR_M:g} m in its plane")
    for name in ("translation", "canting_e", "canting_n"):
        t = getattr(fac, name)
        if t.numel() and float(t.abs().max()) > MAX_MIRROR_M:
            c.fail(f"/field/facets/{name}", f"expected facet offsets within {MAX_MIRROR_M:g} m of the pivot")


# ======================================================================================= from PAINT
def scenario_from_paint(paint_dir, heliostats=None, **kwargs) -> Plant:
    """A plant from a PAINT download (no calibration records), ready for :func:`save_scenario`.

    Parameters
    ----------
    paint_dir : path
        The PAINT folder (tower file + ``<HID>/Properties``).
    heliostats : list of str, optional
        Heliostat ids (default: all).
    **kwargs
        ``surface_control_points``, ``surface_degree`` for :func:`heliotwin.io.paint.load_paint`.

    Returns
    -------
    Plant
        Ideal (flat, canted) surfaces; float64 geometry.
    """
    return load_paint(paint_dir, heliostats, with_records=False, **kwargs).plant


def load_records(paint_dir, scenario=None, heliostats=None, *, plane_tolerance: float = 0.1,
                 require_times: bool = False):
    """The PAINT records of ``heliostats`` (default: all of the scenario, else all of the folder) on the
    scenario's plant (default: the folder's nominal plant): what every learner and checker starts from.

    Parameters
    ----------
    paint_dir : path
        The PAINT folder the records come from.
    scenario : path or Scenario, optional
        Its plant (e.g. calibrated) replaces the folder's nominal plant; same site, heliostats in the folder.
    heliostats : list of str, optional
    plane_tolerance : float
        Largest distance [m] of a focal spot from its target plane (:func:`heliotwin.io.records.build_record_table`).
    require_times : bool
        A flag [-]: a folder without ``metadata/calibration-metadata.csv`` (the records' times) is a one-line
        error, for a caller that orders or plans by the records' times (``report --paint``); see
        :func:`heliotwin.io.paint.load_paint`.

    Returns
    -------
    dataset : heliotwin.io.paint.PaintDataset
        Plant and record table (heliostat axis = the plant's heliostats).
    scenario : Scenario or None
    """
    sc = load_scenario(scenario) if isinstance(scenario, (str, os.PathLike)) else scenario
    if sc is None:
        return load_paint(paint_dir, heliostats, plane_tolerance=plane_tolerance, require_times=require_times), None
    ids = list(heliostats or sc.plant.field.ids)
    in_scenario = set(sc.plant.field.ids)
    unknown = [h for h in ids if h not in in_scenario]
    if unknown:
        raise InputFileError(sc.path, f"heliostat(s) {', '.join(unknown)} not in this scenario", field="/field/ids")
    in_folder = set(list_heliostats(paint_dir))  # listed once: per id it made a 10,000-heliostat report quadratic
    absent = [h for h in ids if h not in in_folder]
    if absent:
        raise InputFileError(sc.path, f"heliostat(s) {', '.join(absent[:5])} not in the PAINT folder {paint_dir}",
                             field="/field/ids")
    ds = load_paint(paint_dir, ids, plane_tolerance=plane_tolerance, require_times=require_times)
    return ds.on_plant(select_heliostats(sc.plant, ids), sc.path), sc
