"""Fields as input: layout CSV + TOML plant description -> Plant -> scenario file, and every bad input as one line."""
import math

import numpy as np
import pytest
import torch
from helpers.cli import assert_one_line_error, run_cli
from helpers.field import PLANT_TOML, dense_field, write_layout, write_plant_toml

from heliotwin.atmosphere import Atmosphere, attenuation
from heliotwin.errors import InputFileError
from heliotwin.field.layout import plant_from_layout, read_layout, read_plant_config
from heliotwin.io.scenario import load_scenario, save_scenario


@pytest.fixture
def case(tmp_path):
    xyz = dense_field(3, 4)
    return write_layout(tmp_path, xyz, ids=[f"h{i}" for i in range(len(xyz))]), write_plant_toml(tmp_path), xyz


def test_layout_reads_ids_positions_and_skips_comments(tmp_path):
    path = tmp_path / "l.csv"
    path.write_text("# SolarPILOT layout\n# x,y,z\nx,y,z\n1.5,30,0\n\n# a comment between rows\n-2.25,31.5,0.5\n")
    lay = read_layout(path)
    assert lay.ids == ["H0000", "H0001"]
    assert lay.position.dtype == torch.float64
    assert lay.position.tolist() == [[1.5, 30.0, 0.0], [-2.25, 31.5, 0.5]]
    assert lay.lines == [4, 7]


def test_plant_from_layout_builds_the_described_plant(case):
    layout, toml, xyz = case
    plant, atm = plant_from_layout(layout, toml)
    assert plant.field.ids == [f"h{i}" for i in range(len(xyz))]
    assert torch.allclose(plant.field.kinematics.position, torch.tensor(xyz, dtype=torch.float64), atol=1e-4, rtol=0)
    rec = plant.targets["receiver"]
    assert rec.kind == "cylinder" and rec.radius == 4.1 and rec.height == 5.0
    assert rec.opening_angle == pytest.approx(2 * math.pi)
    assert torch.allclose(rec.axis_point, torch.tensor([0.0, 0.0, 55.0], dtype=torch.float64))
    # one flat facet spanning the whole 3.22 m x 2.56 m mirror
    fac = plant.field.facets
    assert fac.translation.shape == (len(xyz), 1, 3)
    assert 4 * float(fac.canting_e[0, 0].norm() * fac.canting_n[0, 0].norm()) == pytest.approx(3.22 * 2.56)
    s = plant.sun
    assert (s.sunshape, s.dni, s.reflectivity) == ("limb-darkened", 1000.0, 0.9)
    assert s.slope_error == pytest.approx(1.53e-3)
    assert atm.coefficients == (0.006789, 0.1046, -0.0107, 0.002845)
    assert plant.site.latitude_deg == 50.9134


def test_on_axis_canting_focuses_each_heliostat_at_its_slant_range(tmp_path):
    text = PLANT_TOML.replace('facets = [1, 1]', 'facets = [2, 2]').replace('canting = "flat"', 'canting = "on-axis"')
    xyz = np.array([[0.0, 60.0, 0.0], [30.0, 90.0, 0.0]])
    plant, _ = plant_from_layout(write_layout(tmp_path, xyz), write_plant_toml(tmp_path, text))
    fac = plant.field.facets
    n = torch.linalg.cross(fac.canting_e, fac.canting_n, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True)
    axis = torch.tensor([0.0, 0.0, 55.0], dtype=torch.float64)
    slant = torch.linalg.vector_norm(axis - plant.field.kinematics.position, dim=-1)
    # a facet at lateral offset x tilts by atan(x / 2f) towards the axis
    tilt = torch.atan2(-n[..., 0], n[..., 2])
    expect = torch.atan(fac.translation[..., 0] / (2 * slant[:, None]))
    assert torch.allclose(tilt, expect, atol=1e-12)
    assert float(tilt.abs().min()) > 0


