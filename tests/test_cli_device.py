"""``--device`` on the computing commands, and a GPU smoke test that runs where CUDA is available."""
from __future__ import annotations

import argparse
import json

import pytest
import torch
from helpers.cli import assert_one_line_error, run_cli
from helpers.field import learned_posterior
from helpers.paint import copy_paint

from heliotwin.cli import COMPUTE_COMMANDS, build_parser
from heliotwin.io.scenario import save_scenario
from heliotwin.optimise.testbed import generated_plant

CUDA = torch.cuda.is_available()


def test_every_compute_command_takes_device():
    for command in COMPUTE_COMMANDS:
        p = build_parser()
        argv = {"demo": [], "trace": ["--paint", "P", "--heliostat", "A", "--record", "1", "-o", "f.png"],
                "validate": ["--paint", "P", "--json", "v.json"], "bench": [], "calibrate": ["--paint", "P"],
                "reconstruct": ["--paint", "P", "--heliostat", "A", "--json", "r.json"],
                "predict": ["--scenario", "s.h5", "--json", "p.json"],
                "field": ["--scenario", "s.h5", "--time", "2023-03-20T12:00:00Z", "--json", "f.json"],
                "aimpoints": ["--scenario", "s.h5", "--time", "2023-03-20T12:00:00Z", "--peak-limit", "1e6",
                              "-o", "a.h5", "--json", "a.json"],
                "year": ["--scenario", "s.h5", "--json", "y.json"]}[command]
        assert p.parse_args([command, *argv]).device == "auto"
        assert p.parse_args([command, *argv, "--device", "cpu"]).device == "cpu"


@pytest.fixture()
def small_paint(tmp_path, paint_dir):
    return copy_paint(paint_dir, tmp_path)


def _trace(capsys, root, tmp_path, device, name):
    rid = sorted((root / "AA39" / "Calibration").glob("*-calibration-properties.json"))[0].name.split("-")[0]
    js = tmp_path / f"{name}.json"
    code, _, err = run_cli(capsys, "trace", "--paint", root, "--heliostat", "AA39", "--record", rid, "--integrator",
                           "gaussian", "--samples", "12", "--resolution", "64", "-o", tmp_path / f"{name}.png",
                           "--json", js, "--device", device)
    return code, err, js


@pytest.mark.skipif(CUDA, reason="checks the refusal on a machine without CUDA")
def test_cuda_without_a_device_is_a_one_line_error_and_auto_runs_on_the_cpu(small_paint, tmp_path, capsys):
    code, err, js = _trace(capsys, small_paint, tmp_path, "cuda", "c")
    assert_one_line_error(code, err, "--device cuda", "no CUDA device")
    assert code == 2 and not js.exists()
    code, err, js = _trace(capsys, small_paint, tmp_path, "auto", "a")
    assert code == 0, err
    assert json.loads(js.read_text())["device"] == "cpu"


@pytest.mark.skipif(not CUDA, reason="needs a CUDA device")
def test_gpu_smoke_trace_agrees_with_cpu(small_paint, tmp_path, capsys):
    """The same record traced on the GPU and the CPU (deterministic gaussian integrator): same powers and
    centroid to float32 precision."""
    code, err, js_gpu = _trace(capsys, small_paint, tmp_path, "cuda", "g")
    assert code == 0, err
    code, err, js_cpu = _trace(capsys, small_paint, tmp_path, "cpu", "c")
    assert code == 0, err
    g, c = json.loads(js_gpu.read_text()), json.loads(js_cpu.read_text())
    assert g["device"] == "cuda" and c["device"] == "cpu"
    assert g["total_power_w"] == pytest.approx(c["total_power_w"], rel=1e-4)
    assert g["intercepted_power_w"] == pytest.approx(c["intercepted_power_w"], rel=1e-3)
    assert max(abs(a - b) for a, b in zip(g["centroid_enu_m"], c["centroid_enu_m"])) < 2e-3


def test_cuda_on_a_cpu_only_command_is_refused():
    from heliotwin.cli.common import resolve_device
    from heliotwin.errors import HeliotwinError

    assert resolve_device("auto", False, "x") == "cpu"
    with pytest.raises(HeliotwinError, match="CPU only" if CUDA else "no CUDA device"):
        resolve_device("cuda", False, "x")


