"""PAINT deflectometry HDF5: reading, writing, errors, and fitting a deformed facet."""
import h5py
import numpy as np
import pytest
import torch

from heliotwin import nurbs
from heliotwin.errors import HeliotwinError, InputFileError
from heliotwin.field import facets as fc
from heliotwin.field.plant import Facets
from heliotwin.io import deflectometry as dfl

F64 = torch.float64

AA39 = [
    {"translation_vector": [-0.8075, 0.6425, 0.0402], "canting_e": [0.80248, -0.0, -0.0049846],
     "canting_n": [1.957e-05, 0.63749, 0.0031505]},
    {"translation_vector": [0.8075, -0.6425, 0.0402], "canting_e": [0.80248, -0.0, 0.0049846],
     "canting_n": [1.957e-05, 0.63749, -0.0031505]},
]

AMP, SIGMA = 1.0e-3, 0.35  # bump height [m] and width [m]


def bump(s, t, e_len, n_len, centre):
    """Height h [m] along the facet normal and its derivatives w.r.t. s, t (facet coordinates in [-1,1])."""
    x, y = s * e_len - centre[0], t * n_len - centre[1]
    h = AMP * torch.exp(-(x ** 2 + y ** 2) / (2 * SIGMA ** 2))
    return h, -x / SIGMA ** 2 * h * e_len, -y / SIGMA ** 2 * h * n_len


def deformed_facet(t0, e, n, s, t, centre):
    """Points and unit normals of the canted facet t0 + s e + t n + h(s, t) n_hat."""
    n_hat = torch.nn.functional.normalize(torch.linalg.cross(e, n, dim=-1), dim=-1)
    h, hs, ht = bump(s, t, e.norm(), n.norm(), centre)
    pts = t0 + s[:, None] * e + t[:, None] * n + h[:, None] * n_hat
    normals = torch.linalg.cross(e + hs[:, None] * n_hat, n + ht[:, None] * n_hat, dim=-1)
    return pts, torch.nn.functional.normalize(normals, dim=-1)


def measurement(nx=64, ny=52, jitter=True):
    t0, e, n = fc.facets_from_paint(AA39)
    gen = torch.Generator().manual_seed(11)
    out = []
    for f in range(2):
        gs = torch.linspace(-1, 1, nx, dtype=F64)
        gt = torch.linspace(-1, 1, ny, dtype=F64)
        s, t = (a.reshape(-1) for a in torch.meshgrid(gs, gt, indexing="ij"))
        if jitter:  # scattered, not a grid: the fit must not rely on tensor-product structure
            s = (s + 0.01 * torch.randn(s.shape, generator=gen, dtype=F64)).clamp(-1, 1)
            t = (t + 0.01 * torch.randn(t.shape, generator=gen, dtype=F64)).clamp(-1, 1)
        centre = (0.2, -0.1) if f == 0 else (-0.3, 0.15)
        out.append(deformed_facet(t0[f], e[f], n[f], s, t, centre))
    return out, (t0, e, n)


def test_write_read_roundtrip(tmp_path):
    meas, _ = measurement(10, 8)
    path = tmp_path / "AA39-deflectometry.h5"
    dfl.write_deflectometry(path, meas, dtype="float32")
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind
    with h5py.File(path) as f:
        assert sorted(f.keys()) == ["facet1", "facet2"]
        assert f["facet1/surface_points"].shape == (80, 3)
    back = dfl.read_deflectometry(path)
    assert len(back) == 2
    for (p, n), (p2, n2) in zip(meas, back):
        assert p2.dtype == F64 and p2.shape == p.shape
        assert torch.allclose(p2, p, atol=1e-7) and torch.allclose(n2, n, atol=1e-6)
        assert torch.allclose(n2.norm(dim=1), torch.ones(len(n2), dtype=F64))


