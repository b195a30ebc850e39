"""`include_frames` end to end in the daemon's wiring: a video file's frames become JPEG records."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from host.config import loads_config
from host.frames.sources import Frame
from host.frames.stamps import MIN_FRAMES
from host.recording import RecordingReader, RecordingWriter
from host.service.wiring import CameraPoseLoop, controller_factory, frame_loop_factory

FRAMES = 6


def write_video(path: Path, frames: int = FRAMES, fps: float = 10.0) -> None:
    """A short MJPG file whose frames differ (a bar moving right)."""
    import cv2

    out = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (64, 48))
    assert out.isOpened()
    for i in range(frames):
        image = np.zeros((48, 64, 3), np.uint8)
        image[:, 8 * (i % 8) : 8 * (i % 8) + 8] = 255
        out.write(image)
    out.release()


async def test_camera_frames_are_recorded_as_jpegs(tmp_path: Path) -> None:
    video = tmp_path / "clip.avi"
    write_video(video)
    config = loads_config(f'[camera]\nsource = "{video}"\n')
    writer = RecordingWriter(tmp_path / "rec", include_frames=True, drop_when_full=False)
    writer.open()

    def record(kind: str, t_ns: int, data: Any) -> None:  # the daemon's record tap
        writer.write(kind, t_ns, data)

    controller = controller_factory(config, record)
    loop = frame_loop_factory(config, controller, lambda pose: None, record)
    assert isinstance(loop, CameraPoseLoop)
    await loop.run()  # to the end of the file (no link: every frame unregistered, all recorded)
    assert writer.close()
    frames = [r.data for r in RecordingReader([tmp_path / "rec"]) if r.kind == "frame"]
    assert 1 <= len(frames) <= FRAMES  # the loop keeps the newest frame when it falls behind
    assert writer.frames == len(frames)
    import cv2

    for frame in frames:
        image = cv2.imdecode(np.frombuffer(frame["jpeg"], np.uint8), cv2.IMREAD_COLOR)
        assert image is not None
        assert image.shape == (48, 64, 3)
        assert frame["exposure_ns"] > 0
        assert frame["status"] != "ok"  # no samples: never a guessed pose


class SteadyCamera:
    """A camera at 30 fps whose stamps carry a delivery jitter (no pacing: stamps are given)."""

    def __init__(self, frames: int) -> None:
        jitter = np.random.default_rng(3).uniform(0.0, 2e6, frames)
        self.stamps = [round(5e12 + i * 1e9 / 30 + 20e6 + j) for i, j in enumerate(jitter)]
        self._index = 0

    def read(self) -> Frame | None:
        if self._index == len(self.stamps):
            return None
        self._index += 1
        return Frame(self._index, np.zeros((48, 64, 3), np.uint8), self.stamps[self._index - 1])

    def close(self) -> None:
        pass


async def test_the_camera_is_stamped_on_its_own_clock_unless_told_otherwise(
    tmp_path: Path,
) -> None:
    video = tmp_path / "clip.avi"
    write_video(video)
    for stamps, steady in (("steady", True), ("as-delivered", False)):
        config = loads_config(f'[camera]\nsource = "{video}"\nstamps = "{stamps}"\n')
        controller = controller_factory(config, lambda *_: None)
        loop = frame_loop_factory(config, controller, lambda pose: None, lambda *_: None)
        assert isinstance(loop, CameraPoseLoop)
        await loop.run()
        source = loop.loop.status()["source"]
        assert source["kind"] == "file"  # the camera's own description is still there
        if steady:
            assert source["stamps"]["frames"] == FRAMES  # too few for a line: kept as given
        else:
            assert "stamps" not in source
    # enough frames for a line: the daemon's wiring puts them on it
    config = loads_config('[camera]\nsource = "none"\n')
    controller = controller_factory(config, lambda *_: None)
    camera = SteadyCamera(MIN_FRAMES + 10)
    loop = frame_loop_factory(config, controller, lambda pose: None, lambda *_: None, camera)
    assert isinstance(loop, CameraPoseLoop)
    await loop.run()
    clock = loop.loop.status()["source"]["stamps"]
    assert clock["smoothed"] == 11  # from the 30th frame on
    assert clock["period_us"] == pytest.approx(1e6 / 30, rel=1e-3)
