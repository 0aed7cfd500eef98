"""The whole field against SolarPILOT's output for the same field (the issue's tolerances, where met), energy
bookkeeping of the receiver map, gradients w.r.t. an aim point, and the ``field`` command."""
import csv
import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from helpers.cli import assert_one_line_error, run_cli
from helpers.field import PLANT_TOML, dense_field, solarpilot_dir, write_layout, write_plant_toml

from heliotwin.field.layout import plant_from_layout
from heliotwin.geometry import safe_normalize
from heliotwin.raytrace.field import (
    FieldSettings,
    _footprint_classes,
    _sorted_quantile,
    equator_aim_points,
    field_optics,
    reuse_mirror_samples,
    summary,
)
from heliotwin.sun import direction_from_paint_angles

SUNS = {  # SolarPILOT azimuth (clockwise from north), elevation [deg] -> file suffix
    (179.9882, 62.5237): "az179.99_el62.52", (97.5527, 36.7262): "az97.55_el36.73",
    (179.9965, 39.8270): "az180.00_el39.83", (179.9945, 15.6516): "az179.99_el15.65",
}
HIGH_SOUTH = ("az179.99_el62.52", "az180.00_el39.83")
WINTER = "az179.99_el15.65"


def _sun(solarpilot_az, el):
    """SolarPILOT azimuth (clockwise from north) -> heliotwin's PAINT azimuth = 180 deg - it."""
    return direction_from_paint_angles(torch.tensor(math.radians(180.0 - solarpilot_az), dtype=torch.float64),
                                       torch.tensor(math.radians(el), dtype=torch.float64))


@pytest.fixture(scope="module")
def solarpilot(tmp_path_factory):
    ref = solarpilot_dir()
    plant, atm = plant_from_layout(ref / "layout-500.csv", write_plant_toml(tmp_path_factory.mktemp("sp")))
    results = {f"az{s['sun_azimuth_deg_from_north_clockwise']:.2f}_el{s['sun_elevation_deg']:.2f}": s
               for s in json.loads((ref / "field-results.json").read_text())["suns"]}
    out = {}
    for (az, el), key in SUNS.items():
        with torch.no_grad():
            res = field_optics(plant, _sun(az, el), atmosphere=atm)
        rows = list(csv.DictReader(open(ref / f"per-heliostat_{key}.csv")))
        idx = torch.tensor([plant.field.ids.index(f"H{int(r['id']):04d}") for r in rows])
        theirs = {k: torch.tensor([float(r[k]) for r in rows], dtype=torch.float64)
                  for k in ("cosine", "attenuation", "x_aimpoint", "y_aimpoint", "z_aimpoint")}
        out[key] = (res, idx, theirs, results[key], summary(res, plant))
    return plant, out, atm


@pytest.mark.parametrize("key", sorted(SUNS.values()))
def test_per_heliostat_cosine_attenuation_and_aim_points(solarpilot, key):
    res, idx, theirs, _, _ = solarpilot[1][key]
    assert float((res.cosine[idx] - theirs["cosine"]).abs().max()) < 1e-4
    assert float((res.attenuation[idx] - theirs["attenuation"]).abs().max()) < 1e-4
    aim = torch.stack([theirs[f"{c}_aimpoint"] for c in "xyz"], -1)
    assert float((res.aim[idx] - aim).abs().max()) < 1e-3  # 'simple' aiming = our equator aiming


@pytest.mark.parametrize("key", sorted(SUNS.values()))
def test_field_averages_against_solarpilot(solarpilot, key):
    _, _, _, ref, rep = solarpilot[1][key]
    e = rep["field"]["efficiency"]
    tol = 0.02 if key == WINTER else 0.005
    assert e["shading"] == pytest.approx(ref["eff_shading"], abs=tol)
    if key in HIGH_SOUTH or key == WINTER:
        # East sun (az 97.55): SolarPILOT's reach test drops diagonal neighbours that do block (0.965 exact vs
        # 0.976; docs/physics.md, benchmarks/bench_field.py); the solarpilot model below reproduces it.
        assert e["blocking"] == pytest.approx(ref["eff_blocking"], abs=tol)
    assert e["intercept"] == pytest.approx(ref["eff_intercept"], rel=0.02)
    assert e["cosine"] == pytest.approx(ref["eff_cosine"], abs=1e-5)
    if key != WINTER:  # winter: exact total +2.9 % (SolarPILOT counts overlapping losses twice; docs/physics.md)
        assert e["total"] == pytest.approx(ref["eff_total"], rel=0.02)
        assert rep["receiver"]["power_w"] == pytest.approx(ref["receiver_power_kw"] * 1e3, rel=0.02)
        assert rep["receiver"]["peak_flux_w_m2"] == pytest.approx(ref["peak_flux_kw_m2"]["48x20"] * 1e3, rel=0.10)


