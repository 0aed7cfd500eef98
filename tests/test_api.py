"""The public API (heliotwin.api): three lines from PAINT to a labelled figure, the CLI's defaults, and no
global side effects on import."""
from __future__ import annotations

import inspect
import os
import subprocess
import sys
from pathlib import Path

import pytest

import heliotwin
from heliotwin import api
from heliotwin.cli import build_parser
from heliotwin.workflows.calibrate import CalibrationSettings
from heliotwin.workflows.reconstruct import ReconstructionSettings

SRC = Path(heliotwin.__file__).resolve().parents[1]


def _defaults(*command):
    """The CLI's default of every option of ``heliotwin COMMAND`` (dest -> default)."""
    import argparse

    parser = build_parser()
    for name in command:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[name]
    return {a.dest: a.default for a in parser._actions if a.option_strings}


@pytest.mark.parametrize("func, command, renamed", [
    (api.trace_record, ("trace",), {}),
    (api.calibrate, ("calibrate",), {}),
    (CalibrationSettings, ("calibrate",), {}),  # api.calibrate's settings (its keywords)
    (ReconstructionSettings, ("reconstruct",), {"slope_error_mrad": "slope_error"}),
])
def test_api_defaults_are_the_cli_defaults(func, command, renamed):
    cli = _defaults(*command)
    special = {("reconstruct", "slope_error"): ("auto", None), ("calibrate", "progress"): (False, True),
               ("reconstruct", "progress"): (None, True)}
    checked = 0
    for name, p in inspect.signature(func).parameters.items():
        dest = renamed.get(name, name)
        if p.default is inspect.Parameter.empty or dest not in cli:
            continue
        expected = cli[dest]
        if (command[0], dest) in special:
            expected = special[(command[0], dest)][1]
        if dest == "control_points":
            expected = "7x7"
        assert p.default == expected, (func.__name__, name, p.default, cli[dest])
        checked += 1
    assert checked >= 4


def test_importing_the_api_and_plots_has_no_global_side_effects(tmp_path):
    """Importing ``heliotwin.api`` (which imports torch and the library) keeps the caller's matplotlib backend,
    imports no pyplot, and leaves torch's threads and default dtype as they were."""
    code = ("import sys, matplotlib; matplotlib.use('svg'); import torch; "
            "before = (torch.get_num_threads(), torch.get_default_dtype()); import heliotwin.api, heliotwin.plots; "
            "print(matplotlib.get_backend(), 'matplotlib.pyplot' in sys.modules, "
            "(torch.get_num_threads(), torch.get_default_dtype()) == before)")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")]))
    env.pop("MPLBACKEND", None)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["svg", "False", "True"], proc.stderr


def test_three_lines_from_paint_to_a_labelled_figure(paint_dir, tmp_path):
    ds = api.load(paint_dir, heliostats=["AA39"])
    rid = 151375  # on the lower calibration target
    flux, report = api.trace_record(ds, rid, rays_per_point=8, samples=16, resolution=64)
    fig = api.plot_flux(flux, tmp_path / "flux.png", measured=report)
    assert (tmp_path / "flux.png").read_bytes()[:4] == b"\x89PNG"
    # physics: energy bookkeeping and a centroid near the measured spot (nominal kinematics: < 3 m)
    assert 0 < report["intercepted_power_w"] <= report["total_power_w"] * (1 + 1e-6)
    meas = report["measured_spot_enu_m"]["HeliOS"]
    assert sum((a - b) ** 2 for a, b in zip(report["centroid_enu_m"], meas)) ** 0.5 < 3.0
    assert 0 < report["sun_elevation_deg"] <= 90
    # a figure people read: the camera image next to the prediction, titles, axis labels with units, colour
    # bars, the measured spot in the legend
    camera, ax, camera_bar, cbar = fig.axes
    assert report["measured_flux_png"].endswith("151375-flux.png")
    assert "measured" in camera.get_title() and "predicted" in ax.get_title()
    assert flux.target.name in fig._suptitle.get_text()
    assert "[m]" in camera.get_xlabel() and "relative" in camera_bar.get_ylabel()
    assert "[m]" in ax.get_xlabel() and "[m]" in ax.get_ylabel() and "kW/m²" in cbar.get_ylabel()
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "measured (HeliOS)" in labels and "predicted centroid" in labels
    # same record, same seed: the CLI's numbers
    again, _ = api.trace_record(ds, rid, rays_per_point=8, samples=16, resolution=64)
    assert bool((again.bitmap == flux.bitmap).all())


