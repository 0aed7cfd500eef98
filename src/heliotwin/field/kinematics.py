"""Rigid-body two-axis heliostat kinematics (PAINT / Jülich model): forward and inverse.

Forward: motor steps -> joint angles (actuators) -> ``R_world_heliostat`` and concentrator position.
Inverse: aim point + sun -> mirror normal (bisector) -> joint angles (analytic, exact for any tilts) inside
a fixed-point loop over the concentrator position (which moves with the angles) -> motor steps.

The chain and every parameter are documented on :class:`heliotwin.field.plant.Kinematics`. All
parameters are plain tensors, so any of them may require grad; nothing here knows what is learned.
Shapes broadcast: kinematics fields are ``[H, ...]``, steps ``[..., H, 2]``.
"""
from __future__ import annotations

import math

import torch

from ..errors import OutOfRangeError
from ..geometry import rotation_e, rotation_n, rotation_u
from .actuators import angle_to_steps, steps_to_angle
from .plant import Kinematics

# The elementary rotations live in heliotwin.geometry; short aliases keep the chain formulas readable.
rot_e, rot_n, rot_u = rotation_e, rotation_n, rotation_u


def _actuator_kwargs(kin: Kinematics) -> dict:
    return dict(increment=kin.increment, offset=kin.offset, pivot_radius=kin.pivot_radius,
                initial_angle=kin.initial_angle, initial_stroke_length=kin.initial_stroke_length,
                clockwise=kin.clockwise, linear=kin.linear)


def joint_angles(kin: Kinematics, motor_steps) -> torch.Tensor:
    """Joint angles from motor steps.

    Parameters
    ----------
    kin : Kinematics
        H heliostats.
    motor_steps : tensor-like, shape (..., H, 2)
        Axis-1 and axis-2 motor positions [steps].

    Returns
    -------
    torch.Tensor, shape (..., H, 2)
        ``(theta1, theta2)`` [rad] in PAINT's convention (``theta1`` before the -pi/2 shift).
    """
    return steps_to_angle(torch.as_tensor(motor_steps), **_actuator_kwargs(kin))


def _tilts(kin: Kinematics):
    t1 = rot_u(kin.joint_tilt[..., 0, 2]) @ rot_n(kin.joint_tilt[..., 0, 1])
    t2 = rot_e(kin.joint_tilt[..., 1, 0]) @ rot_n(kin.joint_tilt[..., 1, 1])
    ct = kin.concentrator_tilt
    t3 = rot_e(ct[..., 0]) @ rot_n(ct[..., 1]) @ rot_u(ct[..., 2])
    return t1, t2, t3


def _mount(kin: Kinematics) -> torch.Tensor:
    """``R3 R_E(pi/2)``: concentrator tilt times the heliostat-frame alignment, shape (H, 3, 3)."""
    _, _, t3 = _tilts(kin)
    quarter = torch.full_like(kin.concentrator_tilt[..., 0], math.pi / 2)
    return t3 @ rot_e(quarter)