def test_fit_reproduces_bumped_facet(tmp_path):
    meas, placement = measurement()
    path = tmp_path / "bump.h5"
    dfl.write_deflectometry(path, meas)
    read = dfl.read_deflectometry(path)
    nets, report = dfl.fit_deflectometry(read, placement, num_control_points=(10, 10), degree=(3, 3))
    assert nets.shape == (2, 10, 10, 3) and nets.dtype == F64
    assert torch.all(report.rms_m < 2e-5) and torch.all(report.normal_rms_mrad < 0.1)
    assert torch.all(report.outside_fraction == 0)
    assert "facet2" in str(report)
    # independent check on a fresh grid of facet coordinates against the analytic surface
    t0, e, n = placement
    gen = torch.Generator().manual_seed(3)
    s = 2 * torch.rand(500, generator=gen, dtype=F64) - 1
    t = 2 * torch.rand(500, generator=gen, dtype=F64) - 1
    for f, centre in enumerate([(0.2, -0.1), (-0.3, 0.15)]):
        truth, truth_n = deformed_facet(t0[f], e[f], n[f], s, t, centre)
        # parameters of the true points (the bump moves them along the normal only)
        uv = torch.stack(((s + 1) / 2, (t + 1) / 2), -1)
        got, su, sv = nurbs.evaluate_points(nets[f], 3, 3, uv)
        n_hat = fc.facet_normals(e[f], n[f])
        height_err = ((got - truth) * n_hat).sum(-1).abs()
        assert height_err.max() < 5e-5  # 0.05 mm
        assert (got - truth).norm(dim=-1).max() < 5e-5
        fit_n = torch.nn.functional.normalize(torch.linalg.cross(su, sv, dim=-1), dim=-1)
        angle = torch.atan2(torch.linalg.cross(fit_n, truth_n, dim=-1).norm(dim=-1), (fit_n * truth_n).sum(-1))
        assert angle.max() < 2e-4  # 0.2 mrad
        # and the bump is really there: the ideal flat facet is off by about AMP
        assert ((truth - (t0[f] + s[:, None] * e[f] + t[:, None] * n[f])) * n_hat).sum(-1).max() > 0.9 * AMP


def test_coarse_fit_is_reported_as_poor():
    # too few control points for the bump: the report must say so (the metric can fail)
    meas, placement = measurement(30, 24)
    _, report = dfl.fit_deflectometry(meas, placement, num_control_points=(3, 3), degree=(2, 2))
    assert torch.all(report.rms_m > 5e-5) and torch.all(report.normal_max_mrad > 0.5)


def test_fit_accepts_placement_forms():
    meas, (t0, e, n) = measurement(20, 16, jitter=False)
    a, _ = dfl.fit_deflectometry(meas, (t0, e, n), (5, 5), (2, 2))
    b, _ = dfl.fit_deflectometry(meas, Facets(t0[None], e[None], n[None]), (5, 5), (2, 2))
    c, _ = dfl.fit_deflectometry(meas, [(t0[i], e[i], n[i]) for i in range(2)], (5, 5), (2, 2))
    assert torch.allclose(a, b) and torch.allclose(a, c)
    with pytest.raises(HeliotwinError, match="facets"):
        dfl.fit_deflectometry(meas[:1], (t0, e, n), (5, 5), (2, 2))


def test_points_outside_facet_are_reported():
    meas, (t0, e, n) = measurement(12, 10, jitter=False)
    shifted = [(p + torch.tensor([0.5, 0.0, 0.0], dtype=F64), q) for p, q in meas]  # wrong frame
    _, report = dfl.fit_deflectometry(shifted, (t0, e, n), (4, 4), (2, 2))
    assert torch.all(report.outside_fraction > 0.2)


def test_fitted_net_matches_ideal_for_flat_measurement():
    t0, e, n = fc.facets_from_paint(AA39)
    g = torch.linspace(-1, 1, 15, dtype=F64)
    s, t = (a.reshape(-1) for a in torch.meshgrid(g, g, indexing="ij"))
    normals = fc.facet_normals(e, n)
    meas = [(t0[f] + s[:, None] * e[f] + t[:, None] * n[f], normals[f].expand(len(s), 3)) for f in range(2)]
    nets, report = dfl.fit_deflectometry(meas, (t0, e, n), (4, 4), (2, 2))
    ideal = fc.flat_control_points(Facets(t0, e, n), (4, 4), (2, 2))
    assert torch.allclose(nets, ideal, atol=1e-9)
    assert torch.all(report.normal_max_mrad < 1e-6)


