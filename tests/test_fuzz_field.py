"""Misuse of the field commands (``scenario from-layout``, ``field``, ``aimpoints``) and their readers: every bad
input is refused with one line naming the file or option -- no traceback, no "internal error", no hang, no
silent NaN or out-of-range result, no input modified, nothing left behind; an unmet peak limit says so and
exits 3. The ~1,000-case campaign behind these cases is ``benchmarks/fuzz_field.py``.
"""
from __future__ import annotations

import contextlib
import glob
import hashlib
import json
import math
import os
import tempfile
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from helpers.cli import assert_one_line_error
from helpers.field import PLANT_TOML, dense_field, write_layout, write_plant_toml

from heliotwin.errors import HeliotwinError, InputFileError
from heliotwin.field.layout import check_memory, check_spacing

SUN = ("--sun-azimuth", "10", "--sun-elevation", "40")
FAST = ("--resolution", "8x4", "--quiet")
AIM_FAST = ("--resolution", "8x4", "--iterations", "3", "--no-baselines", "--quiet")


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A 6-heliostat field: layout, plant description, scenario and the scenario with learned aim points."""
    d = tmp_path_factory.mktemp("base")
    write_layout(d, dense_field(2, 3), ids=[f"h{i}" for i in range(6)])
    write_plant_toml(d)
    from heliotwin.cli import main

    with contextlib.redirect_stdout(None):
        assert main(["scenario", "from-layout", str(d / "layout.csv"), "--config", str(d / "plant.toml"), "-o",
                     str(d / "p.h5"), "--quiet"]) == 0
        assert main(["aimpoints", "--scenario", str(d / "p.h5"), *SUN, "--peak-limit", "1e6", *AIM_FAST,
                     "-o", str(d / "a.h5"), "--json", str(d / "a.json")]) == 0
    return d


@pytest.fixture
def work(base, tmp_path):
    """A fresh folder with copies of the base files; ``work.check()`` asserts the inputs are untouched."""
    for name in ("layout.csv", "plant.toml", "p.h5", "a.h5"):
        (tmp_path / name).write_bytes((base / name).read_bytes())
    before = _snapshot(tmp_path)
    errorfiles = set(glob.glob(os.path.join(tempfile.gettempdir(), "pytorch-errorfile-*")))

    def check(expect_new=()):
        after = _snapshot(tmp_path)
        assert {k: v for k, v in after.items() if k in before} == before, "an input was modified"
        assert sorted(set(after) - set(before)) == sorted(expect_new), "unexpected files left"
        assert set(glob.glob(os.path.join(tempfile.gettempdir(), "pytorch-errorfile-*"))) <= errorfiles

    old = os.getcwd()
    os.chdir(tmp_path)
    yield _Work(tmp_path, check)
    os.chdir(old)


class _Work(type(Path())):
    """The case folder (a path) with its ``check`` of inputs and leftovers."""

    def __new__(cls, path, check):
        self = super().__new__(cls, path)
        self.check = check
        return self


def run_cli(capsys, *argv):
    """``heliotwin ARGV...`` in-process: (exit status, stdout, stderr); argparse's refusals (SystemExit) too."""
    from heliotwin.cli import main

    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def _snapshot(folder: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir() if p.is_file()}


def _finite_report(path: Path) -> dict:
    """A report with no null, no NaN and every efficiency within [0, 1]."""
    doc = json.loads(path.read_text())

    def walk(obj, where=""):
        if isinstance(obj, dict):
            for k, v in obj.items():
                walk(v, f"{where}.{k}")
                if k in ("cosine", "shading", "blocking", "attenuation", "intercept", "total") and \
                        isinstance(v, float):
                    assert 0.0 <= v <= 1.0, (where, k, v)
        elif isinstance(obj, list):
            for v in obj:
                walk(v, where)
        else:
            assert obj is not None or where.endswith(".scenario"), where
            assert not isinstance(obj, float) or math.isfinite(obj), where
    walk(doc)
    return doc


