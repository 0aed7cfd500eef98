"""The field over a year: the efficiency table is the field model at its nodes, interpolation is periodic in
azimuth, and the annual energy is the clear-sky DNI x area x efficiency sum over the daylight instants."""
import json
import math

import numpy as np
import pandas as pd
import pvlib
import pytest
import torch
from helpers.cli import run_cli
from helpers.field import dense_field, write_layout, write_plant_toml

from heliotwin.field.layout import plant_from_layout
from heliotwin.raytrace.field import field_optics
from heliotwin.raytrace.yearly import annual_energy, efficiency_table, interpolate_efficiency
from heliotwin.sun import daylight_times, direction_from_paint_angles

AZ = (-90.0, 0.0, 90.0, 180.0)
EL = (10.0, 40.0, 80.0)


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("year")
    layout, toml = write_layout(tmp, dense_field(3, 4, first_row=30.0)), write_plant_toml(tmp)
    plant, atm = plant_from_layout(layout, toml)
    return plant, atm, efficiency_table(plant, atmosphere=atm, azimuths_deg=AZ, elevations_deg=EL), layout, toml


def test_table_nodes_are_the_field_model(small):
    plant, atm, table, _, _ = small
    for i, j in ((0, 1), (1, 3), (2, 0)):
        sun = direction_from_paint_angles(torch.tensor(math.radians(AZ[j]), dtype=torch.float64),
                                          torch.tensor(math.radians(EL[i]), dtype=torch.float64))
        with torch.no_grad():
            r = field_optics(plant, sun, atmosphere=atm)
        direct = float(r.power_w.sum() / (r.dni * r.mirror_area.sum()))
        # the table uses a smaller map: the analytic intercept is the same up to float32 rounding
        assert table["efficiency"][i, j] == pytest.approx(direct, rel=1e-6)
        at = interpolate_efficiency(table, torch.tensor([math.radians(AZ[j])], dtype=torch.float64),
                                    torch.tensor([math.radians(EL[i])], dtype=torch.float64))
        assert float(at[0]) == pytest.approx(table["efficiency"][i, j], rel=1e-12)
    # low sun from the south (behind the northern field: high cosine) beats low sun from the north
    assert table["efficiency"][0, 1] > table["efficiency"][0, 3]


def test_interpolation_is_periodic_in_azimuth(small):
    table = small[2]
    e = table["efficiency"]
    # -135 deg lies half-way between 180 (= -180) and -90
    v = interpolate_efficiency(table, torch.tensor([math.radians(-135.0)], dtype=torch.float64),
                               torch.tensor([math.radians(40.0)], dtype=torch.float64))
    assert float(v[0]) == pytest.approx(0.5 * (e[1, 3] + e[1, 0]), rel=1e-12)


def test_annual_energy_is_the_clear_sky_sum(small):
    plant, atm, table, _, _ = small
    rep = annual_energy(plant, 2023, "3h", atmosphere=atm, table=table)
    s = plant.site
    times, az, el = daylight_times(2023, "3h", s.latitude_deg, s.longitude_deg, s.altitude_m)
    dni = pvlib.location.Location(s.latitude_deg, s.longitude_deg, altitude=s.altitude_m).get_clearsky(
        times, model="ineichen")["dni"].to_numpy()
    eta = interpolate_efficiency(table, az, el).numpy()
    area = 12 * 3.22 * 2.56
    assert rep["mirror_area_m2"] == pytest.approx(area)
    assert rep["instants"] == len(times) > 300
    assert rep["annual_optical_energy_mwh"] == pytest.approx(float(np.sum(dni * area * eta)) * 3 / 1e6, rel=1e-9)
    assert 0.3 < rep["mean_efficiency"] < 0.85
    assert 1.5 < rep["annual_dni_energy_on_mirrors_mwh"] / area < 3.0  # clear-sky DNI at 51 N: ~2 MWh/m2/yr
    assert pd.Timedelta("3h").total_seconds() == 3 * 3600


def test_field_year_command(small, tmp_path, capsys):
    _, _, _, layout, toml = small
    h5, js = tmp_path / "p.h5", tmp_path / "y.json"
    assert run_cli(capsys, "scenario", "from-layout", layout, "--config", toml, "-o", h5)[0] == 0
    code, out, err = run_cli(capsys, "field", "--scenario", h5, "--year", 2023, "--every", "6h",
                             "--table-azimuth-step", 90, "--json", js)
    assert code == 0, err
    rep = json.loads(js.read_text())
    assert rep["annual_optical_energy_mwh"] > 0 and len(rep["table"]["azimuth_deg"]) == 4
    assert len(rep["table"]["efficiency"]) == len(rep["table"]["elevation_deg"])