def test_scenario_round_trip_keeps_plant_and_atmosphere(case, tmp_path):
    layout, toml, _ = case
    plant, atm = plant_from_layout(layout, toml)
    out = save_scenario(plant, tmp_path / "p.h5", extras=atm.to_extras())
    sc = load_scenario(out)
    assert sc.plant.field.ids == plant.field.ids
    assert sc.plant.sun == plant.sun
    assert torch.equal(sc.plant.field.kinematics.position, plant.field.kinematics.position)
    rec, rec2 = plant.targets["receiver"], sc.plant.targets["receiver"]
    assert rec2.kind == "cylinder" and rec2.opening_angle == rec.opening_angle
    assert torch.equal(rec2.center, rec.center)
    assert Atmosphere.from_extras(sc.extras) == atm
    assert Atmosphere.from_extras({}) == Atmosphere()  # scenarios without atmosphere: SolarPILOT's default


def test_attenuation_polynomial_value():
    # 1 - (c0 + c1 s + c2 s^2 + c3 s^3) at s = 0.1 km
    c = (0.006789, 0.1046, -0.0107, 0.002845)
    expect = 1 - (c[0] + c[1] * 0.1 + c[2] * 0.01 + c[3] * 0.001)
    assert float(attenuation(torch.tensor(100.0, dtype=torch.float64))) == pytest.approx(expect, abs=1e-15)


def test_cli_from_layout_writes_a_scenario(case, tmp_path, capsys):
    layout, toml, xyz = case
    out = tmp_path / "plant.h5"
    code, stdout, err = run_cli(capsys, "scenario", "from-layout", layout, "--config", toml, "-o", out)
    assert code == 0, err
    assert f"{len(xyz)} heliostats" in stdout
    sc = load_scenario(out)
    assert len(sc.plant.field.ids) == len(xyz)
    assert sc.provenance[-1]["step"] == "from-layout"


BAD_TOML = [
    ('type = "cylinder"', "type = 'tower'", "receiver.type", "unknown value 'tower'"),
    ("[receiver]", "[receiver", None, "malformed TOML"),
    ("reflectivity = 0.9", "reflectivity = 0.9\nreflectivty = 0.8", "heliostat.reflectivty", "unknown key"),
    ("width = 3.22", "width = -3.22", "heliostat.width", "expected a value >= 0.05"),
    ('shape = "limb-darkened"', "shape = 'square'", "sun.shape", "unknown value"),
    ("coefficients = [0.006789", "coefficients = ['a', 0.006789", "atmosphere.coefficients", "expected a list"),
    ("radius = 4.1\n", "", "receiver.radius", "missing"),
]


@pytest.mark.parametrize("old,new,field,needle", BAD_TOML)
def test_bad_toml_is_one_line_naming_file_and_field(case, tmp_path, capsys, old, new, field, needle):
    layout, _, _ = case
    assert old in PLANT_TOML
    toml = write_plant_toml(tmp_path, PLANT_TOML.replace(old, new, 1))
    out = tmp_path / "plant.h5"
    code, _, err = run_cli(capsys, "scenario", "from-layout", layout, "--config", toml, "-o", out)
    assert_one_line_error(code, err, str(toml), needle, *([f"[{field}]"] if field else []))
    assert not out.exists()


BAD_CSV = [
    ("x,y,z\n1,40,0\n2,abc,0\n", "[line 3, y]", "expected a number"),
    ("x,y\n1,40\n", "[line 1]", "missing column 'z'"),
    ("x,y,z\n1,40\n", "[line 2, z]", "missing value"),
    ("id,x,y,z\na,1,40,0\na,9,40,0\n", "[line 3, id]", "duplicate id 'a'"),
    ("x,y,z\n1,3,0\n", "[line 2]", "inside the tower"),
    ("# only a comment\n", None, "no header"),
    ("x,y,z\n1,nan,0\n", "[line 2, y]", "finite"),
]


@pytest.mark.parametrize("text,field,needle", BAD_CSV)
def test_bad_layout_is_one_line_naming_file_and_line(tmp_path, capsys, text, field, needle):
    layout = tmp_path / "bad.csv"
    layout.write_text(text)
    toml = write_plant_toml(tmp_path)
    out = tmp_path / "plant.h5"
    code, _, err = run_cli(capsys, "scenario", "from-layout", layout, "--config", toml, "-o", out)
    assert_one_line_error(code, err, str(layout), needle, *([field] if field else []))
    assert not out.exists()


def test_missing_files_are_one_line(tmp_path):
    with pytest.raises(InputFileError, match="cannot read"):
        read_plant_config(tmp_path / "nope.toml")
    with pytest.raises(InputFileError, match="cannot read layout"):
        read_layout(tmp_path / "nope.csv")