def test_every_command_with_a_device_option_can_take_cuda():
    """A command that offers ``--device`` must not refuse ``cuda`` as CPU-only: the flag ``supports_cuda`` has to
    survive wrappers (``field`` and ``aimpoints`` lost it to their argument check, so a GPU run was refused)."""
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    offered = {name for name, p in sub.choices.items() if any("--device" in a.option_strings for a in p._actions)}
    assert {"field", "aimpoints", "calibrate", "reconstruct", "predict", "demo"} <= offered
    refused = sorted(n for n in offered if not getattr(sub.choices[n].get_default("func"), "supports_cuda", False))
    assert refused == []


def test_the_fit_commands_run_on_the_cuda_capable_path_on_the_cpu(small_paint, tmp_path, capsys):
    """``--device cpu`` goes through the same device plumbing (plant moved, results back) as cuda would."""
    from heliotwin.calibrate.protocol.pipeline import resolve_device

    assert resolve_device("auto") == ("cuda" if CUDA else "cpu")
    js = tmp_path / "v.json"
    code, _, err = run_cli(capsys, "validate", "--paint", small_paint, "--json", js, "--samples", "4",
                           "--resolution", "32", "--no-images", "--device", "cpu", "--quiet")
    assert code == 0, err
    assert json.loads(js.read_text())["settings"]["device"] == "cpu"


# ------------------------------------------------------------------------------ GPU smoke, one per command
gpu = pytest.mark.skipif(not CUDA, reason="needs a CUDA device")


@pytest.fixture()
def fit_paint(tmp_path, paint_dir):
    return copy_paint(paint_dir, tmp_path, heliostats=("AA39", "AK46", "BG23"), metadata=True)


def _both(capsys, tmp_path, name, *argv, out="--json", devices=("cuda", "cpu")):
    """Run a command on cuda and on the cpu; return both JSON reports."""
    reports = {}
    for device in devices:
        js = tmp_path / f"{name}-{device}.json"
        code, _, err = run_cli(capsys, *argv, out, js, "--device", device, "--quiet")
        assert code == 0, (device, err)
        reports[device] = json.loads(js.read_text())
    return reports[devices[0]], reports[devices[1]]


@gpu
def test_gpu_smoke_validate(small_paint, tmp_path, capsys):
    g, c = _both(capsys, tmp_path, "v", "validate", "--paint", small_paint, "--samples", "8", "--resolution", "64")
    assert g["settings"]["device"] == "cuda"
    assert g["overall"]["records"] == c["overall"]["records"]
    assert g["overall"]["median_pointing_error_mrad"] == pytest.approx(c["overall"]["median_pointing_error_mrad"],
                                                                       abs=1e-6)
    assert g["overall"]["median_distance_m"] == pytest.approx(c["overall"]["median_distance_m"], abs=5e-3)


@gpu
def test_gpu_smoke_bench(tmp_path, capsys):
    js = tmp_path / "b.json"
    code, _, err = run_cli(capsys, "bench", "--device", "cuda", "--surface-points", "400", "--rays-per-point", "10",
                           "--resolution", "64", "--json", js, "--quiet")
    assert code == 0, err
    r = json.loads(js.read_text())
    assert r["device"].startswith("cuda") and r["mc"]["forward_rays_per_s"] > 0 and r["peak_device_mb"] > 0


@gpu
def test_gpu_smoke_calibrate(fit_paint, tmp_path, capsys):
    argv = ("calibrate", "--paint", fit_paint, "--heliostats", "AK46,BG23", "--train", "12", "--test", "10",
            "--min-records", "20", "--no-plots")
    g, c = _both(capsys, tmp_path, "c", *argv)
    assert g["config"]["device"] == "cuda" and c["config"]["device"] == "cpu"
    for hid, rep in c["heliostats"].items():
        assert g["heliostats"][hid]["mean_test_mrad"] == pytest.approx(rep["mean_test_mrad"], abs=1e-6)