# ------------------------------------------------------------------------------------------ arguments
@pytest.mark.parametrize("extra, needle", [
    (("--sun-azimuth=nan", "--sun-elevation=40"), "--sun-azimuth"),
    (("--sun-azimuth=1e308", "--sun-elevation=40"), "--sun-azimuth"),
    (("--sun-azimuth=10", "--sun-elevation=inf"), "--sun-elevation"),
    (("--sun-azimuth=10", "--sun-elevation=nan"), "--sun-elevation"),
    (("--sun-azimuth=10", "--sun-elevation=-5"), "below the horizon"),
    (("--sun-azimuth=10", "--sun-elevation=90.5"), "--sun-elevation"),
    ((*SUN, "--dni=inf"), "--dni"),
    ((*SUN, "--dni=nan"), "--dni"),
    ((*SUN, "--dni=-1"), "--dni"),
    ((*SUN, "--dni=1e30"), "--dni"),
    (("--time=2023-06-21T00:00Z",), "below the horizon"),
    (("--time=garbage",), "--time"),
    (("--year=0",), "--year"),
    (("--year=2023", "--every=0min"), "--every"),
    (("--year=2023", "--every=31d"), "a whole number of days"),
    (("--year=2023", "--every=1d"), "a whole number of days"),
    (("--year=2023", "--every=7h", "--table-azimuth-step=0"), "--table-azimuth-step"),
    ((*SUN, "--resolution=0x4"), "--resolution"),
    ((*SUN, "--nproc=0"), "--nproc"),
    ((*SUN, "--seed=-1"), "--seed"),
    ((*SUN, "--aim", "scenario"), "no aim points"),
])
def test_field_refuses_bad_arguments_in_one_line(work, capsys, extra, needle):
    code, out, err = run_cli(capsys, "field", "--scenario", "p.h5", "--json", "f.json", *FAST, *extra)
    assert code == 2
    assert_one_line_error(code, err, needle)
    work.check()


@pytest.mark.parametrize("extra, needle", [
    (("--peak-limit=nan", *SUN), "--peak-limit"),
    (("--peak-limit=inf", *SUN), "--peak-limit"),
    (("--peak-limit=0", *SUN), "--peak-limit"),
    (("--peak-limit=1e6", "--day=2023-06-21", "--every=0min"), "--every"),
    (("--peak-limit=1e6", "--day=2023-06-21", "--every=31d"), "longer than the day"),
    (("--peak-limit=1e6", "--day=0"), "--day"),
    (("--peak-limit=1e6", "--time=,"), "--time"),
    (("--peak-limit=1e6", "--sun-azimuth=nan", "--sun-elevation=40"), "--sun-azimuth"),
    (("--peak-limit=1e6", "--target=missing.csv", *SUN), "missing.csv"),
])
def test_aimpoints_refuses_bad_arguments_in_one_line(work, capsys, extra, needle):
    code, out, err = run_cli(capsys, "aimpoints", "--scenario", "p.h5", "-o", "o.h5", "--json", "o.json",
                             *AIM_FAST, *extra)
    assert_one_line_error(code, err, needle)
    assert code == 2
    work.check()


def test_a_huge_receiver_map_is_the_out_of_memory_line(work, capsys):
    code, _, err = run_cli(capsys, "field", "--scenario", "p.h5", "--json", "f.json", *SUN, "--quiet",
                           "--resolution", "100000x100000")
    assert code == 1 and err.startswith("heliotwin: error: out of memory") and "internal error" not in err
    work.check()


def test_a_year_is_a_finite_report(work, capsys):
    code, out, err = run_cli(capsys, "field", "--scenario", "p.h5", "--json", "y.json", "--year", "2023",
                             "--every", "7h", "--table-azimuth-step", "90")
    assert code == 0, err
    report = _finite_report(work / "y.json")
    assert report["instants"] > 0 and 0 < report["mean_efficiency"] < 1
    assert "nan" not in out.lower()
    work.check(["y.json"])


