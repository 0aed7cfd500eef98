"""Weather files as sites deliver them (issue 43, item 2): pvlib's shipped TMY3 and TMY2, and EPW, SAM CSV (both
metadata layouts, DNI or Beam, months of different years) and NSRDB PSM3 files written here in the layouts pvlib's
readers and SAM expect, from pvlib's clear sky at far-east and far-west sites. Each is read with its own time
convention, so that the sun is up whenever DNI > 0 (the share of DNI energy below the horizon <= 0.5 %, tens of
percent when read hours off); the file's site against the plant's; leap days; non-weather files; no warnings."""
from __future__ import annotations

import json
import os
import warnings

import numpy as np
import pandas as pd
import pvlib
import pytest
from helpers.cli import assert_one_line_error, run_cli
from helpers.weather import YEARS, hour_means, write_epw, write_psm3, write_sam

from heliotwin.errors import InputFileError
from heliotwin.field.demo import demo_field_plant
from heliotwin.io.scenario import save_scenario
from heliotwin.io.weather import (
    dni_share_below_horizon,
    read_dni_series,
    site_offset_km,
    site_warning,
    weather_for_year,
)
from heliotwin.raytrace.yearly import efficiency_table
from heliotwin.workflows.field_year import weather_energy
from heliotwin.workflows.predict import prediction_energy

DATA = os.path.join(os.path.dirname(pvlib.__file__), "data")
TMY3, TMY2 = os.path.join(DATA, "723170TYA.CSV"), os.path.join(DATA, "12839.tm2")
#: far east and far west of their time zones' meridians is not needed: UTC read as local is 9-10 h off here
EAST = {"name": "Tokyo", "lat": 35.69, "lon": 139.69, "alt": 40.0, "tz": 9}
WEST = {"name": "Honolulu", "lat": 21.31, "lon": -157.86, "alt": 5.0, "tz": -10}
LIMIT = 0.005  # share of the DNI energy below the horizon for a correct reading


@pytest.fixture(scope="module")
def hourly():
    """Per site: the local standard hours of a non-leap year (their starts, naive), the hour-mean clear-sky DNI
    [W/m^2] (10-min samples) and the instantaneous DNI at each hour's :30 (NSRDB's stamp)."""
    out = {}
    starts = pd.date_range("2001-01-01", periods=8760, freq="1h")
    for site in (EAST, WEST):
        out[site["name"]] = (starts, *hour_means(site, starts))
    return out


def _share(series, year=2023, site=None):
    wy = weather_for_year(series, year)
    i = series.info if site is None else {"latitude_deg": site["lat"], "longitude_deg": site["lon"],
                                          "elevation_m": site["alt"]}
    return wy, dni_share_below_horizon(wy, i["latitude_deg"], i["longitude_deg"], i.get("elevation_m", 0.0))


def _wrong(wy, hours):
    """The same year read ``hours`` off (e.g. local standard time taken for UTC)."""
    return type(wy)(wy.year, wy.times + pd.Timedelta(hours=hours), wy.dni, wy.hours, wy.step_hours, wy.annual,
                    wy.coverage, wy.assumptions, wy.source)


@pytest.mark.parametrize("path, kind, tz, lat", [(TMY3, "tmy3", -5.0, 36.1), (TMY2, "tmy2", -5.0, 25.8)])
def test_pvlibs_shipped_tmy3_and_tmy2_are_hour_ending_local_time_with_the_sun_up(path, kind, tz, lat):
    s = read_dni_series(path)
    assert s.kind == kind and s.typical and len(s.times) == 8760 and "hour-ending" in s.convention
    assert s.info["time_zone_hours"] == tz and s.info["latitude_deg"] == pytest.approx(lat)
    wy, share = _share(s)
    assert wy.annual and len(wy.times) == 8760 and share <= LIMIT
    assert wy.source["typical_year"] and wy.source["time_convention"] == s.convention == wy.convention
    # the file's first hour (local 00:00-01:00 on 1 January, UTC-5) is at 05:30 UTC
    assert pd.Timestamp("2023-01-01 05:30", tz="UTC") in wy.times
    # read 5 h off (the local stamps taken for UTC): much of the DNI falls at night
    i = s.info
    assert dni_share_below_horizon(_wrong(wy, -5.0), i["latitude_deg"], i["longitude_deg"]) > 0.1


