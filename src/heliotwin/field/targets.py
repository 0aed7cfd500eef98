"""Targets on the tower: planar calibration targets and the cylindrical receiver, as plain data.

Each target carries its own 2-D in-surface basis, so flux is binned in the target's coordinates, not in
world east/up. The image convention is PAINT's: a viewer in the field looks at the target along
``-normal``; image columns grow along ``right`` (west for a north-facing target, so image left = east)
and image rows grow downwards (row 0 is the top edge).

Local target coordinates ``(x, y)`` [m] have their origin at the target centre, ``x`` along ``right``
and ``y`` along ``up``. For the cylinder, ``x`` is the arc length along the circumference (measured
from the central generator line towards ``right``) and ``y`` the distance along the axis.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.norm(v)


def in_plane_basis(normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Image basis of a surface facing ``normal``.

    Parameters
    ----------
    normal : torch.Tensor, shape (3,)
        Unit normal pointing towards the field (ENU).

    Returns
    -------
    right, up : torch.Tensor, shape (3,)
        ``right = up_world x normal`` (the viewer's right when looking along ``-normal``) and
        ``up = normal x right``; for a horizontal-looking normal ``up`` is the world up projected into
        the plane. A normal along world up uses north as the reference up instead.
    """
    z = normal.new_tensor([0.0, 0.0, 1.0])
    if float(torch.abs(normal @ z)) > 0.999:
        z = normal.new_tensor([0.0, 1.0, 0.0])
    right = _unit(torch.linalg.cross(z, normal))
    up = _unit(torch.linalg.cross(normal, right))
    return right, up


@dataclass
class PlanarTarget:
    """A rectangular planar target (e.g. a calibration target on the tower).

    Attributes
    ----------
    name : str
    center : torch.Tensor, shape (3,), float64
        Centre of the rectangle, ENU [m].
    normal : torch.Tensor, shape (3,), float64
        Unit normal pointing towards the field.
    right, up : torch.Tensor, shape (3,), float64
        In-plane unit basis (see module docstring).
    width, height : float
        Extent along ``right`` and ``up`` [m].
    """

    name: str
    center: torch.Tensor
    normal: torch.Tensor
    right: torch.Tensor
    up: torch.Tensor
    width: float
    height: float
    kind: str = "planar"

    @classmethod
    def from_center_normal(cls, name: str, center, normal, width: float, height: float) -> "PlanarTarget":
        """Build from centre, normal and size; the basis follows :func:`in_plane_basis`.

        ``center`` is a tensor-like of shape (3,), ENU [m]; ``normal`` (3,) points towards the field
        (normalised here); ``width`` and ``height`` are the extents along ``right`` and ``up`` [m].
        """
        c = torch.as_tensor(center, dtype=torch.float64)
        n = _unit(torch.as_tensor(normal, dtype=torch.float64))
        r, u = in_plane_basis(n)
        return cls(name, c, n, r, u, float(width), float(height))

    @classmethod
    def from_corners(cls, name: str, corners: dict, normal, center=None) -> "PlanarTarget":
        """Build from ENU corner points as the PAINT tower file lists them.

        Parameters
        ----------
        corners : dict of str -> tensor-like (3,)
            ENU [m] of at least ``upper_left, upper_right, lower_left, lower_right``.
        normal : tensor-like (3,)
            Normal as stored in the tower file (ENU); the basis is derived from it and the corner
            extents are measured along that basis.
        center : tensor-like (3,), optional
            Stored centre; default the mean of the four corners.
        """
        pts = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in corners.items()}
        quad = torch.stack([pts[k] for k in ("upper_left", "upper_right", "lower_left", "lower_right")])
        c = quad.mean(0) if center is None else torch.as_tensor(center, dtype=torch.float64)
        n = _unit(torch.as_tensor(normal, dtype=torch.float64))
        r, u = in_plane_basis(n)
        width = float(((pts["upper_right"] - pts["upper_left"]) @ r + (pts["lower_right"] - pts["lower_left"]) @ r) / 2)
        height = float(((pts["upper_left"] - pts["lower_left"]) @ u
                        + (pts["upper_right"] - pts["lower_right"]) @ u) / 2)
        # Centre the rectangle on the corners in-plane but keep the stored centre's depth along the normal.
        mid = quad.mean(0)
        c = c + r * ((mid - c) @ r) + u * ((mid - c) @ u)
        return cls(name, c, n, r, u, abs(width), abs(height))

    def to_local(self, points: torch.Tensor) -> torch.Tensor:
        """ENU points (..., 3) -> in-plane coordinates (..., 2) ``(x, y)`` [m] (drops the normal part)."""
        d = points - self.center.to(points)
        return torch.stack((d @ self.right.to(points), d @ self.up.to(points)), dim=-1)

    def to_world(self, xy: torch.Tensor) -> torch.Tensor:
        """In-plane coordinates (..., 2) [m] -> ENU points (..., 3) on the plane."""
        c, r, u = (t.to(xy) for t in (self.center, self.right, self.up))
        return c + xy[..., :1] * r + xy[..., 1:2] * u

    def distance_to_plane(self, points: torch.Tensor) -> torch.Tensor:
        """Signed distance (...,) [m] of ENU points from the plane, positive on the field side."""
        return (points - self.center.to(points)) @ self.normal.to(points)


