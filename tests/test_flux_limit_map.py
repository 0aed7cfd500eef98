"""Allowable-flux maps: the HALOS-layout CSV reader (units, conservative resampling, one-line errors naming the file and
row/column), per-panel limits with a flow-path derating in the plant TOML, every cell held under its own limit on
the exact model, a constant map giving the peak limit's aim points bit for bit, the map stored with the aim points
(and kept by ``daily``), and the split of the aim-point module (its facade, module sizes and parameter counts)."""
import ast
import inspect
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from helpers.cli import assert_one_line_error, run_cli
from helpers.field import PLANT_TOML, write_plant_toml

import heliotwin.optimise as optimise_pkg
from heliotwin.errors import InputFileError
from heliotwin.field.layout import read_plant_config
from heliotwin.optimise import aimpoints as facade
from heliotwin.optimise.aimpoints import (
    AimProblem,
    AimSettings,
    FluxLimit,
    WarmStart,
    aiming_factor,
    calibrate_images,
    optimise_aimpoints,
    solve,
)
from heliotwin.optimise.aimstate import stored_flux_limit
from heliotwin.optimise.fluxmap import load_flux_limit, panel_limit_grid, read_flux_limit_csv, resample_min
from heliotwin.optimise.testbed import flux_limit_map, generated_plant, scaled_to_bind
from heliotwin.sun import direction_from_time

RES = (20, 48)
KNOBS = AimSettings(iterations=150, rounds=5)


