"""Weather files generated in code, as sites deliver them (EPW, SAM CSV in both header layouts, NSRDB PSM3), for
the weather tests and ``benchmarks/bench_year.py``."""
from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pvlib

YEARS = [1977, 1985, 1990, 2005, 1999, 1988, 1996, 2001, 1983, 1979, 2003, 1994]  # one per month, a TMY's way


def clear_dni(site, utc) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loc = pvlib.location.Location(site["lat"], site["lon"], altitude=site["alt"])
        return loc.get_clearsky(pd.DatetimeIndex(utc), model="ineichen")["dni"].to_numpy()


def hour_means(site, starts) -> tuple[np.ndarray, np.ndarray]:
    """Hour-mean clear-sky DNI [W/m^2] (10-min samples) of the local standard hours ``starts`` (naive) and the
    instantaneous DNI at each hour's :30 (NSRDB's stamp), at ``site`` (name, lat, lon, alt, tz)."""
    utc = (starts - pd.Timedelta(hours=site["tz"])).tz_localize("UTC")
    samples = np.stack([clear_dni(site, utc + pd.Timedelta(minutes=m)) for m in (5, 15, 25, 35, 45, 55)])
    return samples.mean(axis=0).round(1), clear_dni(site, utc + pd.Timedelta(minutes=30))


def write_epw(path, site, starts, dni):
    head = [f"LOCATION,{site['name']},-,XXX,TMY,000000,{site['lat']},{site['lon']},{site['tz']:.1f},{site['alt']}",
            "DESIGN CONDITIONS,0", "TYPICAL/EXTREME PERIODS,0", "GROUND TEMPERATURES,0",
            "HOLIDAYS/DAYLIGHT SAVINGS,No,0,0,0", "COMMENTS 1,generated", "COMMENTS 2,clear sky",
            "DATA PERIODS,1,1,Data,Sunday, 1/ 1,12/31"]
    with open(path, "w") as fh:
        fh.write("\n".join(head) + "\n")
        for t, v in zip(starts, dni):  # hour h (1-24) = the hour ending at h:00, local standard time
            row = [YEARS[t.month - 1], t.month, t.day, t.hour + 1, 60, "?9?9?9?9E0?9?9?9*9*9?9*9*9?9*9*9?9*9*9*9",
                   20.0, 10.0, 50, 101325, 0, 1415, 300, 0, v, 0, 0, 0, 0, 0, 180, 2.0, 0, 0, 20.0, 77777, 9,
                   999999999, 10, 0.1, 0, 88, 0.2, 0, 0]
            fh.write(",".join(str(x) for x in row) + "\n")
    return path


def write_sam(path, site, starts, dni, layout="source", column="DNI", minute=False):
    """A SAM CSV: ``layout`` "source" (``Source,Location ID,City,State,...``) or "location" (SolarPILOT's
    ``Location,City,Region,...,Source``); Hour 0-23 = the hour starting there; months of different years."""
    with open(path, "w") as fh:
        if layout == "source":
            fh.write("Source,Location ID,City,State,Country,Latitude,Longitude,Time Zone,Elevation\n")
            fh.write(f"test,0,{site['name']},-,XXX,{site['lat']},{site['lon']},{site['tz']},{site['alt']}\n")
        else:
            fh.write("Location,City,Region,Country,Latitude,Longitude,Time Zone,Elevation,Source\n")
            fh.write(f"000,{site['name']},-,XXX,{site['lat']},{site['lon']},{site['tz']},{site['alt']},test\n")
        fh.write("Year,Month,Day,Hour," + ("Minute," if minute else "") + f"GHI,{column},DHI\n")
        for t, v in zip(starts, dni):
            stamp = f"{t.hour},30," if minute else f"{t.hour},"
            fh.write(f"{YEARS[t.month - 1]},{t.month},{t.day},{stamp}0,{v},0\n")
    return path


def write_psm3(path, site, starts, dni):
    """An NSRDB PSM3 CSV as the API writes it (utc=false): stamps at :30 local standard time, instantaneous."""
    fields = ["Source", "Location ID", "City", "State", "Country", "Latitude", "Longitude", "Time Zone", "Elevation",
              "Local Time Zone", "DNI Units", "Version"]
    values = ["NSRDB", "1", "-", "-", "-", site["lat"], site["lon"], site["tz"], int(site["alt"]), site["tz"],
              "w/m2", "3.2.2"]
    with open(path, "w") as fh:
        fh.write(",".join(fields) + "\n" + ",".join(str(v) for v in values) + "\n")
        fh.write("Year,Month,Day,Hour,Minute,DHI,DNI,GHI,Temperature\n")
        for t, v in zip(starts, dni):
            fh.write(f"2001,{t.month},{t.day},{t.hour},30,0,{v:.1f},0,20\n")
    return path
