"""``python -m heliotwin ...``: the ``heliotwin`` command without the installed console script."""
import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
