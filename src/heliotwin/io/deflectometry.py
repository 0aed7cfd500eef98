"""PAINT deflectometry (HDF5) -> per-facet NURBS control nets.

File layout (PAINT)
-------------------
One group per facet, named ``facet1``, ``facet2``, ... (1-based, in the order of the heliostat's
``facet_properties.facets`` list), each with two datasets:

``surface_points``  [N, 3]  measured mirror points, heliostat frame [m]
``surface_normals`` [N, 3]  measured unit normals at those points, heliostat frame

Other top-level objects are ignored. N may differ between facets.

Fitting
-------
Each point gets surface parameters from the ideal facet: solving
``p - translation = s canting_e + t canting_n + h n_hat`` (exact even if the spans are not orthogonal)
and mapping s, t from [-1, 1] to u, v in [0, 1] (clamped). Because the ideal facet's NURBS is linear
in (u, v) (see :mod:`heliotwin.field.facets`), a fitted net is directly comparable to -- and can
replace -- the ideal one. :func:`heliotwin.nurbs.fit` then solves the linear least-squares problem on
points and normals.
"""
from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import torch

from .. import nurbs
from ..errors import HeliotwinError, InputFileError
from ..field.plant import Facets
from ..geometry import angle_between
from .hdf5 import open_for_reading
from .report import atomic_path

POINTS = "surface_points"
NORMALS = "surface_normals"
_FACET_GROUP = re.compile(r"facet(\d+)$")


# --------------------------------------------------------------------------------------------------
# Reading and writing
# --------------------------------------------------------------------------------------------------
#: Largest magnitude of a deflectometry point coordinate [m] or normal component accepted on reading.
MAX_ABS_VALUE = 1e3


