"""Outputs of the daemon: poses and overlays to other programs."""
