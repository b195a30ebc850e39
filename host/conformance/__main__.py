"""`python -m host.conformance URL`."""

import sys

from host.conformance.run import main

sys.exit(main())
