"""A learned surface in the scenario file: written into the plant, read back for prediction."""
from __future__ import annotations

import torch

from heliotwin.errors import HeliotwinError
from heliotwin.field.demo import demo_plant
from heliotwin.field.plant import SunSettings
from heliotwin.io.scenario import load_scenario, write_scenario
from heliotwin.surfaces.learning import LearnableSurface
from heliotwin.surfaces.state import learned_surface, with_learned_surface


def _facets_of(plant, h):
    from dataclasses import fields, replace

    fac = plant.field.facets
    return replace(fac, **{f.name: getattr(fac, f.name)[h:h + 1] for f in fields(fac)})


def test_learned_surface_round_trip_keeps_the_rest_of_the_plant(tmp_path):
    plant = demo_plant(num_heliostats=4)
    hid = plant.field.ids[2]
    model = LearnableSurface(_facets_of(plant, 2), (5, 5), (2, 2))
    with torch.no_grad():
        model.displacement_mm.normal_(0.0, 0.3, generator=torch.Generator().manual_seed(1))
    optics = SunSettings(sunshape="buie", csr=0.05, slope_error=2e-3)
    path = write_scenario(with_learned_surface(None, plant, hid, model.surfaces(), model.displacement.detach(),
                                               optics, train_records=[11, 12, 13], target="receiver",
                                               settings={"loss": "kl"}, source="/data/paint"), tmp_path / "s.h5")
    sc = load_scenario(path)
    item = learned_surface(sc, hid)
    assert torch.allclose(item["surfaces"].control_points, model.surfaces().control_points.detach(), atol=0)
    assert item["optics"] == optics and item["train_records"] == [11, 12, 13] and item["target"] == "receiver"
    # The ideal counterpart on the same net is flat: the learned one differs from it by the displacement.
    d = (item["surfaces"].control_points - item["ideal"].control_points).norm(dim=-1)
    assert torch.allclose(d, model.displacement.detach().abs().reshape(d.shape), atol=1e-12)
    # Other heliostats keep their shape (carried over to the 5x5 net) and the provenance names the step.
    assert sc.plant.field.surfaces.control_points.shape[2:4] == (5, 5)
    assert sc.provenance[-1]["step"] == "reconstruct" and sc.provenance[-1]["heliostat"] == hid
    try:
        learned_surface(sc, plant.field.ids[0])
    except HeliotwinError as exc:
        assert "no learned surface" in str(exc) and hid in str(exc)
    else:
        raise AssertionError("a heliostat without a learned surface must raise")
