"""Scenario files (HDF5 round trips, versioning, atomic writes) and the embedded demo plant."""
from __future__ import annotations

import dataclasses
import math
import os
import re

import h5py
import numpy as np
import pytest
import torch

from heliotwin.errors import HeliotwinError, InputFileError, ScenarioVersionError
from heliotwin.field import demo as demo_mod
from heliotwin.field import kinematics as kin_ops
from heliotwin.field.demo import demo_plant, demo_targets
from heliotwin.field.facets import facet_normals, ideal_surfaces, receiver_canting
from heliotwin.field.plant import Kinematics, Plant, Surfaces
from heliotwin.field.targets import CylinderTarget, PlanarTarget
from heliotwin.io import scenario as sc
from heliotwin.io.scenario import FORMAT, VERSION, load_scenario, provenance_entry, save_scenario, scenario_from_paint
from heliotwin.site import JUELICH_REFERENCE
from heliotwin.sun import direction_from_paint_angles


# ============================================================================================== helpers
def assert_same(a, b, where=""):
    """Recursive exact equality: tensors bit for bit (NaN == NaN) with equal dtypes, dataclasses field-wise."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor), where
        torch.testing.assert_close(b, a, rtol=0, atol=0, equal_nan=True, msg=lambda m: f"{where}: {m}")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype, where
        np.testing.assert_array_equal(a, b, err_msg=where)
    elif dataclasses.is_dataclass(a):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), where
        for k in a:
            assert_same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert list(a) == list(b), where
    elif isinstance(a, float) and math.isnan(a):
        assert isinstance(b, float) and math.isnan(b), where
    else:
        assert type(a) is type(b) and a == b, f"{where}: {a!r} != {b!r}"


def leftovers(folder, keep=()) -> list[str]:
    return sorted(p for p in os.listdir(folder) if p not in keep)


@pytest.fixture(scope="module")
def demo():
    return demo_plant(12, seed=0)


@pytest.fixture(scope="module")
def paint_plant(paint_dir):
    return scenario_from_paint(paint_dir)


# ========================================================================================== round trips
def test_demo_round_trip_with_extras_and_metadata(demo, tmp_path):
    extras = {
        "axis_offsets": torch.randn(12, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)),
        "mask": torch.tensor([True, False, True]),
        "steps": torch.arange(6, dtype=torch.int64).reshape(3, 2),
        "loss_curve": np.linspace(1.0, 0.1, 5, dtype=np.float32),
        "per_heliostat": {"AA36": {"tilt": torch.tensor([1e-3, -2e-4], dtype=torch.float32)}, "lr": 0.01},
        "epochs": 300, "converged": True, "optimizer": "adam",
    }
    meta = {"source": "/data/paint", "heliostats": ["AA39", "AK32"], "rmse_mrad": 0.73, "n": 3, "ok": False,
            "config": {"a": [1, 2], "b": None}}
    path = save_scenario(demo, tmp_path / "demo.h5", extras=extras, metadata=meta)
    assert path == tmp_path / "demo.h5" and leftovers(tmp_path) == ["demo.h5"]
    scenario = load_scenario(path)
    plant, ex, md = scenario  # unpacks as a tuple
    assert scenario.version == VERSION and scenario.path == str(path)
    assert_same(demo, plant, "plant")
    assert_same(extras, ex, "extras")
    assert md["created_by"].startswith("heliotwin ") and re.match(r"\d{4}-\d\d-\d\dT", md["created_utc"])
    assert {k: md[k] for k in meta} == meta
    with h5py.File(path, "r") as h5:
        assert h5.attrs["format"] == FORMAT and h5.attrs["version"] == VERSION == 2
        assert h5["field/kinematics/clockwise"].dtype == np.bool_
        assert h5["field/kinematics/position"].dtype == np.float64


def test_learned_state_and_provenance_round_trip(demo, tmp_path):
    learned = {"calibration": {"method": "lm", "heliostats": ["AA36", "AB38"], "parameter_names": ["a", "b"],
                               "deviations": torch.tensor([[1e-3, -2e-3], [0.0, 5e-4]], dtype=torch.float64),
                               "networks": {"AA36": {"config": '{"hidden": 4}',
                                                     "state": {"w": torch.ones(4, 2, dtype=torch.float32)}}}}}
    steps = [provenance_entry("from-paint", source="/data/paint"),
             provenance_entry("calibrate", method="lm", records={"AA36": [1, 2, 3]})]
    path = save_scenario(demo, tmp_path / "l.h5", learned=learned, provenance=steps)
    sc = load_scenario(path)
    assert_same(learned, sc.learned, "learned")
    assert sc.provenance == steps
    assert [p["step"] for p in sc.provenance] == ["from-paint", "calibrate"]
    assert all(p["heliotwin"] and re.match(r"\d{4}-\d\d-\d\dT", p["utc"]) for p in sc.provenance)
    # a nominal plant has no learned state and no provenance
    bare = load_scenario(save_scenario(demo, tmp_path / "n.h5"))
    assert bare.learned == {} and bare.provenance == []


def test_version_1_files_still_load(demo, tmp_path):
    path = save_scenario(demo, tmp_path / "v1.h5", extras={"x": torch.zeros(2)})
    with h5py.File(path, "a") as h5:
        h5.attrs["version"] = 1
    sc = load_scenario(path)
    assert sc.version == 1 and sc.learned == {} and sc.provenance == []
    assert_same(demo, sc.plant, "plant")


def test_bad_provenance_is_one_line_error(demo, tmp_path):
    with pytest.raises(HeliotwinError, match=r"\[/provenance\]: not strict JSON"):
        save_scenario(demo, tmp_path / "p.h5", provenance=[{"x": float("nan")}])
    assert leftovers(tmp_path) == []
    path = save_scenario(demo, tmp_path / "p.h5", provenance=[{"step": "x"}])
    with h5py.File(path, "a") as h5:
        del h5["provenance"]
        h5.create_dataset("provenance", data="{not json", dtype=h5py.string_dtype("utf-8"))
    assert _error(path).field == "/provenance"


def test_paint_plant_round_trip(paint_plant, paint_dir, tmp_path):
    assert len(paint_plant.field.ids) == 30
    path = save_scenario(paint_plant, tmp_path / "paint.h5", metadata={"source": paint_dir})
    plant, extras, meta = load_scenario(path)
    assert_same(paint_plant, plant, "plant")
    assert list(plant.targets) == list(paint_plant.targets)  # order kept
    assert isinstance(plant.targets["receiver"], CylinderTarget)
    assert isinstance(plant.targets["multi_focus_tower"], PlanarTarget)
    assert extras == {} and meta["source"] == str(paint_dir)
    # float64 exactly: the ENU positions survive bit for bit
    assert plant.field.kinematics.position.dtype == torch.float64
    assert torch.equal(plant.field.kinematics.position.view(torch.int64),
                       paint_plant.field.kinematics.position.view(torch.int64))


def test_round_trip_keeps_dtypes_weights_degrees_and_nan(demo, tmp_path):
    f = demo.field
    weights = torch.rand(f.surfaces.control_points.shape[:-1], generator=torch.Generator().manual_seed(1)) + 0.5
    kin = f.kinematics.to(dtype=torch.float32).replace(min_angle=torch.full((12, 2), float("nan")))
    cp = f.surfaces.control_points.to(torch.float32).requires_grad_()
    surfaces = Surfaces(cp, 3, 1, weights)  # degree (3, 1) on a 4 x 4 net, rational
    field = dataclasses.replace(f, kinematics=kin, surfaces=surfaces)
    plant = dataclasses.replace(demo, field=field, sun=dataclasses.replace(demo.sun, sunshape="pillbox", dni=812.5))
    loaded = load_scenario(save_scenario(plant, tmp_path / "p.h5")).plant
    assert_same(plant, loaded)
    assert loaded.field.kinematics.position.dtype == torch.float32
    assert loaded.field.kinematics.linear.dtype == torch.bool
    assert loaded.field.surfaces.weights.dtype == torch.float32
    assert (loaded.field.surfaces.degree_u, loaded.field.surfaces.degree_v) == (3, 1)
    assert not loaded.field.surfaces.control_points.requires_grad


def test_overwrite_replaces_atomically(demo, tmp_path):
    path = tmp_path / "s.h5"
    save_scenario(demo, path, metadata={"run": 1})
    os.chmod(path, 0o640)
    save_scenario(demo, path, metadata={"run": 2})
    assert load_scenario(path).metadata["run"] == 2
    assert os.stat(path).st_mode & 0o777 == 0o640  # an existing file's permissions are kept
    assert leftovers(tmp_path) == ["s.h5"]


# ============================================================================================ bad files
def _error(path, cls=InputFileError):
    with pytest.raises(cls) as exc:
        load_scenario(path)
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg
    return exc.value


def test_missing_folder_and_text_files(tmp_path):
    e = _error(tmp_path / "nope.h5")
    assert "not found" in str(e)
    _error(tmp_path)  # a folder
    text = tmp_path / "scenario.h5"
    text.write_text("this is not HDF5\n")
    e = _error(text)
    assert not isinstance(e, ScenarioVersionError) and "not an HDF5 file" in str(e)
    npz = tmp_path / "x.h5"
    np.savez(npz, a=np.zeros(3))
    os.replace(str(npz) + ".npz", npz)
    _error(npz)


def test_truncated_file(demo, tmp_path):
    path = save_scenario(demo, tmp_path / "s.h5")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    _error(path)


def test_another_hdf5_format(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("flux", data=np.zeros((4, 4)))
    e = _error(path, ScenarioVersionError)
    assert e.field == "/@format" and "not a heliotwin scenario" in str(e)
    with h5py.File(path, "a") as h5:
        h5.attrs["format"] = "artist-scenario"
    assert "artist-scenario" in str(_error(path, ScenarioVersionError))


@pytest.mark.parametrize("version, words", [(0, "older"), (3, "newer"), ("1", "non-integer"), (1.5, "non-integer")])
def test_wrong_version(demo, tmp_path, version, words):
    path = save_scenario(demo, tmp_path / "s.h5")
    with h5py.File(path, "a") as h5:
        h5.attrs["version"] = version
    e = _error(path, ScenarioVersionError)
    assert e.field == "/@version" and words in str(e)


def _edit(path, fn):
    with h5py.File(path, "a") as h5:
        fn(h5)


@pytest.mark.parametrize("edit, field", [
    (lambda h5: h5.__delitem__("sun"), "/sun"),
    (lambda h5: h5.__delitem__("field/kinematics/linear"), "/field/kinematics/linear"),
    (lambda h5: h5.__delitem__("field/surfaces/control_points"), "/field/surfaces/control_points"),
    (lambda h5: h5["targets/receiver"].__delitem__("up"), "/targets/receiver/up"),
    (lambda h5: h5["site"].attrs.__delitem__("latitude_deg"), "/site@latitude_deg"),
    (lambda h5: h5["site"].attrs.__setitem__("latitude_deg", "fifty"), "/site@latitude_deg"),
    (lambda h5: h5["targets/receiver"].attrs.__setitem__("kind", "sphere"), "/targets/receiver@kind"),
    (lambda h5: h5["field/surfaces"].attrs.__delitem__("degree_u"), "/field/surfaces@degree_u"),
    (lambda h5: (h5["field/kinematics"].__delitem__("position"),
                 h5["field/kinematics"].create_dataset("position", data=np.zeros((12, 2)))),
     "/field/kinematics/position"),
    (lambda h5: (h5["field/kinematics"].__delitem__("linear"),
                 h5["field/kinematics"].create_dataset("linear", data=np.ones((12, 2)))), "/field/kinematics/linear"),
    (lambda h5: (h5["field"].__delitem__("ids"), h5["field"].create_dataset("ids", data=np.arange(12))), "/field/ids"),
    (lambda h5: (h5["field"].__delitem__("ids"),
                 h5["field"].create_dataset("ids", data=[f"AA{i:02d}" for i in range(11)], dtype=h5py.string_dtype())),
     "/field/surfaces/control_points"),  # the first per-heliostat dataset, refused before it is read
    (lambda h5: (h5["field/facets"].__delitem__("canting_e"),
                 h5["field/facets"].create_group("canting_e")), "/field/facets/canting_e"),
    (lambda h5: (h5["field/facets"].__delitem__("translation"),
                 h5["field/facets"].create_dataset("translation", data="abc", dtype=h5py.string_dtype())),
     "/field/facets/translation"),
])
def test_missing_or_bad_objects(demo, tmp_path, edit, field):
    path = save_scenario(demo, tmp_path / "s.h5")
    _edit(path, edit)
    e = _error(path)
    assert not isinstance(e, ScenarioVersionError)
    assert e.field == field, str(e)


# ======================================================================================= atomic writing
def test_failure_mid_write_leaves_no_file(demo, tmp_path, monkeypatch):
    calls = []

    def broken(group, obj, path, where):  # fail after site, targets and part of the field are written
        calls.append(where)
        if where == "/field/facets":
            raise RuntimeError("disk on fire")
        return original(group, obj, path, where)

    original = sc._write_dataclass
    monkeypatch.setattr(sc, "_write_dataclass", broken)
    with pytest.raises(RuntimeError, match="disk on fire"):
        save_scenario(demo, tmp_path / "s.h5")
    assert "/field/kinematics" in calls  # it really failed mid-write
    assert leftovers(tmp_path) == []


def test_failure_keeps_the_previous_file(demo, tmp_path, monkeypatch):
    path = save_scenario(demo, tmp_path / "s.h5", metadata={"run": 1})
    before = path.read_bytes()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(sc, "_write_extras", interrupted)
    with pytest.raises(KeyboardInterrupt):
        save_scenario(demo, path, extras={"x": torch.zeros(2)}, metadata={"run": 2})
    assert path.read_bytes() == before and leftovers(tmp_path) == ["s.h5"]
    assert load_scenario(path).metadata["run"] == 1


def test_failing_rename_is_a_clean_error(demo, tmp_path, monkeypatch):
    def no_replace(src, dst):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(sc.os, "replace", no_replace)
    with pytest.raises(InputFileError, match="cannot write") as exc:
        save_scenario(demo, tmp_path / "s.h5")
    assert "\n" not in str(exc.value)
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("extras, metadata, words", [
    ({"model": object()}, None, "/extras/model"),
    ({"a/b": torch.zeros(1)}, None, "'a/b'"),
    ({"half": torch.zeros(2, dtype=torch.bfloat16)}, None, "bfloat16"),
    (None, {"when": object()}, "/metadata@when"),
])
def test_unsupported_extras_or_metadata(demo, tmp_path, extras, metadata, words):
    with pytest.raises(HeliotwinError, match=re.escape(words)):
        save_scenario(demo, tmp_path / "s.h5", extras=extras, metadata=metadata)
    assert leftovers(tmp_path) == []


def test_inconsistent_plant_is_rejected_before_writing(demo, tmp_path):
    kin = demo.field.kinematics.replace(position=demo.field.kinematics.position[:5])
    bad = dataclasses.replace(demo, field=dataclasses.replace(demo.field, kinematics=kin))
    with pytest.raises(HeliotwinError, match=re.escape("[/field/kinematics/position]")):
        save_scenario(bad, tmp_path / "s.h5")
    clockwise = demo.field.kinematics.replace(clockwise=demo.field.kinematics.clockwise.double())
    bad = dataclasses.replace(demo, field=dataclasses.replace(demo.field, kinematics=clockwise))
    with pytest.raises(HeliotwinError, match="bool"):
        save_scenario(bad, tmp_path / "s.h5")
    with pytest.raises(InputFileError, match="cannot write"):
        save_scenario(demo, tmp_path / "no" / "such" / "folder" / "s.h5")
    assert leftovers(tmp_path) == []


# ============================================================================================ demo plant
def test_demo_is_deterministic_and_uses_no_global_rng():
    torch_state, np_state = torch.random.get_rng_state(), np.random.get_state()
    a, b, c = demo_plant(20, seed=3), demo_plant(20, seed=3), demo_plant(20, seed=4)
    assert torch.equal(torch.random.get_rng_state(), torch_state)
    assert np.array_equal(np.random.get_state()[1], np_state[1])
    assert_same(a, b)
    assert a.field.ids != c.field.ids or not torch.equal(a.field.kinematics.position, c.field.kinematics.position)


def test_demo_field_layout_and_types():
    plant = demo_plant(500, seed=0)
    f, k = plant.field, plant.field.kinematics
    assert isinstance(plant, Plant) and plant.site.reference == JUELICH_REFERENCE
    assert len(f.ids) == 500 == len(set(f.ids)) and f.ids == sorted(f.ids)
    assert all(re.fullmatch(r"[A-Z]{2}[0-9]{2}", i) for i in f.ids)
    assert k.position.dtype == torch.float64 and k.clockwise.dtype == torch.bool and k.linear.all()
    east, north, up = k.position.unbind(-1)
    assert east.abs().max() < 60.2 and north.min() > 20.0 and north.max() < 155.0
    assert up.min() >= 1.45 and up.max() <= 1.80
    # neighbours never collide (characteristic diameter sqrt(3.22^2 + 2.56^2) = 4.11 m)
    d = torch.cdist(k.position[:, :2], k.position[:, :2]) + torch.eye(500, dtype=torch.float64) * 1e9
    assert d.min() > 4.11
    assert torch.equal(k.concentrator_translation,
                       torch.tensor([[0.0, 0.175, 0.0]], dtype=torch.float64).expand(500, 3))
    assert torch.equal(k.clockwise, torch.tensor([[False, True]]).expand(500, 2))
    assert (k.min_steps == 0).all()
    assert (k.max_steps[:, 0] >= 68400).all() and (k.max_steps[:, 1] <= 76100).all()
    assert torch.allclose(k.increment, torch.full_like(k.increment, 154166.6667))
    assert (k.min_angle < k.max_angle).all()
    assert f.facets.translation.shape == (500, 4, 3)
    assert f.surfaces.control_points.shape == (500, 4, 4, 4, 3) and f.surfaces.weights is None
    assert_same(ideal_surfaces(f.facets), f.surfaces)
    more = demo_plant(700, seed=0)  # more than the 22-150 m field holds: rows continue northwards
    assert len(set(more.field.ids)) == 700 and more.field.kinematics.position[:, 1].max() > 150.0
    for bad in (0, -3, 2.5, True):
        with pytest.raises(HeliotwinError):
            demo_plant(bad)


def test_demo_targets_are_juelich_like():
    t = demo_targets()
    assert list(t) == ["solar_tower_juelich_upper", "solar_tower_juelich_lower", "multi_focus_tower", "receiver"]
    for name, centre, size in [("solar_tower_juelich_upper", (0.0, -3.24, 43.1), (8.6, 7.2)),
                               ("solar_tower_juelich_lower", (0.0, -3.24, 35.9), (8.6, 7.2)),
                               ("multi_focus_tower", (-17.6, -2.75, 52.0), (5.4, 6.4))]:
        p = t[name]
        assert isinstance(p, PlanarTarget)
        assert torch.allclose(p.center, torch.tensor(centre, dtype=torch.float64), atol=0.05)
        assert torch.allclose(p.normal, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
        assert abs(p.width - size[0]) < 0.05 and abs(p.height - size[1]) < 0.05
    r = t["receiver"]
    assert isinstance(r, CylinderTarget) and r.radius == 4.14 and abs(math.degrees(r.opening_angle) - 60) < 1e-12
    assert torch.allclose(r.normal, torch.tensor([0.0, 0.90630779, -0.42261826], dtype=torch.float64), atol=1e-8)
    assert abs(float(r.up @ r.normal)) < 1e-12 and 54.5 < float(r.center[2]) < 55.5


def test_demo_targets_match_the_paint_tower(paint_plant):
    demo_t = demo_targets()
    for name, target in paint_plant.targets.items():
        d = demo_t[name]
        for attr in ("center", "normal", "right", "up"):
            assert torch.allclose(getattr(d, attr), getattr(target, attr), atol=1e-3), (name, attr)
        assert abs(d.width - target.width) < 1e-3 and abs(d.height - target.height) < 1e-3


def test_receiver_canting_reproduces_paint(paint_plant):
    """PAINT's AA39 facets are canted for a 65 m focus; the same construction gives the same spans."""
    i = paint_plant.field.index_of("AA39")
    fac = paint_plant.field.facets
    e, n = receiver_canting(fac.translation[i:i + 1], demo_mod.FACET_HALF_WIDTH, demo_mod.FACET_HALF_HEIGHT,
                            torch.tensor([65.0], dtype=torch.float64))
    assert torch.allclose(e, fac.canting_e[i:i + 1], atol=2e-7)  # PAINT stores float32-rounded values
    assert torch.allclose(n, fac.canting_n[i:i + 1], atol=2e-7)


