"""`python -m host.control COMMAND …`: the same command line as `orbitar` (host/cli.py)."""

import sys

from host.cli import main

sys.exit(main())
