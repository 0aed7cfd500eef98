"""The aim-point problem: the plant at one sun, the receiver's allowable flux (a limit per map cell), the objective's
weights, and the exact field model every result is judged on.

    maximise P(a)  subject to  F_c(a) <= L_c for every cell c of the reporting map

(or minimise the mismatch of ``F / P`` to a target shape under the same limits). ``L`` is a
:class:`FluxLimit`: one peak limit (the same ``L`` in every cell, SolarPILOT's and SAM's "allowable peak flux") or an
allowable-flux map (:mod:`heliotwin.optimise.fluxmap`: a HALOS ``allowable_flux.csv``, per-panel limits with a
flow-path derating). The solver (:mod:`heliotwin.optimise.solver`) only ever sees the map; a uniform limit is the
constant map, and its decisions are written so that a constant map gives the uniform limit's aim points bit for bit
(``max(F / L) = max(F) / L`` exactly: division by a positive constant is monotone under correct rounding).

Shapes: H heliostats; aim points [H, 3] ENU [m]; maps [rows, cols] [W/m^2] (row 0 = top); powers [W].
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.distributed as dist

from ..distributed import field_optics_sharded, gather_rows, shard
from ..errors import HeliotwinError
from ..field.plant import Plant
from ..raytrace.field import FieldSettings, field_optics

__all__ = ["AimResult", "AimProblem", "FluxLimit", "WarmStart", "BINDING_WITHIN", "check_settings", "evaluate",
           "uniform_target", "load_target", "target_mismatch"]

#: A cell is *binding* when its flux is within this fraction of its own limit [-] (the maps mark them).
BINDING_WITHIN = 0.01


@dataclass(frozen=True)
class FluxLimit:
    """The allowable flux on every cell of the receiver map.

    Attributes
    ----------
    cells : torch.Tensor, [rows, cols], float64
        Limit per cell [W/m^2] on the model's map (row 0 = top; columns along the unrolled receiver, as
        ``heliotwin field`` draws it).
    source : str
        Where it came from (``"peak limit"``, a file), for reports.
    """

    cells: torch.Tensor
    source: str = "peak limit"

    @classmethod
    def uniform(cls, peak_limit: float, resolution) -> FluxLimit:
        """The same limit [W/m^2] on every cell of a ``(rows, cols)`` map."""
        rows, cols = (int(r) for r in resolution)
        return cls(torch.full((rows, cols), float(peak_limit), dtype=torch.float64))

    @classmethod
    def of(cls, limit, resolution) -> FluxLimit:
        """``limit`` as a :class:`FluxLimit` on a ``(rows, cols)`` map: a float (uniform), a [rows, cols] tensor or
        array [W/m^2], or a :class:`FluxLimit` (checked against the grid)."""
        rows, cols = (int(r) for r in resolution)
        if isinstance(limit, FluxLimit):
            out = limit
        elif isinstance(limit, (torch.Tensor, np.ndarray)) and np.ndim(limit) > 0:
            out = cls(torch.as_tensor(limit).detach().to(torch.float64).cpu(), "map")
        else:
            return cls.uniform(float(limit), resolution)
        if tuple(out.cells.shape) != (rows, cols):
            raise HeliotwinError(f"flux limit map has shape {tuple(out.cells.shape)}, the receiver map is "
                                 f"{rows}x{cols} (rows x cols)")
        return out

    @property
    def is_uniform(self) -> bool:
        """Whether every cell has the same limit."""
        return bool(self.cells.min() == self.cells.max())

    @property
    def minimum(self) -> float:
        """The lowest cell limit [W/m^2]."""
        return float(self.cells.min())

    def on(self, like: torch.Tensor) -> torch.Tensor:
        """The map [rows, cols] in ``like``'s dtype and device."""
        return self.cells.to(like)

    def utilisation(self, flux: torch.Tensor) -> torch.Tensor:
        """``flux / limit`` per cell [rows, cols] [-]."""
        return flux / self.on(flux)

    def ratio(self, flux: torch.Tensor) -> float:
        """The largest ``flux / limit`` over the cells [-] of ``flux`` [rows, cols] [W/m^2] (``peak / limit`` for a
        uniform limit, exactly)."""
        return float(self.utilisation(flux).max())

    def held(self, flux: torch.Tensor) -> bool:
        """Whether every cell of ``flux`` [rows, cols] [W/m^2] is at or below its limit."""
        return bool((flux <= self.on(flux)).all())

    def binding(self, flux: torch.Tensor, within: float = BINDING_WITHIN) -> torch.Tensor:
        """Cells [rows, cols] (bool) whose flux (``flux`` [rows, cols] [W/m^2]) is within ``within`` [-] (a share of
        the limit) of their limit (or over it)."""
        return self.utilisation(flux) >= 1.0 - float(within)

    def key(self, flux: torch.Tensor) -> tuple[float, float]:
        """Order of violation of ``flux`` [rows, cols] [W/m^2] (smaller: less violating): the largest utilisation
        [-], then the peak [W/m^2] (for a uniform limit the same order as the peak's alone)."""
        return self.ratio(flux), float(flux.max())

    def summary(self, flux: torch.Tensor) -> dict:
        """``max_utilisation`` [-] and ``binding_cells`` (within :data:`BINDING_WITHIN` of their limit) of a map
        ``flux`` [rows, cols] [W/m^2]."""
        return {"max_utilisation": self.ratio(flux), "binding_cells": int(self.binding(flux).sum())}