def test_demo_facets_focus_at_the_slant_range(demo):
    f, k = demo.field, demo.field.kinematics
    assert torch.allclose(f.facets.canting_e.norm(dim=-1), torch.full((12, 4), 0.8025, dtype=torch.float64))
    assert torch.allclose(f.facets.canting_n.norm(dim=-1), torch.full((12, 4), 0.6375, dtype=torch.float64))
    assert (f.facets.canting_e[..., 1] == 0).all()  # PAINT's construction
    slant = (demo.targets["receiver"].center - k.position).norm(dim=-1)
    # A ray along -e_z reflected at each facet centre crosses the heliostat axis at height ~ slant range.
    n = facet_normals(f.facets.canting_e, f.facets.canting_n)
    d = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    r = d - 2 * (n @ d)[..., None] * n
    t = -f.facets.translation[..., 0] / r[..., 0]
    focus = f.facets.translation[..., 2] + t * r[..., 2]
    assert torch.allclose(focus, slant[:, None].expand(12, 4), rtol=2e-3)
    assert 40.0 < float(slant.min()) and float(slant.max()) < 200.0


def test_demo_heliostats_can_aim_at_the_receiver(demo):
    """Inverse kinematics lands inside the motor range and the forward pose reflects the sun onto the aim."""
    k = demo.field.kinematics
    sun = direction_from_paint_angles(math.radians(20.0), math.radians(45.0)).expand(12, 3)
    aim = demo.targets["receiver"].center.expand(12, 3)
    steps, reachable = kin_ops.inverse(k, aim, sun)
    assert reachable.all()
    rot, conc = kin_ops.forward(k, steps)
    normal = kin_ops.mirror_normal(rot)
    reflected = -sun + 2 * (normal * sun).sum(-1, keepdim=True) * normal
    to_aim = (aim - conc) / (aim - conc).norm(dim=-1, keepdim=True)
    assert torch.allclose(reflected, to_aim, atol=1e-9)


def test_demo_round_trips_through_a_scenario(tmp_path):
    plant = demo_plant(3, seed=7, num_control_points=(5, 6), degree=(3, 2))
    assert plant.field.surfaces.control_points.shape == (3, 4, 5, 6, 3)
    assert_same(plant, load_scenario(save_scenario(plant, tmp_path / "d.h5")).plant)


def test_kinematics_fields_all_saved(demo, tmp_path):
    path = save_scenario(demo, tmp_path / "s.h5")
    with h5py.File(path, "r") as h5:
        assert set(h5["field/kinematics"]) == {f.name for f in dataclasses.fields(Kinematics)}