def pose_from_angles(kin: Kinematics, angles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Heliostat pose from joint angles.

    Parameters
    ----------
    kin : Kinematics
        H heliostats.
    angles : torch.Tensor, shape (..., H, 2)
        ``(theta1, theta2)`` [rad], PAINT convention.

    Returns
    -------
    R_world_heliostat : torch.Tensor, shape (..., H, 3, 3)
        Maps heliostat-frame vectors to ENU; the mirror normal is its third column.
    concentrator : torch.Tensor, shape (..., H, 3)
        Concentrator position, ENU [m].
    """
    t1, t2, _ = _tilts(kin)
    r1 = t1 @ rot_e(angles[..., 0] - math.pi / 2)
    r2 = t2 @ rot_u(angles[..., 1])
    tj = kin.joint_translation
    inner = tj[..., 1, :] + (r2 @ kin.concentrator_translation.unsqueeze(-1)).squeeze(-1)
    concentrator = kin.position + tj[..., 0, :] + (r1 @ inner.unsqueeze(-1)).squeeze(-1)
    return r1 @ r2 @ _mount(kin), concentrator


#: The coordinates of the chain that :func:`pose_derivatives` differentiates by, in its column order:
#: ``(Kinematics field, index within the per-heliostat tensor)``; ``("angle", (j,))`` is joint angle ``theta_j``.
POSE_COORDINATES: tuple = tuple(
    [("joint_translation", (j, i)) for j in range(2) for i in range(3)]
    + [("joint_tilt", (j, i)) for j in range(2) for i in range(3)]
    + [("concentrator_translation", (i,)) for i in range(3)]
    + [("concentrator_tilt", (i,)) for i in range(3)]
    + [("angle", (j,)) for j in range(2)])
#: (i, j) of the elementary rotation about east, north, up (:func:`heliotwin.geometry.rotation_e` etc.):
#: ``m[i][i] = m[j][j] = cos``, ``m[i][j] = -sin``, ``m[j][i] = sin``.
_PLANE = ((1, 2), (2, 0), (0, 1))


def _times_rotation(columns: list, axis: int, angle: torch.Tensor) -> list:
    """``P @ R_axis(angle)`` for P given by its three columns [N, 3]: a rotation mixes two columns only."""
    i, j = _PLANE[axis]
    c, s = torch.cos(angle).unsqueeze(-1), torch.sin(angle).unsqueeze(-1)
    out = list(columns)
    out[i] = c * columns[i] + s * columns[j]
    out[j] = c * columns[j] - s * columns[i]
    return out


def pose_derivatives(kin: Kinematics, angles: torch.Tensor, coordinates=POSE_COORDINATES):
    """Mirror normal and concentrator of :func:`pose_from_angles` with their derivatives (forward mode, analytic).

    The chain is a product of elementary rotations ``A_1 ... A_10`` (the factors of ``R1 R2 R3 R_E(pi/2)``, see
    :class:`~heliotwin.field.plant.Kinematics`). Turning factor ``k`` by ``dt`` turns everything after it about
    that factor's axis *in the world frame*, ``w_k = (A_1 ... A_k) e_axis``, so the derivative of any vector
    ``A_1 ... A_L v`` (``k <= L``) is ``w_k x (A_1 ... A_L v)``: one pass of prefix products (each mixes two
    columns), no autograd graph and no 3x3 matrix products. Calibration's least squares evaluate this at every
    iteration for every record; it equals three reverse passes through the chain to rounding
    (``tests/test_kinematics.py``) at a fraction of their cost.

    Parameters
    ----------
    kin : Kinematics
        N entries (heliostats, or one per record).
    angles : torch.Tensor, shape (N, 2)
        ``(theta1, theta2)`` [rad], PAINT convention.
    coordinates : sequence of (field, index), length C
        Which of :data:`POSE_COORDINATES` to differentiate by (default all 20), in this order.

    Returns
    -------
    normal : torch.Tensor, shape (N, 3)
        Unit mirror normal, ENU.
    concentrator : torch.Tensor, shape (N, 3)
        ENU [m].
    d_normal, d_concentrator : torch.Tensor, shape (N, 3, C)
        Derivatives by the ``coordinates``: per rad for tilts and angles, per m for translations.
    """
    jt, ct = kin.joint_tilt, kin.concentrator_tilt
    quarter = torch.full_like(ct[..., 0], math.pi / 2)
    # (axis, angle, coordinate) of each factor, in the order of pose_from_angles' product
    factors = [(2, jt[..., 0, 2], ("joint_tilt", (0, 2))), (1, jt[..., 0, 1], ("joint_tilt", (0, 1))),
               (0, angles[..., 0] - math.pi / 2, ("angle", (0,))), (0, jt[..., 1, 0], ("joint_tilt", (1, 0))),
               (1, jt[..., 1, 1], ("joint_tilt", (1, 1))), (2, angles[..., 1], ("angle", (1,))),
               (0, ct[..., 0], ("concentrator_tilt", (0,))), (1, ct[..., 1], ("concentrator_tilt", (1,))),
               (2, ct[..., 2], ("concentrator_tilt", (2,))), (0, quarter, None)]
    eye = torch.eye(3, dtype=ct.dtype, device=ct.device)
    columns = [eye[i].expand(quarter.shape + (3,)) for i in range(3)]
    prefix, world_axis = [], {}
    for axis, angle, coord in factors:
        columns = _times_rotation(columns, axis, angle)
        prefix.append(columns)
        if coord is not None:
            world_axis[coord] = columns[axis]

    def times(cols, v):  # P v, v [N, 3]
        return cols[0] * v[..., 0:1] + cols[1] * v[..., 1:2] + cols[2] * v[..., 2:3]

    tj, ctr = kin.joint_translation, kin.concentrator_translation
    normal = prefix[9][2]
    arm1, arm2 = times(prefix[2], tj[..., 1, :]), times(prefix[5], ctr)  # vectors entering after factors 3, 6
    concentrator = kin.position + tj[..., 0, :] + arm1 + arm2
    level = {c: k for k, (_, _, c) in enumerate(factors) if c is not None}
    zero = torch.zeros_like(normal)
    d_normal, d_conc = [], []
    for field, idx in coordinates:
        coord = (field, tuple(idx))
        if coord in world_axis:
            w, k = world_axis[coord], level[coord]
            d_normal.append(torch.linalg.cross(w, normal))
            arm = (arm1 if k <= 2 else zero) + (arm2 if k <= 5 else zero)
            d_conc.append(torch.linalg.cross(w, arm) if k <= 5 else zero)
        elif field == "joint_translation":  # before joint 1 (fixed) or after it (turned by it)
            d_normal.append(zero)
            d_conc.append(eye[idx[1]].expand_as(normal) if idx[0] == 0 else prefix[2][idx[1]])
        elif field == "concentrator_translation":
            d_normal.append(zero)
            d_conc.append(prefix[5][idx[0]])
        elif coord in (("joint_tilt", (0, 0)), ("joint_tilt", (1, 2))):  # a joint's tilt about its own axis
            d_normal.append(zero)
            d_conc.append(zero)
        else:
            raise ValueError(f"pose_derivatives: unknown coordinate {coord}; known: {POSE_COORDINATES}")
    return normal, concentrator, torch.stack(d_normal, -1), torch.stack(d_conc, -1)


def forward(kin: Kinematics, motor_steps) -> tuple[torch.Tensor, torch.Tensor]:
    """Motor steps -> heliostat pose (see :func:`pose_from_angles`).

    Parameters
    ----------
    motor_steps : tensor-like, shape (..., H, 2)
        [steps].

    Returns
    -------
    R_world_heliostat : torch.Tensor, shape (..., H, 3, 3)
    concentrator : torch.Tensor, shape (..., H, 3), ENU [m]
    """
    return pose_from_angles(kin, joint_angles(kin, motor_steps))


def mirror_normal(R_world_heliostat: torch.Tensor) -> torch.Tensor:
    """The mirror normal (heliostat-frame e_z in ENU), shape (..., 3)."""
    return R_world_heliostat[..., :, 2]


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.norm(v, dim=-1, keepdim=True).clamp_min(1e-300)


def bisector_normal(sun_direction: torch.Tensor, concentrator: torch.Tensor, aim_point: torch.Tensor) -> torch.Tensor:
    """Mirror normal that reflects the sun from ``concentrator`` onto ``aim_point``.

    Parameters
    ----------
    sun_direction : torch.Tensor, shape (..., 3)
        Unit vector towards the sun.
    concentrator, aim_point : torch.Tensor, shape (..., 3)
        ENU [m].

    Returns
    -------
    torch.Tensor, shape (..., 3)
        Unit normal, the bisector of the sun direction and the direction to the aim point.
    """
    return _unit(sun_direction + _unit(aim_point - concentrator))


def angles_for_normal(kin: Kinematics, normal: torch.Tensor,
                      reference_angles: torch.Tensor | None = None) -> torch.Tensor:
    """Joint angles that turn the mirror normal to ``normal`` — analytic, exact for any tilts.

    With ``m = R3 R_E(pi/2) e_z``, the model normal is ``T1 R_E(a) T2 R_U(theta2) m`` (``a = theta1 - pi/2``).
    ``R_E(a)`` keeps the east component, so ``e . (T2 R_U(theta2) m) = e . (T1^T normal)`` is a sinusoid in
    ``theta2`` (``A cos + B sin = D``), solved in closed form on the branch continuous with the nominal
    heliostat (|theta2| < pi/2); ``a`` then follows from the angle in the north-up plane.

    Parameters
    ----------
    normal : torch.Tensor, shape (..., H, 3)
        Desired unit normal, ENU.
    reference_angles : torch.Tensor, shape (..., H, 2), optional
        Unused, reserved: joint angles [rad] near which to choose the branch.

    Returns
    -------
    torch.Tensor, shape (..., H, 2)
        ``(theta1, theta2)`` [rad].
    """
    t1, t2, _ = _tilts(kin)
    m = (_mount(kin) @ normal.new_tensor([0.0, 0.0, 1.0]))  # (H, 3)
    target = (t1.transpose(-1, -2) @ normal.unsqueeze(-1)).squeeze(-1)
    row = t2[..., 0, :]  # east row of T2
    a_coef = row[..., 0] * m[..., 0] + row[..., 1] * m[..., 1]
    b_coef = row[..., 1] * m[..., 0] - row[..., 0] * m[..., 1]
    d = target[..., 0] - row[..., 2] * m[..., 2]
    amp = torch.sqrt(a_coef * a_coef + b_coef * b_coef)
    theta2 = torch.atan2(b_coef, a_coef) - torch.acos((d / amp).clamp(-1.0, 1.0))
    theta2 = torch.remainder(theta2 + math.pi, 2 * math.pi) - math.pi
    w = (t2 @ (rot_u(theta2) @ m.unsqueeze(-1))).squeeze(-1)
    alpha = torch.atan2(target[..., 2], target[..., 1]) - torch.atan2(w[..., 2], w[..., 1])
    theta1 = torch.remainder(alpha + math.pi / 2 + math.pi, 2 * math.pi) - math.pi
    return torch.stack((theta1, theta2), dim=-1)


def aim_angles(kin: Kinematics, aim_point, sun_direction, *, iterations: int = 20,
               tolerance: float = 1e-12) -> torch.Tensor:
    """Joint angles that reflect the sun's centre from the concentrator onto an aim point (no motor range).

    The concentrator moves with the joint angles, so the bisector is re-evaluated at the concentrator
    of the last solution until the angles change by less than ``tolerance`` [rad] (fixed point; the lever
    arm of a few decimetres against ~100 m slant range makes it contract fast). ``tolerance=0`` runs all
    ``iterations``. Shared by :func:`inverse` (-> motor steps) and the conv renderer's measured-spot poses.

    Parameters
    ----------
    kin : Kinematics
        H heliostats (float64 recommended; the result has its dtype).
    aim_point : tensor-like, shape (..., H, 3)
        ENU [m].
    sun_direction : tensor-like, shape (..., H, 3) or (..., 1, 3)
        Unit vector towards the sun.
    iterations : int
        Maximum fixed-point iterations.
    tolerance : float
        [rad].

    Returns
    -------
    torch.Tensor, shape (..., H, 2)
        Joint angles [rad].
    """
    dtype = kin.position.dtype
    aim = torch.as_tensor(aim_point, dtype=dtype)
    sun = torch.as_tensor(sun_direction, dtype=dtype)
    # broadcast_tensors, not torch.broadcast_shapes: the latter imports torch.fx's symbolic shapes (sympy), ~0.8 s
    # of every command that aims a heliostat
    aim, sun, concentrator = torch.broadcast_tensors(aim, sun, kin.position)
    angles = None
    for _ in range(iterations):
        new = angles_for_normal(kin, bisector_normal(sun, concentrator, aim))
        _, concentrator = pose_from_angles(kin, new)
        # No poses (an empty validation set): nothing to iterate, and max() of nothing is undefined.
        done = new.numel() == 0 or (angles is not None and float((new - angles).abs().max()) < tolerance)
        angles = new
        if done:
            break
    return angles


def inverse(kin: Kinematics, aim_point, sun_direction, *, iterations: int = 20, tolerance: float = 1e-12,
            strict: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Motor steps that reflect the sun onto an aim point.

    The concentrator moves with the joint angles, so the bisector is re-evaluated at the concentrator
    of the last solution until the angles change by less than ``tolerance`` [rad] (fixed point; the lever
    arm of a few decimetres against ~100 m slant range makes it contract fast).

    Parameters
    ----------
    kin : Kinematics
        H heliostats (float64 recommended).
    aim_point : tensor-like, shape (..., H, 3)
        ENU [m].
    sun_direction : tensor-like, shape (..., H, 3) or (..., 1, 3)
        Unit vector towards the sun.
    iterations : int
        Maximum fixed-point iterations.
    strict : bool
        Raise :class:`~heliotwin.errors.OutOfRangeError` when any solution is outside the motor range or
        not realisable by the actuator; otherwise report it in ``reachable``.

    Returns
    -------
    motor_steps : torch.Tensor, shape (..., H, 2)
        [steps] (real-valued).
    reachable : torch.Tensor of bool, shape (..., H)
        Within ``[min_steps, max_steps]`` on both axes and realisable.
    """
    angles = aim_angles(kin, aim_point, sun_direction, iterations=iterations, tolerance=tolerance)
    steps, valid = angle_to_steps(angles, **_actuator_kwargs(kin))
    in_range = (steps >= kin.min_steps) & (steps <= kin.max_steps) & valid
    reachable = in_range.all(-1)
    if strict and not bool(reachable.all()):
        bad = (~reachable).nonzero()[0].tolist()
        raise OutOfRangeError(f"aim point not reachable for heliostat index {bad[-1]} (sample {bad[:-1]}): "
                              f"motor steps {steps[tuple(bad)].tolist()} outside "
                              f"[{kin.min_steps[bad[-1]].tolist()}, {kin.max_steps[bad[-1]].tolist()}]")
    return steps, reachable


def aimed_pose(kin: Kinematics, aim_point, sun_direction, *, iterations: int = 8
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose of one heliostat that reflects the sun's centre from its concentrator onto ``aim_point``.

    :func:`aim_angles` then :func:`pose_from_angles` (no motor steps, no range check): used where the
    *measured* focal spot is known (PAINT records), so the pose follows the real tracking instead of the
    (tens of mrad off) nominal kinematics, without learning anything.

    Parameters
    ----------
    kin : Kinematics
        One heliostat (H = 1), float64.
    aim_point : tensor-like, [B, 3]
        ENU [m].
    sun_direction : tensor-like, [B, 3]
        Unit vectors towards the sun.
    iterations : int
        Fixed-point iterations, all run (the concentrator moves with the angles).

    Returns
    -------
    R_world_heliostat : torch.Tensor, [B, 3, 3]
    concentrator : torch.Tensor, [B, 3]
        ENU [m]; both in the kinematics' dtype.
    """
    dtype = kin.position.dtype
    aim = torch.as_tensor(aim_point, dtype=dtype).reshape(-1, 1, 3)
    sun = torch.as_tensor(sun_direction, dtype=dtype).reshape(-1, 1, 3)
    angles = aim_angles(kin, aim, sun, iterations=iterations, tolerance=0.0)
    rot, conc = pose_from_angles(kin, angles)
    return rot[:, 0], conc[:, 0]


def check_motor_range(kin: Kinematics, motor_steps, *, where: str = "motor steps") -> None:
    """Raise :class:`~heliotwin.errors.OutOfRangeError` if any steps (..., H, 2) are outside the range."""
    steps = torch.as_tensor(motor_steps, dtype=kin.min_steps.dtype)
    bad = (steps < kin.min_steps) | (steps > kin.max_steps)
    if bool(bad.any()):
        idx = bad.nonzero()[0].tolist()
        raise OutOfRangeError(f"{where}: axis {idx[-1] + 1} value {steps[tuple(idx)].item():.0f} outside actuator "
                              f"range [{kin.min_steps[..., idx[-1]].flatten()[0].item():.0f}, "
                              f"{kin.max_steps[..., idx[-1]].flatten()[0].item():.0f}]")
