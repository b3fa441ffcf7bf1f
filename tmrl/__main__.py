"""``python -m tmrl``: the command line (see :mod:`tmrl.cli`)."""

import sys

from tmrl.cli import main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(main())
