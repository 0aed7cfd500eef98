"""Weather files used wrongly (issue 31, item 5): one rule for ``field --year --weather`` and ``predict
--weather`` (:func:`heliotwin.io.weather.weather_for_year`). Repeated instants, an all-zero DNI, DNI in kW/m2
or scaled by 10^6, a file of one month or two rows, NaN against negative rows, another year's weather: each is
a one-line error, a stated assumption in the report, or the right energy, and the same in both commands."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from helpers.cli import assert_one_line_error, run_cli

from heliotwin.errors import InputFileError
from heliotwin.field.demo import demo_field_plant
from heliotwin.io.scenario import save_scenario
from heliotwin.io.weather import read_dni_series, weather_for_year
from heliotwin.raytrace.yearly import efficiency_table
from heliotwin.workflows.field_year import weather_energy
from heliotwin.workflows.predict import prediction_energy

AZ = np.arange(-180.0, 180.0, 45.0)
EL = np.array([5.0, 20.0, 40.0, 60.0, 89.0])
YEAR = 2023


def _table(path, times, dni):
    """A plain ``time,dni`` CSV (UTC ISO times); ``dni`` entries may be strings (``"nan"``, ``""``)."""
    with open(path, "w") as fh:
        fh.write("time,dni\n")
        for t, v in zip(times, dni):
            fh.write(f"{pd.Timestamp(t).isoformat()},{v}\n")
    return path


def _day(year=YEAR, month=6, day=21):
    """One day hourly (UTC) with a bell of DNI around noon [W/m^2]."""
    t = pd.date_range(f"{year}-{month:02d}-{day:02d}", periods=24, freq="1h", tz="UTC")
    dni = np.clip(900.0 * np.cos((t.hour - 12) / 7.0 * np.pi / 2), 0.0, None).round(1)
    return t, dni


@pytest.fixture(scope="module")
def plant_table():
    plant, atm = demo_field_plant(4)
    return plant, efficiency_table(plant, atmosphere=atm, azimuths_deg=AZ, elevations_deg=EL)


def _both(plant_table, path, year=YEAR):
    """The field energy [MWh] report and the predict energy report of the same file, for a heliostat whose
    power at the model DNI (900 W/m^2) is 1 kW at every hour of the day of the file's instants."""
    plant, table = plant_table
    field = weather_energy(plant, read_dni_series(path), table, year)
    times = pd.date_range(f"{year}-06-21", periods=24, freq="1h", tz="UTC")
    series = {"time": [t.isoformat() for t in times], "power_w": [1000.0] * 24}
    return field, prediction_energy(series, plant, 900.0, "1h", str(path), year)


def test_repeated_instants_with_one_dni_count_once_in_both_commands(plant_table, tmp_path):
    t, dni = _day()
    once = _both(plant_table, _table(tmp_path / "once.csv", t, dni))
    twice = _both(plant_table, _table(tmp_path / "twice.csv", t.append(t[8:14]), np.append(dni, dni[8:14])))
    for a, b in zip(once, twice):
        key = "optical_energy_mwh" if "optical_energy_mwh" in a else "energy_kwh"
        assert b[key] == pytest.approx(a[key], rel=1e-12)  # the day's energy, not 6 hours more
        assert any("6 rows repeating an instant" in s for s in b["assumptions"])


def test_an_instant_given_two_dnis_is_one_line_naming_it(tmp_path):
    t, dni = _day()
    bad = _table(tmp_path / "bad.csv", t.append(t[12:13]), np.append(dni, 100.0))
    with pytest.raises(InputFileError, match=r"bad.csv \[time\]: the instant 2023-06-21T12:00:00\+00:00 is given 2 "):
        read_dni_series(bad)


@pytest.mark.parametrize("scale, needle", [(0.0, "every DNI"), (1e-3, "kW/m2"), (1e6, "above the 1500 W/m2")])
def test_zero_kw_and_scaled_dni_are_one_line_errors(tmp_path, scale, needle):
    t, dni = _day()
    with pytest.raises(InputFileError, match=needle) as err:
        read_dni_series(_table(tmp_path / "w.csv", t, dni * scale))
    assert "\n" not in str(err.value) and "w.csv [dni]" in str(err.value)


def test_a_daytime_zero_dni_in_the_year_is_an_error_not_a_zero_efficiency(plant_table, tmp_path):
    # DNI only at night: the file is read (some DNI > 0) but no energy can be made in the year
    t = pd.date_range(f"{YEAR}-06-21", periods=24, freq="1h", tz="UTC")
    dni = np.where((t.hour < 2) | (t.hour > 22), 300.0, 0.0)
    from heliotwin.errors import HeliotwinError

    with pytest.raises(HeliotwinError, match="no direct sun"):
        _both(plant_table, _table(tmp_path / "night.csv", t, dni))


