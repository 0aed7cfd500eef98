"""Deviation parameters of the rigid-body chain and how they enter :class:`~heliotwin.field.plant.Kinematics`.

Every calibration method learns a vector of *deviations* per heliostat, ``delta`` [H, P], in physical
units, added to the nominal kinematics by :func:`apply_deviations`. The full set has 28 entries (PAINT's
rigid body with two linear actuators); a method uses a subset by name. Increments are scaled
multiplicatively (``increment * (1 + delta)``: a relative gear-ratio error), everything else is additive.

Two of the 28 are invisible to any measurement (the tilt of each joint about its own axis is redundant
with the joint angle offset, see :class:`Kinematics`); they are kept so that the vector maps one-to-one
onto the data model, and the prior holds them at zero.

The 8-parameter Stone/Jülich error model (:data:`STONE8`) maps onto the chain as follows (joint 1 turns
about east, joint 2 about up):

* two pylon tilts -> ``joint_tilt[0, n]``, ``joint_tilt[0, u]`` (tilt of the first axis);
* axis non-orthogonality -> ``joint_tilt[1, n]`` (second axis leaning towards the first);
* mirror tilt -> ``concentrator_tilt[e]`` (normal not perpendicular to the second axis);
* two axis (encoder zero) offsets -> ``initial_angle[0]``, ``initial_angle[1]``;
* two gear ratios -> ``increment[0]``, ``increment[1]`` (relative).
"""
from __future__ import annotations

import torch

from ..errors import HeliotwinError
from ..field.actuators import law_of_cosines_valid
from ..field.plant import Kinematics

_AX = "enu"

#: (name, Kinematics field, index within the per-heliostat tensor, kind). Kinds set prior scales.
PARAMETERS: tuple = tuple(
    [(f"joint_translation_{j + 1}_{a}", "joint_translation", (j, i), "translation")
     for j in range(2) for i, a in enumerate(_AX)]
    + [(f"joint_tilt_{j + 1}_{a}", "joint_tilt", (j, i), "tilt") for j in range(2) for i, a in enumerate(_AX)]
    + [(f"concentrator_translation_{a}", "concentrator_translation", (i,), "translation") for i, a in enumerate(_AX)]
    + [(f"concentrator_tilt_{a}", "concentrator_tilt", (i,), "tilt") for i, a in enumerate(_AX)]
    + [(f"{k}_{j + 1}", k, (j,), kind) for k, kind in (("increment", "increment"), ("offset", "actuator_length"),
                                                      ("pivot_radius", "actuator_length"),
                                                      ("initial_angle", "angle"),
                                                      ("initial_stroke_length", "actuator_length"))
       for j in range(2)]
)
NAMES: tuple = tuple(p[0] for p in PARAMETERS)
_BY_NAME = {p[0]: p for p in PARAMETERS}
#: Each parameter's (Kinematics field, index within the per-heliostat tensor).
FIELD_OF = {p[0]: (p[1], p[2]) for p in PARAMETERS}
#: The actuators' fields (one value per axis): they move the chain through the joint angles.
ACTUATOR_FIELDS = ("increment", "offset", "pivot_radius", "initial_angle", "initial_stroke_length")

#: Tilts of a joint about its own axis: no measurement can see them (redundant with initial_angle).
REDUNDANT = ("joint_tilt_1_e", "joint_tilt_2_u")

#: The 8-parameter Stone/Jülich model (see module docstring).
STONE8 = ("initial_angle_1", "initial_angle_2", "joint_tilt_1_n", "joint_tilt_1_u", "joint_tilt_2_n",
          "concentrator_tilt_e", "increment_1", "increment_2")

#: All deviations of the chain (28).
ALL = NAMES

#: One "natural unit" per kind: 1 mrad for angles, 1 mm for lengths, 0.1 % for increments. Optimisers work
#: on ``delta / UNIT`` so that every coordinate has a comparable curvature.
UNIT = {"tilt": 1e-3, "angle": 1e-3, "translation": 1e-3, "actuator_length": 1e-3, "increment": 1e-3}


