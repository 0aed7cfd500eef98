"""Site geodesy (WGS84 <-> ENU) and sun directions: round trips, approximations, real PAINT records, gradients."""
from __future__ import annotations

import math

import pandas as pd
import pytest
import torch

from heliotwin.errors import OutOfRangeError
from heliotwin.io import paint as P
from heliotwin.site import JUELICH_REFERENCE, WGS84_A, WGS84_E2, Site, enu_to_wgs84, geodetic_to_ecef, wgs84_to_enu
from heliotwin.sun import direction_from_paint_angles, paint_angles_from_direction, solar_position

REF = torch.tensor(JUELICH_REFERENCE, dtype=torch.float64)
F64 = dict(dtype=torch.float64)


def _random_enu(n: int, extent: float, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    enu = (2 * torch.rand(n, 3, generator=g, **F64) - 1) * extent
    enu[:, 2] = enu[:, 2].abs() * 0.1 - 5.0  # -5 m .. 0.1 extent above the reference
    return enu


# =================================================================================================== site
@pytest.mark.parametrize("reference", [JUELICH_REFERENCE, (-33.9, 18.4, 10.0), (89.5, -120.0, 2800.0),
                                       (0.0, 179.9, 0.0)])
@pytest.mark.parametrize("extent", [200.0, 50_000.0])
def test_wgs84_enu_round_trip(reference, extent):
    enu = _random_enu(2000, extent, seed=1)
    lla = enu_to_wgs84(enu, reference)
    assert lla.dtype == torch.float64
    assert torch.allclose(wgs84_to_enu(lla, reference), enu, rtol=0, atol=1e-6)
    back = enu_to_wgs84(wgs84_to_enu(lla, reference), reference)
    dlon = torch.remainder(back[:, 1] - lla[:, 1] + 180.0, 360.0) - 180.0
    assert (back[:, 0] - lla[:, 0]).abs().max() < 1e-9
    assert dlon.abs().max() < 1e-9
    assert (back[:, 2] - lla[:, 2]).abs().max() < 1e-6


def test_reference_is_origin_and_axes_point_east_north_up():
    site = Site()
    assert site.reference == JUELICH_REFERENCE
    assert site.to_enu(site.reference).abs().max() < 1e-9
    lat, lon, alt = JUELICH_REFERENCE
    e = site.to_enu([lat, lon + 1e-4, alt])
    n = site.to_enu([lat + 1e-4, lon, alt])
    u = site.to_enu([lat, lon, alt + 10.0])
    assert e[0] > 6.9 and abs(e[1]) < 1e-3 and abs(e[2]) < 1e-3  # 1e-4 deg of longitude ~ 7.0 m here
    assert n[1] > 11.1 and abs(n[0]) < 1e-9 and abs(n[2]) < 1e-3  # 1e-4 deg of latitude ~ 11.1 m
    assert torch.allclose(u, torch.tensor([0.0, 0.0, 10.0], **F64), atol=1e-9)
    assert torch.allclose(site.to_wgs84(site.to_enu([lat, lon, 120.0])), torch.tensor([lat, lon, 120.0], **F64),
                          rtol=0, atol=1e-9)


def test_ecef_against_known_values():
    equator = geodetic_to_ecef([0.0, 0.0, 0.0])
    pole = geodetic_to_ecef([90.0, 0.0, 0.0])
    assert torch.allclose(equator, torch.tensor([WGS84_A, 0.0, 0.0], **F64), atol=1e-9)
    b = WGS84_A * math.sqrt(1.0 - WGS84_E2)  # semi-minor axis
    assert torch.allclose(pole, torch.tensor([0.0, 0.0, b], **F64), atol=1e-6)


def test_local_radius_approximation_at_plant_scale():
    """Within 200 m of the reference, ENU agrees with the local-radius (tangent-plane) approximation.

    ``e = dlon (N + h) cos(lat)``, ``n = dlat (M + h)``, ``u = dh - (e^2 + n^2) / (2 R)`` with the prime
    vertical / meridian radii ``N``, ``M`` at the reference and ``R = sqrt(M N)``. What is left
    (< 4 mm at 200 m) is the meridian convergence ``e^2 tan(lat) / (2 N)``.
    """
    lat0 = math.radians(JUELICH_REFERENCE[0])
    s2 = math.sin(lat0) ** 2
    n_rad = WGS84_A / math.sqrt(1 - WGS84_E2 * s2)
    m_rad = WGS84_A * (1 - WGS84_E2) / (1 - WGS84_E2 * s2) ** 1.5
    g = torch.Generator().manual_seed(3)
    k = 5000
    r = 200.0 * torch.rand(k, generator=g, **F64).sqrt()
    phi = 2 * math.pi * torch.rand(k, generator=g, **F64)
    dh = -10.0 + 70.0 * torch.rand(k, generator=g, **F64)
    lla = torch.stack((REF[0] + torch.rad2deg(r * torch.sin(phi) / m_rad),
                       REF[1] + torch.rad2deg(r * torch.cos(phi) / (n_rad * math.cos(lat0))), REF[2] + dh), dim=-1)
    exact = wgs84_to_enu(lla, REF)
    lat = torch.deg2rad(lla[:, 0])
    h = lla[:, 2]
    e = torch.deg2rad(lla[:, 1] - REF[1]) * (n_rad + h) * torch.cos(lat)
    n = torch.deg2rad(lla[:, 0] - REF[0]) * (m_rad + h)
    u = h - REF[2] - (e * e + n * n) / (2 * math.sqrt(m_rad * n_rad))
    err = torch.linalg.vector_norm(torch.stack((e, n, u), -1) - exact, dim=-1)
    assert exact[:, :2].norm(dim=-1).max() < 201.0
    assert err.max() < 5e-3
    # ... and the vertical (curvature) part is what a flat-earth approximation would miss: ~3 mm at 200 m.
    assert (exact[:, 2] - dh).min() < -2.5e-3


def test_wgs84_to_enu_gradcheck():
    # Finite differences need steps well above the float64 round-off of ECEF coordinates (~1e-9 m of
    # 4e6 m): 1e-4 deg / 1e-4 m forward, 1 cm inverse; the analytic Jacobians must match to ~1e-5.
    lla = torch.tensor([[50.9136, 6.3880, 88.7], [50.9150, 6.3850, 90.0], [50.9120, 6.3900, 87.0]],
                       **F64).requires_grad_()
    ref = REF.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda x, r: wgs84_to_enu(x, r), (lla, ref), eps=1e-4, atol=1e-4, rtol=1e-5)
    enu = torch.tensor([[10.0, 25.0, 1.6], [-120.0, 300.0, 1.2]], **F64).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: enu_to_wgs84(x, REF), (enu,), eps=1e-2, atol=1e-6, rtol=1e-4)


