"""``python -m heliotwin`` and ``python -m heliotwin.cli``: the ``heliotwin`` command without the installed
console script."""
import sys

from . import main

if __name__ == "__main__":
    sys.exit(main())