def test_a_month_or_two_rows_is_not_reported_as_annual(plant_table, tmp_path):
    month = pd.date_range(f"{YEAR}-06-01", f"{YEAR}-07-01", freq="1h", tz="UTC", inclusive="left")
    dni = np.clip(900.0 * np.cos((month.hour - 12) / 7.0 * np.pi / 2), 0.0, None)
    field, pred = _both(plant_table, _table(tmp_path / "june.csv", month, dni))
    assert field["annual"] is False and field["annual_optical_energy_mwh"] is None
    assert field["optical_energy_mwh"] > 0 and field["coverage"]["fraction_of_year"] == pytest.approx(30 / 365)
    assert pred["annual"] is False and any("not annual" in s for s in pred["assumptions"])
    t, d = _day()
    field2, pred2 = _both(plant_table, _table(tmp_path / "two.csv", t[11:13], d[11:13]))
    assert field2["annual"] is False and field2["coverage"]["hours"] == pytest.approx(2.0)
    # predict: only the two hours the file covers count (a gap is not 0 W/m2 over the rest of the year)
    assert pred2["coverage"]["instants_with_dni"] == 2
    assert pred2["energy_kwh"] == pytest.approx(sum(d[11:13]) / 900.0, rel=1e-9)


def test_a_full_year_is_annual(plant_table, tmp_path):
    t = pd.date_range(f"{YEAR}-01-01", f"{YEAR + 1}-01-01", freq="1h", tz="UTC", inclusive="left")
    dni = np.clip(800.0 * np.cos((t.hour - 12) / 7.0 * np.pi / 2), 0.0, None)
    plant, table = plant_table
    rep = weather_energy(plant, read_dni_series(_table(tmp_path / "y.csv", t, dni)), table, YEAR)
    assert rep["annual"] is True and rep["annual_optical_energy_mwh"] == rep["optical_energy_mwh"] > 0


@pytest.mark.parametrize("bad", ["nan", "", "-5", "-9999"])
def test_missing_and_negative_rows_are_the_same_gap_in_both_commands(plant_table, tmp_path, bad):
    t, dni = _day()
    ref = _both(plant_table, _table(tmp_path / "ref.csv", t.delete(12), np.delete(dni, 12)))
    gap = _both(plant_table, _table(tmp_path / "gap.csv", t, [bad if i == 12 else v for i, v in enumerate(dni)]))
    assert gap[0]["optical_energy_mwh"] == pytest.approx(ref[0]["optical_energy_mwh"], rel=1e-12)
    assert gap[1]["energy_kwh"] == pytest.approx(ref[1]["energy_kwh"], rel=1e-12)
    assert gap[1]["energy_kwh"] < _both(plant_table, _table(tmp_path / "full.csv", t, dni))[1]["energy_kwh"]
    src = gap[0]["dni_source"]
    assert src["rows_missing"] + src["rows_negative"] == 1
    assert any("gaps" in s for s in gap[0]["assumptions"])


def test_another_years_weather_is_moved_into_the_year_by_both_commands(plant_table, tmp_path):
    t, dni = _day(year=2011)
    moved = _both(plant_table, _table(tmp_path / "tmy.csv", t, dni))
    same = _both(plant_table, _table(tmp_path / "this.csv", *_day()))
    assert moved[0]["dni_source"]["moved_from_year"] == 2011
    assert moved[0]["optical_energy_mwh"] == pytest.approx(same[0]["optical_energy_mwh"], rel=1e-12)
    assert moved[1]["energy_kwh"] == pytest.approx(same[1]["energy_kwh"], rel=1e-12)  # was 0 kWh
    assert moved[1]["energy_kwh"] > 0
    for rep in moved:
        assert any("moved into 2023" in s for s in rep["assumptions"])
    # a file of several other years holds no typical year to move: one line
    t2, d2 = _day(year=2012)
    multi = _table(tmp_path / "multi.csv", t.append(t2), np.append(dni, d2))
    with pytest.raises(InputFileError, match=r"no row in 2023 \(the rows span 2011 to 2012\)"):
        weather_for_year(read_dni_series(multi), YEAR)


def test_a_typical_year_in_a_leap_year_drops_29_february_when_moved(tmp_path):
    t = pd.date_range("2012-02-28", periods=72, freq="1h", tz="UTC")
    wy = weather_for_year(read_dni_series(_table(tmp_path / "leap.csv", t, np.full(72, 500.0))), YEAR)
    assert len(wy.times) == 48 and not ((wy.times.month == 2) & (wy.times.day == 29)).any()
    assert wy.times.is_unique and any("29 February" in s for s in wy.assumptions)


def test_field_year_command_states_a_partial_file_and_refuses_a_bad_one(tmp_path, capsys):
    plant, atm = demo_field_plant(4)
    sc = save_scenario(plant, tmp_path / "p.h5", extras=atm.to_extras())
    t, dni = _day()
    ok = _table(tmp_path / "day.csv", t, dni)
    code, out, err = run_cli(capsys, "field", "--scenario", sc, "--year", YEAR, "--weather", ok, "--json",
                             tmp_path / "y.json", "--table-azimuth-step", 90)
    assert code == 0, err
    assert "NOT annual" in out and "24 h the weather covers" in out
    rep = json.loads((tmp_path / "y.json").read_text())
    assert rep["annual"] is False and rep["annual_optical_energy_mwh"] is None and rep["assumptions"]
    for name, rows in (("rep.csv", (t.append(t[12:13]), np.append(dni, 1.0))), ("kw.csv", (t, dni / 1000.0))):
        code, _, err = run_cli(capsys, "field", "--scenario", sc, "--year", YEAR, "--weather",
                               _table(tmp_path / name, *rows), "--json", tmp_path / "z.json")
        assert_one_line_error(code, err, name)
