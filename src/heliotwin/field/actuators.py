"""Actuators: motor steps <-> joint angles, both directions, batched and differentiable.

Linear actuator (PAINT / Jülich): a linear drive of stroke ``l`` pushes a lever of ``pivot_radius`` r
mounted at distance ``offset`` o from the drive's anchor; by the law of cosines the lever's pivot angle
is ``phi(l) = acos((o^2 + r^2 - l^2) / (2 o r))`` with ``l = steps / increment + initial_stroke_length``.
The joint angle moves by ``delta = phi(0 steps) - phi(steps)``::

    theta = initial_angle + delta   if clockwise_axis_movement
    theta = initial_angle - delta   otherwise

Ideal actuator: ``theta = initial_angle +/- steps / increment`` (increment in steps per radian), same
sign rule.

All arguments are tensors broadcastable to a common shape (typically ``[..., H, 2]``), float64.
"""
from __future__ import annotations

import torch

#: Nominal PAINT/Jülich linear actuators, per axis (steps per metre of stroke, metres, radians): the actuators
#: of the demo plant and of every plant read from a layout.
ACTUATOR_NOMINAL = dict(increment=(154166.6667, 154166.6667), offset=(0.335308, 0.340771),
                        pivot_radius=(0.338095, 0.3191), initial_angle=(0.039009536, 0.943922248),
                        initial_stroke_length=(0.077412795, 0.077522286))

#: Keeps acos away from +/-1 where its derivative is infinite; ~1e-12 rad of angle error at worst.
_COS_EPS = 1e-12


def _pivot_angle(stroke, offset, pivot_radius):
    """Lever pivot angle [rad] from stroke [m] by the law of cosines (clamped so gradients stay finite)."""
    x = (offset * offset + pivot_radius * pivot_radius - stroke * stroke) / (2.0 * offset * pivot_radius)
    return torch.acos(x.clamp(-1.0 + _COS_EPS, 1.0 - _COS_EPS))


def law_of_cosines_valid(stroke, offset, pivot_radius):
    """True where ``|offset - pivot_radius| < stroke < offset + pivot_radius`` (a real triangle).

    ``stroke``, ``offset`` and ``pivot_radius`` [m] are tensors of broadcastable shapes (...); the result is a
    bool tensor of their broadcast shape (...).
    """
    return (stroke > torch.abs(offset - pivot_radius)) & (stroke < offset + pivot_radius)


def steps_to_angle(steps, *, increment, offset, pivot_radius, initial_angle, initial_stroke_length,
                   clockwise, linear):
    """Joint angle from motor steps.

    Parameters
    ----------
    steps : torch.Tensor, shape (...)
        Motor position [steps]. The actuator parameters below broadcast against it (one value per
        heliostat, or scalars).
    increment : torch.Tensor, shape (...)
        Steps per metre of stroke (linear) or per radian (ideal) [1/m or 1/rad].
    offset, pivot_radius : torch.Tensor, shape (...)
        Linear actuator geometry [m].
    initial_angle : torch.Tensor, shape (...)
        Joint angle at zero steps [rad].
    initial_stroke_length : torch.Tensor, shape (...)
        Stroke at zero steps [m].
    clockwise, linear : torch.Tensor of bool, shape (...)
        PAINT ``clockwise_axis_movement``; linear (True) or ideal (False) actuator.

    Returns
    -------
    torch.Tensor, shape (...)
        Joint angle [rad].
    """
    steps = torch.as_tensor(steps).to(initial_angle.dtype)
    stroke = steps / increment + initial_stroke_length
    delta_linear = (_pivot_angle(initial_stroke_length, offset, pivot_radius)
                    - _pivot_angle(stroke, offset, pivot_radius))
    delta = torch.where(linear, delta_linear, steps / increment)
    return torch.where(clockwise, initial_angle + delta, initial_angle - delta)


def angle_to_steps(angle, *, increment, offset, pivot_radius, initial_angle, initial_stroke_length,
                   clockwise, linear):
    """Motor steps for a joint angle; inverse of :func:`steps_to_angle` (same parameters).

    Returns
    -------
    steps : torch.Tensor, shape (...)
        Motor position [steps] (real-valued; round for the drive).
    valid : torch.Tensor of bool, shape (...)
        False where no stroke realises the angle (the law of cosines has no solution).
    """
    delta = torch.where(clockwise, angle - initial_angle, initial_angle - angle)
    phi0 = _pivot_angle(initial_stroke_length, offset, pivot_radius)
    phi = phi0 - delta
    valid_phi = (phi > 0) & (phi < torch.pi)
    stroke_sq = offset * offset + pivot_radius * pivot_radius - 2 * offset * pivot_radius * torch.cos(phi)
    stroke = torch.sqrt(stroke_sq.clamp_min(1e-30))
    steps_linear = (stroke - initial_stroke_length) * increment
    steps = torch.where(linear, steps_linear, delta * increment)
    valid = torch.where(linear, valid_phi, torch.ones_like(valid_phi))
    return steps, valid