def test_tmy3_leap_february_hour_ending_at_midnight_stays_on_28_february():
    """The shipped TMY3's February is 1996's: its "02/28/1996,24:00" row is 23:00-24:00 on 28 February (pvlib's
    own index puts it on 1 March), so the typical year has no 29 February and 1 March keeps its 24 hours."""
    s = read_dni_series(TMY3)
    local = s.times + pd.Timedelta(hours=-5)
    assert not ((local.month == 2) & (local.day == 29)).any()
    assert ((local.month == 3) & (local.day == 1)).sum() == 24


@pytest.mark.parametrize("site", [EAST, WEST], ids=["east", "west"])
def test_generated_epw_is_read_with_the_sun_up_and_read_as_utc_it_is_not(hourly, tmp_path, site):
    starts, dni, _ = hourly[site["name"]]
    s = read_dni_series(write_epw(tmp_path / "w.epw", site, starts, dni))
    assert s.kind == "epw" and s.typical and s.file_years == (1977, 2005) and "EPW" in s.convention
    assert s.info["latitude_deg"] == site["lat"] and s.info["time_zone_hours"] == site["tz"]
    wy, share = _share(s)
    assert share <= LIMIT
    # every hour of the file is in the year (the rows the UTC shift moved past New Year wrap) with its energy
    assert len(wy.times) == 8760 and float((wy.dni * wy.hours).sum()) == pytest.approx(float(dni.sum()))
    assert dni_share_below_horizon(_wrong(wy, site["tz"]), site["lat"], site["lon"], site["alt"]) > 0.2


@pytest.mark.parametrize("layout, column, minute", [("source", "DNI", False), ("location", "Beam", False),
                                                    ("location", "DNI", True), ("source", "Beam", True)])
def test_sam_csv_in_both_layouts_with_months_of_different_years_is_a_typical_year(hourly, tmp_path, layout,
                                                                                  column, minute):
    starts, mean, at30 = hourly["Tokyo"]
    # no Minute column: the hour starting at Hour (its mean); Minute 30: the sun at :30 (the instant's value)
    dni = at30.round(1) if minute else mean
    s = read_dni_series(write_sam(tmp_path / "w.csv", EAST, starts, dni, layout, column, minute))
    assert s.kind == "sam" and s.typical and s.file_years == (1977, 2005)
    assert s.info["site_name"] == "Tokyo" and s.info["longitude_deg"] == EAST["lon"]
    wy, share = _share(s)  # was "no row in 2023 (the rows span 1977 to 2005)"
    assert wy.annual and len(wy.times) == 8760 and share <= LIMIT
    assert any("typical year" in a for a in wy.assumptions) and wy.source["moved_from_year"] is None
    assert float((wy.dni * wy.hours).sum()) == pytest.approx(float(np.sum(dni)))
    assert dni_share_below_horizon(_wrong(wy, EAST["tz"]), EAST["lat"], EAST["lon"]) > 0.2


@pytest.mark.parametrize("site", [EAST, WEST], ids=["east", "west"])
def test_nsrdb_psm3_is_instantaneous_at_its_stamp(hourly, tmp_path, site):
    starts, _, at30 = hourly[site["name"]]
    s = read_dni_series(write_psm3(tmp_path / "psm.csv", site, starts, at30))
    assert s.kind == "psm3" and "instantaneous" in s.convention and s.info["elevation_m"] == int(site["alt"])
    assert s.times[0] == pd.Timestamp("2001-01-01 00:30", tz="UTC") - pd.Timedelta(hours=site["tz"])
    wy, share = _share(s)
    assert share <= LIMIT
    assert dni_share_below_horizon(_wrong(wy, site["tz"]), site["lat"], site["lon"]) > 0.2