# -------------------------------------------------------------------------------------------- outputs
@pytest.mark.parametrize("argv, needle", [
    (("field", "--scenario", "p.h5", *SUN, *FAST, "--json", "p.h5"), "is the input --scenario"),
    (("field", "--scenario", "p.h5", *SUN, *FAST, "--json", "f.json", "--per-heliostat", "p.h5"), "input"),
    (("field", "--scenario", "p.h5", *SUN, *FAST, "--json", "f.json", "--flux", "./p.h5"), "input"),
    (("field", "--scenario", "p.h5", *SUN, *FAST, "--json", "x", "--per-heliostat", "x"), "also the output"),
    (("field", "--scenario", "p.h5", "--year", "2023", "--json", "p.h5"), "input"),
    (("field", "--scenario", "p.h5", *SUN, *FAST, "--json", "f.json", "--per-heliostat", "no/x.csv"),
     "does not exist"),
    (("aimpoints", "--scenario", "p.h5", *SUN, *AIM_FAST, "--peak-limit", "1e6", "-o", "p.h5", "--json", "o.json"),
     "input"),
    (("aimpoints", "--scenario", "p.h5", *SUN, *AIM_FAST, "--peak-limit", "1e6", "-o", "o.h5", "--json", "o.h5"),
     "also the output"),
    (("scenario", "from-layout", "layout.csv", "--config", "plant.toml", "-o", "layout.csv"), "input"),
    (("scenario", "from-layout", "layout.csv", "--config", "plant.toml", "-o", "./plant.toml"), "input"),
])
def test_no_output_replaces_an_input_or_another_output(work, capsys, argv, needle):
    code, _, err = run_cli(capsys, *argv)
    assert code == 2
    assert_one_line_error(code, err, needle)
    work.check()


def test_field_writes_all_its_outputs_or_none(work, capsys, monkeypatch):
    """The flux map fails after the report and the CSV were produced: none of the three is written, and an
    older report stays as it was."""
    import heliotwin.plots as plots

    (work / "f.json").write_text("old\n")
    work.check = _rebase(work)

    def broken(*args, **kwargs):  # plot_receiver_flux(maps, receiver, path, ...)
        raise OSError(28, "No space left on device", str(args[2]))

    monkeypatch.setattr(plots, "plot_receiver_flux", broken)
    code, _, err = run_cli(capsys, "field", "--scenario", "p.h5", *SUN, *FAST, "--json", "f.json",
                           "--per-heliostat", "h.csv", "--flux", "m.png")
    assert code == 2 and "No space left" in err
    assert (work / "f.json").read_text() == "old\n"
    work.check()


def _rebase(folder: Path):
    before = _snapshot(folder)

    def check(expect_new=()):
        after = _snapshot(folder)
        assert {k: v for k, v in after.items() if k in before} == before
        assert sorted(set(after) - set(before)) == sorted(expect_new)
        assert not [p for p in folder.iterdir() if p.name.startswith((".heliotwin-", ".tmp-"))]
    return check


def test_field_writes_its_three_outputs_with_finite_values(work, capsys):
    code, out, err = run_cli(capsys, "field", "--scenario", "p.h5", *SUN, "--resolution", "8x4", "--json",
                             "f.json", "--per-heliostat", "h.csv", "--flux", "m.png")
    assert code == 0, err
    _finite_report(work / "f.json")
    rows = (work / "h.csv").read_text().splitlines()
    assert len(rows) == 7 and "nan" not in (work / "h.csv").read_text().lower()
    work.check(["f.json", "h.csv", "m.png"])


# ----------------------------------------------------------------------------------- plant descriptions
def _replace(text: str, old: str, new: str) -> str:
    assert old in text
    return text.replace(old, new)


COEFFICIENTS = "coefficients = [0.006789, 0.1046, -0.0107, 0.002845]"


