"""Build the API reference (HTML) from the docstrings with pdoc: ``python docs/build_api.py [OUT_DIR]``.

Every module of the package is listed explicitly (``heliotwin/__init__`` has an ``__all__`` that would
otherwise hide the subpackages). CI runs this script, so a docstring or import that breaks the reference
breaks CI. Default output: ``build/api``; open ``index.html``.
"""
from __future__ import annotations

import os
import pkgutil
import sys
import warnings
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")


def modules() -> list[str]:
    import heliotwin

    names = ["heliotwin"]
    names += [m.name for m in pkgutil.walk_packages(heliotwin.__path__, "heliotwin.")
              if not m.name.endswith("__main__")]
    return sorted(names)


def main(out: str = "build/api") -> int:
    import pdoc

    names = modules()
    # A subpackage brings its submodules along; listing them too is harmless, so pdoc need not say so.
    warnings.filterwarnings("ignore", message="The module specification", category=UserWarning)
    pdoc.render.configure(docformat="numpy", footer_text="heliotwin API reference")
    pdoc.pdoc(*names, output_directory=Path(out))
    missing = [n for n in names if not (Path(out) / (n.replace(".", "/") + ".html")).exists()]
    if missing:
        print(f"build_api: no page for {', '.join(missing)}", file=sys.stderr)
        return 1
    print(f"build_api: {len(names)} modules -> {out}/index.html")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
