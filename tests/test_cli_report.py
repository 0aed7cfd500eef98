"""The one output writer (heliotwin.io.report): atomic files, strict JSON, figures -- and what is left on failure."""
from __future__ import annotations

import json
import math
import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import heliotwin
from heliotwin.errors import InputFileError
from heliotwin.io.report import atomic_path, save_figure, write_json


def _write(path, text):
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def test_atomic_path_replaces_only_on_success(tmp_path):
    out = tmp_path / "r.txt"
    _write(out, "old")
    for exc in (RuntimeError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with atomic_path(out) as tmp:
                Path(tmp).write_text("half")
                raise exc
        assert out.read_text() == "old"
        assert [p.name for p in tmp_path.iterdir()] == ["r.txt"]


def test_missing_folder_is_an_error_unless_asked_to_make_it(tmp_path):
    out = tmp_path / "a" / "b" / "r.png"
    with pytest.raises(InputFileError, match="cannot write"):
        _write(out, "x")
    assert list(tmp_path.iterdir()) == []
    with atomic_path(out, make_folder=True) as tmp:
        assert Path(tmp).parent == out.parent and tmp.endswith(".png")  # the format can follow the name
        Path(tmp).write_bytes(b"x")
    assert out.read_bytes() == b"x"
    write_json(tmp_path / "c" / "r.json", {})  # reports make their folder, as they always did
    assert (tmp_path / "c" / "r.json").read_text() == "{}\n"


@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions")
def test_new_files_are_readable_existing_keep_their_mode(tmp_path):
    out = tmp_path / "r.json"
    write_json(out, {})
    assert stat.S_IMODE(out.stat().st_mode) == 0o644  # mkstemp's 0600 must not survive the rename
    out.chmod(0o600)
    write_json(out, {"a": 1})
    assert stat.S_IMODE(out.stat().st_mode) == 0o600


def test_unwritable_destination_names_the_users_path(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    for out in (blocker / "r.json", tmp_path):  # a file where the folder should be; a folder in the way
        with pytest.raises(InputFileError) as exc:
            write_json(out, {"a": 1})
        msg = str(exc.value)
        assert msg.startswith(f"{out}: cannot write") and ".tmp-" not in msg and len(msg.splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_oserror_about_another_file_is_not_relabelled(tmp_path):
    with pytest.raises(FileNotFoundError) as exc:
        with atomic_path(tmp_path / "out.json"):
            open(tmp_path / "input.json")
    assert "input.json" in str(exc.value)
    assert list(tmp_path.iterdir()) == []


def test_write_json_is_strict(tmp_path):
    out = tmp_path / "r.json"
    write_json(out, {"nan": math.nan, "inf": [1.0, -math.inf], "t": torch.tensor([1.5, math.nan]),
                     "a": np.array([[1, 2]]), "np": np.float32(0.5), "n": np.int64(3), "b": np.bool_(True),
                     "path": tmp_path, 1: (2, 3), "scalar": torch.tensor(math.inf)})
    text = out.read_text()
    assert "NaN" not in text and "Infinity" not in text and text.endswith("\n")
    assert json.loads(text) == {"nan": None, "inf": [1.0, None], "t": [1.5, None], "a": [[1, 2]], "np": 0.5, "n": 3,
                                "b": True, "path": str(tmp_path), "1": [2, 3], "scalar": None}


def test_write_json_refuses_what_json_cannot_hold(tmp_path):
    out = tmp_path / "r.json"
    with pytest.raises(TypeError):
        write_json(out, {"ids": {"AA39"}})
    assert list(tmp_path.iterdir()) == []


def test_save_figure_writes_closes_and_leaves_the_backend(tmp_path):
    import matplotlib
    import matplotlib.pyplot as plt
    from matplotlib.figure import Figure

    backend = matplotlib.get_backend()
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    save_figure(fig, tmp_path / "p.png")
    assert not plt.fignum_exists(fig.number)
    fig = Figure()
    fig.subplots().plot([0, 1])
    save_figure(fig, tmp_path / "p.pdf", tight=False)
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "p.pdf").read_bytes()[:4] == b"%PDF"
    assert matplotlib.get_backend() == backend
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.pdf", "p.png"]


def test_plots_do_not_switch_the_callers_backend(tmp_path):
    """A notebook's backend stays; the PNG is still written (figures need no backend)."""
    code = ("import matplotlib, heliotwin.plots as p; "
            "p.plot_validation({'heliostats': {'A': {'median_pointing_error_mrad': 1.0, 'median_distance_m': 0.1}}, "
            f"'overall': {{'median_pointing_error_mrad': 1.0}}}}, {str(tmp_path / 'v.png')!r}); "
            "print(matplotlib.get_backend())")
    env = dict(os.environ, MPLBACKEND="svg",
               PYTHONPATH=os.pathsep.join([str(Path(heliotwin.__file__).resolve().parents[1]),
                                           os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "svg"
    assert (tmp_path / "v.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions")
def test_new_outputs_follow_the_umask(tmp_path):
    from heliotwin.io.report import output_set

    old = os.umask(0o027)
    try:
        write_json(tmp_path / "a.json", {})
        with output_set() as out:
            write_json(out.file(tmp_path / "b.json", "--json"), {})
            folder = out.folder(tmp_path / "demo", "-o")
            write_json(os.path.join(folder, "c.json"), {})
    finally:
        os.umask(old)
    for name in ("a.json", "b.json", "demo/c.json"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o640, name
    assert stat.S_IMODE((tmp_path / "demo").stat().st_mode) == 0o750
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.json", "demo"]


def test_output_set_moves_all_or_nothing(tmp_path):
    from heliotwin.io.report import output_set

    (tmp_path / "b.json").write_text("old")
    with pytest.raises(RuntimeError):
        with output_set() as out:
            write_json(out.file(tmp_path / "a.json", "--json"), {"a": 1})
            write_json(out.file(tmp_path / "b.json", "-o"), {"b": 1})
            raise RuntimeError("the last step fails")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.json"] and (tmp_path / "b.json").read_text() == "old"
    with output_set([("--paint", tmp_path / "b.json")]) as out:
        with pytest.raises(InputFileError, match=r"b.json \[--json\]: is the input --paint"):
            out.file(tmp_path / "b.json", "--json")
        write_json(out.file(tmp_path / "a.json", "--json"), {"a": 1})
    assert json.loads((tmp_path / "a.json").read_text()) == {"a": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.json"]
