"""PAINT reader: the real download, key variants, bad input, and property-based parser robustness."""
from __future__ import annotations

import copy
import json
import math
import shutil
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from heliotwin.errors import InputFileError
from heliotwin.field.plant import Kinematics
from heliotwin.io import paint as P
from heliotwin.site import Site

AA39_RECORD = 151375  # AA39 record with HeliOS and UTIS centroids and both flux PNGs


@pytest.fixture(scope="module")
def dataset(paint_dir):
    return P.load_paint(paint_dir)


@pytest.fixture(scope="module")
def site() -> Site:
    return Site()


def _props_path(root, hid="AA39") -> Path:
    return Path(root) / hid / "Properties" / f"{hid}-heliostat-properties.json"


def _record_path(root, rid=AA39_RECORD, hid="AA39") -> Path:
    return Path(root) / hid / "Calibration" / f"{rid}-calibration-properties.json"


def _load_json(path) -> dict:
    return json.loads(Path(path).read_text())


def _write_json(path, data, text: str | None = None) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1) if text is None else text)
    return path


def _mini_paint(paint_dir, dest, heliostats=("AA39",), calibration=True) -> Path:
    """A PAINT folder in ``dest`` with a few heliostats (JSON only, no PNGs/metadata)."""
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    shutil.copy(P.find_tower_file(paint_dir), dest)
    for h in heliostats:
        shutil.copytree(Path(paint_dir) / h / "Properties", dest / h / "Properties")
        (dest / h / "Calibration").mkdir(parents=True)
        if calibration:
            for f in (Path(paint_dir) / h / "Calibration").glob("*-calibration-properties.json"):
                shutil.copy(f, dest / h / "Calibration")
    return dest


def _assert_clean_error(exc_info, path, field: str | None):
    msg = str(exc_info.value)
    assert "\n" not in msg
    assert str(path) in msg
    if field is not None:
        assert f"[{field}]" in msg, msg
        assert exc_info.value.field == field


# ============================================================================================ real data
def test_real_download_counts(dataset):
    ids = dataset.plant.field.ids
    assert len(ids) == 30 and ids == sorted(ids)
    assert len(dataset.records) == 1704
    aa39 = dataset.records_of("AA39")
    assert len(aa39) == 18
    assert sum(p is not None for p in aa39.flux_png) == 10
    assert all(Path(p).is_file() for p in aa39.flux_png if p)
    assert aa39.record_id.tolist() == sorted(aa39.record_id.tolist())
    assert dataset.skipped == []  # every real record passes the record table's checks
    kin = dataset.plant.field.kinematics
    assert kin.num_heliostats == 30 and kin.position.dtype == torch.float64
    assert kin.clockwise.dtype == torch.bool and kin.linear.dtype == torch.bool
    assert dataset.plant.field.facets.translation.shape == (30, 4, 3)
    assert set(dataset.plant.targets) == {"solar_tower_juelich_upper", "solar_tower_juelich_lower",
                                          "multi_focus_tower", "receiver"}


def test_real_records_sources_and_metadata(dataset):
    t = dataset.records
    has = torch.isfinite(t.focal_spots).all(-1)  # [R, 2]: HeliOS, UTIS
    assert int((has[:, 0] & ~has[:, 1]).sum()) > 0  # HeliOS-only records exist in the real data
    assert int((has[:, 0] & has[:, 1]).sum()) > 0
    utis = t.with_focal_spot("UTIS")
    helios_only = has[:, 0] & ~has[:, 1]
    assert torch.equal(utis.spot[helios_only], t.focal_spots[helios_only, 0])  # falls back to HeliOS
    assert set(utis.source[i] for i in helios_only.nonzero().flatten().tolist()) == {"HeliOS"}
    assert torch.equal(utis.spot[has[:, 1]], t.focal_spots[has[:, 1], 1])
    r = dataset.record(AA39_RECORD)
    assert r.heliostat_ids[int(r.heliostat_index[0])] == "AA39" and r.flux_png[0] and r.flux_centered_png[0]
    assert 0 < float(r.sun_elevation[0]) <= math.pi / 2
    assert sum(d is not None for d in t.datetime) > 1600
    assert int(torch.isfinite(t.weather).any(-1).sum()) > 0


def test_real_data_has_both_kinematics_keys(paint_dir):
    names = ("kinematics_properties", "kinematic_properties")
    keys = {h: next(k for k in names if k in _load_json(_props_path(paint_dir, h)))
            for h in P.list_heliostats(paint_dir)}
    assert set(keys.values()) == {"kinematics_properties", "kinematic_properties"}


