"""`python -m morphgs ...` (also what `accelerate launch -m morphgs train ...` runs)."""

from __future__ import annotations

import sys

from morphgs.cli import main

if __name__ == "__main__":
    sys.exit(main())