# ==================================================================================================== sun
def test_sun_direction_from_paint_angles():
    el = math.radians(30.0)
    south = direction_from_paint_angles(0.0, el)
    east = direction_from_paint_angles(math.pi / 2, el)
    west = direction_from_paint_angles(-math.pi / 2, el)
    north = direction_from_paint_angles(math.pi, el)
    c, s = math.cos(el), math.sin(el)
    assert torch.allclose(south, torch.tensor([0.0, -c, s], **F64), atol=1e-15)
    assert torch.allclose(east, torch.tensor([c, 0.0, s], **F64), atol=1e-15)
    assert torch.allclose(west, torch.tensor([-c, 0.0, s], **F64), atol=1e-15)
    assert torch.allclose(north, torch.tensor([0.0, c, s], **F64), atol=1e-15)
    assert torch.allclose(direction_from_paint_angles(0.3, math.pi / 2), torch.tensor([0.0, 0.0, 1.0], **F64),
                          atol=1e-15)


def test_sun_angles_round_trip_and_horizon():
    g = torch.Generator().manual_seed(5)
    az = (2 * torch.rand(500, generator=g, **F64) - 1) * (math.pi - 1e-6)
    el = torch.rand(500, generator=g, **F64) * (math.pi / 2 - 1e-3) + 1e-3
    d = direction_from_paint_angles(az, el)
    assert torch.allclose(d.norm(dim=-1), torch.ones(500, **F64), atol=1e-15)
    az2, el2 = paint_angles_from_direction(3.0 * d)
    assert torch.allclose(az2, az, atol=1e-12) and torch.allclose(el2, el, atol=1e-12)
    with pytest.raises(OutOfRangeError):
        direction_from_paint_angles(0.0, -0.01)
    assert direction_from_paint_angles(0.0, -0.01, check_horizon=False)[2] < 0


def test_spa_solar_noon_at_equinox():
    """Around true solar noon at the March equinox the sun is due south, ~90 - 50.9 deg high."""
    lat, lon, alt = JUELICH_REFERENCE
    times = pd.date_range("2023-03-20 11:00", "2023-03-20 13:00", freq="1min", tz="UTC")
    az, el = solar_position(times, lat, lon, alt)
    noon = int(el.argmax())
    assert abs(math.degrees(float(az[noon]))) < 0.5
    assert abs(math.degrees(float(el[noon])) - (90.0 - lat)) < 0.6
    assert math.degrees(float(az[0])) > 10 and math.degrees(float(az[-1])) < -10  # morning east (+), afternoon west


