"""Public docstrings state shapes and units, floor by floor (so a floor once done cannot slide back).

The rule is the one ``benchmarks/structure.py`` measures for the whole package (its
``docstring_findings``): every public function or method has a docstring; one that takes or returns a
tensor states a shape (``(N, 3)``, ``[B, P]``, ``(N,)``, ``()`` ...), and so does each ``name : type``
entry whose type is a tensor; one with an argument named after a physical quantity gives a unit in
brackets (``[m]``, ``[W/m^2]``, ``[rad]``, ``[1]``). :data:`DONE` lists the modules that follow it.
"""
from __future__ import annotations

import ast
import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "heliotwin"

#: Every module of the package but the command line (``cli/``: argument parsing, no library API) states
#: shapes and units on its public docstrings; a new module is held to the rule from its first commit.
DONE = tuple(sorted(str(p.relative_to(SRC)) for p in SRC.rglob("*.py") if p.relative_to(SRC).parts[0] != "cli"))


def _structure():
    spec = importlib.util.spec_from_file_location("structure", ROOT / "benchmarks" / "structure.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


STRUCTURE = _structure()


@pytest.mark.parametrize("path", DONE)
def test_public_docstrings_state_shapes_and_units(path):
    source = SRC / path
    assert source.is_file(), f"{path} is listed as done but does not exist (renamed? update DONE)"
    report = STRUCTURE.docstring_report({path: source.read_text(encoding="utf-8")})
    bad = {where: findings for where, findings in report.items() if findings}
    assert not bad, "docstrings lacking shapes/units: " + "; ".join(f"{w} ({', '.join(f)})" for w, f in bad.items())


def _findings(code: str) -> list[str]:
    return STRUCTURE.docstring_findings(ast.parse(code).body[0])


def test_the_rule_catches_what_it_names():
    """The rule itself: a missing docstring, a tensor without a shape and a distance without a unit (in the
    docstring, or in the distance's own entry) are named; a count (``num_points``, an ``int`` entry) needs
    no unit, and a documented function passes."""
    assert _findings("def f(x):\n    pass\n") == ["no docstring"]
    assert "no shape" in _findings('def f(x: torch.Tensor):\n    """Doubles x."""\n')
    assert _findings('def f(distance):\n    """How far."""\n') == ["no unit"]
    assert _findings('def f(num_points: int):\n    """How many."""\n') == []
    entry = ('def f(points, normals):\n    """Mirror points.\n\n    Parameters\n    ----------\n'
             '    points : torch.Tensor, shape (N, 3)\n        ENU [m].\n    normals : torch.Tensor\n'
             '        Unit.\n    """\n')
    assert _findings(entry) == ["no shape for normals"]
    assert _findings(entry.replace("normals : torch.Tensor", "normals : torch.Tensor, [N, 3]")) == []
    ranged = ('def f(distance, size):\n    """Ranges [m].\n\n    Parameters\n    ----------\n'
              '    distance : float\n        Slant range.\n    size : int\n        Pixels.\n    """\n')
    assert _findings(ranged) == ["no unit for distance"]