@pytest.fixture(scope="module")
def solarpilot_model(solarpilot):
    """The same field with ``occlusion_model="solarpilot"`` (SolarPILOT's analytic shading/blocking)."""
    plant = solarpilot[0]
    ref = solarpilot_dir()
    out = {}
    for (az, el), key in SUNS.items():
        with torch.no_grad():
            res = field_optics(plant, _sun(az, el), atmosphere=solarpilot[2],
                               settings=FieldSettings(occlusion_model="solarpilot"))
        rows = list(csv.DictReader(open(ref / f"per-heliostat_{key}.csv")))
        theirs = {k: torch.tensor([float(r[k]) for r in rows], dtype=torch.float64) for k in ("shading", "blocking")}
        out[key] = (res, solarpilot[1][key][1], theirs, solarpilot[1][key][3], summary(res, plant))
    return out


@pytest.mark.parametrize("key", sorted(SUNS.values()))
def test_solarpilot_model_reproduces_solarpilot_per_heliostat_and_meets_every_tolerance(solarpilot_model, key):
    """SolarPILOT's shading and blocking per heliostat to the 1e-4 its files are rounded to; with them the
    field averages, total, power and the 48 x 20 peak meet the issue's tolerances at every sun."""
    res, idx, theirs, ref, rep = solarpilot_model[key]
    assert float((res.shading[idx] - theirs["shading"]).abs().max()) < 2e-4
    assert float((res.blocking[idx] - theirs["blocking"]).abs().max()) < 2e-4
    e = rep["field"]["efficiency"]
    assert e["shading"] == pytest.approx(ref["eff_shading"], abs=1e-4)
    assert e["blocking"] == pytest.approx(ref["eff_blocking"], abs=1e-4)
    assert e["total"] == pytest.approx(ref["eff_total"], rel=0.02)
    assert rep["receiver"]["power_w"] == pytest.approx(ref["receiver_power_kw"] * 1e3, rel=0.02)
    assert rep["receiver"]["peak_flux_w_m2"] == pytest.approx(ref["peak_flux_kw_m2"]["48x20"] * 1e3, rel=0.10)


def test_receiver_map_holds_the_intercepted_power(solarpilot):
    res = solarpilot[1]["az179.99_el62.52"][0]
    assert float(res.flux.sum()) * res.pixel_area == pytest.approx(float(res.power_w.sum()), rel=5e-3)
    assert res.flux.shape == (20, 48)


def test_blocks_of_heliostats_and_samples_give_the_one_piece_result(tmp_path, monkeypatch):
    """The occlusion test in blocks of heliostats and the footprints in blocks of samples (memory bounds) give
    the field model's numbers, gradients included: every heliostat still occludes every block (the factors bit
    for bit; the map to float rounding, as vectorised math takes another path at a block's tail)."""
    import heliotwin.raytrace.field as field_module

    layout = write_layout(tmp_path, dense_field(4, 5, first_row=30.0))
    plant, atm = plant_from_layout(layout, write_plant_toml(tmp_path))
    sun = _sun(150.0, 25.0)  # low: shading and blocking cross the blocks
    aim = equator_aim_points(plant.targets["receiver"], plant.field.kinematics.position).requires_grad_(True)

    def run():
        r = field_optics(plant, sun, atmosphere=atm, aim=aim)
        grad, = torch.autograd.grad(r.power_w.sum() + r.flux.max(), aim)
        return r, grad

    whole, g_whole = run()
    monkeypatch.setattr(field_module, "OCCLUSION_BLOCK", 3)
    monkeypatch.setattr(field_module, "FOOTPRINT_BLOCK", 100)
    blocks, g_blocks = run()
    assert 0.0 < float(whole.shading.detach().min()) < 0.95 or 0.0 < float(whole.blocking.detach().min()) < 0.95
    for name in ("shading", "blocking", "tower_shading"):
        assert torch.equal(getattr(blocks, name), getattr(whole, name)), name
    for name in ("intercept", "power_w", "flux"):
        assert torch.allclose(getattr(blocks, name), getattr(whole, name), rtol=1e-5, atol=0), name
    assert torch.allclose(g_blocks, g_whole, rtol=1e-4, atol=1e-6 * float(g_whole.abs().max()))


