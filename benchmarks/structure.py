"""The package's shape in figures, for a commit or the working tree: lines and modules per package, functions
over 60 lines, the largest parameter lists, imports inside functions, the length of every CLI command body,
and the share of public docstrings that state shapes and units (the rule: :func:`docstring_findings`).
(Import circles and arrows back up a floor are a test: ``tests/test_architecture.py``; the docstrings of the
floors already done are one too: ``tests/test_docstrings.py``, which uses the rule below.)

Usage::

    python benchmarks/structure.py                 # the working tree
    python benchmarks/structure.py --ref 44372f1   # a commit, read through git (nothing checked out)
    python benchmarks/structure.py --ref 44372f1 --json before.json
"""
from __future__ import annotations

import argparse
import ast
import json
import re
import subprocess
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "src/heliotwin"


def sources(ref: str | None) -> dict[str, str]:
    """Path (relative to ``src/heliotwin``) -> text of every Python module, at ``ref`` or in the tree."""
    if ref is None:
        return {str(p.relative_to(ROOT / PACKAGE)): p.read_text(encoding="utf-8")
                for p in sorted((ROOT / PACKAGE).rglob("*.py"))}
    names = subprocess.run(["git", "-C", str(ROOT), "ls-tree", "-r", "--name-only", ref, PACKAGE],
                           check=True, capture_output=True, text=True).stdout.split()
    return {n[len(PACKAGE) + 1:]: subprocess.run(["git", "-C", str(ROOT), "show", f"{ref}:{n}"], check=True,
                                                 capture_output=True, text=True).stdout
            for n in names if n.endswith(".py")}


# ---------------------------------------------------------------------------------------------------------
# docstrings: shapes and units
# ---------------------------------------------------------------------------------------------------------

#: A shape: ``(N, 3)``, ``(B, P)``, ``(N,)``, ``(..., 3)``, ``(...)``, ``[B, rows, cols]``, ``shape ()`` /
#: ``shape (N)`` / ``shape [N]``, "same shape", or the words scalar / 0-d (and, see :func:`_has_shape`, ``[N]``).
_SHAPE = re.compile(r"\((?:\s*(?:[\w.*+\-]+|\.\.\.)\s*,)+\s*(?:[\w.*+\-]+|\.\.\.)?\s*\)"
                    r"|\[(?:\s*(?:[\w.*+\-]+|\.\.\.)\s*,)+\s*(?:[\w.*+\-]+|\.\.\.)\s*\]"
                    r"|\(\s*\.\.\.\s*\)|shape\s*\(\s*[\w.*+\-]*\s*\)|shape\s*\[[^\]]*\]|same shape|\bscalar\b|\b0-d\b",
                    re.IGNORECASE)
#: A unit in brackets: ``[m]``, ``[W/m^2]``, ``[rad]``, ``[px^2]``, ``[deg]``, ``[1]`` (dimensionless) ...
_UNIT_TOKENS = {"m", "mm", "cm", "km", "rad", "mrad", "deg", "°", "W", "kW", "MW", "GW", "Wh", "kWh", "MWh",
                "GWh", "J", "MJ", "s", "ms", "h", "min", "d", "K", "°C", "px", "Pa", "hPa", "sr", "%", "Hz",
                "kg", "step", "steps", "UTC"}
_BRACKET = re.compile(r"\[([^\[\],]{1,16})\]")
#: An entry typed as a count or a flag (``int``, ``(int, int)``, ``tuple of int``, ``bool``): no unit needed.
_COUNT = re.compile(r"(int|\(int, int\)|tuple of int|bool)\b")
#: Argument names that carry a physical quantity (so the docstring must give at least one unit).
_PHYSICAL = re.compile(r"(^|_)(points?|positions?|pos|distances?|dist|radius|width|height|length|size|areas?|"
                       r"angles?|azimuths?|elevations?|zenith|latitude|longitude|lat|lon|altitude|power|flux|dni|"
                       r"irradiance|energy|times?|temperature|pressure|slope_error|sigma|csr|extent|window|"
                       r"translation|offsets?|aim|aimpoints?|deg|rad|m)($|_)")


def _is_physical(name: str) -> bool:
    """A quantity with a unit, not a count of things (``num_control_points``, ``rays_per_point``)."""
    return bool(_PHYSICAL.search(name)) and not (name.startswith(("num_", "n_", "chunk", "batch")) or "_per_" in name)


def _has_shape(text: str) -> bool:
    """A shape pattern, or a one-axis shape in brackets that is not a unit (``[N]``, ``[3]``, ``[n + p + 1]``)."""
    return bool(_SHAPE.search(text)) or any(re.fullmatch(r"[\w.*+\- ]+", m) and not _is_unit(m)
                                            for m in _BRACKET.findall(text))


def _is_unit(text: str) -> bool:
    text = text.strip()
    if text in ("1", "-"):
        return True
    tokens = [t.rstrip("0123456789²³") for t in re.split(r"[\s/*·^()\-]+", text) if t]
    tokens = [t for t in tokens if t]
    return bool(tokens) and all(t in _UNIT_TOKENS for t in tokens)


_ENTRY = re.compile(r"^(\s*)([\w*][\w, *]*?)\s+:\s+(.+)$")


def _typed_entries(doc: str):
    """``(name, text)`` of each numpy-style ``name : type`` entry (type line plus its indented description)."""
    entries, current, indent = [], None, None
    for line in doc.splitlines():
        m = _ENTRY.match(line)
        if m and (indent is None or len(m.group(1)) <= indent):
            indent = len(m.group(1))
            current = [m.group(2), m.group(3)]
            entries.append(current)
        elif current is not None and line.strip() and len(line) - len(line.lstrip()) > indent:
            current[1] += "\n" + line.strip()
        elif current is not None and line.strip():
            current = None
    return [(name, text) for name, text in entries]


