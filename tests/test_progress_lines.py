"""Progress of the long commands in a log: with stdout and stderr not a terminal (a CI log, a pipe) each of
``predict``, ``trace``, ``validate``, ``bench`` and ``reconstruct`` writes plain progress lines on stdout -- no
carriage returns of a bar -- and ``--quiet`` silences them; stderr stays empty for a run that succeeds."""
from __future__ import annotations

import io

import pytest
from helpers.cli import run_cli
from helpers.learned import learned_scenario
from helpers.paint import copy_paint

from heliotwin.progress import Progress, iterate
from heliotwin.workflows.bench import run_benchmark


def _lines(out: str, prefix: str) -> list[str]:
    assert "\r" not in out
    return [ln for ln in out.splitlines() if ln.startswith(prefix)]


def test_progress_writes_a_line_every_tenth_and_the_last_in_a_log():
    log = io.StringIO()
    bar = Progress(40, "heliotwin x: year", unit="chunk", lines=log, stream=io.StringIO())
    for _ in range(40):
        bar.update()
    lines = log.getvalue().splitlines()
    assert len(lines) == 10 and lines[0].startswith("heliotwin x: year: 10% (4/40 chunks")
    assert lines[-1].startswith("heliotwin x: year: 100% (40/40 chunks")
    quiet = io.StringIO()
    assert list(iterate(range(3), "q", enabled=False)) == [0, 1, 2] and quiet.getvalue() == ""


def test_predict_prints_plain_lines_and_nothing_with_quiet(tmp_path, capsys):
    sc = learned_scenario(tmp_path / "s.h5")
    code, out, err = run_cli(capsys, "predict", "--scenario", sc, "--every", "47h", "--json", tmp_path / "p.json")
    assert code == 0, err
    lines = _lines(out, "heliotwin predict: year: ")
    assert lines and lines[-1].startswith("heliotwin predict: year: 100% (") and err == ""
    code, out, err = run_cli(capsys, "predict", "--scenario", sc, "--every", "47h", "--json", tmp_path / "q.json",
                             "--quiet")
    assert code == 0 and out == "" and err == ""


def test_trace_and_validate_print_plain_lines_and_nothing_with_quiet(tmp_path, capsys, paint_dir):
    root = copy_paint(paint_dir, tmp_path)
    rid = sorted((root / "AA39" / "Calibration").glob("*-calibration-properties.json"))[0].name.split("-")[0]
    trace = ("trace", "--paint", root, "--heliostat", "AA39", "--record", rid, "--integrator", "gaussian",
             "--samples", "8", "--resolution", "32", "-o", tmp_path / "t.png")
    code, out, err = run_cli(capsys, *trace)
    assert code == 0, err
    lines = _lines(out, "heliotwin trace: ")
    assert [ln.split(" (")[0] for ln in lines] == [f"heliotwin trace: 1/1 tracing record {rid}",
                                                   f"heliotwin trace: 1/1 tracing record {rid} done"]
    code, out, _ = run_cli(capsys, *trace[:-1], tmp_path / "q.png", "--quiet")
    assert code == 0 and out == ""
    validate = ("validate", "--paint", root, "--resolution", "32", "--samples", "4", "--no-images")
    code, out, err = run_cli(capsys, *validate, "--json", tmp_path / "v.json")
    assert code == 0, err
    assert _lines(out, "heliotwin validate: ")[-1].startswith("heliotwin validate: 100% (")
    code, out, _ = run_cli(capsys, *validate, "--json", tmp_path / "w.json", "--quiet")
    assert code == 0 and out == ""


@pytest.mark.slow  # each measurement runs for at least 2 s: about 10 s
def test_bench_says_each_measurement(capsys):
    run_benchmark(surface_points=64, rays_per_point=2, resolution=16, repeats=1, time_to_accuracy=False,
                  progress=True)
    out = capsys.readouterr().out
    lines = _lines(out, "heliotwin bench: ")
    assert [ln.split(" (")[0] for ln in lines if "done" in ln] == [
        "heliotwin bench: 1/2 forward, 2 rays per point done", "heliotwin bench: 2/2 forward and backward, 2 rays "
                                                                "per point done"]
    run_benchmark(surface_points=64, rays_per_point=2, resolution=16, repeats=1, time_to_accuracy=False)
    assert capsys.readouterr().out == ""


@pytest.mark.slow  # a short reconstruction on real images: about a minute on the busy 2-core machine
def test_reconstruct_prints_its_stages_and_cross_validation_in_plain_lines(tmp_path, capsys, paint_dir):
    root = copy_paint(paint_dir, tmp_path)
    argv = ("reconstruct", "--paint", root, "--heliostat", "AA39", "--steps", "4", "--control-points", "4x4",
            "--degree", "2", "--slope-error", "1")
    code, out, err = run_cli(capsys, *argv, "--json", tmp_path / "r.json")
    assert code == 0, err
    assert _lines(out, "heliotwin reconstruct: 2/2 learning the surface done")
    assert _lines(out, "heliotwin reconstruct: cross-validation: 100% (")  # every image trains: 3 folds
    code, out, _ = run_cli(capsys, *argv, "--json", tmp_path / "q.json", "--quiet")
    assert code == 0 and out == ""
