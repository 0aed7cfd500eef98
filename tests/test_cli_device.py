"""``--device`` on the computing commands, and a GPU smoke test that runs where CUDA is available."""
from __future__ import annotations

import json

import pytest
import torch
from helpers.cli import assert_one_line_error, run_cli
from helpers.paint import copy_paint

from heliotwin.cli import COMPUTE_COMMANDS, build_parser

CUDA = torch.cuda.is_available()


def test_every_compute_command_takes_device():
    for command in COMPUTE_COMMANDS:
        p = build_parser()
        argv = {"demo": [], "trace": ["--paint", "P", "--heliostat", "A", "--record", "1", "-o", "f.png"],
                "validate": ["--paint", "P", "--json", "v.json"], "bench": [], "calibrate": ["--paint", "P"],
                "reconstruct": ["--paint", "P", "--heliostat", "A", "--json", "r.json"],
                "predict": ["--scenario", "s.h5", "--json", "p.json"]}[command]
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


@pytest.mark.skipif(not CUDA, reason="needs a CUDA device")
def test_gpu_cuda_on_a_cpu_only_command_is_refused(tmp_path, capsys):
    code, _, err = run_cli(capsys, "bench", "--device", "cuda", "--surface-points", "10", "--json", tmp_path / "b.json")
    assert_one_line_error(code, err, "--device cuda", "CPU only")
