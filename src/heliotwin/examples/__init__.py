"""Example inputs shipped with the package, so that the README's commands run on a fresh install.

* ``layout.csv``: 300 heliostats in a radial-staggered field north of the tower (the embedded demo field's
  first 300 positions), as SolarPILOT writes a layout (``id, x_location, y_location, z_location``; east,
  north, up [m] about the tower base).
* ``plant.toml``: the plant description ``heliotwin scenario from-layout`` reads with it (Jülich site,
  3.22 x 2.56 m heliostats of 2 x 2 facets canted on-axis, a 360-degree cylinder receiver of radius 4.1 m and
  height 5 m at 55 m, limb-darkened sun at DNI 900 W/m^2, SolarPILOT's default atmosphere).

``heliotwin examples`` lists them; ``heliotwin examples --copy DIR`` copies them into ``DIR``.
"""
from __future__ import annotations

import shutil
from importlib import resources
from pathlib import Path

__all__ = ["EXAMPLES", "example_path", "copy_examples"]

#: File name -> what it is.
EXAMPLES = {"layout.csv": "300-heliostat layout (SolarPILOT columns: id, x/y/z_location [m], tower at the origin)",
            "plant.toml": "plant description for `heliotwin scenario from-layout layout.csv --config plant.toml`"}


def example_path(name: str) -> Path:
    """Where the shipped example ``name`` (a key of :data:`EXAMPLES`) lies in the installed package."""
    if name not in EXAMPLES:
        raise KeyError(f"no example named {name!r}; examples: {', '.join(EXAMPLES)}")
    return Path(str(resources.files(__name__).joinpath(name)))


def copy_examples(folder) -> list[Path]:
    """Copy every example into ``folder`` (which must exist); returns the new paths. Refuses to overwrite."""
    folder = Path(folder)
    out = []
    for name in EXAMPLES:
        dest = folder / name
        if dest.exists():
            raise FileExistsError(17, "exists (remove it or copy elsewhere)", str(dest))
        shutil.copyfile(example_path(name), dest)
        out.append(dest)
    return out
