"""The package's shape in figures, for a commit or the working tree: lines and modules per package, functions
over 60 lines, the largest parameter lists, imports inside functions, and the length of every CLI command body.
(Import circles and arrows back up a floor are a test: ``tests/test_architecture.py``.)

Usage::

    python benchmarks/structure.py                 # the working tree
    python benchmarks/structure.py --ref 44372f1   # a commit, read through git (nothing checked out)
    python benchmarks/structure.py --ref 44372f1 --json before.json
"""
from __future__ import annotations

import argparse
import ast
import json
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
            "cli_command_lines": dict(sorted(commands.items(), key=lambda kv: -kv[1]))}


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