def test_grouped_map_agrees_with_the_exact_window_map(tmp_path):
    layout = write_layout(tmp_path, dense_field(5, 8, first_row=40.0))
    plant, atm = plant_from_layout(layout, write_plant_toml(tmp_path))
    sun = _sun(180.0, 45.0)
    maps = {}
    for mode in ("window", "grouped"):
        with torch.no_grad():
            maps[mode] = field_optics(plant, sun, atmosphere=atm, settings=FieldSettings(resolution=(64, 128),
                                                                                         flux_mode=mode)).flux
    w, g = maps["window"], maps["grouped"]
    assert float(g.max()) == pytest.approx(float(w.max()), rel=0.03)
    assert float((g - w).abs().sum() / w.sum()) < 0.03


def test_footprint_classes_hold_equal_shares_when_the_two_variances_grow_together():
    """Footprints grow in both axes with the slant range: per-axis quantile bins would leave the off-diagonal
    classes empty; the classes split each column bin by its own row quantiles instead. A shard classified
    against every rank's values gets the classes the whole field gives it."""
    gen = torch.Generator().manual_seed(0)
    t = torch.rand(4000, generator=gen, dtype=torch.float64)
    lx, ly = t + 0.05 * torch.randn(4000, generator=gen, dtype=torch.float64), 2 * t + 0.1 * torch.rand(
        4000, generator=gen, dtype=torch.float64)
    g = _footprint_classes(lx, ly, lx, ly, 4)
    counts = torch.bincount(g, minlength=16)
    assert int(counts.min()) >= 240 and int(counts.max()) <= 260  # 4000 / 16 = 250 each
    # and every class is narrow in the row variance (per-axis bins: 0.27 of the range; these: 0.17)
    spread = max(float(ly[g == c].max() - ly[g == c].min()) for c in range(16))
    assert spread < 0.2 * float(ly.max() - ly.min())
    shard = torch.arange(4000) % 3 == 1
    assert torch.equal(_footprint_classes(lx[shard], ly[shard], lx, ly, 4), g[shard])
    assert torch.equal(_footprint_classes(lx, ly, lx, ly, 1), torch.zeros(4000, dtype=torch.long))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_gpu_quantile_is_numpys(dtype):
    """The footprint classes' quantiles off the CPU (one sort; torch.quantile refuses > 2^24 values): NumPy's
    linear interpolation, ties and both ends included."""
    gen = torch.Generator().manual_seed(3)
    x = torch.cat((torch.randn(997, generator=gen, dtype=dtype), torch.full((40,), 0.25, dtype=dtype)))
    q = torch.tensor([0.0, 0.1, 0.25, 1 / 3, 0.5, 0.9, 1.0], dtype=dtype)
    want = torch.from_numpy(np.quantile(x.numpy(), q.numpy()).astype(x.numpy().dtype))
    assert torch.equal(_sorted_quantile(x, q), want) if dtype == torch.float64 else \
        torch.allclose(_sorted_quantile(x, q), want, rtol=0, atol=1e-6)


def test_intercepted_power_gradient_matches_finite_differences(tmp_path):
    """d(receiver power)/d(aim point of one heliostat), smooth occlusion, float64: autograd = central differences."""
    layout = write_layout(tmp_path, dense_field(3, 4, first_row=30.0))
    plant, atm = plant_from_layout(layout, write_plant_toml(tmp_path))
    sun = _sun(180.0, 20.0)
    base = equator_aim_points(plant.targets["receiver"], plant.field.kinematics.position)
    settings = FieldSettings(softness=0.05, flux_samples=4, dtype=torch.float64, flux_mode="window")
    k = 5  # a heliostat whose light is partly shaded and blocked and partly misses the receiver

    def power(offset):
        aim = base.clone()
        aim[k] = aim[k] + offset
        return field_optics(plant, sun, atmosphere=atm, aim=aim, settings=settings).power_w.sum()

    off = torch.tensor([0.3, 0.0, 2.2], dtype=torch.float64, requires_grad=True)  # aim high: intercept < 1
    grad, = torch.autograd.grad(power(off), off)
    h = 1e-4
    fd = torch.stack([(power(off.detach() + h * e) - power(off.detach() - h * e)) / (2 * h)
                      for e in torch.eye(3, dtype=torch.float64)])
    assert float(grad.abs().max()) > 1.0  # W per m: the aim point matters
    assert torch.allclose(grad, fd, rtol=1e-4, atol=1e-3)


