"""Command line: ``python -m torchrot bench [--full] [options]`` (see :mod:`torchrot.bench.cli`)."""
from __future__ import annotations

import sys

from torchrot.bench.cli import main

if __name__ == "__main__":
    sys.exit(main())
