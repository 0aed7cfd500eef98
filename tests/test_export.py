"""Exports to SolarPILOT's layout table (+ heliotwin's TOML) and to SolTrace's input file, checked by re-reading:
the re-read plant gives the same field figures as the plant that was exported."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from heliotwin.field.demo import demo_field_plant
from heliotwin.field.layout import plant_from_layout
from heliotwin.io.export import (
    export_solarpilot,
    export_soltrace,
    read_flux_map_csv,
    read_soltrace,
    write_flux_map_csv,
)
from heliotwin.raytrace.field import field_optics
from heliotwin.sun import direction_from_paint_angles

SUN = direction_from_paint_angles(torch.tensor(0.35, dtype=torch.float64), torch.tensor(0.7, dtype=torch.float64))


@pytest.fixture(scope="module")
def plant():
    return demo_field_plant(60)


@pytest.fixture(scope="module")
def result(plant):
    p, atm = plant
    with torch.no_grad():
        return field_optics(p, SUN, atmosphere=atm)


def test_solarpilot_layout_and_toml_reread_give_the_same_field(plant, result, tmp_path):
    p, atm = plant
    export_solarpilot(p, tmp_path / "layout.csv", tmp_path / "plant.toml", atmosphere=atm, aim=result.aim,
                      source="demo")
    header = [ln for ln in (tmp_path / "layout.csv").read_text().splitlines() if not ln.startswith("#")][0]
    assert header == "id,x_location,y_location,z_location,x_aimpoint,y_aimpoint,z_aimpoint"  # SolarPILOT's columns
    again, atm2 = plant_from_layout(tmp_path / "layout.csv", tmp_path / "plant.toml")
    assert again.field.ids == p.field.ids and atm2 == atm
    torch.testing.assert_close(again.field.kinematics.position, p.field.kinematics.position, atol=1e-6, rtol=0)
    with torch.no_grad():
        r2 = field_optics(again, SUN, atmosphere=atm2)
    for name in ("cosine", "shading", "blocking", "attenuation", "intercept", "efficiency"):
        torch.testing.assert_close(getattr(r2, name), getattr(result, name), atol=1e-6, rtol=0, msg=name)
    assert float(r2.power_w.sum()) == pytest.approx(float(result.power_w.sum()), rel=1e-6)
    torch.testing.assert_close(r2.flux, result.flux, atol=1e-3 * float(result.flux.max()), rtol=0)


def test_soltrace_input_reread_gives_positions_normals_optics_and_cosines(plant, result, tmp_path):
    p, _ = plant
    export_soltrace(p, tmp_path / "field.stinput", SUN, result.normal, source="demo")
    text = (tmp_path / "field.stinput").read_text()
    assert text.startswith("# SOLTRACE VERSION 3.1.0 INPUT FILE")
    st = read_soltrace(tmp_path / "field.stinput")
    torch.testing.assert_close(st["position"], p.field.kinematics.position, atol=1e-5, rtol=0)
    torch.testing.assert_close(st["normal"], result.normal.to(torch.float64), atol=1e-6, rtol=0)
    torch.testing.assert_close(st["sun"], SUN, atol=1e-9, rtol=0)
    # the field figure a re-reader computes first: cosine efficiency n . s, equal to the field model's
    torch.testing.assert_close(st["normal"] @ st["sun"], result.cosine.to(torch.float64), atol=1e-6, rtol=0)
    assert st["optics"]["heliostat"]["reflectivity"] == pytest.approx(p.sun.reflectivity)
    assert st["optics"]["heliostat"]["slope_error_mrad"] == pytest.approx(p.sun.slope_error * 1e3)
    receiver = st["stages"][1]["elements"][0]
    assert receiver["surface"][0] == "t" and receiver["surface"][1][0] == pytest.approx(1 / 4.1)
    assert [e["aperture"][1][:2] for e in st["stages"][0]["elements"][:1]] == [[3.22, 2.56]]


def test_flux_map_csv_round_trip_keeps_values_and_cell_centres(result, tmp_path):
    extent = result.extent.tolist()
    write_flux_map_csv(tmp_path / "map.csv", result.flux, extent)
    flux, xs, ys = read_flux_map_csv(tmp_path / "map.csv")
    np.testing.assert_allclose(flux, result.flux.numpy(), rtol=1e-5, atol=1e-3)
    rows, cols = result.flux.shape
    assert xs[0] == pytest.approx(extent[0] + (extent[1] - extent[0]) / (2 * cols), abs=1e-4)
    assert ys[0] == pytest.approx(extent[3] - (extent[3] - extent[2]) / (2 * rows), abs=1e-4)  # top row first
    # the map integrates to the receiver power it came from
    cell = (extent[1] - extent[0]) * (extent[3] - extent[2]) / (rows * cols)
    assert flux.sum() * cell == pytest.approx(float(result.flux.sum()) * cell, rel=1e-5)
