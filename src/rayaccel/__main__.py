"""``python -m rayaccel``: the command line of :mod:`rayaccel.cli`."""

from __future__ import annotations

import sys

from rayaccel.cli import main

if __name__ == "__main__":
    sys.exit(main())
