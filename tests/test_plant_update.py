"""Learned values written back into a plant: only the chosen heliostats change, surfaces carry over nets."""
from __future__ import annotations

import torch

from heliotwin.field import facets as facet_ops
from heliotwin.field.demo import demo_plant
from heliotwin.field.plant import Surfaces
from heliotwin.field.update import resample_surfaces, with_kinematics, with_surfaces


def test_with_kinematics_changes_only_the_chosen_heliostats():
    plant = demo_plant(num_heliostats=6)
    ids = [plant.field.ids[4], plant.field.ids[1]]
    kin = plant.field.kinematics.index([4, 1])
    kin = kin.replace(joint_tilt=kin.joint_tilt + torch.tensor([1e-3, -2e-3], dtype=torch.float64)[:, None, None])
    out = with_kinematics(plant, ids, kin)
    d = (out.field.kinematics.joint_tilt - plant.field.kinematics.joint_tilt).abs().amax(dim=(1, 2))
    assert torch.allclose(d, torch.tensor([0, 2e-3, 0, 0, 1e-3, 0], dtype=torch.float64))
    assert torch.equal(out.field.kinematics.position, plant.field.kinematics.position)
    assert plant.field.kinematics.joint_tilt.abs().max() == 0  # the input plant is untouched


def test_ideal_surfaces_resample_exactly_to_a_learned_net():
    plant = demo_plant(num_heliostats=3)
    fac = plant.field.facets
    coarse = facet_ops.ideal_surfaces(fac, num_control_points=(4, 4), degree=(2, 2))
    fine = facet_ops.ideal_surfaces(fac, num_control_points=(7, 7), degree=(3, 3))
    moved = resample_surfaces(coarse, (7, 7), (3, 3))
    p0, n0, _ = facet_ops.surface_points(fine, (9, 9))
    p1, n1, _ = facet_ops.surface_points(moved, (9, 9))
    assert (p1 - p0).abs().max() < 1e-9 and (n1 - n0).abs().max() < 1e-9


def test_with_surfaces_puts_the_learned_net_on_its_heliostat_and_carries_the_rest_over():
    plant = demo_plant(num_heliostats=3)
    fac = plant.field.facets
    fine = facet_ops.ideal_surfaces(fac, num_control_points=(7, 7), degree=(3, 3))
    bumped = fine.control_points[1:2].clone()
    bumped[..., 3, 3, 2] += 2e-3  # a 2 mm bump on every facet of heliostat 1
    out = with_surfaces(plant, [plant.field.ids[1]], Surfaces(bumped, 3, 3))
    cp = out.field.surfaces.control_points
    assert cp.shape[2:4] == (7, 7) and (out.field.surfaces.degree_u, out.field.surfaces.degree_v) == (3, 3)
    assert torch.equal(cp[1], bumped[0])
    p_out, _, _ = facet_ops.surface_points(Surfaces(cp[[0, 2]], 3, 3), (9, 9))
    p_ref, _, _ = facet_ops.surface_points(Surfaces(fine.control_points[[0, 2]], 3, 3), (9, 9))
    assert (p_out - p_ref).abs().max() < 1e-9