def test_field_command_writes_json_csv_png(tmp_path, capsys):
    layout = write_layout(tmp_path, dense_field(3, 4, first_row=30.0))
    h5 = tmp_path / "plant.h5"
    assert run_cli(capsys, "scenario", "from-layout", layout, "--config", write_plant_toml(tmp_path), "-o", h5)[0] == 0
    js, per, png = tmp_path / "f.json", tmp_path / "f.csv", tmp_path / "f.png"
    code, out, err = run_cli(capsys, "field", "--scenario", h5, "--sun-azimuth", "0", "--sun-elevation", "40",
                             "--json", js, "--per-heliostat", per, "--flux", png)
    assert code == 0, err
    rep = json.loads(js.read_text())
    for key in ("total", "cosine", "shading", "blocking", "attenuation", "intercept", "reflectance"):
        assert 0.0 < rep["field"]["efficiency"][key] <= 1.0
    assert rep["receiver"]["power_w"] > 0 and rep["receiver"]["peak_flux_w_m2"] > 0 and rep["seconds"] > 0
    rows = list(csv.DictReader(open(per)))
    assert list(rows[0]) == ["id", "x", "y", "z", "aim_x", "aim_y", "aim_z", "efficiency", "cosine", "shading",
                             "blocking", "attenuation", "intercept", "reflectance", "power_w"]
    assert len(rows) == 12
    total = sum(float(r["power_w"]) for r in rows)
    assert total == pytest.approx(rep["receiver"]["power_w"])
    prod = [math.prod(float(r[k]) for k in ("cosine", "shading", "blocking", "attenuation", "intercept",
                                             "reflectance")) for r in rows]
    assert prod == pytest.approx([float(r["efficiency"]) for r in rows])
    assert png.stat().st_size > 0


@pytest.mark.parametrize("argv,needle", [
    (["--sun-azimuth", "0", "--sun-elevation", "-3"], "below the horizon"),
    (["--time", "2023-06-21T23:30Z"], "below the horizon"),
    (["--sun-azimuth", "0", "--sun-elevation", "30", "--aim", "scenario"], "no aim points"),
])
def test_field_command_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, argv, needle):
    layout = write_layout(tmp_path, dense_field(2, 2, first_row=30.0))
    h5 = tmp_path / "plant.h5"
    assert run_cli(capsys, "scenario", "from-layout", layout, "--config", write_plant_toml(tmp_path), "-o", h5)[0] == 0
    js = tmp_path / "f.json"
    code, _, err = run_cli(capsys, "field", "--scenario", h5, *argv, "--json", js)
    assert_one_line_error(code, err, needle)
    assert not js.exists()


