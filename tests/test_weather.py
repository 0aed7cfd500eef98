"""DNI time series (SAM/typical-year files, PAINT's calibration weather, plain tables) for the yearly energy:
a file holding pvlib's clear sky gives the clear-sky energy; local standard time becomes UTC; PAINT's measured
DNI is read as recorded; bad files are one-line errors naming the field."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from heliotwin.errors import InputFileError
from heliotwin.field.demo import demo_field_plant
from heliotwin.io.scenario import Scenario
from heliotwin.io.weather import read_dni_series
from heliotwin.raytrace.yearly import annual_energy, clear_sky_dni, efficiency_table
from heliotwin.workflows.field_year import field_year, weather_energy

AZ = np.arange(-180.0, 180.0, 30.0)
EL = np.array([5.0, 15.0, 30.0, 45.0, 60.0, 75.0, 89.0])


def _sam(path, times_local, dni, tz=0.0):
    with open(path, "w") as fh:
        fh.write("Source,Location ID,City,State,Country,Latitude,Longitude,Time Zone,Elevation\n")
        fh.write(f"test,0,Juelich,NRW,DEU,50.9134,6.3878,{tz},87.0\n")
        fh.write("Year,Month,Day,Hour,Minute,GHI,DNI,DHI\n")
        for t, v in zip(times_local, dni):
            fh.write(f"{t.year},{t.month},{t.day},{t.hour},{t.minute},0,{v:.4f},0\n")
    return path


@pytest.fixture(scope="module")
def small():
    plant, atm = demo_field_plant(20)
    table = efficiency_table(plant, atmosphere=atm, azimuths_deg=AZ, elevations_deg=EL)
    return plant, atm, table


def test_a_file_holding_clear_sky_gives_the_clear_sky_energy(small, tmp_path):
    plant, atm, table = small
    times = pd.date_range("2023-01-01", "2024-01-01", freq="1h", tz="UTC", inclusive="left")
    dni = clear_sky_dni(times, plant)
    series = read_dni_series(_sam(tmp_path / "w.csv", times.tz_localize(None), dni))
    assert series.kind == "sam" and series.step_hours == pytest.approx(1.0) and len(series.times) == 8760
    ours = weather_energy(plant, series, table, 2023)
    ref = annual_energy(plant, 2023, "1h", atmosphere=atm, table=table)
    # the clear-sky run skips instants below 5 deg elevation, where the DNI is small: within 1 %
    assert ours["annual_optical_energy_mwh"] == pytest.approx(ref["annual_optical_energy_mwh"], rel=0.01)
    assert ours["annual_dni_energy_on_mirrors_mwh"] == pytest.approx(ref["annual_dni_energy_on_mirrors_mwh"], rel=0.01)
    assert ours["mean_efficiency"] == pytest.approx(ref["mean_efficiency"], rel=0.005)
    # half the DNI, half the energy
    half = read_dni_series(_sam(tmp_path / "h.csv", times.tz_localize(None), dni / 2))
    assert weather_energy(plant, half, table, 2023)["annual_optical_energy_mwh"] == pytest.approx(
        ours["annual_optical_energy_mwh"] / 2, rel=1e-6)  # the file keeps 4 decimals


def test_local_standard_time_becomes_utc_and_a_typical_year_moves_into_the_asked_year(small, tmp_path):
    plant, _, table = small
    local = pd.date_range("2011-06-21 12:30", periods=3, freq="1h")
    series = read_dni_series(_sam(tmp_path / "w.csv", local, [800.0, 700.0, 600.0], tz=1.0))
    assert str(series.times[0]) == "2011-06-21 11:30:00+00:00"
    rep = weather_energy(plant, series, table, 2023)
    assert rep["dni_source"]["moved_from_year"] == 2011 and rep["instants"] == 3


def test_paint_calibration_weather_is_read_as_measured(paint_dir):
    series = read_dni_series(paint_dir / "metadata" / "calibration-weather.csv")
    assert series.kind == "paint" and len(series.times) > 100
    i = series.times.get_loc(pd.Timestamp("2022-06-01T13:26:51Z"))
    assert series.dni[i] == pytest.approx(870.7785)


def test_bad_weather_files_are_one_line_errors(tmp_path):
    (tmp_path / "a.csv").write_text("time,ghi\n2023-01-01T12:00Z,300\n")
    with pytest.raises(InputFileError, match=r"a.csv \[dni\]"):
        read_dni_series(tmp_path / "a.csv")
    (tmp_path / "b.csv").write_text("when,dni\nnoon,300\n")
    with pytest.raises(InputFileError, match=r"b.csv \[time\]"):
        read_dni_series(tmp_path / "b.csv")
    (tmp_path / "c.csv").write_text("time,dni\n2023-01-01T12:00Z,-5\n")
    with pytest.raises(InputFileError, match="no row"):
        read_dni_series(tmp_path / "c.csv")


def test_field_year_with_weather_names_its_source(small, tmp_path):
    plant, atm, _ = small
    sc = Scenario(plant=plant, extras=atm.to_extras())
    times = pd.date_range("2023-06-01", "2023-06-03", freq="1h", tz="UTC", inclusive="left")
    series = read_dni_series(_sam(tmp_path / "w.csv", times.tz_localize(None), np.full(len(times), 500.0)))
    rep = field_year(sc, 2023, azimuth_step_deg=60.0, weather=series)
    assert "w.csv" in rep["dni_model"] and rep["instants"] > 20
    assert 0.5 < rep["mean_efficiency"] < 0.95


def test_predicted_energy_scales_each_instant_by_its_dni(tmp_path):
    from heliotwin.workflows.predict import prediction_energy

    plant, _ = demo_field_plant(4)
    series = {"time": ["2023-06-21T10:00:00+00:00", "2023-06-21T11:00:00+00:00", "2023-06-21T12:00:00+00:00"],
              "power_w": [1000.0, 1000.0, 1000.0]}
    local = pd.date_range("2023-06-21 09:00", periods=5, freq="1h")
    w = _sam(tmp_path / "w.csv", local, [0.0, 450.0, 450.0, 450.0, 0.0])
    e = prediction_energy(series, plant, 900.0, "1h", str(w))
    assert e["energy_kwh"] == pytest.approx(1.5) and series["dni_w_m2"] == [450.0] * 3
    clear = prediction_energy(dict(series), plant, 900.0, "1h", None)
    assert clear["dni_source"].startswith("pvlib") and 2.0 < clear["energy_kwh"] < 3.5  # ~800-900 W/m2 at noon
