"""The package's shape as a test: floors that import only downwards, no import circles, imports at the top.

Every module of ``heliotwin`` sits on one floor of :data:`FLOORS` (lowest first). A module may import
modules of its own floor or below, never above ("arrows back up"), and the module import graph has no
circle. Below the workflows floor every import stands at the top of its module (ruff ``PLC0415`` checks
the same in CI; this test also names the circle an import would close). The command line (``cli``) is the
one exception: it imports the library inside each command so that ``heliotwin --help`` stays torch-free.
"""
from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "heliotwin"

#: Floors, lowest first: (name, module prefixes). A module belongs to the floor of its longest prefix.
FLOORS = (
    ("building blocks", ("errors", "devices", "geometry", "site", "sun", "sunangles", "sunspa", "sunshape", "timefmt",
                         "nurbs", "atmosphere", "shrinkage", "examples", "progress")),
    ("plant as data", ("field",)),
    ("optics", ("raytrace", "scene", "evaluation")),
    ("data edge", ("io",)),
    ("figures", ("plots",)),
    # calibration by role: shared parts < methods (and what reads their results) < protocol
    ("calibration's shared parts", ("calibrate",)),
    ("calibration methods", ("calibrate.methods", "calibrate.scenario", "calibrate.report", "calibrate.twinstate",
                                 "calibrate.spread")),
    ("calibration protocol", ("calibrate.protocol",)),
    ("learning and acting", ("surfaces", "optimise", "distributed", "validate", "simulate")),
    ("workflows", ("workflows",)),
    ("public API", ("api",)),
    ("command line", ("cli", "__main__")),
)

#: Floors whose modules may import inside functions (the torch-free ``--help`` path).
LOCAL_IMPORTS_ALLOWED = ("command line",)
#: Imports inside a function elsewhere, each with its reason: ``torch._dynamo`` is imported for its side effect
#: just before a process group is created (heliotwin.distributed.init_process_group) and costs 1-3 s, which no
#: command that never creates a group should pay.
LOCAL_IMPORT_EXCEPTIONS = {("distributed", "import torch._dynamo")}


def _modules() -> dict[str, Path]:
    mods = {}
    for path in SRC.rglob("*.py"):
        parts = list(path.relative_to(SRC).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = path
    return mods


MODULES = _modules()


def floor_of(module: str) -> int:
    """Index into :data:`FLOORS` of a module name relative to the package (``""`` is the package itself)."""
    if module == "":
        return 0
    best, floor = -1, None
    for i, (_, prefixes) in enumerate(FLOORS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best:
                best, floor = len(p), i
    if floor is None:
        raise AssertionError(f"module heliotwin.{module} is on no floor: add it to FLOORS in {__file__}")
    return floor


def _targets(module: str, node) -> list[str]:
    """Package-relative module names an import statement of ``module`` loads (only heliotwin's own)."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
        base = [n[len("heliotwin."):] if n.startswith("heliotwin.") else ("" if n == "heliotwin" else None)
                for n in names]
        return [b for b in base if b is not None]
    if node.level == 0:
        if node.module != "heliotwin" and not (node.module or "").startswith("heliotwin."):
            return []
        target = (node.module or "")[len("heliotwin."):] if node.module != "heliotwin" else ""
    else:
        here = module.split(".") if module else []
        is_package = MODULES[module].name == "__init__.py"
        base = here if is_package else here[:-1]
        base = base[: len(base) - (node.level - 1)]
        target = ".".join(base + ([node.module] if node.module else []))
    out = []
    for alias in node.names:
        sub = f"{target}.{alias.name}" if target else alias.name
        out.append(sub if sub in MODULES else target)
    return out


def _known(name: str) -> str:
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name


def import_graph() -> tuple[dict[str, set], list[tuple[str, int, str]]]:
    """``(edges, local)``: every module's imported heliotwin modules, and each import inside a function as
    ``(module, line, statement)``."""
    edges: dict[str, set] = {m: set() for m in MODULES}
    local = []
    for module, path in MODULES.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        inside = set()
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                inside.update(id(n) for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom)))
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            if id(node) in inside:
                local.append((module, node.lineno, ast.unparse(node)))
            for t in _targets(module, node):
                t = _known(t)
                if t != module and not module.startswith(t + ".") and (t or module):
                    edges[module].add(t)
    return edges, local


EDGES, LOCAL = import_graph()


def circles(edges: dict[str, set]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index, low, on, stack, out = {}, {}, set(), [], []
    counter = 0
    for root in edges:
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(edges.get(w, ())))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_every_module_is_on_a_floor():
    for module in MODULES:
        floor_of(module)


def test_no_import_circles():
    found = circles(EDGES)
    assert found == [], "import circles: " + "; ".join(" <-> ".join(c) for c in found)


def test_no_import_runs_back_up_a_floor():
    up = [f"{m} ({FLOORS[floor_of(m)][0]}) -> {t} ({FLOORS[floor_of(t)][0]})"
          for m, ts in EDGES.items() for t in ts if floor_of(t) > floor_of(m)]
    assert up == [], "imports back up a floor:\n" + "\n".join(sorted(up))


def test_imports_at_the_top_of_modules():
    allowed = {i for i, (name, _) in enumerate(FLOORS) if name in LOCAL_IMPORTS_ALLOWED}
    bad = [f"heliotwin/{m.replace('.', '/')}.py:{line}: {stmt}" for m, line, stmt in LOCAL
           if floor_of(m) not in allowed and (m, stmt) not in LOCAL_IMPORT_EXCEPTIONS]
    assert bad == [], f"{len(bad)} imports inside functions:\n" + "\n".join(sorted(bad))


def test_the_checks_can_fail():
    """The checks above see what they must: a circle, an upward arrow and a local import in made-up trees."""
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert floor_of("field.plant") < floor_of("raytrace.flux") < floor_of("io.images") < floor_of("cli.field")
    assert floor_of("calibrate.params") < floor_of("calibrate.methods.lm") < floor_of("calibrate.protocol.pipeline")
    tree = ast.parse("def f():\n    from .x import y\n")
    assert any(isinstance(n, ast.ImportFrom) for n in ast.walk(tree.body[0]))



def test_command_bodies_stay_thin():
    """A command parses, calls one workflow, writes its staged outputs and prints: about 40 lines at most.
    A longer one is growing workflow logic that belongs in :mod:`heliotwin.workflows`."""
    long = []
    for module, path in MODULES.items():
        if floor_of(module) != floor_of("cli"):
            continue
        for fn in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(fn, ast.FunctionDef) and fn.name.startswith("cmd_"):
                n = fn.end_lineno - fn.lineno + 1
                if n > 40:
                    long.append(f"heliotwin/{module.replace('.', '/')}.py:{fn.name} ({n} lines)")
    assert long == [], "command bodies over 40 lines:\n" + "\n".join(long)
