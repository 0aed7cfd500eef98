"""Shading and blocking: the grid-candidate ray tests against an all-pairs brute-force reference, the candidate
count stays bounded as the field grows, and the smooth occlusion is differentiable and tends to the hard one."""
import math

import pytest
import torch
from helpers.field import brute_force_unoccluded, dense_field, write_layout, write_plant_toml

from heliotwin.field.facets import surface_points
from heliotwin.field.layout import plant_from_layout
from heliotwin.geometry import reflect, safe_normalize
from heliotwin.raytrace.field import equator_aim_points, tracked_mirror_samples, tracking_normals
from heliotwin.raytrace.occlusion import (
    OccluderSet,
    mirror_blocks,
    mirror_frame,
    occluder_candidates,
    solarpilot_interference,
    unoccluded,
    unoccluded_tracked,
)
from heliotwin.sun import direction_from_paint_angles


def _sun(az_deg, el_deg):
    return direction_from_paint_angles(torch.tensor(math.radians(az_deg), dtype=torch.float64),
                                       torch.tensor(math.radians(el_deg), dtype=torch.float64))


def _field(tmp_path, rows, cols, **kw):
    plant, _ = plant_from_layout(write_layout(tmp_path, dense_field(rows, cols, **kw)), write_plant_toml(tmp_path))
    return plant


def _rays(plant, sun, samples=6):
    pos = plant.field.kinematics.position
    aim = equator_aim_points(plant.targets["receiver"], pos)
    n = tracking_normals(pos, aim, sun)
    occ = OccluderSet(pos, n, plant.field.width, plant.field.height)
    pts, nrm, _ = tracked_mirror_samples(plant, n, samples, torch.float64)
    return occ, pts, reflect(-sun.expand_as(nrm), nrm), aim


@pytest.mark.parametrize("az,el", [(0.0, 62.5), (82.4, 36.7), (0.0, 15.65), (-60.0, 8.0)])
def test_grid_candidates_reproduce_the_all_pairs_reference(tmp_path, az, el):
    """Dense block (4.0 m x 3.6 m pitch for 3.22 m x 2.56 m mirrors): shading and blocking per ray equal the
    brute-force all-pairs ray-rectangle test."""
    plant = _field(tmp_path, 6, 8)
    sun = _sun(az, el)
    occ, pts, refl, aim = _rays(plant, sun)
    h = pts.shape[0]
    args = (occ.center, occ.normal, occ.width_axis, occ.height_axis, 2 * occ.half_width, 2 * occ.half_height)
    for dirs, rep in ((sun.expand(h, 1, 3), sun), (refl, aim - occ.center)):
        idx, valid = occluder_candidates(occ, rep)
        fast = unoccluded(pts, dirs, occ, idx, valid)
        ref = brute_force_unoccluded(pts, dirs, *args)
        assert torch.equal(fast, ref)


def test_bowed_mirrors_and_spread_rays_still_match_the_all_pairs_reference(tmp_path):
    """The exact test ray-tests only the pairs a conservative bound keeps (box of the mirror's points, spread
    of its rays' directions): with points ~10 cm (sd) off the mirror plane and every reflected ray turned by
    ~30 mrad (sd) it still equals the all-pairs reference ray for ray, and so does shading at a low sun."""
    plant = _field(tmp_path, 6, 8, spacing=(3.5, 2.9))
    sun = _sun(30.0, 12.0)
    occ, pts, refl, aim = _rays(plant, sun, samples=8)
    g = torch.Generator().manual_seed(0)
    bow = 0.1 * torch.randn(pts.shape[:2], generator=g, dtype=pts.dtype)
    pts = pts + bow.unsqueeze(-1) * occ.normal.unsqueeze(1)
    spread = safe_normalize(refl + 0.02 * torch.randn(refl.shape, generator=g, dtype=refl.dtype))
    args = (occ.center, occ.normal, occ.width_axis, occ.height_axis, 2 * occ.half_width, 2 * occ.half_height)
    h = pts.shape[0]
    for dirs, rep in ((spread, aim - occ.center), (sun.expand(h, 1, 3), sun)):
        idx, valid = occluder_candidates(occ, rep)
        ref = brute_force_unoccluded(pts, dirs, *args)
        assert float((ref == 0).float().mean()) > 0.01  # the case does occlude
        assert torch.equal(unoccluded(pts, dirs, occ, idx, valid), ref)


@pytest.mark.parametrize("az,el,bow", [(0.0, 62.5, 0.0), (82.4, 36.7, 0.0), (0.0, 50.0, 0.0), (-60.0, 8.0, 0.0),
                                        (30.0, 12.0, 0.1), (0.0, 50.0, 0.1)])
