"""The command line as a package: every command registered and documented, a torch-free parser, one error
reporter, and no library module depending on the CLI."""
from __future__ import annotations

import argparse
import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.cli import assert_one_line_error, run_cli

import heliotwin
from heliotwin.cli import build_parser, main, run_command
from heliotwin.errors import HeliotwinError

SRC = Path(heliotwin.__file__).resolve().parent

#: Every command a user can run. A group that fails to import must fail these tests, not vanish from --help.
COMMANDS = {("demo",), ("scenario", "from-paint"), ("scenario", "from-layout"), ("trace",), ("validate",), ("bench",),
            ("calibrate",), ("split",), ("aim",), ("plan",), ("reconstruct",), ("predict",), ("field",),
            ("aimpoints",), ("scenario", "show"), ("scenario", "export"), ("examples",), ("update",), ("history",),
            ("simulate",), ("score",), ("report",), ("daily",), ("year",)}


def _leaf_commands(parser, prefix=()):
    """Paths of the runnable (leaf) subcommands of ``parser``."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        return [prefix]
    return [leaf for name, p in subs[0].choices.items() for leaf in _leaf_commands(p, prefix + (name,))]


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(SRC.parent)] + [p for p in [env.get("PYTHONPATH")] if p])
    return env


def test_every_command_is_registered():
    assert set(_leaf_commands(build_parser())) == COMMANDS


@pytest.mark.parametrize("command", sorted(COMMANDS), ids=" ".join)
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*command, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: heliotwin {' '.join(command)}")


def test_a_command_group_that_fails_to_import_breaks_the_cli():
    """No 'except ImportError: continue': a broken group is an error, not a command that quietly vanishes."""
    code = ("import sys; sys.modules['heliotwin.cli.calibrate'] = None\n"  # None in sys.modules: import fails
            "try:\n    import heliotwin.cli\nexcept ImportError as exc:\n    print('ImportError', exc.name)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(), timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "ImportError heliotwin.cli.calibrate"


def test_parser_does_not_import_torch():
    """``heliotwin --help`` must not pay for torch (or numpy/matplotlib): the library loads when a command runs."""
    code = ("import sys, heliotwin.cli as c; c.build_parser().format_help(); "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'numpy', 'matplotlib', 'h5py'}))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(), timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def test_python_dash_m_heliotwin_reports_one_line_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "heliotwin", "predict", "--scenario", str(tmp_path / "missing.h5"),
                           "--json", str(tmp_path / "o.json")], capture_output=True, text=True, env=_env(), timeout=300)
    assert proc.returncode == 2
    assert_one_line_error(proc.returncode, proc.stderr, "missing.h5")
    assert not (tmp_path / "o.json").exists()


def test_leave_skips_the_teardown_but_not_the_exit_functions_the_output_or_the_status(tmp_path):
    """``heliotwin``'s exit after a command (``cli.common.leave``): the status, every line of a long stdout and the
    exit functions (here one that writes a file) survive; the interpreter's teardown (here a module-level object
    whose finaliser writes a file) is skipped. The ordinary exit, teardown included, where another non-daemon
    thread still runs (its file is written after the main thread left) or a profiler watches (``python -m
    cProfile`` writes its statistics after the command). In a child process: in this one ``leave`` would end the
    test run."""
    marker, thread_file, teardown = tmp_path / "atexit.txt", tmp_path / "thread.txt", tmp_path / "teardown.txt"
    code = ("import atexit, sys, threading, time, torch\n"
            "from heliotwin.cli.common import leave\n"
            "mode, folder = sys.argv[1], sys.argv[2]\n"
            "atexit.register(lambda: open(folder + '/atexit.txt', 'w').write('ran'))\n"
            "class Finalised:\n"
            "    def __del__(self, open=open, path=folder + '/teardown.txt'):  # builtins go early in a teardown\n"
            "        open(path, 'w').write('ran')\n"
            "kept = Finalised()\n"
            "sys.stdout.write(''.join(f'line {i}\\n' for i in range(20000)))\n"
            "if mode == 'thread':\n"
            "    late = lambda: (time.sleep(1.0), open(folder + '/thread.txt', 'w').write('done'))\n"
            "    threading.Thread(target=late).start()\n"
            "if mode == 'profiled':\n"
            "    sys.setprofile(lambda *args: None)\n"
            "leave(3)\n")
    for mode in ("plain", "thread", "profiled"):
        proc = subprocess.run([sys.executable, "-c", code, mode, str(tmp_path)], capture_output=True, text=True,
                              env=_env(), timeout=300)
        assert proc.returncode == 3, proc.stderr
        lines = proc.stdout.splitlines()
        assert len(lines) == 20000 and lines[-1] == "line 19999"
        assert marker.read_text() == "ran"
        assert teardown.exists() == (mode != "plain"), mode
        marker.unlink()
        teardown.unlink(missing_ok=True)
    assert thread_file.read_text() == "done"


def test_library_never_imports_the_cli():
    """Only ``heliotwin.cli`` itself may import ``heliotwin.cli`` (``python -m heliotwin`` runs
    ``heliotwin/cli/__main__.py`` by name), and only it imports the notebook edge ``heliotwin.api`` (the library's
    own device helpers live in ``heliotwin.devices``); the old per-package entry points are gone."""
    assert not (SRC / "cli.py").exists()
    assert not (SRC / "calibrate" / "cli.py").exists() and not (SRC / "surfaces" / "cli.py").exists()
    offenders = []
    for path in SRC.rglob("*.py"):
        rel = path.relative_to(SRC)
        if rel.parts[0] == "cli" or rel.name == "api.py":
            continue
        package = [heliotwin.__name__, *rel.parent.parts]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                base = package[:len(package) - node.level + 1] if node.level else []
                module = ".".join([*base, *([node.module] if node.module else [])])
                names = [module] + [f"{module}.{alias.name}" for alias in node.names]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            else:
                continue
            if any(n in ("heliotwin.cli", "heliotwin.api") or n.startswith(("heliotwin.cli.", "heliotwin.api."))
                   for n in names):
                offenders.append(f"{rel}:{node.lineno}")
    assert offenders == []


# ------------------------------------------------------------------------------------------------ errors
def _command(exc):
    def func(args):
        raise exc
    return argparse.Namespace(func=func)


@pytest.mark.parametrize("exc, line", [
    (HeliotwinError("a.json [field]: bad\nmore detail"), "heliotwin: error: a.json [field]: bad"),
    (KeyError("unknown heliostat 'ZZ99'; this field has AA39"), "heliotwin: error: unknown heliostat 'ZZ99'; "
                                                                "this field has AA39"),
    (FileNotFoundError(2, "No such file or directory", "x.h5"), "heliotwin: error: x.h5: No such file or directory"),
    (NotImplementedError("cylinder targets need the mc integrator"), "heliotwin: error: cylinder targets need "
                                                                     "the mc integrator"),
])
def test_user_errors_are_one_line_exit_2(exc, line, capsys):
    assert run_command(_command(exc)) == 2
    assert capsys.readouterr().err == line + "\n"


@pytest.mark.parametrize("exc", [KeyError("median_test_mrad"), KeyError(3), TypeError("bug"), ZeroDivisionError(),
                                 RuntimeError("CUDA error: device-side assert\ntriggered"), RecursionError()])
def test_internal_errors_are_one_line_exit_1_traceback_only_on_request(exc, capsys, monkeypatch):
    """A bug is still one line (exit 1, saying it is internal and how to see more); --debug or
    HELIOTWIN_DEBUG=1 adds the traceback."""
    monkeypatch.delenv("HELIOTWIN_DEBUG", raising=False)
    assert run_command(_command(exc)) == 1
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith("heliotwin: error: ") and "Traceback" not in err
    assert "--debug" in err
    args = _command(exc)
    args.debug = True
    assert run_command(args) == 1
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and err.splitlines()[-1].startswith("heliotwin: error: ")
    monkeypatch.setenv("HELIOTWIN_DEBUG", "1")
    assert run_command(_command(exc)) == 1
    assert "Traceback" in capsys.readouterr().err


def test_debug_flag_before_or_after_the_command():
    assert build_parser().parse_args(["--debug", "bench"]).debug is True
    assert build_parser().parse_args(["bench", "--debug"]).debug is True
    assert build_parser().parse_args(["scenario", "from-paint", "P", "-o", "x.h5", "--debug"]).debug is True
    assert build_parser().parse_args(["bench"]).debug is False


def test_bad_argument_types_are_usage_errors(capsys):
    for argv in (["bench", "--rays-per-point", "10,x"], ["bench", "--rays-per-point", ","],
                 ["demo", "--heliostats", "0"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2
        assert "heliotwin" in capsys.readouterr().err


def test_output_folder_checked_before_training(tmp_path, capsys):
    code, _, err = run_cli(capsys, "reconstruct", "--paint", tmp_path, "--heliostat", "AA39",
                           "--json", tmp_path / "missing" / "r.json")
    assert_one_line_error(code, err, "--json", "does not exist")
    assert list(tmp_path.iterdir()) == []


def test_aim_rejects_bad_aim_point_before_reading(tmp_path, capsys):
    out = tmp_path / "a.json"
    code, _, err = run_cli(capsys, "aim", "--scenario", tmp_path / "none.h5", "--heliostat", "AA39",
                           "--sun-azimuth", "0", "--sun-elevation", "30", "--aim", "1,2", "--json", out)
    assert_one_line_error(code, err, "--aim")
    assert not out.exists()


def test_split_writes_paint_csv_and_json(paint_dir, tmp_path, capsys):
    csv_path, js = tmp_path / "s.csv", tmp_path / "s.json"
    code, out, err = run_cli(capsys, "split", "--paint", paint_dir, "--heliostats", "BH60", "--min-records", "5",
                             "--train", "6", "--validation", "0", "--test", "4", "--csv", csv_path, "--json", js)
    assert code == 0, err
    lines = csv_path.read_text().splitlines()
    assert lines[0] == "Id,HeliostatId,Split" and len(lines) == 1 + 6 + 4
    assert {ln.split(",")[2] for ln in lines[1:]} == {"train", "test"}
    rows = json.loads(js.read_text())["split"]
    assert [f"{r['Id']},{r['HeliostatId']},{r['Split']}" for r in rows] == lines[1:]
    assert "BH60: train 6" in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv", "s.json"]  # no temp file left behind


# ------------------------------------------------------------------------------------------------- docs
ROOT = SRC.parents[1]


def test_readme_documents_every_exit_code_and_shared_flag():
    from heliotwin.cli import common

    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    for code in (common.EXIT_OK, common.EXIT_INTERNAL, common.EXIT_INPUT, 3, common.EXIT_INTERRUPTED,
                 common.EXIT_TERMINATED):
        assert f"| {code} " in readme or f"{code} /" in readme or f"/ {code}" in readme, code
    for flag in ("--paint", "-o/--output", "--json", "--quiet", "--device", "--debug", "HELIOTWIN_DEBUG"):
        assert flag in readme, flag


def test_licence_citation_and_glossary_are_there():
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    cff = (ROOT / "CITATION.cff").read_text()
    assert "cff-version: 1.2.0" in cff and "license: MIT" in cff and "PAINT" in cff
    glossary = (ROOT / "docs" / "glossary.md").read_text(encoding="utf-8")
    for term in ("**Pointing error**", "**L1 (normalised L1)**", "**IMP**", "ENU", "WGS84"):
        assert term in glossary, term
    data = (ROOT / "docs" / "data.md").read_text(encoding="utf-8")
    assert "CDLA-Permissive-2.0" in data and "paint-csp" in data
    assert "## Limits" in (ROOT / "docs" / "physics.md").read_text(encoding="utf-8")


def test_help_is_fast_and_torch_free_through_python_dash_m():
    """``python -m heliotwin --help`` never imports torch (the < 1 s promise; time itself is not asserted)."""
    code = ("import runpy, sys; sys.argv = ['heliotwin', 'calibrate', '--help']\n"
            "try:\n    runpy.run_module('heliotwin', run_name='__main__')\nexcept SystemExit:\n    pass\n"
            "print('TORCH' if 'torch' in sys.modules else 'NO-TORCH', file=sys.stderr)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(), timeout=120)
    assert proc.stderr.strip().endswith("NO-TORCH"), proc.stderr
    assert "--device" in proc.stdout and "--curve" in proc.stdout


def test_stage_lines_only_on_a_terminal_and_not_when_quiet():
    import io

    from heliotwin.cli.common import stage

    class Tty(io.StringIO):
        def isatty(self):
            return True

    args = argparse.Namespace(command="calibrate", quiet=False)
    tty, pipe = Tty(), io.StringIO()
    stage(args, "fitting (lm)", tty)
    stage(args, "fitting (lm)", pipe)
    assert tty.getvalue() == "heliotwin calibrate: fitting (lm)\n" and pipe.getvalue() == ""
    args.quiet = True
    stage(args, "fitting (lm)", tty)
    assert tty.getvalue() == "heliotwin calibrate: fitting (lm)\n"