@pytest.mark.parametrize("site", [JUELICH_REFERENCE, (37.4, -5.9, 20.0), (-23.5, 133.9, 600.0), (0.0, 0.0, 0.0),
                                  (70.0, 20.0, 2500.0)])
def test_spa_without_pvlib_equals_pvlib(site):
    """:func:`solar_position` (pvlib's NumPy SPA, :mod:`heliotwin.sunspa`, without pvlib's package import) gives
    pvlib's numbers: ``get_solarposition(method="nrel_numpy")`` at 2,000 instants over 1990-2060, day and night."""
    import numpy as np
    import pvlib  # the reference (imported here only: the library itself does not import pvlib for the sun)

    g = np.random.default_rng(3)
    times = pd.to_datetime(g.integers(pd.Timestamp("1990-01-01").value, pd.Timestamp("2060-01-01").value, 2000),
                           utc=True)
    lat, lon, alt = site
    az, el = solar_position(times, lat, lon, alt)
    ref = pvlib.solarposition.get_solarposition(times, lat, lon, altitude=alt, method="nrel_numpy")
    az_ref = np.angle(np.exp(1j * (math.pi - np.deg2rad(ref["azimuth"].to_numpy()))))
    assert np.abs(az.numpy() - az_ref).max() < 1e-12
    assert np.abs(el.numpy() - np.deg2rad(ref["apparent_elevation"].to_numpy())).max() < 1e-12


def test_one_sun_commands_do_not_import_pvlib():
    """The sun at a time needs no pvlib (:mod:`heliotwin.sunspa`), the one-sun field model no pandas either
    (~0.7 s of such a command's start-up): the field at sun angles, the sun at a time, the aimpoints workflow."""
    import subprocess
    import sys

    code = ("import sys, heliotwin.workflows.field_one_sun; assert 'pvlib' not in sys.modules "
            "and 'pandas' not in sys.modules; import heliotwin.workflows.field, heliotwin.workflows.aimpoints; "
            "assert 'pvlib' not in sys.modules, 'pvlib'")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.fixture(scope="module")
def dated_records(paint_dir):
    """Records of a few real heliostats with their metadata DateTime (UTC)."""
    site, targets = P.read_tower(P.find_tower_file(paint_dir))
    times, _ = P.read_metadata(paint_dir)
    out = []
    for h in ("AA39", "AK46", "BG23"):
        for f in sorted((paint_dir / h / "Calibration").glob("*-calibration-properties.json")):
            r = P.read_calibration_record(f, site, h, known_targets=targets)
            if times.get(r.record_id):
                out.append((r, times[r.record_id]))
    assert len(out) > 90
    return site, out


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.rad2deg(torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1)))


def test_spa_agrees_with_paint_record_angles(dated_records):
    """pvlib's SPA at the metadata DateTime reproduces the records' sun angles to < 0.05 deg.

    Known exception: AA39's record 86500 is stamped exactly one hour early (the README's shifted
    timestamps of older releases; "trust the sun angles"): it agrees at DateTime + 1 h.
    """
    site, records = dated_records
    shifted = {86500: pd.Timedelta(hours=1)}
    times = [pd.Timestamp(t) + shifted.get(r.record_id, pd.Timedelta(0)) for r, t in records]
    az, el = solar_position(times, site.latitude_deg, site.longitude_deg, site.altitude_m)
    spa = direction_from_paint_angles(az, el)
    paint = direction_from_paint_angles(torch.tensor([r.sun_azimuth for r, _ in records], **F64),
                                        torch.tensor([r.sun_elevation for r, _ in records], **F64))
    err = _angle_deg(spa, paint)
    worst = int(err.argmax())
    assert float(err.max()) < 0.05, f"record {records[worst][0].record_id}: {float(err[worst]):.3f} deg"
    assert 86500 in {r.record_id for r, _ in records}
    # Without the one-hour correction record 86500 is ~15 deg off.
    (r86500, t86500), = [(r, t) for r, t in records if r.record_id == 86500]
    az0, el0 = solar_position([t86500], site.latitude_deg, site.longitude_deg, site.altitude_m)
    off = _angle_deg(direction_from_paint_angles(az0, el0)[0],
                     direction_from_paint_angles(r86500.sun_azimuth, r86500.sun_elevation))
    assert float(off) > 10.0