@pytest.mark.parametrize("toml, needle", [
    (_replace(PLANT_TOML, COEFFICIENTS, "coefficients = [-5.0, 0.0, 0.0, 0.0]"), "attenuation"),
    (_replace(PLANT_TOML, COEFFICIENTS, "coefficients = [0.0, 50.0, 0.0, 0.0]"), "attenuation"),
    (_replace(PLANT_TOML, "center = [0.0, 0.0, 55.0]", "center = [0.0, 0.0, -20.0]"), "below the ground"),
    (_replace(PLANT_TOML, "center = [0.0, 0.0, 55.0]", "center = [0.0, 0.0, 1.0]"), "below the ground"),
    (_replace(PLANT_TOML, "facets = [1, 1]", "facets = [3000, 3000]"), "heliostat.facets"),
    (_replace(PLANT_TOML, "dni = 1000.0", "dni = inf"), "sun.dni"),
    (_replace(PLANT_TOML, "dni = 1000.0", "dni = 1e9"), "sun.dni"),
    (_replace(PLANT_TOML, "width = 3.22            # m", "width = 1e6"), "heliostat.width"),
    (_replace(PLANT_TOML, "latitude = 50.9134", "latitude = nan"), "site.latitude"),
    (bytes(range(256)) * 4, "not UTF-8"),
    (b"a=" + b"[" * 5000 + b"]" * 5000, "plant.toml"),
])
def test_an_impossible_plant_description_is_refused(work, capsys, toml, needle):
    (work / "plant.toml").write_bytes(toml if isinstance(toml, bytes) else toml.encode())
    work.check = _rebase(work)
    code, _, err = run_cli(capsys, "scenario", "from-layout", "layout.csv", "--config", "plant.toml", "-o", "x.h5")
    assert code == 2
    assert_one_line_error(code, err, needle)
    work.check()


@pytest.mark.parametrize("extra_rows, needle", [
    (["dup,-4.0,30.0,0.0"], "collide"),  # on the pivot of h0
    (["near,-3.5,30.0,0.0"], "collide"),
    (["far,0.0,1e7,0.0"], "from the tower base"),
    (["far,0.0,1e300,0.0"], "from the tower base"),
    (["tower,0.0,0.0,0.0"], "inside the tower"),
    (["h\x00x,0.0,80.0,0.0"], "control character"),
])
def test_an_impossible_layout_is_refused(work, capsys, extra_rows, needle):
    with open(work / "layout.csv", "a") as fh:
        fh.write("\n".join(extra_rows) + "\n")
    work.check = _rebase(work)
    code, _, err = run_cli(capsys, "scenario", "from-layout", "layout.csv", "--config", "plant.toml", "-o", "x.h5")
    assert code == 2
    assert_one_line_error(code, err, needle, "layout.csv")
    work.check()


def test_spacing_check_matches_all_pairs_and_passes_a_dense_field():
    gen = torch.Generator().manual_seed(0)
    for _ in range(20):
        p = torch.rand(150, 3, generator=gen, dtype=torch.float64) * 50.0
        d = torch.cdist(p[:, :2], p[:, :2]) + torch.eye(150) * 1e9
        too_close = bool((d < 2.56).any())
        try:
            check_spacing(p, 2.56, "x.csv")
            refused = False
        except InputFileError:
            refused = True
        assert refused == too_close
    check_spacing(torch.as_tensor(dense_field(30, 30), dtype=torch.float64), 2.56, "x.csv")  # 3.6 m rows


def test_a_plant_larger_than_memory_is_the_out_of_memory_error():
    with pytest.raises(MemoryError, match="GiB"):
        check_memory(10**9, (8, 8), (4, 4), "huge.csv")
    check_memory(10_000, (1, 1), (4, 4), "fine.csv")


# -------------------------------------------------------------------------------------------- scenarios
def _damage(path: Path, name: str, value=None, attr: str | None = None, delete: bool = False):
    with h5py.File(path, "r+") as h5:
        if attr is not None:
            h5[name].attrs[attr] = value
        elif delete:
            del h5[name]
        else:
            attrs = dict(h5[name].attrs)
            del h5[name]
            h5[name] = value
            h5[name].attrs.update(attrs)


