"""The conformance suite: checks a controller against PROTOCOL.md's rules through its wire only.

    orbitar conformance URL [--no-motion] [--home-speed UM_S] [--only NAME]
    python -m host.conformance URL

Each check names the `[R-…]` rule ids of PROTOCOL.md it covers (docs/CONFORMANCE.md).
"""

from host.conformance.run import SuiteResult, add_parser, main, run_suite

__all__ = ["SuiteResult", "add_parser", "main", "run_suite"]
