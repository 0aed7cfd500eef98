"""The plant as plain data: site, targets, and the heliostat field as a structure of arrays.

Nothing here computes physics; functions elsewhere transform these containers. Learnable quantities are
ordinary tensors (the optimiser layer decides which ones require grad).

Heliostat frame
---------------
Facets and surfaces are given in the *heliostat frame*: x = east, y = north, z = up when the mirror
lies flat facing the zenith, origin at the concentrator (the point the kinematics positions). The
kinematics returns ``R_world_heliostat`` (3, 3) and the concentrator position, so a world point is
``concentrator + R_world_heliostat @ p_heliostat`` and the mirror normal is ``R_world_heliostat @ e_z``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import torch

from ..site import Site
from .targets import CylinderTarget, PlanarTarget

#: Names of the per-axis actuator tensors in :class:`Kinematics` (each shape [H, 2]).
ACTUATOR_FIELDS = ("increment", "offset", "pivot_radius", "initial_angle", "initial_stroke_length")


@dataclass
class Kinematics:
    """Rigid-body two-axis kinematics with actuators, for H heliostats (PAINT / Jülich model).

    Chain (all deviations zero in the nominal PAINT model except the concentrator translation)::

        concentrator = position + joint_translation[0]
                       + R1 (joint_translation[1] + R2 concentrator_translation)
        R_world_heliostat = R1 R2 R3 R_E(pi/2)
        R1 = R_U(joint_tilt[0,2]) R_N(joint_tilt[0,1]) R_E(theta1 - pi/2)    (joint 1 turns about east)
        R2 = R_E(joint_tilt[1,0]) R_N(joint_tilt[1,1]) R_U(theta2)           (joint 2 turns about up)
        R3 = R_E(concentrator_tilt[0]) R_N(concentrator_tilt[1]) R_U(concentrator_tilt[2])

    ``theta_i`` come from the actuators (see :mod:`heliotwin.field.actuators`). The ``- pi/2`` is PAINT's
    convention: the zero of axis 1's ``initial_angle`` is a quarter turn from the joint's zero.
    ``R_E(pi/2)`` turns the heliostat frame's mirror normal ``e_z`` into PAINT's initial orientation
    ``(0, -1, 0)`` (facing south).

    Attributes
    ----------
    position : torch.Tensor, [H, 3], float64
        Heliostat position (pivot of joint 1), ENU [m].
    joint_translation : torch.Tensor, [H, 2, 3]
        Translation before joint 1 / between joint 1 and 2, ENU components [m].
    concentrator_translation : torch.Tensor, [H, 3]
        From joint 2 to the concentrator [m].
    joint_tilt : torch.Tensor, [H, 2, 3]
        Small rotations (e, n, u) [rad] of each joint's axis; the component about the joint's own axis
        (joint 1: e, joint 2: u) is redundant with ``initial_angle`` and ignored.
    concentrator_tilt : torch.Tensor, [H, 3]
        Rotation (e, n, u) [rad] of the concentrator about its mount.
    increment : torch.Tensor, [H, 2]
        Linear actuator: motor steps per metre of stroke [1/m]; ideal actuator: steps per radian.
    offset, pivot_radius : torch.Tensor, [H, 2]
        Linear actuator geometry (law of cosines) [m].
    initial_angle : torch.Tensor, [H, 2]
        Joint angle at zero steps [rad].
    initial_stroke_length : torch.Tensor, [H, 2]
        Stroke at zero steps [m].
    clockwise : torch.Tensor, [H, 2], bool
        PAINT ``clockwise_axis_movement``.
    linear : torch.Tensor, [H, 2], bool
        True for a linear actuator, False for an ideal (angle proportional to steps) one.
    min_steps, max_steps : torch.Tensor, [H, 2]
        Motor range [steps].
    min_angle, max_angle : torch.Tensor, [H, 2]
        PAINT ``min/max_movement_angle`` [rad] (informative).
    """

    position: torch.Tensor
    joint_translation: torch.Tensor
    concentrator_translation: torch.Tensor
    joint_tilt: torch.Tensor
    concentrator_tilt: torch.Tensor
    increment: torch.Tensor
    offset: torch.Tensor
    pivot_radius: torch.Tensor
    initial_angle: torch.Tensor
    initial_stroke_length: torch.Tensor
    clockwise: torch.Tensor
    linear: torch.Tensor
    min_steps: torch.Tensor
    max_steps: torch.Tensor
    min_angle: torch.Tensor
    max_angle: torch.Tensor

    @property
    def num_heliostats(self) -> int:
        """H, the length of the leading (heliostat) axis of every field."""
        return int(self.position.shape[0])

    def index(self, idx) -> "Kinematics":
        """Select heliostats (int, slice, list or index tensor of shape (K,)); returns a new container (views).

        Every field keeps its trailing shape: ``position`` (H, 3) becomes (K, 3), and so on (an int gives K = 1).
        """
        if isinstance(idx, int):
            idx = [idx]
        return Kinematics(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})

    def replace(self, **changes) -> "Kinematics":
        """A copy with some fields replaced (e.g. learnable deviations)."""
        return replace(self, **changes)

    def to(self, dtype=None, device=None) -> "Kinematics":
        """Float tensors to ``dtype``/``device``; bool tensors keep their dtype; shapes (H, ...) unchanged."""
        out = {}
        for f in fields(self):
            t = getattr(self, f.name)
            out[f.name] = t.to(device=device) if t.dtype == torch.bool else t.to(device=device, dtype=dtype or t.dtype)
        return Kinematics(**out)

    @staticmethod
    def concatenate(items: list["Kinematics"]) -> "Kinematics":
        """Stack several fields' kinematics along the heliostat axis."""
        return Kinematics(**{f.name: torch.cat([getattr(k, f.name) for k in items]) for f in fields(Kinematics)})