@pytest.mark.parametrize("file, name, value, attr, delete, needle", [
    ("p.h5", "targets/receiver/center", np.array([0.0, np.nan, 55.0]), None, False, "/targets/receiver/center"),
    ("p.h5", "targets/receiver/normal", np.zeros(3), None, False, "/targets/receiver/normal"),
    ("p.h5", "targets/receiver", np.nan, "radius", False, "/targets/receiver@radius"),
    ("p.h5", "targets/receiver", -5.0, "height", False, "/targets/receiver@height"),
    ("p.h5", "sun", np.nan, "dni", False, "/sun@dni"),
    ("p.h5", "field/width", np.full(6, np.nan), None, False, "/field/width"),
    ("p.h5", "extras/atmosphere/coefficients", np.array([-5.0, 0, 0, 0]), None, False, "attenuation"),
    ("p.h5", "extras/atmosphere/coefficients", np.array([np.nan, 0, 0, 0]), None, False, "coefficients"),
    ("a.h5", "learned/aimpoints/aim", np.full((6, 3), np.nan), None, False, "/learned/aimpoints/aim"),
    ("a.h5", "learned/aimpoints/sun_direction", None, None, True, "/learned/aimpoints/sun_direction"),
    ("a.h5", "learned/aimpoints/instants/i000/sun_direction", np.array([0.0, 0.0, 0.0]), None, False,
     "sun_direction"),
    ("a.h5", "learned/aimpoints/instants/i000/aim", np.zeros((5, 3)), None, False, "shape"),
    ("a.h5", "learned/aimpoints/motor_steps", np.full((6, 2), np.inf), None, False, "motor_steps"),
])
def test_a_damaged_scenario_is_refused_naming_the_dataset(work, capsys, file, name, value, attr, delete, needle):
    _damage(work / file, name, value, attr, delete)
    work.check = _rebase(work)
    code, _, err = run_cli(capsys, "field", "--scenario", file, *SUN, *FAST, "--json", "f.json", "--aim",
                           "scenario" if file == "a.h5" else "equator")
    assert code == 2
    assert_one_line_error(code, err, needle, file)
    work.check()


def test_field_with_stored_aim_points_is_finite(work, capsys):
    code, _, err = run_cli(capsys, "field", "--scenario", "a.h5", *SUN, *FAST, "--json", "f.json", "--aim",
                           "scenario")
    assert code == 0, err
    _finite_report(work / "f.json")


# ------------------------------------------------------------------------------------------- FIFOs
@contextlib.contextmanager
def _unblocking(fifo: Path, after: float = 20.0):
    """Should a reader block on ``fifo`` after all, feed it garbage after ``after`` s so the test fails instead
    of hanging."""
    done = threading.Event()

    def feed():
        if done.wait(after):
            return
        while not done.is_set():
            try:
                fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
            except OSError:
                time.sleep(0.05)
                continue
            os.close(fd)
    t = threading.Thread(target=feed, daemon=True)
    t.start()
    try:
        yield
    finally:
        done.set()
        t.join()


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="POSIX FIFOs")
@pytest.mark.parametrize("fifo, argv", [
    ("layout.csv", ("scenario", "from-layout", "layout.csv", "--config", "plant.toml", "-o", "x.h5")),
    ("plant.toml", ("scenario", "from-layout", "layout.csv", "--config", "plant.toml", "-o", "x.h5")),
    ("p.h5", ("field", "--scenario", "p.h5", *SUN, *FAST, "--json", "f.json")),
    ("t.csv", ("aimpoints", "--scenario", "p.h5", *SUN, *AIM_FAST, "--peak-limit", "1e6", "--target", "t.csv",
               "-o", "o.h5", "--json", "o.json")),
])
def test_a_fifo_where_a_file_is_expected_is_refused_at_once(work, capsys, fifo, argv):
    (work / fifo).unlink(missing_ok=True)
    os.mkfifo(work / fifo)
    work.check = _rebase(work)
    with _unblocking(work / fifo):
        code, _, err = run_cli(capsys, *argv)
    assert code == 2
    assert_one_line_error(code, err, "FIFO", fifo)


def test_library_readers_refuse_a_fifo(tmp_path):
    from heliotwin.field.layout import read_layout, read_plant_config
    from heliotwin.io.scenario import load_scenario

    os.mkfifo(tmp_path / "x")
    with _unblocking(tmp_path / "x"):
        for reader in (read_layout, read_plant_config, load_scenario):
            with pytest.raises(InputFileError, match="FIFO"):
                reader(tmp_path / "x")