def test_focal_spots_lie_on_their_target_planes(dataset):
    dist, outside = [], []
    t = dataset.records
    for i, name in enumerate(t.target):
        target = dataset.plant.target(name)
        for spot in t.focal_spots[i]:
            if not bool(torch.isfinite(spot).all()):
                continue
            dist.append(float(target.distance_to_plane(spot)))
            xy = target.to_local(spot)
            outside.append(float((xy.abs() - xy.new_tensor([target.width / 2, target.height / 2])).max()))
    assert len(dist) > 1704
    assert max(abs(d) for d in dist) < 0.1
    assert max(outside) <= 0.0  # and inside the target rectangle


@pytest.mark.parametrize("new_key", ["kinematics_properties", "kinematic_properties"])
def test_old_and_new_kinematics_key(paint_dir, tmp_path, new_key):
    """The same heliostat reads identically under either key."""
    root = _mini_paint(paint_dir, tmp_path / "paint", ("AA39", "AK32"), calibration=False)
    reference = P.load_paint(root, with_records=False).plant.field.kinematics
    for h in ("AA39", "AK32"):
        data = _load_json(_props_path(root, h))
        old = "kinematics_properties" if "kinematics_properties" in data else "kinematic_properties"
        data = {(new_key if k == old else k): v for k, v in data.items()}
        _write_json(_props_path(root, h), data)
    renamed = P.load_paint(root, with_records=False).plant.field.kinematics
    for name in Kinematics.__dataclass_fields__:
        a, b = getattr(reference, name), getattr(renamed, name)
        assert a.dtype == b.dtype and torch.equal(a, b), name


@pytest.mark.parametrize("keep", ["HeliOS", "UTIS"])
def test_record_with_a_single_source(paint_dir, tmp_path, site, keep):
    data = _load_json(_record_path(paint_dir))
    full = P.read_calibration_record(_record_path(paint_dir), site, "AA39")
    drop = "UTIS" if keep == "HeliOS" else "HeliOS"
    for variant in ("missing", "null"):
        d = copy.deepcopy(data)
        if variant == "missing":
            del d["focal_spot"][drop]
        else:
            d["focal_spot"][drop] = None
        path = _write_json(tmp_path / variant / f"{AA39_RECORD}-calibration-properties.json", d)
        rec = P.read_calibration_record(path, site, "AA39")
        assert set(rec.focal_spot) == {keep}
        assert torch.equal(rec.focal_spot[keep], full.focal_spot[keep])
        assert torch.equal(rec.spot(drop), full.focal_spot[keep])  # prefers drop, falls back to keep


# ============================================================================================ bad input
def _mutated(data: dict, dotted: str, value=..., *, delete: bool = False) -> dict:
    d = copy.deepcopy(data)
    keys = [int(k) if k.isdigit() else k for k in dotted.replace("[", ".").replace("]", "").split(".")]
    node = d
    for k in keys[:-1]:
        node = node[k]
    if delete:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return d


PROPERTY_CASES = [  # (dotted path, value or "DELETE", expected error field)
    ("heliostat_position", "DELETE", "heliostat_position"),
    ("heliostat_position", [6.38, 50.91, 88.0, 1.0], "heliostat_position"),
    ("heliostat_position", [123.0, 6.38, 88.0], "heliostat_position"),
    ("kinematic_properties.actuators", {"a": 1}, "kinematic_properties.actuators"),
    ("kinematic_properties.actuators[0].increment", "DELETE", "kinematic_properties.actuators[0].increment"),
    ("kinematic_properties.actuators[0].increment", "154166", "kinematic_properties.actuators[0].increment"),
    ("kinematic_properties.actuators[1].increment", 0, "kinematic_properties.actuators[1].increment"),
    ("kinematic_properties.actuators[1].offset", -0.3, "kinematic_properties.actuators[1].offset"),
    ("kinematic_properties.actuators[0].type_axis", "hydraulic", "kinematic_properties.actuators[0].type_axis"),
    ("kinematic_properties.actuators[0].clockwise_axis_movement", 2,
     "kinematic_properties.actuators[0].clockwise_axis_movement"),
    ("kinematic_properties.actuators[1].max_increment", -5, "kinematic_properties.actuators[1].max_increment"),
    ("kinematic_properties.concentrator_translation_n", None, "kinematic_properties.concentrator_translation_n"),
    ("facet_properties.facets", [], "facet_properties.facets"),
    ("facet_properties.facets[2].canting_n", [0.0, 0.6], "facet_properties.facets[2].canting_n"),
    ("facet_properties.facets[1].canting_e", [0, 0, 0], "facet_properties.facets[1].canting_e"),
    ("width", "wide", "width"),
]