@dataclass
class Facets:
    """Facet placement for H heliostats with F facets each, heliostat frame [m].

    Attributes
    ----------
    translation : torch.Tensor, [H, F, 3]
        Facet centre relative to the concentrator (PAINT ``translation_vector``).
    canting_e, canting_n : torch.Tensor, [H, F, 3]
        Half-width / half-height span vectors (PAINT ``canting_e`` / ``canting_n``); their directions
        carry the canting, their lengths half the facet size.
    """

    translation: torch.Tensor
    canting_e: torch.Tensor
    canting_n: torch.Tensor


@dataclass
class Surfaces:
    """NURBS mirror surfaces, one per facet, in the heliostat frame.

    Attributes
    ----------
    control_points : torch.Tensor, [H, F, nu, nv, 3]
        Control points [m] (heliostat frame).
    degree_u, degree_v : int
    weights : torch.Tensor or None, [H, F, nu, nv]
        Rational weights; None means all ones (a B-spline).
    """

    control_points: torch.Tensor
    degree_u: int = 2
    degree_v: int = 2
    weights: torch.Tensor | None = None


@dataclass
class Field:
    """The heliostat field (structure of arrays over H heliostats).

    Attributes
    ----------
    ids : list of str
        Heliostat names (e.g. ``"AA39"``), length H.
    kinematics : Kinematics
    facets : Facets
    surfaces : Surfaces
    width, height : torch.Tensor, [H]
        Overall heliostat size from the properties file [m] (informative).
    renovation : list of str
        Date of last renovation per heliostat (ISO), or "".
    """

    ids: list[str]
    kinematics: Kinematics
    facets: Facets
    surfaces: Surfaces
    width: torch.Tensor
    height: torch.Tensor
    renovation: list[str] = field(default_factory=list)

    def index_of(self, heliostat_id: str) -> int:
        """Position of a heliostat by name; raises :class:`KeyError` listing the valid names."""
        try:
            return self.ids.index(heliostat_id)
        except ValueError:
            raise KeyError(f"unknown heliostat {heliostat_id!r}; this field has {', '.join(self.ids)}") from None


@dataclass
class SunSettings:
    """Sun and mirror optics used when tracing.

    Attributes
    ----------
    sunshape : str
        ``"gaussian"``, ``"pillbox"`` or ``"buie"``.
    sigma : float
        Gaussian sunshape standard deviation per axis [rad].
    radius : float
        Pillbox half-angle [rad] (4.65 mrad: the solar disc).
    csr : float
        Buie circumsolar ratio [-].
    slope_error : float
        Mirror slope error, standard deviation per axis [rad] (0 = perfect mirrors).
    dni : float
        Direct normal irradiance [W/m^2].
    reflectivity : float
        Mirror reflectivity [-].
    """

    sunshape: str = "buie"
    sigma: float = 2.51e-3
    radius: float = 4.65e-3
    csr: float = 0.05
    slope_error: float = 1.0e-3
    dni: float = 900.0
    reflectivity: float = 0.94


@dataclass
class Plant:
    """A whole plant: site, tower targets, heliostat field and optics settings."""

    site: Site
    targets: dict[str, PlanarTarget | CylinderTarget]
    field: Field
    sun: SunSettings = field(default_factory=SunSettings)

    def target(self, name: str) -> PlanarTarget | CylinderTarget:
        """Target by name; raises :class:`KeyError` listing the known names."""
        try:
            return self.targets[name]
        except KeyError:
            raise KeyError(f"unknown target {name!r}; known targets: {', '.join(sorted(self.targets))}") from None