def kinds(names) -> list[str]:
    """Kind of each named parameter."""
    return [_BY_NAME[n][3] for n in names]


def units(names, dtype=torch.float64, device=None) -> torch.Tensor:
    """``UNIT`` of each named parameter, [P]."""
    return torch.tensor([UNIT[k] for k in kinds(names)], dtype=dtype, device=device)


def check_names(names) -> tuple:
    """Validate parameter names (one-line error listing the known ones)."""
    bad = [n for n in names if n not in _BY_NAME]
    if bad:
        raise HeliotwinError(f"unknown calibration parameter(s) {', '.join(bad)}; known: {', '.join(NAMES)}")
    return tuple(names)


def apply_deviations(kin: Kinematics, delta: torch.Tensor, names) -> Kinematics:
    """Kinematics with deviations added (differentiable in ``delta``).

    Parameters
    ----------
    kin : Kinematics
        H heliostats, nominal.
    delta : torch.Tensor, [H, P]
        Deviations in physical units (rad, m; relative for increments), ordered as ``names``.
    names : sequence of str, length P

    Returns
    -------
    Kinematics
        New container; fields not named are shared with ``kin``.
    """
    add, scale = {}, {}
    for p, name in enumerate(names):
        _, fname, idx, kind = _BY_NAME[name]
        base = getattr(kin, fname)
        # Scatter the column into a zero tensor of the field's shape (out of place, so autograd follows).
        onehot = torch.zeros_like(base)
        onehot[(slice(None),) + idx] = 1.0
        col = delta[:, p].reshape((-1,) + (1,) * (base.dim() - 1))
        target = scale if kind == "increment" else add
        target[fname] = target.get(fname, 0.0) + onehot * col
    changes = {}
    for fname in set(add) | set(scale):
        v = getattr(kin, fname)
        if fname in scale:
            v = v * (1.0 + scale[fname])
        if fname in add:
            v = v + add[fname]
        changes[fname] = v
    return kin.replace(**changes)


def read_deviations(kin: Kinematics, nominal: Kinematics, names) -> torch.Tensor:
    """Inverse of :func:`apply_deviations`: the deviations of ``kin`` from ``nominal``, [H, P]."""
    out = []
    for name in names:
        _, fname, idx, kind = _BY_NAME[name]
        a = getattr(kin, fname)[(slice(None),) + idx]
        b = getattr(nominal, fname)[(slice(None),) + idx]
        out.append(a / b - 1.0 if kind == "increment" else a - b)
    return torch.stack(out, -1)


def actuator_margin(kin: Kinematics) -> torch.Tensor:
    """Smallest law-of-cosines margin [m] over the motor range, [H, 2] (negative = invalid triangle).

    The stroke is monotone in the steps, so checking both range ends covers the whole range.
    """
    margins = []
    for steps in (kin.min_steps, kin.max_steps):
        stroke = steps / kin.increment + kin.initial_stroke_length
        lo = stroke - torch.abs(kin.offset - kin.pivot_radius)
        hi = kin.offset + kin.pivot_radius - stroke
        margins.append(torch.minimum(lo, hi))
    m = torch.minimum(*margins)
    # Ideal actuators have no triangle: report a large margin.
    return torch.where(kin.linear, m, torch.full_like(m, 1.0))


def actuators_valid(kin: Kinematics) -> torch.Tensor:
    """[H] bool: every linear actuator realises its whole motor range (law of cosines)."""
    return (actuator_margin(kin) > 0).all(-1)


__all__ = ["PARAMETERS", "NAMES", "FIELD_OF", "ACTUATOR_FIELDS",
           "STONE8", "ALL", "REDUNDANT", "UNIT", "apply_deviations", "read_deviations",
           "actuator_margin", "actuators_valid", "kinds", "units", "check_names", "law_of_cosines_valid"]