@dataclass(frozen=True)
class AimProblem:
    """One aim-point problem: the plant at one sun under a flux limit, and what the objective weighs.

    Attributes
    ----------
    plant : Plant
        Field and ``receiver`` target (tensors on the device the work runs on).
    sun : torch.Tensor, [3]
        Unit vector towards the sun, ENU.
    limit : FluxLimit
        The allowable flux per map cell (on the options' resolution).
    atmosphere : Atmosphere, optional
    target : torch.Tensor, [rows, cols], optional
        A target shape (unit sum): minimise ``|F/sum F - target|^2 / |target|^2 - 0.1 P / P_eq`` instead of
        maximising power.
    group : ProcessGroup, optional
        Shard the heliostats over this group (every rank solves the same problem).
    """

    plant: Plant
    sun: torch.Tensor
    limit: FluxLimit
    atmosphere: object = None
    target: torch.Tensor | None = None
    group: object = None


@dataclass(frozen=True)
class WarmStart:
    """Where the previous instant ended, to start the next from (:meth:`from_result` of its :class:`AimResult`).

    Attributes
    ----------
    aim : torch.Tensor, [H, 3]
        Aim points ENU [m] (projected onto the receiver's height and each heliostat's visible arc).
    multipliers : torch.Tensor, [rows, cols], optional
        The augmented Lagrangian's multipliers to start from.
    margin : float, optional
        The internal margin to start from [-].
    field : FieldResult, optional
        The exact result of ``aim`` at the earlier sun: round 0 is then predicted from it (cosine-scaled powers,
        the earlier map plus the image model's change) instead of an exact check.
    """

    aim: torch.Tensor
    multipliers: torch.Tensor | None = None
    margin: float | None = None
    field: object = None

    @classmethod
    def from_result(cls, result: AimResult, *, predict: bool = True) -> WarmStart:
        """The warm start a result leaves (``predict``: with its exact field, so round 0 is predicted)."""
        return cls(result.aim, result.multipliers, result.parameter, result.exact if predict else None)


@dataclass
class AimResult:
    """Aim points [H, 3] and what the exact model gives for them: receiver power [W], peak [W/m^2], map."""

    aim: torch.Tensor
    power_w: float
    peak_flux_w_m2: float
    flux: torch.Tensor
    seconds: float = 0.0
    iterations: int = 0
    parameter: float | None = None
    history: list = field(default_factory=list)
    standby: int = 0  #: heliostats sent off the receiver (standby) so that the limit holds
    #: the augmented Lagrangian's multipliers per map cell [rows, cols] [-] at the end (a warm start's)
    multipliers: torch.Tensor | None = None
    #: the power [W] the objective was relative to: equator aiming's on the exact model, or (a warm start without
    #: the equator check) the corrected image model's estimate of it
    reference_power_w: float | None = None
    #: exact field-model evaluations made (the rounds' checks, the warm start's, the standby search's)
    exact_checks: int = 0
    #: the exact model's :class:`~heliotwin.raytrace.field.FieldResult` of these aim points (the next instant's
    #: ``start_field``)
    exact: object = None

    def violation(self, limit) -> float:
        """Relative excess over the limit (0 when met): of the peak over a float limit [W/m^2], or the largest
        utilisation's over 1 for a :class:`FluxLimit`."""
        if isinstance(limit, FluxLimit):
            return max(0.0, limit.ratio(self.flux) - 1.0)
        return max(0.0, self.peak_flux_w_m2 / float(limit) - 1.0)