def test_the_files_site_against_the_plants_with_a_warning_beyond_50_km(hourly, tmp_path):
    starts, dni, _ = hourly["Honolulu"]
    s = read_dni_series(write_epw(tmp_path / "hnl.epw", WEST, starts, dni))
    assert site_offset_km(s, WEST["lat"], WEST["lon"]) == pytest.approx(0.0, abs=1e-9)
    # 0.3 deg of latitude is 33 km: no warning; 0.6 deg (67 km) is one, naming the file and both sites
    assert site_offset_km(s, WEST["lat"] + 0.3, WEST["lon"]) == pytest.approx(33.4, abs=0.2)
    assert site_warning(s, WEST["lat"] + 0.3, WEST["lon"]) is None
    text = site_warning(s, WEST["lat"] + 0.6, WEST["lon"])
    assert "hnl.epw" in text and "21.310 N, 157.860 W" in text and "21.910 N" in text and "\n" not in text
    plant, atm = demo_field_plant(4)  # at Jülich
    assert site_offset_km(s, plant.site) == pytest.approx(12_000, rel=0.05)
    table = efficiency_table(plant, atmosphere=atm, azimuths_deg=np.arange(-180.0, 180.0, 90.0),
                             elevations_deg=np.array([5.0, 30.0, 60.0, 89.0]))
    rep = weather_energy(plant, s, table, 2023)
    assert rep["site_offset_km"] > 50 and len(rep["warnings"]) == 1 and "hnl.epw" in rep["warnings"][0]
    assert rep["weather_site"]["site_name"] == "Honolulu" and "EPW" in rep["time_convention"]
    # Honolulu's DNI at Jülich's sun: much of it falls at Jülich's night, which the share shows
    assert rep["dni_share_below_horizon"] > 0.2
    # a plain table names no site: nothing to compare
    (tmp_path / "t.csv").write_text("time,dni\n2023-06-21T12:00Z,800\n")
    assert site_offset_km(read_dni_series(tmp_path / "t.csv"), plant.site) is None


def test_leap_days_of_a_typical_year(hourly, tmp_path):
    starts, dni, _ = hourly["Tokyo"]
    s = read_dni_series(write_sam(tmp_path / "w.csv", EAST, starts, dni))
    wy = weather_for_year(s, 2024)  # a typical year in a leap year: 8760 h, no 29 February, stated
    assert len(wy.times) == 8760 and wy.annual
    local = wy.times + pd.Timedelta(hours=9)
    assert not ((local.month == 2) & (local.day == 29)).any()
    assert any("no 29 February" in a for a in wy.assumptions)
    # a typical year with 29 February (February of a leap year) in a non-leap year: that day dropped, stated
    leap = starts[(starts.month == 2) & (starts.day == 28)] + pd.Timedelta(days=1)
    feb29 = pd.DatetimeIndex([t.replace(year=1996, month=2, day=29) for t in leap])
    rows = starts.append(feb29).sort_values()
    values = np.append(dni, dni[(starts.month == 2) & (starts.day == 28)])[np.argsort(starts.append(feb29))]
    path = tmp_path / "leap.csv"
    with open(path, "w") as fh:
        fh.write("Source,Location ID,City,State,Country,Latitude,Longitude,Time Zone,Elevation\n")
        fh.write(f"t,0,Tokyo,-,JPN,{EAST['lat']},{EAST['lon']},9,40\nYear,Month,Day,Hour,DNI\n")
        for t, v in zip(rows, values):
            fh.write(f"{1996 if t.month == 2 else YEARS[t.month - 1]},{t.month},{t.day},{t.hour},{v}\n")
    s = read_dni_series(path)
    assert s.typical and len(s.times) == 8784
    wy = weather_for_year(s, 2023)
    assert len(wy.times) == 8760 and any("29 February dropped" in a for a in wy.assumptions)


def test_files_that_are_not_weather_are_one_line_errors_naming_them(tmp_path, capsys):
    import h5py

    (tmp_path / "image.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4)
    with h5py.File(tmp_path / "plant.h5", "w") as f:
        f["x"] = np.arange(3)
    (tmp_path / "prices.csv").write_text("hour,price_eur\n1,50\n2,60\n")
    (tmp_path / "noise.bin").write_bytes(bytes(np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8)))
    for name, needle in (("image.png", "PNG"), ("plant.h5", "HDF5"), ("prices.csv", "not a weather file"),
                         ("noise.bin", "not a weather file")):
        with pytest.raises(InputFileError, match=name) as info:
            read_dni_series(tmp_path / name)
        assert needle in str(info.value) and "\n" not in str(info.value)
    plant, atm = demo_field_plant(4)
    sc = save_scenario(plant, tmp_path / "p.h5", extras=atm.to_extras())
    code, _, err = run_cli(capsys, "field", "--scenario", sc, "--year", 2023, "--weather", tmp_path / "image.png",
                           "--json", tmp_path / "y.json")
    assert_one_line_error(code, err, "image.png", "PNG")