@dataclass
class CylinderTarget:
    """A convex cylindrical receiver segment.

    Attributes
    ----------
    name : str
    center : torch.Tensor, shape (3,), float64
        The apex: the point of the surface on the central generator line at mid-height, ENU [m].
    normal : torch.Tensor, shape (3,)
        Outward unit normal at the apex (towards the field), perpendicular to ``axis``.
    up : torch.Tensor, shape (3,)
        Unit cylinder axis (the surface's "up").
    right : torch.Tensor, shape (3,)
        ``up x normal``... chosen so that ``(right, up, normal)`` is right-handed like a plane's basis.
    radius : float
        [m].
    height : float
        Extent along the axis [m].
    opening_angle : float
        Full angular extent of the segment about the axis [rad].
    """

    name: str
    center: torch.Tensor
    normal: torch.Tensor
    right: torch.Tensor
    up: torch.Tensor
    radius: float
    height: float
    opening_angle: float
    kind: str = "cylinder"

    @property
    def width(self) -> float:
        """Arc length of the segment [m] (the unrolled bitmap's width)."""
        return self.radius * self.opening_angle

    @property
    def axis_point(self) -> torch.Tensor:
        """The point on the axis at mid-height, shape (3,), ENU [m]."""
        return self.center - self.radius * self.normal

    def to_local(self, points: torch.Tensor) -> torch.Tensor:
        """ENU points (..., 3) on/near the surface -> unrolled ``(arc, axial)`` coordinates (..., 2) [m]."""
        d = points - self.axis_point.to(points)
        ang = torch.atan2(d @ self.right.to(points), d @ self.normal.to(points))
        return torch.stack((self.radius * ang, d @ self.up.to(points)), dim=-1)

    def to_world(self, xy: torch.Tensor) -> torch.Tensor:
        """Unrolled ``(arc, axial)`` (..., 2) [m] -> ENU points (..., 3) on the surface."""
        a = xy[..., :1] / self.radius
        n, r, u, p = (t.to(xy) for t in (self.normal, self.right, self.up, self.axis_point))
        return p + self.radius * (torch.cos(a) * n + torch.sin(a) * r) + xy[..., 1:2] * u

    @classmethod
    def from_outer_corners(cls, name: str, corners: dict, normal, radius: float, opening_angle: float
                           ) -> "CylinderTarget":
        """Build from the four outer edge corners (ENU) of the segment and the stored aperture normal.

        The corners lie on the two edge generator lines; the apex lies ``radius * (1 - cos(half angle))``
        in front of their mid-point along the normal.

        ``corners`` maps ``upper_left, upper_right, lower_left, lower_right`` to tensor-likes of shape (3,),
        ENU [m]; ``normal`` (3,) is the stored aperture normal; ``radius`` [m] and ``opening_angle`` [rad] (the
        full angle the segment spans about its axis).
        """
        pts = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in corners.items()}
        ul, ur, ll, lr = (pts[k] for k in ("upper_left", "upper_right", "lower_left", "lower_right"))
        n = _unit(torch.as_tensor(normal, dtype=torch.float64))
        axis = (ul + ur) / 2 - (ll + lr) / 2
        axis = _unit(axis - (axis @ n) * n)
        right = _unit(torch.linalg.cross(axis, n))
        mid = (ul + ur + ll + lr) / 4
        half = opening_angle / 2
        center = mid + radius * (1.0 - torch.cos(torch.tensor(half, dtype=torch.float64))) * n
        height = float(((ul + ur) / 2 - (ll + lr) / 2) @ axis)
        return cls(name, center, n, right, axis, float(radius), abs(height), float(opening_angle))


Target = PlanarTarget | CylinderTarget
