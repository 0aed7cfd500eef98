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

#: Modules (relative to ``src/heliotwin``) whose public docstrings all state shapes and units. The floors
#: in order: building blocks; optics (the integrators, splats, images, yearly energy; the scene glue); the
#: data edge (all of io but the PAINT reader, the record table and the scenario file); figures; surface
#: learning (all of surfaces/) and forward-model validation; the public API and its helpers (progress, the
#: shipped examples); then the field, the field optics and occlusion, aim-point optimisation, sharding, the
#: PAINT reader and the record table, calibration's shared parts and its lm/batched/gradient methods and
#: protocol, the simulated plant, and the workflows those floors serve.
DONE = (
    "errors.py", "devices.py", "geometry.py", "site.py", "sun.py", "sunshape.py", "nurbs.py", "atmosphere.py",
    "shrinkage.py", "calibrate/choice.py",
    "raytrace/montecarlo.py", "raytrace/gaussian.py", "raytrace/conv.py", "raytrace/splat.py", "raytrace/flux.py",
    "raytrace/yearly.py", "scene.py",
    "io/checkpoint.py", "io/deflectometry.py", "io/hdf5.py", "io/images.py", "io/report.py",
    "plots.py",
    "surfaces/__init__.py", "surfaces/acceptance.py", "surfaces/baselines.py", "surfaces/deflectometry.py",
    "surfaces/edges.py", "surfaces/fit.py", "surfaces/generalise.py", "surfaces/imaging.py",
    "surfaces/insilico.py", "surfaces/learning.py", "surfaces/losses.py", "surfaces/mismatch.py",
    "surfaces/nuisance.py", "surfaces/observations.py", "surfaces/plantprior.py", "surfaces/plots.py",
    "surfaces/predict.py", "surfaces/state.py", "validate.py",
    "api.py", "progress.py", "examples/__init__.py",
    "field/__init__.py", "field/actuators.py", "field/demo.py", "field/facets.py", "field/kinematics.py",
    "field/layout.py", "field/plant.py", "field/targets.py", "field/update.py",
    "raytrace/field.py", "raytrace/occlusion.py", "raytrace/__init__.py",
    "optimise/__init__.py", "optimise/aimpoints.py", "optimise/aimstate.py",
    "distributed.py", "__init__.py",
    "io/paint.py", "io/records.py", "io/__init__.py", "io/export.py", "io/weather.py",
    "workflows/aimpoints.py", "workflows/field.py", "workflows/plan.py", "workflows/calibrate.py",
    "workflows/update.py", "workflows/simulate.py", "workflows/show.py", "workflows/demo.py",
    "workflows/__init__.py",
    "calibrate/__init__.py", "calibrate/assimilate.py", "calibrate/drift.py", "calibrate/fitloop.py",
    "calibrate/inputs.py", "calibrate/metrics.py", "calibrate/model.py", "calibrate/params.py",
    "calibrate/priors.py", "calibrate/report.py", "calibrate/scenario.py", "calibrate/uncertainty.py",
    "calibrate/methods/lm.py", "calibrate/methods/batched.py", "calibrate/methods/gradient.py",
    "calibrate/methods/__init__.py",
    "calibrate/protocol/config.py", "calibrate/protocol/online.py", "calibrate/protocol/suspicious.py",
    "calibrate/protocol/archive.py", "calibrate/protocol/selection.py", "calibrate/protocol/pipeline.py",
    "calibrate/protocol/plan.py", "calibrate/protocol/__init__.py",
    "simulate/__init__.py", "simulate/images.py", "simulate/plant.py", "simulate/score.py", "simulate/writer.py",
)


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
