"""Raw link bytes: the transport tap records them; `LinkReplay` re-runs the clock sync on them.

The controller is the firmware mirror on the test's loop behind a MemoryTransport, so the bytes
and clock probes are real; the live samples come from the real `Controller`.
"""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
import pytest

from host.frames.registrar import Registration
from host.frames.sources import Frame
from host.link.controller import Controller
from host.link.reconnect import BackoffConfig
from host.link.session import SessionConfig
from host.recording import RecordingReader, RecordingWriter
from host.recording.link_replay import LinkReplay
from host.recording.taps import FrameTap, attach_link_tap
from host.registration.pose_buffer import LookupStatus
from host.transport.memory import MemoryTransport
from protocol import Stream
from tests.link.sim_bridge import SimBridge

CFG = SessionConfig(rto_initial_s=0.05)


class Samples:
    """A SampleSink keeping what it is given."""

    def __init__(self) -> None:
        self.encoder: list[tuple[int, float]] = []
        self.head: list[tuple[int, float, float]] = []

    def on_encoder(self, t_host_ns: int, s_mm: float, velocity_mm_s: float, inputs: int) -> None:
        self.encoder.append((t_host_ns, s_mm))

    def on_head(self, t_host_ns: int, pan_rad: float, tilt_rad: float) -> None:
        self.head.append((t_host_ns, pan_rad, tilt_rad))

    def on_range(self, t_host_ns: int, distance_mm: float, quality: int) -> None:
        pass

    def on_mark(self, t_host_ns: int, s_mm: float) -> None:
        pass


async def test_replayed_bytes_give_the_live_samples_at_the_live_times() -> None:
    bridge = SimBridge()
    bridge.start()
    tapped: list[tuple[str, int, Any]] = []
    attach_link_tap(bridge.transport, lambda kind, t, d: tapped.append((kind, t, d)))
    ctrl = Controller(bridge.transport, CFG, BackoffConfig(0.02, 0.2), seed=1)
    live = Samples()
    ctrl.add_sink(live)
    try:
        await ctrl.connect()
        await ctrl.set_streams({Stream.ENCODER: 100, Stream.HEAD: 20})
        await ctrl.set_param(8, 200_000)
        await (await ctrl.home()).done(15.0)
        await (await ctrl.move_to(200.0, 400.0, 2000.0)).done(10.0)
    finally:
        await ctrl.close()
        await bridge.stop()
    assert {d["dir"] for _, _, d in tapped} == {"rx", "tx"}
    replayed = Samples()
    link = LinkReplay(replayed)
    for _, t_ns, d in tapped:
        link.feed(d["dir"], t_ns, d["bytes"])
    # Probes go out at 10 Hz over a run of a few seconds; a loaded machine sends fewer.
    assert link.stats.probes_used >= 2
    assert link.stats.handshakes == 1
    assert len(replayed.encoder) == len(live.encoder) > 100
    t_live = np.array([t for t, _ in live.encoder])
    t_replay = np.array([t for t, _ in replayed.encoder])
    # The session stamps its probes with the transport's own stamps, which the tap records:
    # the replayed clock fit is the live one, to the nanosecond.
    assert np.array_equal(t_live, t_replay)
    assert [s for _, s in replayed.encoder] == [s for _, s in live.encoder]
    assert len(replayed.head) == len(live.head)


async def test_a_failing_tap_never_breaks_the_link() -> None:
    to_peer: list[bytes] = []
    received: list[bytes] = []
    transport = MemoryTransport(to_peer.append)

    def broken(direction: str, t_ns: int, data: bytes) -> None:
        raise RuntimeError("disk on fire")

    transport.set_tap(broken)
    transport.set_receiver(received.append)
    await transport.open()
    transport.send(b"\x01\x02\x00")
    transport.inject(b"\x03\x00")
    for _ in range(5):
        await asyncio.sleep(0)
    await transport.close()
    assert to_peer == [b"\x01\x02\x00"]
    assert received == [b"\x03\x00"]
    assert transport.stats.extra["tap_errors"] == 2


def test_frames_are_recorded_as_jpegs_with_their_exposure_stamps(tmp_path: Any) -> None:
    ramp = np.tile(np.arange(64, dtype=np.uint8) * 4, (48, 1))
    image = np.dstack([ramp, ramp[::-1], np.full_like(ramp, 128)])

    def registrar(frame: Frame) -> Registration:
        return Registration(
            frame.index, frame.exposure_ns, LookupStatus.OK, None, 0, 0, 0, None, 0, None, None
        )

    for include in (True, False):
        writer = RecordingWriter(tmp_path / str(include), include_frames=include)
        writer.open()
        tap = FrameTap(registrar, writer.write)
        for i in range(3):
            tap(Frame(i, image, 1_000_000 * i + 7))
        assert writer.close()
        frames = [r for r in RecordingReader([tmp_path / str(include)]) if r.kind == "frame"]
        assert [(r.t_ns, r.data["exposure_ns"]) for r in frames] == [
            (1_000_000 * i + 7, 1_000_000 * i + 7) for i in range(3)
        ]
        assert all("image" not in r.data for r in frames)
        if not include:
            assert all("jpeg" not in r.data for r in frames)
            continue
        import cv2

        decoded = cv2.imdecode(np.frombuffer(frames[0].data["jpeg"], np.uint8), cv2.IMREAD_COLOR)
        assert decoded is not None
        assert decoded.shape == image.shape
        assert (frames[0].data["width"], frames[0].data["height"]) == (64, 48)
        assert np.mean(np.abs(decoded.astype(int) - image.astype(int))) < 4.0
        assert writer.frames == 3


@pytest.mark.parametrize("direction", ["rx", "tx"])
def test_garbage_bytes_are_counted_not_raised(direction: str) -> None:
    link = LinkReplay(Samples())
    link.feed(direction, 0, b"\x05\xff\xfe\xfd\x00" * 10)
    assert link.stats.samples == 0
