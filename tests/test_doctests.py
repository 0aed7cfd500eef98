"""The examples in the public docstrings run, and give what they say (``python -m doctest`` style)."""
from __future__ import annotations

import doctest
import importlib

import pytest

#: Modules whose docstrings carry examples; each must have at least one.
MODULES = ("heliotwin.geometry", "heliotwin.site", "heliotwin.nurbs", "heliotwin.io.scenario",
           "heliotwin.workflows.plan", "heliotwin.workflows.trace", "heliotwin.workflows.field", "heliotwin.api",
           "heliotwin.calibrate.choice", "heliotwin.workflows.field_one_sun")


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0, f"{name} has no docstring example"
    assert result.failed == 0