# ---------------------------------------------------------------- malformed files
def _write_raw(path, build):
    with h5py.File(path, "w") as f:
        build(f)
    return path


def _good_group(f, name, n=5):
    g = f.create_group(name)
    g.create_dataset("surface_points", data=np.zeros((n, 3)))
    g.create_dataset("surface_normals", data=np.tile([0.0, 0.0, 1.0], (n, 1)))
    return g


def test_not_hdf5(tmp_path):
    path = tmp_path / "fake.h5"
    path.write_text("this is not an HDF5 file\n")
    with pytest.raises(InputFileError, match="fake.h5.*HDF5") as err:
        dfl.read_deflectometry(path)
    assert err.value.path.endswith("fake.h5")


def test_missing_file(tmp_path):
    with pytest.raises(InputFileError, match="nope.h5"):
        dfl.read_deflectometry(tmp_path / "nope.h5")


def test_missing_dataset(tmp_path):
    def build(f):
        _good_group(f, "facet1")
        g = f.create_group("facet2")
        g.create_dataset("surface_points", data=np.zeros((5, 3)))
    path = _write_raw(tmp_path / "missing.h5", build)
    with pytest.raises(InputFileError, match=r"missing\.h5 \[facet2/surface_normals\]: missing dataset") as err:
        dfl.read_deflectometry(path)
    assert err.value.field == "facet2/surface_normals"


def test_wrong_shape(tmp_path):
    def build(f):
        g = f.create_group("facet1")
        g.create_dataset("surface_points", data=np.zeros((5, 4)))
        g.create_dataset("surface_normals", data=np.zeros((5, 3)))
    path = _write_raw(tmp_path / "shape.h5", build)
    with pytest.raises(InputFileError, match=r"shape\.h5 \[facet1/surface_points\].*\[N, 3\]"):
        dfl.read_deflectometry(path)


def test_mismatched_rows(tmp_path):
    def build(f):
        g = f.create_group("facet1")
        g.create_dataset("surface_points", data=np.zeros((5, 3)))
        g.create_dataset("surface_normals", data=np.tile([0.0, 0.0, 1.0], (4, 1)))
    with pytest.raises(InputFileError, match=r"facet1/surface_normals"):
        dfl.read_deflectometry(_write_raw(tmp_path / "rows.h5", build))


def test_nan_values(tmp_path):
    def build(f):
        g = _good_group(f, "facet1")
        del g["surface_points"]
        pts = np.zeros((5, 3))
        pts[2, 1] = np.nan
        g.create_dataset("surface_points", data=pts)
    with pytest.raises(InputFileError, match=r"\[facet1/surface_points\].*NaN"):
        dfl.read_deflectometry(_write_raw(tmp_path / "nan.h5", build))


def test_no_facets_or_gap(tmp_path):
    with pytest.raises(InputFileError, match=r"\[facet1\]"):
        dfl.read_deflectometry(_write_raw(tmp_path / "empty.h5", lambda f: f.create_group("metadata")))

    def gap(f):
        _good_group(f, "facet1")
        _good_group(f, "facet3")
    with pytest.raises(InputFileError, match=r"\[facet2\]"):
        dfl.read_deflectometry(_write_raw(tmp_path / "gap.h5", gap))


def test_zero_normals(tmp_path):
    def build(f):
        g = f.create_group("facet1")
        g.create_dataset("surface_points", data=np.zeros((5, 3)))
        g.create_dataset("surface_normals", data=np.zeros((5, 3)))
    with pytest.raises(InputFileError, match=r"facet1/surface_normals.*zero-length"):
        dfl.read_deflectometry(_write_raw(tmp_path / "zero.h5", build))


def test_write_rejects_bad_input_and_leaves_no_file(tmp_path):
    path = tmp_path / "out.h5"
    with pytest.raises(HeliotwinError, match="facet1"):
        dfl.write_deflectometry(path, [(torch.zeros(4, 2), torch.zeros(4, 2))])
    with pytest.raises(HeliotwinError):
        dfl.write_deflectometry(path, [])
    assert list(tmp_path.iterdir()) == []
