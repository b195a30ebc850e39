"""`python -m hil_sim`: the emulator without the host CLI (same options as `orbitar sim`)."""

from __future__ import annotations

import sys

from hil_sim.cli import main

if __name__ == "__main__":
    sys.exit(main())