def test_no_library_warning_reaches_the_user(hourly, tmp_path, recwarn, monkeypatch):
    starts, dni, at30 = hourly["Tokyo"]
    # pandas and pvlib warn as they please (a DtypeWarning on a mixed column, a deprecation): made to here
    read_csv = pd.read_csv

    def noisy(*args, **kwargs):
        warnings.warn("Columns (2) have mixed types", pd.errors.DtypeWarning, stacklevel=2)
        warnings.warn("a deprecated pandas thing", FutureWarning, stacklevel=2)
        return read_csv(*args, **kwargs)

    monkeypatch.setattr(pd, "read_csv", noisy)
    # a TMY3 with a mixed-type column (pandas' DtypeWarning on a plain read: the issue's first symptom)
    with open(TMY3) as fh:
        lines = fh.read().splitlines(keepends=True)
    lines[5000] = lines[5000].replace(",A,7,", ",x,7,", 1)
    (tmp_path / "mixed.csv").write_text("".join(lines))
    files = [TMY3, TMY2, tmp_path / "mixed.csv", write_epw(tmp_path / "w.epw", EAST, starts, dni),
             write_sam(tmp_path / "s.csv", EAST, starts, dni, "location", "Beam"),
             write_psm3(tmp_path / "p.csv", EAST, starts, at30)]
    for path in files:
        weather_for_year(read_dni_series(path), 2024)
    assert [str(w.message) for w in recwarn] == []


def test_field_year_and_predict_read_a_tmy3_with_its_convention_share_and_site(tmp_path, capsys):
    plant, atm = demo_field_plant(4)  # at Jülich: Greensboro's TMY3 is ~6,900 km away
    sc = save_scenario(plant, tmp_path / "p.h5", extras=atm.to_extras())
    code, out, err = run_cli(capsys, "field", "--scenario", sc, "--year", 2023, "--weather", TMY3, "--json",
                             tmp_path / "y.json", "--table-azimuth-step", 90)
    assert code == 0, err
    rep = json.loads((tmp_path / "y.json").read_text())
    assert rep["annual"] and rep["time_convention"].startswith("TMY3: local standard time (UTC-05:00")
    assert rep["dni_source"]["time_convention"] == rep["time_convention"] and rep["dni_source"]["typical_year"]
    # Greensboro's hours at Jülich's sun: the share says the site is wrong, the warning says why
    assert rep["site_offset_km"] == pytest.approx(6900, rel=0.05) and rep["dni_share_below_horizon"] > 0.05
    warn = [ln for ln in err.splitlines() if ln.startswith("heliotwin: warning: ")]
    assert len(warn) == 1 and "723170TYA.CSV" in warn[0] and "36.100 N, 79.950 W" in warn[0]
    assert rep["warnings"] == [warn[0].removeprefix("heliotwin: warning: ")]
    # predict reads the same file through the same code and states the same
    series = {"time": ["2023-06-21T17:00:00+00:00"], "power_w": [1000.0]}
    e = prediction_energy(series, plant, 900.0, "1h", TMY3, 2023)
    assert e["time_convention"] == rep["time_convention"] and e["warnings"] == rep["warnings"]
    assert e["dni_share_below_horizon"] == pytest.approx(rep["dni_share_below_horizon"])


def test_the_tmy3_at_its_own_site_has_no_warning_and_the_sun_up(tmp_path):
    s = read_dni_series(TMY3)
    wy, share = _share(s, 2023, {"lat": 36.1, "lon": -79.95, "alt": 273.0})
    assert share <= LIMIT and site_warning(s, 36.1, -79.95) is None and site_offset_km(s, 36.1, -79.95) < 1e-6