@gpu
def test_gpu_smoke_reconstruct_and_predict(fit_paint, tmp_path, capsys):
    argv = ("reconstruct", "--paint", fit_paint, "--heliostat", "AA39", "--steps", "10", "--control-points", "4x4",
            "--degree", "2", "--no-mc", "--slope-error", "1")
    g, c = _both(capsys, tmp_path, "r", *argv)
    assert g["median_l1_learned"] == pytest.approx(c["median_l1_learned"], abs=2e-3)
    scenario = tmp_path / "learned.h5"
    code, _, err = run_cli(capsys, *argv, "--json", tmp_path / "r.json", "-o", scenario, "--device", "cpu", "--quiet")
    assert code == 0, err
    g, c = _both(capsys, tmp_path, "p", "predict", "--scenario", scenario, "--every", "169h")
    assert g["device"] == "cuda" and g["instants"] == c["instants"]
    ga, ca = g["statistics"]["l1_ideal_vs_learned"], c["statistics"]["l1_ideal_vs_learned"]
    assert ga["median"] == pytest.approx(ca["median"], abs=2e-3)


@gpu
def test_gpu_smoke_field_demo_with_aim_points(tmp_path, capsys):
    """The field demo (field model with shading and blocking, aim points) on cuda agrees with the cpu."""
    reports = {}
    for device in ("cuda", "cpu"):
        out = tmp_path / f"demo-{device}"
        code, _, err = run_cli(capsys, "demo", "-o", out, "--heliostats", "30", "--device", device, "--quiet")
        assert code == 0, (device, err)
        reports[device] = json.loads((out / "summary.json").read_text())
    g, c = reports["cuda"], reports["cpu"]
    for key in ("total", "shading", "blocking", "intercept"):
        assert g["field"]["efficiency"][key] == pytest.approx(c["field"]["efficiency"][key], rel=1e-4)
    assert g["aim_points"]["violation"] == 0.0 and c["aim_points"]["violation"] == 0.0
    assert g["aim_points"]["power_vs_equator"] == pytest.approx(c["aim_points"]["power_vs_equator"], abs=2e-3)


def _field_and_robust_aimpoints(capsys, tmp_path, devices):
    """``field`` and ``aimpoints --confidence`` on a generated plant with a pointing posterior, on two devices:
    the same field factors, the limit held by both, the same power and exceedance within float tolerance."""
    plant, atm = generated_plant("radial", 40, "cylinder", tower=30.0)
    path = save_scenario(plant, tmp_path / "p.h5", extras=atm.to_extras(), learned=learned_posterior(plant))
    when = ("--sun-azimuth", "10", "--sun-elevation", "50")
    g, c = _both(capsys, tmp_path, "f", "field", "--scenario", path, *when, devices=devices)
    for key in ("total", "shading", "blocking", "intercept"):
        assert g["field"]["efficiency"][key] == pytest.approx(c["field"]["efficiency"][key], rel=1e-4)
    limit = 0.8 * c["receiver"]["peak_flux_w_m2"]
    g, c = _both(capsys, tmp_path, "a", "aimpoints", "--scenario", path, *when, "--peak-limit", limit,
                 "--confidence", "0.9", "--draws", "100", "-o", tmp_path / "a.h5", devices=devices)
    assert g["optimised"]["limit_met"] and c["optimised"]["limit_met"]
    assert g["optimised"]["power_vs_equator"] == pytest.approx(c["optimised"]["power_vs_equator"], abs=2e-3)
    gp, cp = g["robust"]["robust"]["exceedance_probability"], c["robust"]["robust"]["exceedance_probability"]
    assert gp == pytest.approx(cp, abs=0.03)  # the same seeded draws; peaks within float tolerance of the limit


@pytest.mark.slow
def test_field_and_robust_aimpoints_agree_between_two_cpu_runs(tmp_path, capsys):
    """The GPU comparison below, on the CPU twice (so that its checks are themselves checked without a GPU;
    slow: 6 s)."""
    _field_and_robust_aimpoints(capsys, tmp_path, ("cpu", "cpu"))


@gpu
def test_gpu_smoke_field_and_robust_aimpoints(tmp_path, capsys):
    _field_and_robust_aimpoints(capsys, tmp_path, ("cuda", "cpu"))
