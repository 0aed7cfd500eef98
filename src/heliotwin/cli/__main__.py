"""``python -m heliotwin`` and ``python -m heliotwin.cli``: the ``heliotwin`` command without the installed
console script."""
from . import console

if __name__ == "__main__":
    console()