def test_field_from_paint_and_scenario(paint_dir, tmp_path):
    from heliotwin.io.scenario import save_scenario

    plant = api.field(paint_dir, ["AA39", "AB38"])
    assert plant.field.ids == ["AA39", "AB38"]
    save_scenario(plant, tmp_path / "p.h5")
    again = api.field(tmp_path / "p.h5", ["AB38"])
    assert again.field.ids == ["AB38"]
    assert bool((again.field.kinematics.position[0] == plant.field.kinematics.position[1]).all())


def test_to_device_moves_every_tensor_and_keeps_dtypes(paint_dir):
    import torch

    ds = api.load(paint_dir, heliostats=["AA39"])
    moved = api.to_device((ds.plant.field.kinematics, ds.records), "cpu")
    assert moved[0].position.dtype == torch.float64 and moved[0].clockwise.dtype == torch.bool
    assert bool((moved[1].sun == ds.records.sun).all())


def test_to_device_copies_networks():
    import torch

    net = torch.nn.Linear(2, 2).double()
    moved = api.to_device({"net": net}, "cpu")["net"]
    assert moved is not net and torch.equal(moved.weight, net.weight)


def test_api_fits_refuse_a_checkpoint_of_other_settings_before_any_work(tmp_path):
    """``checkpoint=``/``resume=`` as the CLI's ``--resume``: a checkpoint of another run is one clear error,
    raised before the PAINT folder is read (it does not even exist here); without ``resume`` an existing
    checkpoint is never overwritten."""
    from heliotwin.errors import HeliotwinError
    from heliotwin.io.checkpoint import Checkpoint

    path = tmp_path / "run.ckpt"
    Checkpoint(path, "another run", min_interval_s=0).put("fit/0", {"step": 3})
    for fit in (lambda **kw: api.calibrate(tmp_path / "no-paint", checkpoint=path, **kw),
                lambda **kw: api.reconstruct(tmp_path / "no-paint", "AA39", checkpoint=path, **kw)):
        with pytest.raises(HeliotwinError, match="other settings or inputs"):
            fit(resume=True)
        with pytest.raises(HeliotwinError, match="rerun with --resume"):
            fit()
    assert path.exists()


def test_calibrate_reports_its_stages_to_a_progress_callback(paint_dir, tmp_path):
    """Every named step of the run, in order, to a callable ``progress`` (the CLI shows them as a tqdm bar)."""
    from helpers.paint import copy_paint

    from heliotwin.calibrate.protocol.pipeline import STEPS

    root = copy_paint(paint_dir, tmp_path, ("AK46",), metadata=True)
    seen = []
    report, model, _ = api.calibrate(root, train=10, test=5, min_records=20, device="cpu",
                                     progress=lambda name, i, n: seen.append((name, i, n)))
    assert [s[0] for s in seen] == [name for name, _ in STEPS]
    assert [s[1] for s in seen] == list(range(len(STEPS))) and {s[2] for s in seen} == {len(STEPS)}
    assert report["config"]["device"] == "cpu" and bool(model.ok.all())


def test_api_simulate_and_score_truth_against_itself_and_the_nominal_plant(tmp_path):
    """The in-silico plant through the API: the truth scores 0 against itself, and the nominal plant read from
    the simulated folder is off by the drawn deviations (far above the 0.15 mrad centroid noise)."""
    from heliotwin import api
    from heliotwin.io.scenario import save_scenario, scenario_from_paint

    report, truth = api.simulate(tmp_path / "paint", heliostats=5, years=0.2, seed=3, truth=tmp_path / "t.h5")
    assert report["heliostats"] == 5 and report["records"] > 0
    assert api.score(tmp_path / "t.h5", truth, flux=False)["pointing_mrad"]["median"] < 1e-9
    save_scenario(scenario_from_paint(str(tmp_path / "paint")), tmp_path / "nominal.h5")
    assert api.score(truth, tmp_path / "nominal.h5", flux=False)["pointing_mrad"]["median"] > 1.0
