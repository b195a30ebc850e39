"""Recording of what reached the daemon, and deterministic replay of it."""

from host.recording.reader import Record, RecordingReader, recording_files
from host.recording.replay import ReplayStats, replay
from host.recording.writer import FORMAT_NAME, FORMAT_VERSION, RecordingWriter

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "Record",
    "RecordingReader",
    "RecordingWriter",
    "ReplayStats",
    "recording_files",
    "replay",
]
