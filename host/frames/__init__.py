"""Camera frames into the daemon: sources and the frame loop that registers each frame."""
