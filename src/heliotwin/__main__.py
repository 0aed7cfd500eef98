"""``python -m heliotwin``: hands over to the command line's own entry point (``heliotwin/cli/__main__.py``),
so the edge stays inside the ``cli`` package and no module outside it imports the CLI."""
import runpy

if __name__ == "__main__":
    runpy.run_module("heliotwin.cli", run_name="__main__", alter_sys=True)
