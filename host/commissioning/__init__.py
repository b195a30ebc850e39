"""Commissioning: calibrating a rig on site through the running daemon (docs/COMMISSIONING.md)."""

# host.control.ops registers this package's operations at its end, and our ops module imports
# its OpContext: importing it here first makes either import order work.
import host.control.ops  # noqa: F401