def _read_vectors(path, group, name: str, field: str) -> np.ndarray:
    if name not in group:
        raise InputFileError(path, "missing dataset", field=field)
    ds = group[name]
    if not hasattr(ds, "shape") or not hasattr(ds, "dtype"):
        raise InputFileError(path, "expected a dataset, found a group", field=field)
    if len(ds.shape) != 2 or ds.shape[1] != 3 or ds.shape[0] == 0:
        raise InputFileError(path, f"expected shape [N, 3] with N >= 1, got {list(ds.shape)}", field=field)
    try:
        data = np.asarray(ds[()], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputFileError(path, f"not numeric ({exc})", field=field) from None
    bad = ~np.isfinite(data).all(axis=1)
    if bad.any():
        raise InputFileError(path, f"{int(bad.sum())} of {data.shape[0]} rows contain NaN/inf "
                                   f"(first at row {int(np.argmax(bad))})", field=field)
    # Points are metres on a mirror of a few metres and normals are (near-)unit vectors: anything beyond
    # MAX_ABS_VALUE is corrupt, and squaring it (normalising a normal) would overflow to inf or 0.
    big = np.abs(data).max(axis=1) > MAX_ABS_VALUE
    if big.any():
        raise InputFileError(path, f"{int(big.sum())} of {data.shape[0]} rows have a value beyond "
                                   f"{MAX_ABS_VALUE:g} (first at row {int(np.argmax(big))})", field=field)
    return data


def read_deflectometry(path) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Read a PAINT deflectometry HDF5 file.

    Parameters
    ----------
    path : str or Path
        The ``.h5`` file.

    Returns
    -------
    list of (points, normals), one per facet (``facet1`` first)
        points : torch.Tensor, [N, 3], float64, heliostat frame [m];
        normals : torch.Tensor, [N, 3], float64, re-normalised to unit length.

    Raises
    ------
    InputFileError
        Missing or unreadable file, not HDF5, no ``facetK`` groups or a gap in their numbering, a
        missing dataset, a shape other than [N, 3] (or different N for points and normals), NaN/inf
        values, or zero-length normals. The message names the file and the dataset.
    """
    path = Path(path)
    out = []
    with open_for_reading(path) as f:
        numbers = sorted(int(m.group(1)) for key in f.keys() if (m := _FACET_GROUP.match(key)))
        if not numbers:
            raise InputFileError(path, "no facet groups (expected facet1, facet2, ...)", field="facet1")
        expected = list(range(1, len(numbers) + 1))
        if numbers != expected:
            missing = sorted(set(range(1, max(numbers) + 1)) - set(numbers))
            name = f"facet{missing[0]}" if missing else f"facet{numbers[0]}"
            raise InputFileError(path, f"facet groups must be numbered 1..K without gaps, found "
                                       f"{', '.join(f'facet{k}' for k in numbers)}", field=name)
        for k in expected:
            group = f[f"facet{k}"]
            if not hasattr(group, "keys"):
                raise InputFileError(path, "expected a group with surface_points/surface_normals", field=f"facet{k}")
            points = _read_vectors(path, group, POINTS, f"facet{k}/{POINTS}")
            normals = _read_vectors(path, group, NORMALS, f"facet{k}/{NORMALS}")
            if normals.shape != points.shape:
                raise InputFileError(path, f"has {normals.shape[0]} rows but {POINTS} has {points.shape[0]}",
                                     field=f"facet{k}/{NORMALS}")
            length = np.linalg.norm(normals, axis=1)
            if (length < 1e-12).any():
                raise InputFileError(path, f"{int((length < 1e-12).sum())} zero-length normals",
                                     field=f"facet{k}/{NORMALS}")
            out.append((torch.from_numpy(points), torch.from_numpy(normals / length[:, None])))
    return out


def write_deflectometry(path, facets_points_normals: Sequence[tuple[torch.Tensor, torch.Tensor]],
                        dtype: str = "float64") -> None:
    """Write measurements in the PAINT deflectometry layout (atomically).

    The file is written under a temporary name in the target directory and renamed into place, so a
    crash never leaves a half-written file at ``path``.

    Parameters
    ----------
    path : str or Path
        Output ``.h5`` file (overwritten).
    facets_points_normals : sequence of (points [N, 3], normals [N, 3])
        One entry per facet, heliostat frame [m]; becomes ``facet1``, ``facet2``, ...
    dtype : str
        Stored dtype (``"float64"`` or ``"float32"``; PAINT uses float32).

    Raises
    ------
    HeliotwinError
        Empty input or shapes other than [N, 3] / mismatched N.
    """
    path = Path(path)
    if len(facets_points_normals) == 0:
        raise HeliotwinError("write_deflectometry: need at least one facet")
    arrays = []
    for k, (points, normals) in enumerate(facets_points_normals, start=1):
        p = np.asarray(torch.as_tensor(points).detach().cpu(), dtype=dtype)
        n = np.asarray(torch.as_tensor(normals).detach().cpu(), dtype=dtype)
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0 or n.shape != p.shape:
            raise HeliotwinError(f"write_deflectometry: facet{k} needs points and normals of the same shape "
                                 f"[N, 3], got {list(p.shape)} and {list(n.shape)}")
        arrays.append((p, n))
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            for k, (p, n) in enumerate(arrays, start=1):
                g = f.create_group(f"facet{k}")
                g.create_dataset(POINTS, data=p)
                g.create_dataset(NORMALS, data=n)


# --------------------------------------------------------------------------------------------------
# Fitting
# --------------------------------------------------------------------------------------------------
@dataclass
class DeflectometryFit:
    """Quality of a per-facet deflectometry fit (all tensors [F], float64).

    Attributes
    ----------
    rms_m, max_m : torch.Tensor
        RMS / max distance |S(u_k, v_k) - p_k| between fitted surface and measured points [m].
    normal_rms_mrad, normal_max_mrad : torch.Tensor
        RMS / max angle between fitted and measured normals [mrad].
    outside_fraction : torch.Tensor
        Fraction of points whose parameters fell outside the facet (|s| or |t| > 1 + 1e-6) and were
        clamped to its edge. Large values mean the points are not in the heliostat frame or the facet
        placement does not match the measurement.
    num_points : list of int
        Points per facet.
    """

    rms_m: torch.Tensor
    max_m: torch.Tensor
    normal_rms_mrad: torch.Tensor
    normal_max_mrad: torch.Tensor
    outside_fraction: torch.Tensor
    num_points: list[int]

    def __str__(self) -> str:
        rows = [f"facet{k + 1}: N={n}, rms {1e3 * float(r):.4f} mm (max {1e3 * float(m):.4f}), normals rms "
                f"{float(a):.4f} mrad (max {float(b):.4f}), outside {100 * float(o):.2f} %"
                for k, (n, r, m, a, b, o) in enumerate(zip(self.num_points, self.rms_m, self.max_m,
                                                           self.normal_rms_mrad, self.normal_max_mrad,
                                                           self.outside_fraction))]
        return "\n".join(rows)


def _facet_placement(facets) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    # Accept Facets ([F, 3] or [1, F, 3]), a stacked triple of [F, 3] tensors (facets_from_paint), or a
    # per-facet sequence of (translation, canting_e, canting_n).
    if isinstance(facets, Facets):
        parts = (facets.translation, facets.canting_e, facets.canting_n)
    elif (isinstance(facets, Sequence) and len(facets) == 3
          and all(isinstance(x, torch.Tensor) and x.dim() == 2 for x in facets)):
        parts = tuple(facets)
    elif isinstance(facets, Sequence) and len(facets) > 0:
        try:
            parts = tuple(torch.stack([torch.as_tensor(f[i], dtype=torch.float64) for f in facets]) for i in range(3))
        except (TypeError, IndexError, RuntimeError, ValueError):
            raise HeliotwinError("fit_deflectometry: facets must be Facets, (translation, canting_e, canting_n) "
                                 "[F, 3] tensors, or a list of per-facet (translation, canting_e, canting_n)") from None
    else:
        raise HeliotwinError("fit_deflectometry: facets must be Facets or a sequence of facet placements")
    parts = tuple(p.to(torch.float64) for p in parts)
    parts = tuple(p[0] if p.dim() == 3 and p.shape[0] == 1 else p for p in parts)
    if any(p.dim() != 2 or p.shape[-1] != 3 or p.shape != parts[0].shape for p in parts):
        raise HeliotwinError(f"fit_deflectometry: facet placement must be [F, 3] for one heliostat, got "
                             f"{[tuple(p.shape) for p in parts]}")
    return parts


def facet_parameters(points: torch.Tensor, translation: torch.Tensor, canting_e: torch.Tensor,
                     canting_n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Surface parameters of points from the ideal facet's affine frame.

    Parameters
    ----------
    points : torch.Tensor, [N, 3]
        Points near the facet, heliostat frame [m].
    translation, canting_e, canting_n : torch.Tensor, [3]
        The facet's placement [m].

    Returns
    -------
    uv : torch.Tensor, [N, 2]
        ``((s + 1) / 2, (t + 1) / 2)`` clamped to [0, 1], where ``p - translation = s canting_e +
        t canting_n + h n_hat`` (solved exactly, so non-orthogonal spans are fine).
    outside : torch.Tensor, [N], bool
        Points with |s| or |t| > 1 + 1e-6 (clamped).
    """
    x = points.to(torch.float64)
    e, n, t0 = (v.to(dtype=x.dtype, device=x.device) for v in (canting_e, canting_n, translation))
    normal = torch.linalg.cross(e, n, dim=-1)
    basis = torch.stack((e, n, normal / torch.linalg.vector_norm(normal)), dim=-1)  # columns [3, 3]
    coeff = torch.linalg.solve(basis, (x - t0).T).T  # [N, 3] = (s, t, h)
    st = coeff[:, :2]
    outside = (st.abs() > 1.0 + 1e-6).any(dim=1)
    return ((st + 1.0) / 2.0).clamp(0.0, 1.0), outside


def fit_deflectometry(measurements: Sequence[tuple[torch.Tensor, torch.Tensor]], facets,
                      num_control_points: tuple[int, int] = (8, 8), degree: tuple[int, int] = (3, 3),
                      normal_weight: float = 1.0, ridge: float = 1e-9) -> tuple[torch.Tensor, DeflectometryFit]:
    """Fit one NURBS control net per facet to deflectometry points and normals.

    Parameters
    ----------
    measurements : sequence of (points [N_f, 3], normals [N_f, 3])
        As returned by :func:`read_deflectometry`, heliostat frame [m].
    facets : Facets or placement
        The heliostat's facet placement: :class:`~heliotwin.field.plant.Facets` with [F, 3] or
        [1, F, 3] tensors, the ``(translation, canting_e, canting_n)`` triple of [F, 3] tensors from
        :func:`~heliotwin.field.facets.facets_from_paint`, or a list of per-facet triples of [3].
    num_control_points : (int, int)
        (nu, nv); u along ``canting_e``, v along ``canting_n``.
    degree : (int, int)
        (p, q).
    normal_weight : float
        Weight of the normal constraints in :func:`heliotwin.nurbs.fit` (0 = points only).
    ridge : float
        Relative ridge regularisation of :func:`heliotwin.nurbs.fit`.

    Returns
    -------
    control_points : torch.Tensor, [F, nu, nv, 3], float64
        Heliostat-frame control nets [m] (non-rational); stack over heliostats for
        :class:`~heliotwin.field.plant.Surfaces`.
    report : DeflectometryFit
        Residuals of the fit per facet.

    Raises
    ------
    HeliotwinError
        Facet count of the measurement and the placement differ, or bad shapes.
    """
    translation, canting_e, canting_n = _facet_placement(facets)
    if len(measurements) != translation.shape[0]:
        raise HeliotwinError(f"fit_deflectometry: the measurement has {len(measurements)} facets but the "
                             f"placement has {translation.shape[0]}")
    p, q = (int(x) for x in degree)
    nets, rms, mx, nrms, nmax, outside_frac, counts = [], [], [], [], [], [], []
    for f, (points, normals) in enumerate(measurements):  # few facets, each with its own N
        points = torch.as_tensor(points, dtype=torch.float64)
        normals = torch.as_tensor(normals, dtype=torch.float64, device=points.device)
        if points.dim() != 2 or points.shape[-1] != 3 or normals.shape != points.shape:
            raise HeliotwinError(f"fit_deflectometry: facet{f + 1} points/normals must both be [N, 3], got "
                                 f"{tuple(points.shape)} and {tuple(normals.shape)}")
        normals = normals / torch.linalg.vector_norm(normals, dim=-1, keepdim=True).clamp_min(nurbs.NORM_EPS)
        uv, outside = facet_parameters(points, translation[f].to(points.device), canting_e[f].to(points.device),
                                       canting_n[f].to(points.device))
        net = nurbs.fit(points, uv, num_control_points, (p, q), normals=normals, normal_weight=normal_weight,
                        ridge=ridge)
        s, su, sv = nurbs.evaluate_points(net, p, q, uv)
        dist = torch.linalg.vector_norm(s - points, dim=-1)
        fitted_normal = torch.linalg.cross(su, sv, dim=-1)
        ang = angle_between(fitted_normal, normals) * 1e3
        nets.append(net)
        rms.append(dist.square().mean().sqrt())
        mx.append(dist.max())
        nrms.append(ang.square().mean().sqrt())
        nmax.append(ang.max())
        outside_frac.append(outside.to(torch.float64).mean())
        counts.append(int(points.shape[0]))
    report = DeflectometryFit(torch.stack(rms), torch.stack(mx), torch.stack(nrms), torch.stack(nmax),
                              torch.stack(outside_frac), counts)
    return torch.stack(nets), report