@pytest.mark.parametrize("dotted, value, field", PROPERTY_CASES)
def test_bad_properties(paint_dir, tmp_path, site, dotted, value, field):
    data = _load_json(_props_path(paint_dir))  # AA39 uses the old key "kinematic_properties"
    bad = _mutated(data, dotted, delete=True) if value == "DELETE" else _mutated(data, dotted, value)
    path = _write_json(_props_path(tmp_path), bad)
    with pytest.raises(InputFileError) as exc:
        P.read_heliostat_properties(path, site)
    _assert_clean_error(exc, path, field)


RECORD_CASES = [
    ("motor_position", "DELETE", "motor_position"),
    ("motor_position.axis_2_motor_position", "DELETE", "motor_position.axis_2_motor_position"),
    ("motor_position.axis_1_motor_position", "30076", "motor_position.axis_1_motor_position"),
    ("motor_position.axis_1_motor_position", True, "motor_position.axis_1_motor_position"),
    ("target_name", 7, "target_name"),
    ("target_name", "solar_tower_juelich_middle", "target_name"),
    ("focal_spot", [1, 2, 3], "focal_spot"),
    ("focal_spot", {}, "focal_spot"),
    ("focal_spot.HeliOS", "50.9, 6.3, 122.0", "focal_spot.HeliOS"),
    ("focal_spot.UTIS", [50.9, 6.38], "focal_spot.UTIS"),
    ("sun_azimuth", "DELETE", "sun_azimuth"),
    ("sun_azimuth", [50.3], "sun_azimuth"),
    ("sun_elevation", -5.0, "sun_elevation"),  # below the horizon
    ("sun_elevation", 0.0, "sun_elevation"),  # on the horizon
    ("sun_elevation", 91.0, "sun_elevation"),
]


@pytest.mark.parametrize("dotted, value, field", RECORD_CASES)
def test_bad_calibration_record(paint_dir, tmp_path, site, dotted, value, field):
    data = _load_json(_record_path(paint_dir))
    bad = _mutated(data, dotted, delete=True) if value == "DELETE" else _mutated(data, dotted, value)
    path = _write_json(tmp_path / f"{AA39_RECORD}-calibration-properties.json", bad)
    known = {"solar_tower_juelich_upper": None, "solar_tower_juelich_lower": None, "multi_focus_tower": None}
    with pytest.raises(InputFileError) as exc:
        P.read_calibration_record(path, site, "AA39", known_targets=known)
    _assert_clean_error(exc, path, field)


@pytest.mark.parametrize("text", ["", "{", '{"motor_position": {"axis_1_motor_position": 1,}}', "[1, 2]", "\xff\xfe"])
def test_malformed_json(tmp_path, site, text):
    path = tmp_path / f"{AA39_RECORD}-calibration-properties.json"
    path.write_bytes(text.encode("latin-1"))
    with pytest.raises(InputFileError) as exc:
        P.read_calibration_record(path, site, "AA39")
    _assert_clean_error(exc, path, None)
    with pytest.raises(InputFileError) as exc:
        P.read_heliostat_properties(path, site)
    _assert_clean_error(exc, path, None)


def test_missing_file(tmp_path, site):
    path = tmp_path / "AA39-heliostat-properties.json"
    with pytest.raises(InputFileError, match="not found"):
        P.read_heliostat_properties(path, site)


def test_unknown_target_name_through_load_paint(paint_dir, tmp_path):
    root = _mini_paint(paint_dir, tmp_path / "paint")
    rec = _record_path(root)
    _write_json(rec, _mutated(_load_json(rec), "target_name", "solar_tower_juelich_middle"))
    with pytest.raises(InputFileError) as exc:
        P.load_paint(root)
    _assert_clean_error(exc, rec, "target_name")
    assert "solar_tower_juelich_upper" in str(exc.value)  # lists the known targets