def _csv(tmp_path, text, name="allowable_flux.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _sun(plant, text="2024-06-21T11:00:00Z"):
    s = plant.site
    return direction_from_time(pd.DatetimeIndex([pd.Timestamp(text)]), s.latitude_deg, s.longitude_deg,
                               s.altitude_m)[0]


@pytest.fixture(scope="module")
def small():
    """40 heliostats north of a flat receiver at noon in June: the equator-aimed map and its image model."""
    plant, atm = generated_plant("radial", 40, "flat", tower=40.0)
    sun = _sun(plant)
    model, eq = calibrate_images(plant, sun, atm, RES)
    return plant, atm, sun, model, eq


# ------------------------------------------------------------------------------------------ CSV reader
def test_halos_csv_is_read_rows_top_to_bottom_and_resampled_to_each_cells_lowest_limit(tmp_path):
    # 2 rows x 3 columns in W/m2: the top row first, the columns left to right
    p = _csv(tmp_path, "1e6,2e6,3e6\n4e6,5e6,6e6\n")
    grid = read_flux_limit_csv(p)
    assert grid.tolist() == [[1e6, 2e6, 3e6], [4e6, 5e6, 6e6]]
    # finer grid: every model cell lies in one file cell and takes its limit
    fine = resample_min(grid, (4, 6))
    assert fine[0].tolist() == [1e6, 1e6, 2e6, 2e6, 3e6, 3e6] and fine[3].tolist() == [4e6, 4e6, 5e6, 5e6, 6e6, 6e6]
    # coarser: a model column over two file columns takes the lower (conservative), rows likewise
    coarse = resample_min(grid, (1, 2))
    assert coarse.tolist() == [[1e6, 2e6]]
    # 3 file columns onto 4 model columns: the middle model columns straddle a file boundary
    assert resample_min(grid, (2, 4))[1].tolist() == [4e6, 4e6, 5e6, 6e6]
    fl = load_flux_limit(p, (4, 6))
    assert fl.cells.shape == (4, 6) and fl.minimum == 1e6 and fl.source == "allowable_flux.csv"


def test_halos_own_unit_needs_its_unit_line_and_is_converted(tmp_path):
    # HALOS writes kW/m2 without a header: refused with the line to add ...
    p = _csv(tmp_path, "300,300\n600,800\n300,300\n")
    with pytest.raises(InputFileError, match=r"allowable_flux.csv: .*kW/m2.*'# unit: kW/m2'"):
        read_flux_limit_csv(p)
    # ... and converted with it (kW/m2 and MW/m2)
    assert read_flux_limit_csv(_csv(tmp_path, "# unit: kW/m2\n300,300\n600,800\n")).tolist() == \
        [[3e5, 3e5], [6e5, 8e5]]
    assert read_flux_limit_csv(_csv(tmp_path, "# unit = MW/m²\n0.3,1.2\n")).tolist() == [[3e5, 1.2e6]]
    with pytest.raises(InputFileError, match=r"\[line 1\]: unknown unit 'btu/ft2'"):
        read_flux_limit_csv(_csv(tmp_path, "# unit: BTU/ft2\n1,2\n"))


@pytest.mark.parametrize(("text", "where"), [
    ("1e6,2e6\n1e6\n", r" \[row 2 \(line 2\)\]: 1 columns, the first row has 2"),
    ("# c\n1e6,abc,2e6\n", r" \[row 1 \(line 2\), column 2\]: expected a finite number, got 'abc'"),
    ("1e6,nan\n", r" \[row 1 \(line 1\), column 2\]"),
    ("1e6,2e6\n1e6,5e9\n", r" \[row 2, column 2\]: limit 5e\+09 W/m2 out of"),
    ("# only a comment\n", r": no rows"),
])
def test_bad_flux_limit_csv_is_one_error_naming_file_and_row_column(tmp_path, text, where):
    p = _csv(tmp_path, text, "bad.csv")
    with pytest.raises(InputFileError, match=r"bad\.csv" + where) as err:
        read_flux_limit_csv(p)
    assert "\n" not in str(err.value)


def test_aimpoints_with_a_bad_map_is_one_line_and_writes_nothing(tmp_path, capsys):
    from heliotwin.io.scenario import save_scenario

    plant, atm = generated_plant("radial", 6, "flat", tower=30.0)
    h5 = tmp_path / "p.h5"
    save_scenario(plant, h5, extras=atm.to_extras())
    bad = _csv(tmp_path, "1e6,x\n", "lim.csv")
    out, js = tmp_path / "a.h5", tmp_path / "a.json"
    code, _, err = run_cli(capsys, "aimpoints", "--scenario", h5, "--time", "2024-06-21T11:00:00Z", "--flux-limit",
                           bad, "--no-baselines", "-o", out, "--json", js)
    assert_one_line_error(code, err, "lim.csv")
    assert "column 2" in err and not out.exists() and not js.exists()
    code, _, err = run_cli(capsys, "aimpoints", "--scenario", h5, "--time", "2024-06-21T11:00:00Z",
                           "--no-baselines", "-o", out, "--json", js)
    assert_one_line_error(code, err, "--flux-limit")


# ------------------------------------------------------------------------------------------ TOML
FLUX_TOML = """
[receiver.flux_limit]
panels_w_m2 = [1.0e6, 1.0e6, 1.0e6, 1.0e6]
flow_path = [1, 0, 3, 2]
derating = [1.0, 0.8, 0.5, 0.33]
top_bottom_w_m2 = 3.0e5
"""


def _plant_toml(tmp_path, extra=FLUX_TOML):
    text = PLANT_TOML.replace("[sun]", extra.strip() + "\n[sun]")
    return write_plant_toml(tmp_path, text)


def test_per_panel_limits_derate_along_the_flow_path(tmp_path):
    path = _plant_toml(tmp_path)
    cfg = read_plant_config(path)  # the plant TOML with the table still builds a plant
    assert cfg.receiver["flux_limit"]["panels"] == [0.8e6, 1.0e6, 0.33e6, 0.5e6]  # panel p x derating at its step
    fl = load_flux_limit(path, (4, 8))
    want_row = [0.8e6] * 2 + [1.0e6] * 2 + [0.33e6] * 2 + [0.5e6] * 2
    assert fl.cells[1].tolist() == want_row and fl.cells[2].tolist() == want_row
    assert fl.cells[0].tolist() == [min(v, 3e5) for v in want_row] == fl.cells[3].tolist()
    # 4 panels onto 6 columns: the columns over two panels take the lower limit
    assert panel_limit_grid({**cfg.receiver["flux_limit"], "top_bottom": None}, (1, 6))[0].tolist() == \
        [0.8e6, 0.8e6, 1.0e6, 0.33e6, 0.33e6, 0.5e6]


@pytest.mark.parametrize(("body", "field", "reason"), [
    ("panels_w_m2 = [1e6, 1e6]\nderating = [1.0]", "receiver.flux_limit.derating", "expected 2 entries"),
    ("panels_w_m2 = [1e6, 1e6]\nderating = [1.0, 1.2]", "receiver.flux_limit.derating[1]", "in (0, 1]"),
    ("panels_w_m2 = [1e6, 1e6]\nflow_path = [0, 0]", "receiver.flux_limit.flow_path", "0..1 once"),
    ("panels_w_m2 = [1000, 600]", "receiver.flux_limit.panels_w_m2[1]", "W/m2, not kW/m2"),
    ("panel_w_m2 = [1e6]", "receiver.flux_limit.panel_w_m2", "unknown key"),
    ("derating = [1.0]", "receiver.flux_limit.panels_w_m2", "missing key"),
])
def test_bad_per_panel_limits_are_one_error_naming_file_and_key(tmp_path, body, field, reason):
    path = _plant_toml(tmp_path, "[receiver.flux_limit]\n" + body)
    for read in (read_plant_config, lambda p: load_flux_limit(p, RES)):
        with pytest.raises(InputFileError) as err:
            read(path)
        assert f"plant.toml [{field}]" in str(err.value) and reason in str(err.value)


# ------------------------------------------------------------------------------------------ the solver
@pytest.mark.slow  # ~8-20 s on 2 shared cores
def test_every_cell_is_held_under_its_own_limit_and_the_map_lets_more_power_through_than_its_minimum(small):
    plant, atm, sun, model, eq = small
    limit = scaled_to_bind(flux_limit_map("flow-path", RES), eq.flux, 0.7, "flow-path")
    assert limit.ratio(eq.flux) == pytest.approx(1 / 0.7)  # equator aiming exceeds the map by 43 %
    assert not limit.is_uniform and limit.minimum < 0.4 * float(limit.cells.max())
    best = optimise_aimpoints(plant, sun, limit, KNOBS, atmosphere=atm, equator=eq, model=model)
    assert bool((best.flux <= limit.cells).all()) and best.standby == 0  # the exact map, cell by cell
    over_flat = best.flux > limit.minimum
    assert bool(over_flat.any())  # cells above the map's minimum: only their own (higher) limit holds them
    flat = optimise_aimpoints(plant, sun, limit.minimum, KNOBS, atmosphere=atm, equator=eq, model=model)
    assert float(flat.flux.max()) <= limit.minimum
    assert best.power_w > 1.05 * flat.power_w
    # a per-cell limit on the heuristics too: image-size priority holds every cell
    isp = facade.image_size_priority(plant, sun, limit, atmosphere=atm, model=model, steps=3)
    assert bool((isp.flux <= limit.cells).all()) or isp.parameter == 0.0


def test_a_constant_map_gives_the_peak_limits_aim_points_bit_for_bit(small):
    plant, atm, sun, model, eq = small
    peak = 0.75 * float(eq.flux.max())
    a = optimise_aimpoints(plant, sun, peak, KNOBS, atmosphere=atm, equator=eq, model=model)
    b = optimise_aimpoints(plant, sun, torch.full(RES, peak, dtype=torch.float64), KNOBS, atmosphere=atm,
                           equator=eq, model=model)
    assert torch.equal(a.aim, b.aim) and a.power_w == b.power_w and a.history == b.history
    # the warm start as one argument, through the solver itself
    w1 = optimise_aimpoints(plant, sun, peak, KNOBS, atmosphere=atm, start_aim=a.aim, start_multipliers=a.multipliers,
                            start_margin=a.parameter, start_field=a.exact)
    w2 = solve(AimProblem(plant, sun, FluxLimit.uniform(peak, RES), atm), KNOBS, WarmStart.from_result(a))
    assert torch.equal(w1.aim, w2.aim) and w1.exact_checks == w2.exact_checks
    f1 = aiming_factor(plant, sun, peak, atmosphere=atm, model=model, steps=3)
    f2 = aiming_factor(plant, sun, FluxLimit.uniform(peak, RES), atmosphere=atm, model=model, steps=3)
    assert torch.equal(f1.aim, f2.aim) and f1.parameter == f2.parameter


# ------------------------------------------------------------------------------------------ stored, daily
@pytest.mark.slow  # ~8-20 s on 2 shared cores
def test_the_map_is_stored_with_the_aim_points_and_reported(tmp_path, capsys):
    from heliotwin.io.scenario import load_scenario, save_scenario

    plant, atm = generated_plant("radial", 10, "flat", tower=30.0)
    eq = calibrate_images(plant, _sun(plant), atm, RES)[1]
    h5 = tmp_path / "p.h5"
    save_scenario(plant, h5, extras=atm.to_extras())
    fine = scaled_to_bind(flux_limit_map("halos", RES), eq.flux, 0.8)
    scale = float(fine.cells.max()) / float(flux_limit_map("halos", RES).max())
    lim = tmp_path / "allowable_flux.csv"  # a coarse HALOS-like file in HALOS' own unit
    np.savetxt(lim, flux_limit_map("halos", (4, 7)) * scale / 1e3, delimiter=",", header="unit: kW/m2")
    out, js, maps = tmp_path / "a.h5", tmp_path / "a.json", tmp_path / "maps"
    code, stdout, err = run_cli(capsys, "aimpoints", "--scenario", h5, "--time", "2024-06-21T11:00:00Z",
                                "--flux-limit", lim, "--no-baselines", "--iterations", 50, "-o", out, "--json", js,
                                "--flux", maps)
    rep = json.loads(js.read_text())
    o = rep["optimised"]
    assert code == (0 if o["limit_met"] else 3), err
    want = load_flux_limit(lim, RES)
    assert rep["flux_limit"]["source"] == "allowable_flux.csv" and rep["flux_limit"]["min_w_m2"] == want.minimum
    stored = stored_flux_limit(load_scenario(out))
    assert torch.equal(stored.cells, want.cells)
    assert rep["peak_limit_w_m2"] == float(want.cells.max())  # no cell may go above it
    assert o["peak_vs_limit"] == o["max_utilisation"] <= 1.0 and o["binding_cells"] >= 0
    assert "binding cells" in stdout and (maps / "i000_utilisation.png").stat().st_size > 0
    # daily without a limit given keeps the stored map
    from heliotwin.workflows.daily import DailySettings, _aim

    aimed, summary = _aim(load_scenario(out), "2024-06-22", DailySettings(aim_times="2024-06-22T11:00:00Z"))
    assert summary["flux_limit"]["source"] == "allowable_flux.csv"
    assert torch.equal(stored_flux_limit(aimed).cells, want.cells)
    assert summary["instants"][0]["max_utilisation"] <= 1.0 + 1e-6


# ------------------------------------------------------------------------------------------ the split
SPLIT = ("aimpoints", "problem", "images", "alm", "solver", "baselines", "fluxmap", "fluxplots")


def test_the_split_modules_are_small_and_their_functions_take_at_most_six_parameters():
    folder = Path(optimise_pkg.__file__).parent
    for name in SPLIT:
        text = (folder / f"{name}.py").read_text()
        assert len(text.splitlines()) <= 500, name
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + bool(a.vararg) + bool(a.kwarg)
                assert n <= 6, f"{name}.{node.name}: {n} parameters"


def test_the_facade_keeps_the_entry_points_and_refuses_unknown_keywords(small):
    plant, atm, sun, model, eq = small
    for name in ("optimise_aimpoints", "calibrate_images", "evaluate", "aiming_factor", "image_size_priority",
                 "run_aimpoints_sharded", "load_target", "uniform_target", "target_mismatch", "AimSettings",
                 "AimResult", "ImageModel", "check_settings", "image_moments", "VISIBLE_HALF_ANGLE", "_local",
                 "_world", "_axis_profile", "_field_power_gradient"):
        assert hasattr(facade, name), name
    assert list(inspect.signature(optimise_aimpoints).parameters)[:4] == ["plant", "sun", "peak_limit", "settings"]
    with pytest.raises(TypeError, match="start_aims"):
        optimise_aimpoints(plant, sun, 1e5, atmosphere=atm, start_aims=None)