def _public_functions(tree: ast.Module):
    """Module-level functions and the methods of module-level classes whose names (and class) are public."""
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
            yield node.name, node
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for fn in node.body:
                if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)) and not fn.name.startswith("_"):
                    yield f"{node.name}.{fn.name}", fn


def docstring_findings(fn: ast.FunctionDef) -> list[str]:
    """What a public function's docstring lacks under the rule (empty: it passes).

    The rule: (1) there is a docstring; (2) a function that takes or returns a tensor (an annotation, or its
    docstring, names ``Tensor``) states at least one shape -- ``(N, 3)``, ``[B, P]``, ``(N,)``, ``[N]``, ``()``
    or "scalar" -- and so does every numpy-style ``name : type`` entry whose type names a tensor; (3) a
    function with an argument named after a physical quantity (points, distance,
    azimuth, power, flux, dni, time, ... see ``_PHYSICAL``; counts such as ``num_control_points`` are not)
    gives at least one unit in brackets -- ``[m]``, ``[W/m^2]``, ``[rad]``, ``[1]`` or ``[-]`` -- and so does
    every ``name : type`` entry of such an argument (or returned quantity). It is a floor, not a proof: it
    checks that shapes and units are written where it can see tensors and physical names, not that they are
    right, and an undocumented argument of a function that has a docstring goes unseen.
    """
    doc = ast.get_docstring(fn)
    if not doc:
        return ["no docstring"]
    missing = []
    args = [a for a in (*fn.args.posonlyargs, *fn.args.args, *fn.args.kwonlyargs) if a.arg not in ("self", "cls")]
    notes = " ".join(ast.unparse(a.annotation) for a in args if a.annotation is not None)
    notes += " " + (ast.unparse(fn.returns) if fn.returns is not None else "")
    if ("Tensor" in notes or "tensor" in doc.lower()) and not _has_shape(doc):
        missing.append("no shape")
    missing += [f"no shape for {name}" for name, entry in _typed_entries(doc)
                if "tensor" in entry.splitlines()[0].lower() and not _has_shape(entry)]
    if any(_is_physical(a.arg) for a in args) and not any(_is_unit(m) for m in _BRACKET.findall(doc)):
        missing.append("no unit")
    missing += [f"no unit for {name}" for name, entry in _typed_entries(doc)
                if any(_is_physical(n.strip()) for n in name.split(",")) and not _COUNT.match(entry)
                and not any(_is_unit(m) for m in _BRACKET.findall(entry))]
    return missing


def docstring_report(files: dict[str, str], skip=("cli/",)) -> dict[str, list[str]]:
    """``"path:function" -> findings`` for every public function of the modules (cli/ left out)."""
    out = {}
    for path, text in files.items():
        if path.startswith(skip) or path == "__main__.py":
            continue
        for name, fn in _public_functions(ast.parse(text)):
            out[f"{path}:{name}"] = docstring_findings(fn)
    return out


def measure(files: dict[str, str]) -> dict:
    lines, modules, long_functions, params, local, commands = Counter(), Counter(), [], [], Counter(), {}
    for path, text in files.items():
        package = path.split("/")[0] if "/" in path else "(top)"
        lines[package] += len(text.splitlines())
        modules[package] += 1
        tree = ast.parse(text)
        for fn in ast.walk(tree):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            n = fn.end_lineno - fn.lineno + 1
            where = f"{path}:{fn.name}"
            if n > 60:
                long_functions.append((n, where))
            a = fn.args
            params.append((len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs), where))
            local[package] += sum(isinstance(s, (ast.Import, ast.ImportFrom)) for s in ast.walk(fn))
            if path.startswith("cli/") and fn.name.startswith("cmd_"):
                commands[where] = n
    return {"lines": sum(lines.values()), "lines_per_package": dict(sorted(lines.items())),
            "modules": sum(modules.values()), "modules_per_package": dict(sorted(modules.items())),
            "functions_over_60_lines": len(long_functions),
            "longest_functions": [f"{w} ({n})" for n, w in sorted(long_functions, reverse=True)[:10]],
            "largest_parameter_lists": [f"{w} ({n})" for n, w in sorted(params, reverse=True)[:10]],
            "imports_inside_functions": sum(local.values()),
            "imports_inside_functions_per_package": {k: v for k, v in sorted(local.items()) if v},
            "cli_command_lines": dict(sorted(commands.items(), key=lambda kv: -kv[1])),
            **_docstring_figures(files)}


def _docstring_figures(files: dict[str, str]) -> dict:
    report = docstring_report(files)
    total, good = Counter(), Counter()
    for where, findings in report.items():
        package = where.split("/")[0] if "/" in where.split(":")[0] else where.split(":")[0].removesuffix(".py")
        total[package] += 1
        good[package] += not findings
    n, ok = sum(total.values()), sum(good.values())
    return {"public_functions": n,
            "docstrings_with_shapes_and_units": f"{ok}/{n} ({100.0 * ok / max(n, 1):.0f}%)",
            "docstrings_with_shapes_and_units_per_module": {k: f"{good[k]}/{total[k]}" for k in sorted(total)}}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ref", help="a git commit (default: the working tree)")
    p.add_argument("--json", help="also write the figures here")
    a = p.parse_args(argv)
    figures = measure(sources(a.ref))
    for key, value in figures.items():
        if isinstance(value, dict):
            print(f"{key}: " + ", ".join(f"{k} {v}" for k, v in value.items()))
        elif isinstance(value, list):
            print(f"{key}: " + "; ".join(value))
        else:
            print(f"{key}: {value}")
    if a.json:
        Path(a.json).write_text(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
