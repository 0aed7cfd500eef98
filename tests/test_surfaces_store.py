"""Learned-surface HDF5 round trip and version check."""
from __future__ import annotations

import h5py
import pytest
import torch
from helpers.surfaces import kinematics_at as _kinematics
from helpers.surfaces import small_scene

from heliotwin.errors import InputFileError
from heliotwin.field.plant import SunSettings
from heliotwin.surfaces.learning import LearnableSurface
from heliotwin.surfaces.store import LearnedHeliostat, load_learned, save_learned


def test_round_trip_and_version(tmp_path):
    facets, _, target = small_scene()
    model = LearnableSurface(facets, (5, 5), (2, 2))
    with torch.no_grad():
        model.displacement_mm.fill_(0.3)
    kin = _kinematics([0.0, 20.0, 1.0])
    item = LearnedHeliostat("AA39", model.surfaces(), model.displacement.detach(), facets, kin,
                            {"t": target}, (50.9, 6.39, 87.0), SunSettings(slope_error=2e-3), {"a": 1})
    path = tmp_path / "l.h5"
    save_learned(path, item)
    back = load_learned(path)
    assert back.heliostat_id == "AA39" and back.sun.slope_error == 2e-3
    assert torch.allclose(back.surfaces.control_points, item.surfaces.control_points.detach())
    assert torch.allclose(back.targets["t"].center, target.center)
    with h5py.File(path, "a") as h5:
        h5.attrs["version"] = 99
    with pytest.raises(InputFileError, match="version"):
        load_learned(path)
