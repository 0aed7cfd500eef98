"""NREL's solar position algorithm (SPA) as pvlib implements it in NumPy, without pvlib's package import.

A command that needs the sun at a few instants should not pay for ``import pvlib`` (~0.5 s: its package imports
pull in pandas-heavy modules and scipy.integrate). pvlib's SPA lives in one self-contained module,
``pvlib/spa.py`` (NumPy only); this module loads *that file of the installed pvlib* under a private name,
without executing ``pvlib/__init__``: the code and numbers are pvlib's own (no copy here), so a pvlib upgrade
is picked up as it is. :func:`heliotwin.sun.solar_position` calls :func:`solar_position_numpy` as
``pvlib.solarposition.get_solarposition(method="nrel_numpy")`` does; ``tests/test_site_sun.py`` checks the two
agree.

Reda, I. and Andreas, A., Solar position algorithm for solar radiation applications, Solar Energy 76 (2004)
577-589 (corrigendum: Solar Energy 81 (2007) 838).
"""
from __future__ import annotations

import importlib.util
import os

__all__ = ["solar_position_numpy", "spa_module"]


def spa_module():
    """The installed pvlib's ``spa`` module, loaded from its file as ``heliotwin._pvlib_spa`` (pvlib's package
    ``__init__`` is not run). Raises ImportError when pvlib is not installed."""
    spec = importlib.util.find_spec("pvlib")  # a top-level name: found, not imported
    if spec is None or not spec.submodule_search_locations:
        raise ImportError("heliotwin needs pvlib (its NREL SPA gives the sun's position)")
    path = os.path.join(list(spec.submodule_search_locations)[0], "spa.py")
    spa_spec = importlib.util.spec_from_file_location("heliotwin._pvlib_spa", path)
    module = importlib.util.module_from_spec(spa_spec)
    spa_spec.loader.exec_module(module)
    return module


#: ``pvlib.spa.solar_position_numpy``: (unixtime [s], lat, lon [deg], elev [m], pressure [mbar], temp [degC],
#: delta_t [s], atmos_refract [deg], numthreads) -> apparent zenith, zenith, apparent elevation, elevation,
#: azimuth (from north, clockwise), equation of time [deg, min].
solar_position_numpy = spa_module().solar_position_numpy
