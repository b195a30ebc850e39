"""`python -m host.service daemon --config PATH`."""

import sys

from host.service.main import main

sys.exit(main())
