"""Deflectometry -> NURBS surface for tracing, and the learned-vs-deflectometry comparison (mm, mrad)."""
from __future__ import annotations

import torch
from helpers.surfaces import small_scene

from heliotwin.cli import main
from heliotwin.field import facets as facet_ops
from heliotwin.field.plant import SunSettings
from heliotwin.io.deflectometry import write_deflectometry
from heliotwin.surfaces.deflectometry import compare_surfaces, deflectometry_surface
from heliotwin.surfaces.imaging import evaluate_images, predict_images
from heliotwin.surfaces.learning import LearnableSurface, learnable_surfaces


def _dome_truth(facets, amp=1.5e-3, net=(5, 5), deg=(2, 2)):
    u = torch.linspace(-1, 1, net[0], dtype=torch.float64)
    dome = amp * (1 - u[:, None] ** 2) * (1 - u[None, :] ** 2)
    base = LearnableSurface(facets, net, deg).base
    return learnable_surfaces(facets, base, dome.expand(1, 4, *net).clone(), deg)


def _write_measurement(path, truth, samples=(20, 20), noise_mrad=0.0, seed=0):
    pts, nrm, _ = facet_ops.surface_points(truth, samples)
    nf, p = truth.control_points.shape[1], samples[0] * samples[1]
    gen = torch.Generator().manual_seed(seed)
    meas = []
    for f in range(nf):
        n = nrm[0, f * p:(f + 1) * p].detach()
        if noise_mrad:
            n = n + noise_mrad * 1e-3 * torch.randn(n.shape, generator=gen, dtype=n.dtype)
            n = n / n.norm(dim=-1, keepdim=True)
        meas.append((pts[0, f * p:(f + 1) * p].detach(), n))
    write_deflectometry(path, meas, dtype="float32")


def test_deflectometry_fit_traces_and_compares(tmp_path):
    facets, obs, _ = small_scene(distance=20.0, n=2)
    truth = _dome_truth(facets)
    path = tmp_path / "defl.h5"
    _write_measurement(path, truth)
    defl, fit = deflectometry_surface(path, facets, (5, 5), (2, 2))  # the truth's spline space
    assert defl.control_points.shape == (1, 4, 5, 5, 3)
    assert max(fit["rms_mm"]) < 0.05 and max(fit["outside_fraction"]) == 0.0
    # The fitted surface is the truth to well below what images resolve ...
    same = compare_surfaces(facets, defl, truth)
    assert same["normal_deviation_mrad"] < 0.1 and same["height_rms_mm"] < 0.01, same
    # ... while the ideal surface differs by the dome (mm and mrad scale), and the comparison is symmetric.
    ideal = LearnableSurface(facets, (5, 5), (2, 2)).surfaces()
    off = compare_surfaces(facets, ideal, defl)
    assert off["normal_deviation_mrad"] > 2.0 and 0.2 < off["height_rms_mm"] < 1.5, off
    back = compare_surfaces(facets, defl, ideal)
    assert abs(back["normal_deviation_mrad"] - off["normal_deviation_mrad"]) < 1e-9
    # It is a surface for tracing: its images match the truth's, the ideal's do not.
    sun = SunSettings(sunshape="buie", slope_error=0.5e-3)
    with torch.no_grad():
        obs.images, _, _ = predict_images(truth, obs, sun, samples=(16, 16), resolution=32)
    kw = dict(samples=(16, 16), resolution=32)
    l1_defl = max(evaluate_images(defl, obs, sun, **kw)["l1"])
    l1_ideal = min(evaluate_images(ideal, obs, sun, **kw)["l1"])
    assert l1_defl < 0.05 < l1_ideal, (l1_defl, l1_ideal)
    # And it can seed the learning: LearnableSurface(initial=...) reproduces it on its own net.
    start = LearnableSurface(facets, (7, 7), (3, 3), initial=defl.control_points, initial_degree=(2, 2), fix_gauge=True)
    assert compare_surfaces(facets, start.surfaces(), defl)["normal_deviation_mrad"] < 0.1


def test_cli_deflectometry_bad_file_one_line_error(paint_dir, tmp_path, capsys):
    bad = tmp_path / "defl.h5"
    bad.write_text("not hdf5")
    out_json = tmp_path / "r.json"
    rc = main(["reconstruct", "--paint", str(paint_dir), "--heliostat", "AA39", "--deflectometry", str(bad),
               "--json", str(out_json), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "defl.h5" in err
    assert not out_json.exists()