def test_block_culled_test_of_tracked_mirrors_equals_the_all_pairs_reference(tmp_path, az, el, bow):
    """The field model's test (:func:`unoccluded_tracked`: mirror samples in the heliostat frame, culled per
    block of samples with bounds from the blocks' boxes and normals) equals the all-pairs reference ray for ray,
    on flat canted mirrors and on mirrors bowed by ~10 cm (sd) with normals turned by ~20 mrad (sd)."""
    plant = _field(tmp_path, 6, 8, spacing=(3.5, 2.9))
    sun = _sun(az, el)
    f64 = torch.float64
    pos = plant.field.kinematics.position.to(f64)
    aim = equator_aim_points(plant.targets["receiver"], pos)
    n = tracking_normals(pos, aim, sun)
    occ = OccluderSet(pos, n, plant.field.width, plant.field.height)
    per_direction = 8
    pts, nrm, _ = (t.to(f64) for t in surface_points(plant.field.surfaces, (per_direction, per_direction)))
    if bow:
        g = torch.Generator().manual_seed(1)
        pts = pts + bow * torch.randn(pts.shape[:2], generator=g, dtype=f64).unsqueeze(-1) * torch.tensor([0, 0, 1.0])
        nrm = safe_normalize(nrm + 0.02 * torch.randn(nrm.shape, generator=g, dtype=f64))
    rot = torch.stack((*mirror_frame(n), n), dim=-1)
    world = pos.unsqueeze(1) + pts @ rot.transpose(-1, -2)
    nw = nrm @ rot.transpose(-1, -2)
    blocks = mirror_blocks(pts, nrm, plant.field.facets.translation.shape[1], per_direction)
    args = (occ.center, occ.normal, occ.width_axis, occ.height_axis, 2 * occ.half_width, 2 * occ.half_height)
    occluded = 0.0
    for reflected, rep, dirs in ((False, sun, sun.expand(pos.shape[0], 1, 3)),
                                 (True, aim - pos, reflect(-sun.expand_as(nw), nw))):
        idx, valid = occluder_candidates(occ, rep)
        ref = brute_force_unoccluded(world, dirs, *args)
        assert torch.equal(unoccluded_tracked(blocks, rot, occ, idx, valid, sun, reflected=reflected), ref)
        occluded += float((ref == 0).float().mean())
    assert occluded > 0.01  # the case does occlude


def test_blocking_on_a_dense_field_costs_over_ten_percent_and_matches_brute_force(tmp_path):
    """The issue's independent check: a field dense enough that blocking costs > 10 % of the light."""
    plant = _field(tmp_path, 6, 8, spacing=(3.5, 2.9), first_row=100.0)
    sun = _sun(0.0, 50.0)
    occ, pts, refl, aim = _rays(plant, sun, samples=8)
    idx, valid = occluder_candidates(occ, aim - occ.center)
    fast = unoccluded(pts, refl, occ, idx, valid)
    ref = brute_force_unoccluded(pts, refl, occ.center, occ.normal, occ.width_axis, occ.height_axis,
                                 2 * occ.half_width, 2 * occ.half_height)
    assert torch.equal(fast, ref)
    assert 1.0 - float(ref.mean()) > 0.10


def test_candidate_count_does_not_grow_with_the_field(tmp_path):
    """Cost ~ linear: the number of candidates per heliostat is set by the neighbourhood, not by H."""
    sun = _sun(0.0, 15.65)
    ks = []
    for rows, cols in ((6, 8), (24, 24)):
        plant = _field(tmp_path, rows, cols)
        occ, _, _, aim = _rays(plant, sun, samples=2)
        idx, valid = occluder_candidates(occ, sun)
        ks.append(idx.shape[1])
        assert int(valid.sum(1).max()) == idx.shape[1]
    assert ks[1] <= ks[0] + 4 and ks[1] < 30


def test_smooth_occlusion_tends_to_the_hard_one(tmp_path):
    plant = _field(tmp_path, 4, 5)
    sun = _sun(0.0, 15.65)
    occ, pts, _, _ = _rays(plant, sun)
    idx, valid = occluder_candidates(occ, sun)
    hard = unoccluded(pts, sun.expand(pts.shape[0], 1, 3), occ, idx, valid)
    assert 0.05 < 1 - float(hard.mean()) < 0.6  # the low sun really shades this block
    errs = [float((unoccluded(pts, sun.expand(pts.shape[0], 1, 3), occ, idx, valid, softness=tau) - hard).abs().mean())
            for tau in (0.1, 0.01, 1e-4)]
    assert errs[0] > errs[1] > errs[2] and errs[2] < 2e-3