# ------------------------------------------------------------------------------------------ exact model
class _Group:
    """All-reduce and field model of one process group (or of one process when ``group`` is None)."""

    def __init__(self, group=None):
        self.group = group
        if group is None:
            self.rank, self.world = 0, 1
        else:
            self.rank, self.world = dist.get_rank(group), dist.get_world_size(group)

    def rows(self, h: int, device) -> torch.Tensor:
        if self.group is None:
            return torch.arange(h, device=device)
        return shard(h, self.rank, self.world).to(device)

    def sum(self, t: torch.Tensor) -> torch.Tensor:
        """Sum over ranks, keeping the gradient of this rank's part (straight-through)."""
        if self.group is None:
            return t
        total = t.detach().clone()
        dist.all_reduce(total, group=self.group)
        return t + (total - t.detach())

    def gather(self, t: torch.Tensor, h: int) -> torch.Tensor:
        if self.group is None:
            return t
        return gather_rows(t.detach(), [len(shard(h, k, self.world)) for k in range(self.world)], self.group)

    def field(self, plant, sun, atmosphere, aim, settings):
        with torch.no_grad():
            if self.group is None:
                return field_optics(plant, sun, atmosphere=atmosphere, aim=aim, settings=settings)
            return field_optics_sharded(plant, sun, group=self.group, atmosphere=atmosphere, aim=aim,
                                        settings=settings)


def check_settings(resolution=(20, 48)) -> FieldSettings:
    """The exact model every result is judged with: hard occlusion on the reporting grid, the map exactly as
    ``heliotwin field`` draws it (``flux_mode="auto"``: every flux sample's own Gaussian on small fields,
    footprint classes on large ones, where one map costs ~15 s per-sample against ~0.5 s; the map is the same
    in one process and sharded), in float64: the rounds feed it back into the optimiser, and a float32 map's
    summation order (one process or shards) changed the sharded aim points by millimetres."""
    return FieldSettings(resolution=tuple(int(r) for r in resolution), dtype=torch.float64)


def evaluate(plant: Plant, sun: torch.Tensor, aim: torch.Tensor, atmosphere=None, resolution=(20, 48), *,
             group=None) -> AimResult:
    """The exact (hard-occlusion, per-sample map) field model at fixed aim points.

    ``sun`` is the unit vector towards the sun, shape (3,), ENU; ``aim`` the aim points, shape (H, 3), ENU [m];
    ``resolution`` the receiver map's ``(rows, cols)``. The result holds the receiver power [W], the peak
    [W/m^2] and the map, shape (rows, cols) [W/m^2].
    """
    r = _Group(group).field(plant, sun, atmosphere, aim, check_settings(resolution))
    return AimResult(aim.detach(), float(r.power_w.sum()), float(r.flux.max()), r.flux)


# ------------------------------------------------------------------------------------------ targets
def uniform_target(equator_flux: torch.Tensor) -> torch.Tensor:
    """Target shape [rows, cols]: flat over the receiver height, laterally the equator map's column profile
    (an external receiver is lit only on the side facing the field), normalised to unit sum [1].

    ``equator_flux`` is the map with every heliostat aimed at the equator, shape (rows, cols) [W/m^2]; the
    result has the same shape, float64.
    """
    col = equator_flux.to(torch.float64).sum(0, keepdim=True).clamp_min(0.0)
    t = col.expand(equator_flux.shape[0], -1).clone()
    return t / t.sum().clamp_min(1e-30)


def load_target(path, resolution) -> torch.Tensor:
    """A target flux map (or shape) from a ``.npy`` or ``.csv`` file, [rows, cols] as the reporting grid (row
    0 = top), non-negative; returned normalised to unit sum (only the shape counts)."""
    rows, cols = (int(r) for r in resolution)
    text = str(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # numpy's "no data" warning: the shape check says it
            arr = np.load(text) if text.endswith(".npy") else np.loadtxt(text, delimiter=",", comments="#",
                                                                           ndmin=2)
    except (OSError, ValueError) as exc:
        raise HeliotwinError(f"{text}: cannot read the target flux map ({exc})") from None
    arr = np.asarray(arr, dtype=np.float64)
    if arr.shape != (rows, cols):
        raise HeliotwinError(f"{text}: target map has shape {arr.shape[0] if arr.ndim else 0}x"
                             f"{arr.shape[1] if arr.ndim > 1 else 0} (rows x cols), the receiver grid is "
                             f"{rows}x{cols}")
    if not np.isfinite(arr).all() or (arr < 0).any() or not (arr > 0).any():
        raise HeliotwinError(f"{text}: target map must be finite, non-negative and not all zero")
    t = torch.as_tensor(arr / arr.max())  # scaled first: a sum of values near 1e308 would overflow
    return t / t.sum()


def target_mismatch(flux: torch.Tensor, target: torch.Tensor) -> float:
    """Relative L2 mismatch ``|F / sum F - T| / |T|`` of a map to a unit-sum target shape.

    ``flux`` is a map, shape (rows, cols) [W/m^2] (only its shape counts); ``target`` the unit-sum target of
    the same shape [1]. Returns a float scalar [1].
    """
    f = flux.to(torch.float64)
    t = target.to(f)
    return float(torch.linalg.vector_norm(f / f.sum().clamp_min(1e-30) - t) / torch.linalg.vector_norm(t))