# ------------------------------------------------------------------------------------------- peak limit
def test_a_limit_no_full_field_can_hold_is_held_with_heliostats_on_standby(work, capsys):
    """1 kW/m2 (the lowest plausible limit) is below what the field puts on the receiver: the best feasible answer
    sends heliostats to standby (less power, the limit held) and says so; exit 3 is kept for a limit no aim points at
    all hold."""
    code, out, err = run_cli(capsys, "aimpoints", "--scenario", "p.h5", *SUN, *AIM_FAST, "--peak-limit",
                             "1000", "-o", "o.h5", "--json", "o.json")
    assert code == 0, err
    report = json.loads((work / "o.json").read_text())
    best = report["optimised"] if "optimised" in report else report["instants"][0]["optimised"]
    assert best["peak_flux_w_m2"] <= 1000 * (1 + 1e-6)
    assert "standby" in json.dumps(report)
    work.check(["o.h5", "o.json"])


# -------------------------------------------------------------------------------------------- workers
def test_nproc_above_the_heliostat_count_is_clamped(work, monkeypatch):
    import heliotwin.workflows.field_one_sun as wf  # where the field workflow (and its run_sharded) lives
    from heliotwin.io.scenario import load_scenario

    used = []

    def fake(plant, sun, nproc, **kwargs):
        used.append(nproc)
        with torch.no_grad():
            return wf.field_optics(plant, sun, **kwargs)

    monkeypatch.setattr(wf, "run_sharded", fake)
    sc = load_scenario(work / "p.h5")
    report, _ = wf.field(sc, wf.sun_from_angles(10.0, 40.0), wf.FieldRunSettings(resolution=(4, 8), nproc=50))
    assert used == [6]
    assert 0 < report["field"]["efficiency"]["total"] < 1


def test_settings_refuse_what_no_run_can_use():
    from heliotwin.workflows.aimpoints import AimpointSettings
    from heliotwin.workflows.field import FieldRunSettings
    from heliotwin.workflows.plan import PlanSettings

    for bad in (dict(dni=float("nan")), dict(dni=float("inf")), dict(dni=-1.0), dict(resolution=(0, 4)),
                dict(nproc=0)):
        with pytest.raises(HeliotwinError):
            FieldRunSettings(**bad)
    with pytest.raises(MemoryError):
        FieldRunSettings(resolution=(100_000, 100_000))
    for limit in (float("nan"), float("inf"), 0.0, -1.0):
        with pytest.raises(HeliotwinError, match="--peak-limit"):
            AimpointSettings(peak_limit_w_m2=limit)
    for bad in (dict(every="0min"), dict(every="1D"), dict(every="x"), dict(year=0), dict(count=0),
                dict(min_elevation=float("nan"))):
        with pytest.raises(HeliotwinError):
            PlanSettings(**bad)


def _raise_input_error(job, group):
    raise HeliotwinError(f"rank {job['n']}: a bad value")


@pytest.mark.slow  # spawns a torch process: about 20 s on the busy 2-core machine
def test_a_worker_error_is_one_line_and_leaves_no_error_file():
    from heliotwin.distributed import run_spawned

    before = set(glob.glob(os.path.join(tempfile.gettempdir(), "pytorch-errorfile-*")))
    with pytest.raises(HeliotwinError) as info:
        run_spawned(_raise_input_error, {"n": 0}, 1)
    assert str(info.value) == "rank 0: a bad value"
    assert set(glob.glob(os.path.join(tempfile.gettempdir(), "pytorch-errorfile-*"))) <= before


# ------------------------------------------------------------------------------------------------ README
def test_every_command_example_in_the_readme_parses():
    """A README example the parser refuses (the ``aim --time`` one once lacked ``--aim``) is a broken promise.

    Optional parts (``[--nproc 2]``) are left out; the values are only parsed, nothing runs."""
    import re
    import shlex

    from heliotwin.cli import _join_signed_values, build_parser

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    commands = [line.split(" #")[0].strip()
                for block in re.findall(r"^```[a-z]*\n(.*?)^```", readme, re.S | re.M)
                for line in block.replace("\\\n", " ").splitlines() if line.strip().startswith("heliotwin ")]
    assert len(commands) >= 20 and any(c.startswith("heliotwin aim ") and "--time" in c for c in commands)
    for command in commands:
        argv = shlex.split(re.sub(r"\[[^\]]*\]", "", command))[1:]
        try:
            build_parser().parse_args(_join_signed_values(argv))
        except SystemExit:
            pytest.fail(f"README example refused: {command}")