def test_smooth_occlusion_gradcheck(tmp_path):
    """float64 gradcheck of the smooth test w.r.t. ray origins, occluder centres and normals."""
    plant = _field(tmp_path, 2, 2, spacing=(3.6, 3.0))
    sun = _sun(0.0, 20.0)
    occ, pts, _, _ = _rays(plant, sun, samples=2)
    idx, valid = occluder_candidates(occ, sun)
    w, hgt = plant.field.width, plant.field.height

    def f(origins, center, normal):
        o = OccluderSet(center, normal / normal.norm(dim=-1, keepdim=True), w, hgt)
        return unoccluded(origins, sun.expand(origins.shape[0], 1, 3), o, idx, valid, softness=0.3)

    inputs = (pts.clone().requires_grad_(), occ.center.clone().requires_grad_(), occ.normal.clone().requires_grad_())
    out = f(*inputs)
    assert 0.0 < float(out.detach().min()) < 0.9  # some rays are partly stopped: the gradient is not trivially zero
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6)


def test_solarpilot_estimate_equals_the_exact_area_for_parallel_mirrors_in_line():
    """SolarPILOT's per-pair estimate is exact where its assumptions hold: two parallel mirrors, the neighbour
    straight ahead along the direction, its upper corners landing inside: the lost fraction is the area under
    the projected upper edge, as a dense ray test finds."""
    n = torch.nn.functional.normalize(torch.tensor([[0.0, -0.6, 0.8]] * 2, dtype=torch.float64), dim=-1)
    d = torch.nn.functional.normalize(torch.tensor([0.1, -0.8, 0.5], dtype=torch.float64), dim=0)
    center = torch.zeros(2, 3, dtype=torch.float64)
    center[1] = center[0] + 3.0 * d + torch.tensor([0.4, 0.0, -1.2], dtype=torch.float64)  # ahead, a bit lower
    w = torch.tensor([3.22, 3.22], dtype=torch.float64)
    h = torch.tensor([2.56, 2.56], dtype=torch.float64)
    occ = OccluderSet(center, n, w, h)
    idx, valid = torch.tensor([[1], [0]]), torch.tensor([[True], [False]])
    sp = solarpilot_interference(center, n, w, h, d, idx, valid, distance_cutoff=False)
    g = (torch.arange(200, dtype=torch.float64) + 0.5) / 200 - 0.5
    u, v = torch.meshgrid(g * 3.22, g * 2.56, indexing="ij")
    pts = center[0] + u.reshape(-1, 1) * occ.width_axis[0] + v.reshape(-1, 1) * occ.height_axis[0]
    exact = unoccluded(pts.unsqueeze(0), d.expand(1, 1, 3), occ, idx[:1], valid[:1])
    assert 0.1 < 1 - float(sp[0]) < 0.9  # a real partial overlap
    assert float(sp[0]) == pytest.approx(float(exact.mean()), abs=5e-3)
    assert float(sp[1]) == 1.0


def test_solarpilot_reach_test_drops_diagonal_neighbours_that_block(tmp_path):
    """The mechanism behind the east-sun gap (docs/physics.md): SolarPILOT compares the 3-D pivot distance with
    an along-the-ray reach, so on a staggered field under an east sun some heliostats it calls unblocked are
    blocked by a diagonal neighbour, by the exact test and by the brute-force all-pairs reference."""
    plant = _field(tmp_path, 6, 8, spacing=(4.0, 3.6), first_row=60.0)
    sun = _sun(82.4, 36.7)
    occ, pts, refl, aim = _rays(plant, sun, samples=8)
    direction = torch.nn.functional.normalize(aim - occ.center, dim=-1)
    idx, valid = occluder_candidates(occ, direction)
    args = (occ.center, occ.normal, 2 * occ.half_width, 2 * occ.half_height, direction, idx, valid)
    sp = solarpilot_interference(*args)
    no_reach = solarpilot_interference(*args, distance_cutoff=False)
    exact = brute_force_unoccluded(pts, refl, occ.center, occ.normal, occ.width_axis, occ.height_axis,
                                   2 * occ.half_width, 2 * occ.half_height).mean(1)
    dropped = (sp > 0.9999) & (no_reach < 0.99) & (exact < 0.99)
    assert int(dropped.sum()) >= 3
    assert float(no_reach.mean()) == pytest.approx(float(exact.mean()), abs=0.005)
    assert float(sp.mean()) > float(exact.mean()) + 0.003
