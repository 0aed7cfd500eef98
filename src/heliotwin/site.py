"""Plant site: WGS84 geodetic coordinates <-> local East-North-Up (ENU), exact, float64.

The conversion goes through Earth-centred Earth-fixed (ECEF) coordinates on the WGS84 ellipsoid, so it
is exact at any distance (no small-area approximation). Inputs may be any tensor-like; outputs are
float64 tensors on the input's device. Functions are differentiable.

Convention
----------
Geodetic coordinates are ``[latitude_deg, longitude_deg, altitude_m]`` (latitude first, as PAINT stores
them). ENU is right-handed: x = east, y = north, z = up, in metres, with origin at the plant reference.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

WGS84_A = 6378137.0  #: semi-major axis [m]
WGS84_F = 1.0 / 298.257223563  #: flattening [-]
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  #: first eccentricity squared [-]

#: The Jülich solar tower plant reference (PAINT plant WRI1030197), [lat_deg, lon_deg, alt_m].
JUELICH_REFERENCE = (50.913421122592574, 6.387824755874856, 87.0)


def _as64(x) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(torch.float64)
    return torch.as_tensor(x, dtype=torch.float64)


def geodetic_to_ecef(lla) -> torch.Tensor:
    """WGS84 geodetic -> ECEF.

    Parameters
    ----------
    lla : tensor-like, shape (..., 3)
        ``[latitude, longitude]`` [deg] and ellipsoidal altitude [m].

    Returns
    -------
    torch.Tensor, shape (..., 3), float64
        ECEF x, y, z [m].
    """
    lla = _as64(lla)
    lat, lon, alt = torch.deg2rad(lla[..., 0]), torch.deg2rad(lla[..., 1]), lla[..., 2]
    s, c = torch.sin(lat), torch.cos(lat)
    n = WGS84_A / torch.sqrt(1.0 - WGS84_E2 * s * s)
    return torch.stack(((n + alt) * c * torch.cos(lon), (n + alt) * c * torch.sin(lon),
                        (n * (1.0 - WGS84_E2) + alt) * s), dim=-1)


def ecef_to_geodetic(xyz) -> torch.Tensor:
    """ECEF -> WGS84 geodetic by Bowring's method refined with Newton steps (sub-micrometre).

    Parameters
    ----------
    xyz : tensor-like, shape (..., 3)
        ECEF coordinates [m].

    Returns
    -------
    torch.Tensor, shape (..., 3), float64
        ``[latitude_deg, longitude_deg, altitude_m]``.
    """
    xyz = _as64(xyz)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    lon = torch.atan2(y, x)
    p = torch.sqrt(x * x + y * y)
    lat = torch.atan2(z, p * (1.0 - WGS84_E2))
    for _ in range(5):  # fixed-point on latitude; converges to 1e-15 rad in ~4 steps near the surface
        s = torch.sin(lat)
        n = WGS84_A / torch.sqrt(1.0 - WGS84_E2 * s * s)
        lat = torch.atan2(z + WGS84_E2 * n * s, p)
    s, c = torch.sin(lat), torch.cos(lat)
    n = WGS84_A / torch.sqrt(1.0 - WGS84_E2 * s * s)
    # Altitude from the form that stays accurate at every latitude.
    alt = p * c + z * s - WGS84_A * WGS84_A / n
    return torch.stack((torch.rad2deg(lat), torch.rad2deg(lon), alt), dim=-1)


def _enu_rotation(reference) -> torch.Tensor:
    """Rows are the ENU unit vectors expressed in ECEF, shape (3, 3)."""
    ref = _as64(reference)
    lat, lon = torch.deg2rad(ref[0]), torch.deg2rad(ref[1])
    sl, cl, so, co = torch.sin(lat), torch.cos(lat), torch.sin(lon), torch.cos(lon)
    zero = torch.zeros_like(sl)
    return torch.stack((torch.stack((-so, co, zero)),
                        torch.stack((-sl * co, -sl * so, cl)),
                        torch.stack((cl * co, cl * so, sl))))


def wgs84_to_enu(lla, reference=JUELICH_REFERENCE) -> torch.Tensor:
    """WGS84 geodetic -> local ENU about ``reference``.

    Parameters
    ----------
    lla : tensor-like, shape (..., 3)
        ``[latitude_deg, longitude_deg, altitude_m]``.
    reference : tensor-like, shape (3,)
        The ENU origin, same layout.

    Returns
    -------
    torch.Tensor, shape (..., 3), float64
        East, north, up [m].

    Examples
    --------
    A point 0.001° north of the Jülich reference and 10 m higher is 111.2 m north and 10 m up:

    >>> from heliotwin.site import JUELICH_REFERENCE
    >>> lat, lon, alt = JUELICH_REFERENCE
    >>> [round(x, 1) + 0.0 for x in wgs84_to_enu([lat + 0.001, lon, alt + 10.0]).tolist()]
    [0.0, 111.2, 10.0]
    """
    rot = _enu_rotation(reference)
    d = geodetic_to_ecef(lla) - geodetic_to_ecef(reference)
    return d @ rot.T


def enu_to_wgs84(enu, reference=JUELICH_REFERENCE) -> torch.Tensor:
    """Local ENU about ``reference`` -> WGS84 geodetic; inverse of :func:`wgs84_to_enu`.

    Parameters
    ----------
    enu : tensor-like, shape (..., 3)
        East, north, up [m].
    reference : tensor-like, shape (3,)
        ``[latitude_deg, longitude_deg, altitude_m]`` of the ENU origin.

    Returns
    -------
    torch.Tensor, shape (..., 3), float64
        ``[latitude_deg, longitude_deg, altitude_m]``.
    """
    rot = _enu_rotation(reference)
    return ecef_to_geodetic(_as64(enu) @ rot + geodetic_to_ecef(reference))


#: Plausible ranges of a site's coordinates: (low, high) of latitude [deg], longitude [deg] and ellipsoidal altitude
#: [m] (the Dead Sea shore is about -430 m, the highest solar plants near 5,000 m; the geoid is within about 110 m of
#: the ellipsoid).
SITE_RANGES = {"latitude_deg": (-90.0, 90.0), "longitude_deg": (-180.0, 180.0), "altitude_m": (-1000.0, 9000.0)}


def site_problem(name: str, value) -> str | None:
    """Why ``value`` is not a plausible ``name`` (a :data:`SITE_RANGES` key) of a site, or None when it is."""
    lo, hi = SITE_RANGES[name]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value == value:
        return f"expected a finite number, got {value!r}"
    if not lo <= float(value) <= hi:
        unit = "m" if name == "altitude_m" else "deg"
        return f"expected {name.rsplit('_', 1)[0]} in [{lo:g}, {hi:g}] {unit}, got {value!r}"
    return None


@dataclass(frozen=True)
class Site:
    """The plant's geodetic reference (ENU origin).

    Attributes
    ----------
    latitude_deg, longitude_deg : float
        WGS84 [deg].
    altitude_m : float
        Ellipsoidal altitude of the ENU origin [m].
    name : str
        Plant identifier (e.g. ``"WRI1030197"``).
    """

    latitude_deg: float = JUELICH_REFERENCE[0]
    longitude_deg: float = JUELICH_REFERENCE[1]
    altitude_m: float = JUELICH_REFERENCE[2]
    name: str = "WRI1030197"

    @property
    def reference(self) -> tuple[float, float, float]:
        """``(latitude_deg, longitude_deg, altitude_m)``."""
        return (self.latitude_deg, self.longitude_deg, self.altitude_m)

    def to_enu(self, lla) -> torch.Tensor:
        """WGS84 -> ENU about this site, shape (..., 3) [m], float64."""
        return wgs84_to_enu(lla, self.reference)

    def to_wgs84(self, enu) -> torch.Tensor:
        """ENU about this site -> WGS84, shape (..., 3) ``[lat_deg, lon_deg, alt_m]``."""
        return enu_to_wgs84(enu, self.reference)