@pytest.mark.parametrize("command", [("scenario", "from-layout"), ("field",), ("aimpoints",)])
def test_new_commands_have_help(command, capsys):
    from heliotwin.cli import main

    with pytest.raises(SystemExit) as exc:
        main([*command, "--help"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: heliotwin {' '.join(command)}")


def test_tower_shadow_matches_a_direct_ray_test_on_every_point(solarpilot):
    """The tower (receiver radius, up to its top) shades the heliostats behind it at a low southern sun; the
    bounding pre-test keeps exactly the direct all-heliostat ray-cylinder result."""
    from heliotwin.field.facets import surface_points
    from heliotwin.geometry import ray_cylinder
    from heliotwin.raytrace.field import _tower_shading, tracked_mirror_samples
    from heliotwin.raytrace.occlusion import mirror_frame

    plant = solarpilot[0]
    res = solarpilot[1][WINTER][0]
    pts, nrm, area = tracked_mirror_samples(plant, res.normal, 8, torch.float64)
    local = surface_points(plant.field.surfaces, (8, 8))[0].to(torch.float64)
    rot = torch.stack((*mirror_frame(res.normal), res.normal), dim=-1)  # the mirrors' own frames
    lit = area * (nrm * res.sun).sum(-1).clamp_min(0)
    rec = plant.targets["receiver"]
    t, hit, _ = ray_cylinder(pts, res.sun.expand_as(pts), rec.axis_point, rec.up, rec.radius)
    shaded = hit & ((pts + t.unsqueeze(-1) * res.sun - rec.axis_point)[..., 2] <= rec.height / 2)
    direct = (lit * ~shaded).sum(1) / lit.sum(1)
    pivot = plant.field.kinematics.position.to(torch.float64)
    assert torch.allclose(_tower_shading(plant, pivot, local, rot, res.sun, lit), direct)
    assert 5 < int((direct < 1).sum()) < 100
    assert torch.all(plant.field.kinematics.position[direct < 1][:, 0].abs() < 10.0)  # behind the tower only


def test_monte_carlo_map_agrees_with_the_gaussian_map(solarpilot):
    """Same samples, occlusion and attenuation; the Monte-Carlo map samples the true limb-darkened sun."""
    plant = solarpilot[0]
    g = solarpilot[1]["az179.99_el62.52"][0]
    with torch.no_grad():
        m = field_optics(plant, g.sun, settings=FieldSettings(integrator="mc", rays_per_point=32, seed=3))
    assert float(m.flux.max()) == pytest.approx(float(g.flux.max()), rel=0.05)
    assert float(m.flux.sum()) == pytest.approx(float(g.flux.sum()), rel=0.02)
    assert float((m.flux - g.flux).abs().sum() / g.flux.sum()) < 0.08


def test_full_cylinder_map_wraps_at_its_seam(tmp_path):
    """A heliostat behind a north-facing 360-degree receiver lights the seam: the unrolled map is periodic, so
    the map holds all the intercepted power and both edges carry the two halves of the spot alike."""
    toml = write_plant_toml(tmp_path, PLANT_TOML.replace("opening_angle_deg = 360",
                                                         "opening_angle_deg = 360\nnormal = [0.0, 1.0, 0.0]"))
    plant, atm = plant_from_layout(write_layout(tmp_path, [[0.3, -80.0, 0.0], [40.0, 60.0, 0.0]]), toml)
    for mode in ("window", "grouped"):
        with torch.no_grad():
            res = field_optics(plant, _sun(180.0, 40.0), atmosphere=atm, settings=FieldSettings(flux_mode=mode))
        assert float(res.flux.sum()) * res.pixel_area == pytest.approx(float(res.power_w.sum()), rel=1e-2)
        left, right = res.flux[:, :3].sum(), res.flux[:, -3:].sum()
        assert float(left) > 0.1 * float(res.flux.max()) and float(right) == pytest.approx(float(left), rel=0.3)


def test_field_command_occlusion_solarpilot_reproduces_solarpilots_east_blocking(tmp_path, capsys):
    """``field --occlusion solarpilot`` on SolarPILOT's own layout: its field-average blocking at the east sun,
    where the exact ray test finds more blocking (docs/physics.md: SolarPILOT's reach test)."""
    ref = solarpilot_dir()
    h5 = tmp_path / "sp.h5"
    assert run_cli(capsys, "scenario", "from-layout", ref / "layout-500.csv", "--config", write_plant_toml(tmp_path),
                   "-o", h5)[0] == 0
    theirs = next(s for s in json.loads((ref / "field-results.json").read_text())["suns"]
                  if abs(s["sun_azimuth_deg_from_north_clockwise"] - 97.55) < 0.01)
    blocking = {}
    for model in ("exact", "solarpilot"):
        js = tmp_path / f"{model}.json"
        code, _, err = run_cli(capsys, "field", "--scenario", h5, "--sun-azimuth", f"{180 - 97.55}",
                               "--sun-elevation", "36.73", "--occlusion", model, "--json", js)
        assert code == 0, err
        rep = json.loads(js.read_text())
        assert rep["occlusion"] == model
        blocking[model] = rep["field"]["efficiency"]["blocking"]
    sp = theirs["eff_blocking"]
    assert blocking["solarpilot"] == pytest.approx(sp, abs=5e-4)
    assert blocking["exact"] < sp - 0.005  # the diagonal neighbours SolarPILOT's reach test drops


def test_conv_integrator_keeps_the_exact_sunshape_and_agrees_with_monte_carlo(tmp_path):
    """``integrator="conv"``: the pillbox sun cone per footprint class; the map matches a Monte-Carlo trace of the
    same samples (independent sampling of the same sun) and carries the same power."""
    toml = PLANT_TOML.replace('shape = "limb-darkened"', 'shape = "pillbox"')
    plant, atm = plant_from_layout(write_layout(tmp_path, dense_field(3, 4, first_row=30.0)),
                                   write_plant_toml(tmp_path, toml))
    sun = _sun(170.0, 45.0)
    maps = {}
    for integrator in ("conv", "mc"):
        settings = FieldSettings(integrator=integrator, resolution=(40, 96), rays_per_point=1000)
        with torch.no_grad():
            maps[integrator] = field_optics(plant, sun, atmosphere=atm, settings=settings).flux.double()
    conv, mc = maps["conv"], maps["mc"]
    assert float((conv / conv.sum() - mc / mc.sum()).abs().sum()) < 0.03  # measured 0.016
    assert float(conv.sum() / mc.sum()) == pytest.approx(1.0, abs=0.01)
    assert float(conv.max() / mc.max()) == pytest.approx(1.0, abs=0.05)


def test_sun_cone_kernels_gradcheck_and_match_a_gaussian_sun():
    """The class kernels are differentiable in the footprint covariance (float64 gradcheck); for a Gaussian sun
    they are the Gaussian of that covariance."""
    from heliotwin.field.plant import SunSettings
    from heliotwin.raytrace.conv import angular_density
    from heliotwin.raytrace.field import _gaussian_kernels, _sun_cone_kernels

    sun = SunSettings(sunshape="gaussian", sigma=2.51e-3, slope_error=0.0)
    dens, half_width = angular_density(sun)
    var = 2.51e-3 ** 2
    density = (dens, half_width, var, 0.0)
    cov = torch.tensor([[[2.0, 0.4], [0.4, 1.2]]], dtype=torch.float64)
    k = _sun_cone_kernels(cov, density, 6, supersample=8)
    g = _gaussian_kernels(cov + torch.eye(2, dtype=torch.float64) / 12.0, 6)  # a pixel box ~ 1/12 px^2
    assert float((k - g).abs().sum()) < 0.03
    def kernel(abc):  # a symmetric covariance from its three entries (as the footprints' covariances are)
        cov = torch.stack((torch.stack((abc[0], abc[1])), torch.stack((abc[1], abc[2])))).unsqueeze(0)
        return _sun_cone_kernels(cov, density, 3, supersample=2)

    abc = torch.tensor([2.0, 0.4, 1.2], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(kernel, (abc,), eps=1e-6, atol=1e-6)


def test_reused_mirror_samples_change_nothing_and_learned_surfaces_keep_their_gradient(tmp_path):
    """Within ``reuse_mirror_samples`` (the aim-point rounds) repeated field evaluations equal fresh ones, and
    surfaces that require a gradient are sampled afresh, so the gradient still reaches them."""
    plant, atm = plant_from_layout(write_layout(tmp_path, dense_field(3, 4, first_row=30.0)),
                                   write_plant_toml(tmp_path))
    sun = safe_normalize(torch.tensor([0.3, -0.6, 0.7], dtype=torch.float64))
    aim = equator_aim_points(plant.targets["receiver"], plant.field.kinematics.position.to(torch.float64))
    fresh = [field_optics(plant, sun, atmosphere=atm, aim=aim + dz) for dz in (0.0, 0.5)]
    with reuse_mirror_samples():
        reused = [field_optics(plant, sun, atmosphere=atm, aim=aim + dz) for dz in (0.0, 0.5)]
    for a, b in zip(fresh, reused):
        assert torch.equal(a.efficiency, b.efficiency) and torch.equal(a.flux, b.flux)
    assert not torch.equal(fresh[0].flux, fresh[1].flux)
    cp = plant.field.surfaces.control_points.clone().requires_grad_()
    plant = replace(plant, field=replace(plant.field, surfaces=replace(plant.field.surfaces, control_points=cp)))
    with reuse_mirror_samples():
        field_optics(plant, sun, atmosphere=atm, settings=FieldSettings(softness=0.05))
        power = field_optics(plant, sun, atmosphere=atm, settings=FieldSettings(softness=0.05)).power_w.sum()
    grad, = torch.autograd.grad(power, cp)
    assert float(grad.abs().sum()) > 0.0
