"""The PAINT folder writer: each file's bytes are what ``json.dumps`` of the record's / heliostat's dict gives
(the format the reader and PAINT's own files follow), however the writer batches its formatting."""
from __future__ import annotations

import json
import os

import torch

from heliotwin.io.records import SOURCES
from heliotwin.simulate import SimulationSettings, simulate_plant, write_paint_folder, writer
from heliotwin.simulate.writer import _lla


def _reference_properties(kin, facets, width, height, lla, h: int) -> dict:
    """A heliostat's properties dict built value by value from the tensors (the writer's earlier form)."""
    acts = [{"type_axis": "linear" if bool(kin.linear[h, a]) else "ideal",
             "min_increment": float(kin.min_steps[h, a]), "max_increment": float(kin.max_steps[h, a]),
             "increment": float(kin.increment[h, a]), "offset_shift": 0,
             "initial_stroke_length": float(kin.initial_stroke_length[h, a]),
             "offset": float(kin.offset[h, a]), "pivot_radius": float(kin.pivot_radius[h, a]),
             "radius_shift": 0, "clockwise_axis_movement": int(bool(kin.clockwise[h, a])),
             "initial_angle": float(kin.initial_angle[h, a]),
             "min_movement_angle": float(kin.min_angle[h, a]), "max_movement_angle": float(kin.max_angle[h, a]),
             "movement_speed": 0} for a in range(2)]
    kp = {"actuators": acts}
    for j in range(2):
        for i, ax in enumerate("enu"):
            kp[f"joint_translation_{ax}_{j + 1}"] = float(kin.joint_translation[h, j, i])
    for i, ax in enumerate("enu"):
        kp[f"concentrator_translation_{ax}"] = float(kin.concentrator_translation[h, i])
    fac = [{"translation_vector": facets.translation[h, f].tolist(), "canting_e": facets.canting_e[h, f].tolist(),
            "canting_n": facets.canting_n[h, f].tolist()} for f in range(facets.translation.shape[1])]
    return {"heliostat_position": lla, "height": float(height), "width": float(width),
            "initial_orientation": [0.0, -1.0, 0.0], "kinematic_properties": kp,
            "facet_properties": {"canting_type": "receiver canting", "number_of_facets": len(fac), "facets": fac},
            "renovation": ""}


def test_written_files_are_json_dumps_of_each_record_byte_for_byte(tmp_path, monkeypatch):
    monkeypatch.setattr(writer, "_RECORD_BLOCK", 40)  # several blocks of heliostats, one heliostat over a block
    sim = simulate_plant(SimulationSettings(heliostats=7, seed=11, years=0.5, records_per_month=6,
                                            utis_missing=0.3))
    root = write_paint_folder(sim, tmp_path / "plant")
    plant, rec = sim.plant, sim.records
    fl = plant.field
    assert (~torch.isfinite(rec.focal_spots).all(-1)).any(), "the case must have a missing focal spot (null)"
    pos = _lla(plant.site, fl.kinematics.position.double()).tolist()
    for h, hid in enumerate(fl.ids):
        path = os.path.join(root, hid, "Properties", f"{hid}-heliostat-properties.json")
        want = json.dumps(_reference_properties(fl.kinematics, fl.facets, fl.width[h], fl.height[h], pos[h], h),
                          indent=2)
        assert open(path, "rb").read() == want.encode("utf-8")
    r = len(rec)
    spots = _lla(plant.site, torch.nan_to_num(rec.focal_spots.reshape(-1, 3))).reshape(r, 2, 3)
    written = 0
    for i in range(r):
        hid = fl.ids[int(rec.heliostat_index[i])]
        present = torch.isfinite(rec.focal_spots[i]).all(-1)
        doc = {"motor_position": {"axis_1_motor_position": int(rec.motor_steps[i, 0]),
                                  "axis_2_motor_position": int(rec.motor_steps[i, 1])},
               "target_name": rec.target[i],
               "focal_spot": {src: (spots[i, k].tolist() if bool(present[k]) else None)
                              for k, src in enumerate(SOURCES)},
               "sun_elevation": float(torch.rad2deg(rec.sun_elevation[i])),
               "sun_azimuth": float(torch.rad2deg(rec.sun_azimuth[i]))}
        path = os.path.join(root, hid, "Calibration", f"{int(rec.record_id[i])}-calibration-properties.json")
        assert open(path, "rb").read() == json.dumps(doc).encode("utf-8")
        written += 1
    on_disk = sum(len([f for f in os.listdir(os.path.join(root, hid, "Calibration")) if f.endswith(".json")])
                  for hid in fl.ids)
    assert written == on_disk == r > 50
    assert oct(os.stat(path).st_mode & 0o777) == oct(0o666 & ~_umask())


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