def test_bad_tower_file(paint_dir, tmp_path):
    tower = _load_json(P.find_tower_file(paint_dir))
    cases = [
        (_mutated(tower, "receiver.type", "concave_sphere"), "receiver.type"),
        (_mutated(tower, "power_plant_properties", delete=True), "power_plant_properties"),
        (_mutated(tower, "multi_focus_tower.coordinates.upper_left", [6.38, 50.91, 142.0][:2]),
         "multi_focus_tower.coordinates.upper_left"),
        (_mutated(tower, "receiver.radius", -4.14), "receiver.radius"),
    ]
    for i, (data, field) in enumerate(cases):
        path = _write_json(tmp_path / f"{i}" / "WRI1030197-tower-measurements.json", data)
        with pytest.raises(InputFileError) as exc:
            P.read_tower(path)
        _assert_clean_error(exc, path, field)


def test_load_paint_bad_folder_and_ids(paint_dir, tmp_path):
    with pytest.raises(InputFileError) as exc:
        P.load_paint(paint_dir, ["AA39", "ZZ99"], with_records=False)
    _assert_clean_error(exc, paint_dir, "heliostats")
    with pytest.raises(InputFileError, match="tower-measurements"):
        P.load_paint(tmp_path, with_records=False)
    with pytest.raises(InputFileError, match="not found"):
        P.list_heliostats(tmp_path / "nope")


# ============================================================================= property-based (hypothesis)
_NUMBER = st.one_of(st.integers(-10**6, 10**6), st.floats(-1e9, 1e9),
                    st.sampled_from([math.nan, math.inf, -math.inf, 10**400, -(10**400), 0, 1e-320]))
_VALUE = st.one_of(st.none(), st.booleans(), _NUMBER, st.text(max_size=4),
                   st.lists(_NUMBER, max_size=4), st.dictionaries(st.text(max_size=3), _NUMBER, max_size=2))


def _paths(node, prefix=()):
    """Every key/index path in a JSON tree."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for k, v in items:
        yield prefix + (k,)
        yield from _paths(v, prefix + (k,))


def _apply_mutations(data, draw):
    """Drop keys/elements or replace values (wrong type, NaN/inf, huge, non-list ...), 1-3 times."""
    d = copy.deepcopy(data)
    for _ in range(draw(st.integers(1, 3))):
        paths = list(_paths(d))
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        node = d
        for k in path[:-1]:
            node = node[k]
        if draw(st.sampled_from(["drop", "replace"])) == "drop":
            del node[path[-1]]
        else:
            node[path[-1]] = draw(_VALUE)
    return d


def _write_mutation(folder: Path, name: str, data) -> Path:
    path = folder / name
    path.write_text(json.dumps(data, allow_nan=True))  # NaN / Infinity tokens, which json.load accepts
    return path


@pytest.fixture(scope="module")
def mutation_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("mutations")


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_properties_parser_never_crashes(paint_dir, mutation_dir, site, data):
    base = _load_json(_props_path(paint_dir, "AA39"))
    path = _write_mutation(mutation_dir, "AA39-heliostat-properties.json", _apply_mutations(base, data.draw))
    try:
        props = P.read_heliostat_properties(path, site)
    except InputFileError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
        return
    kin = props.kinematics
    for name in Kinematics.__dataclass_fields__:
        t = getattr(kin, name)
        if name in ("min_angle", "max_angle"):  # informative; NaN when absent from the file
            assert not torch.isinf(t).any(), name
        elif t.dtype != torch.bool:
            assert torch.isfinite(t).all(), name
    assert (kin.increment > 0).all()
    for t in (props.facets.translation, props.facets.canting_e, props.facets.canting_n):
        assert torch.isfinite(t).all()
    assert not math.isinf(props.width) and not math.isinf(props.height)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_calibration_parser_never_crashes(paint_dir, mutation_dir, site, data):
    base = _load_json(_record_path(paint_dir))
    mutated = _apply_mutations(base, data.draw)
    path = _write_mutation(mutation_dir, f"{AA39_RECORD}-calibration-properties.json", mutated)
    known = {"solar_tower_juelich_upper", "solar_tower_juelich_lower", "multi_focus_tower", "receiver"}
    try:
        rec = P.read_calibration_record(path, site, "AA39", known_targets=known)
    except InputFileError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
        return
    assert rec.target in known
    assert all(math.isfinite(s) for s in rec.motor_steps)
    assert math.isfinite(rec.sun_azimuth) and 0.0 < rec.sun_elevation <= math.pi / 2
    assert rec.focal_spot and all(torch.isfinite(p).all() for p in rec.focal_spot.values())
