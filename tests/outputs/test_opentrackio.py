"""OpenTrackIO: header and checksum decoded independently, segmentation, the axis mapping, every
sample valid against the published schema, and the UDP sender on loopback."""

from __future__ import annotations

import asyncio
import json
import math
import struct
import time
from pathlib import Path
from typing import Any

import cbor2
import jsonschema
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from host.config import loads_config
from host.config_fields import ConfigError
from host.config_opentrackio import OpenTrackIOConfig
from host.control.api import PoseSample
from host.geometry.camera import CameraModel
from host.outputs.opentrackio import OpenTrackIOSender, TaiClock, pan_tilt_roll_deg, transform
from host.outputs.opentrackio_packet import (
    Encoding,
    Reassembler,
    decode_segment,
    encode_segment,
    fletcher16,
    segment_payload,
)
from host.outputs.tracking import TrackingOutputs

SCHEMA = json.loads((Path(__file__).parent / "data" / "opentrackio-1.0.1.schema.json").read_text())
VALIDATOR = jsonschema.Draft202012Validator(SCHEMA)
# Camera looking along world +Y, level, image top = world +Z: x_c = +X, y_c = -Z, z_c = +Y.
LEVEL_ALONG_Y = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])


def rot(axis: str, deg: float) -> np.ndarray:
    """A right-handed rotation about a coordinate axis."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def camera_pose(pan: float, tilt: float, roll: float, at: tuple[float, ...] = (0, 0, 0)) -> Any:
    """T_w_c whose OpenTrackIO angles are (pan, tilt, roll): R = Rz Rx Ry applied to the base."""
    T = np.eye(4)
    T[:3, :3] = rot("z", pan) @ rot("x", tilt) @ rot("y", roll) @ LEVEL_ALONG_Y
    T[:3, 3] = at
    return T


def sender(**overrides: Any) -> OpenTrackIOSender:
    """A sender with no destinations (samples are built, not sent)."""
    config = OpenTrackIOConfig(enabled=True, destinations=(), **overrides)
    return OpenTrackIOSender(config, CameraModel(), fps=30.0)


def test_fletcher16_matches_published_check_values() -> None:
    assert fletcher16(b"abcde") == 0xC8F0
    assert fletcher16(b"abcdef") == 0x2057
    assert fletcher16(b"abcdefgh") == 0x0627


def test_header_layout_decoded_independently() -> None:
    datagram = encode_segment(Encoding.CBOR, 0x1234, 0, True, b"payload")
    ident, reserved, encoding, seq, offset, length, checksum = struct.unpack(
        ">4sBBHIHH", datagram[:16]
    )
    assert (ident, reserved, encoding, seq, offset) == (b"OTrk", 0, 0x02, 0x1234, 0)
    assert length == 0x8000 | len(b"payload")  # last-segment flag + this segment's length
    body = datagram[:14] + datagram[16:]
    c0 = sum(body) % 255
    c1 = sum((len(body) - i) * b for i, b in enumerate(body)) % 255
    assert checksum == (c1 << 8) | c0


def test_damaged_datagrams_are_refused_with_a_reason() -> None:
    datagram = bytearray(encode_segment(Encoding.JSON, 7, 0, True, b'{"a":1}'))
    datagram[-1] ^= 0x01
    with pytest.raises(ValueError, match="checksum"):
        decode_segment(bytes(datagram))
    with pytest.raises(ValueError, match="identifier"):
        decode_segment(b"XTrk" + bytes(datagram[4:]))
    with pytest.raises(ValueError, match="shorter"):
        decode_segment(bytes(datagram[:10]))
    with pytest.raises(ValueError, match="payload bytes"):
        decode_segment(bytes(datagram[:-2]))


def test_large_samples_are_segmented_to_the_mtu_and_reassembled() -> None:
    payload = bytes(range(256)) * 20  # 5120 bytes
    datagrams = segment_payload(Encoding.JSON, 99, payload, mtu_bytes=1500)
    assert len(datagrams) == 4
    assert all(len(d) <= 1500 - 28 for d in datagrams)
    segments = [decode_segment(d) for d in datagrams]
    assert [s.last for s in segments] == [False, False, False, True]
    assert {s.sequence for s in segments} == {99}
    assert [s.offset for s in segments] == [0, 1456, 2912, 4368]
    joiner = Reassembler()
    results = [joiner.feed(s) for s in segments]
    assert results[:3] == [None, None, None]
    assert results[3] == payload


def test_a_lost_segment_loses_only_its_sample() -> None:
    first = [decode_segment(d) for d in segment_payload(Encoding.JSON, 1, b"x" * 3000)]
    second = [decode_segment(d) for d in segment_payload(Encoding.JSON, 2, b"y" * 3000)]
    joiner = Reassembler()
    assert joiner.feed(first[0]) is None
    assert joiner.feed(first[2]) is None  # segment 1 lost: sample 1 cannot complete
    got = [joiner.feed(s) for s in second]
    assert got[-1] == b"y" * 3000
    assert joiner.dropped == 1


@given(st.floats(-179.0, 179.0), st.floats(-89.0, 89.0), st.floats(-179.0, 179.0))
def test_pan_tilt_roll_come_back(pan: float, tilt: float, roll: float) -> None:
    got = transform(camera_pose(pan, tilt, roll))["rotation"]
    assert got["pan"] == pytest.approx(pan, abs=1e-6)
    assert got["tilt"] == pytest.approx(tilt, abs=1e-6)
    assert got["roll"] == pytest.approx(roll, abs=1e-6)


def test_known_directions_in_opentrackio_terms() -> None:
    level = transform(camera_pose(0, 0, 0, at=(1500.0, -250.0, 4000.0)))
    assert level["translation"] == pytest.approx({"x": 1.5, "y": -0.25, "z": 4.0})
    assert level["rotation"] == pytest.approx({"pan": 0.0, "tilt": 0.0, "roll": 0.0}, abs=1e-9)
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]])  # looks along +X, level
    assert transform(T)["rotation"]["pan"] == pytest.approx(-90.0)  # right-handed about +Z
    down = np.eye(4)
    down[:3, :3] = np.diag([1.0, -1.0, -1.0])  # optical axis -Z, image top towards +Y
    pan, tilt, roll = pan_tilt_roll_deg(tuple(map(tuple, _axes(down))))
    assert (pan, tilt, roll) == pytest.approx((0.0, -90.0, 0.0), abs=1e-9)


def _axes(T: np.ndarray) -> np.ndarray:
    """OpenTrackIO camera axes (right, forward, up) of T_w_c as columns."""
    return np.column_stack([T[:3, 0], T[:3, 2], -T[:3, 1]])


def test_stage_origin_and_yaw_move_the_pose() -> None:
    T = camera_pose(30, 10, 0, at=(1000.0, 0.0, 4000.0))
    moved = transform(T, origin_mm=(1000.0, 0.0, 0.0), yaw_rad=math.radians(90))
    assert moved["translation"] == pytest.approx({"x": 0.0, "y": 0.0, "z": 4.0}, abs=1e-12)
    assert moved["rotation"]["pan"] == pytest.approx(30 - 90)


@pytest.mark.parametrize("encoding", ["json", "cbor"])
def test_every_sample_is_valid_against_the_published_schema(encoding: str) -> None:
    out = sender(encoding=encoding, sync_source="ptp")
    pose = PoseSample(time.monotonic_ns(), camera_pose(10, -5, 1, at=(0, 0, 4000.0)), "MOVING")
    with_static = out.sample(pose, now_ns=0)
    without = out.sample(pose, now_ns=10**9)  # within static_interval_s: no static block
    assert "static" in with_static
    assert "static" not in without
    for sample in (with_static, without):
        decoded = (
            json.loads(out.encode(sample))
            if encoding == "json"
            else cbor2.loads(out.encode(sample))
        )
        errors = sorted(VALIDATOR.iter_errors(decoded), key=str)
        assert not errors, [e.message for e in errors]


def test_static_block_repeats_at_its_interval() -> None:
    out = sender(static_interval_s=2.0)
    pose = PoseSample(0, camera_pose(0, 0, 0), "READY")
    times_s = [0.0, 0.5, 1.9, 2.0, 3.0, 4.1]
    flags = ["static" in out.sample(pose, now_ns=round(t * 1e9)) for t in times_s]
    assert flags == [True, False, False, True, False, True]


def test_lens_comes_from_the_calibrated_intrinsics() -> None:
    cam = CameraModel()
    out = sender(pixel_pitch_um=5.3)
    lens = out.sample(PoseSample(0, np.eye(4), "READY"))["lens"]
    assert lens["pinholeFocalLength"] == pytest.approx(cam.fx * 0.0053)
    assert lens["projectionOffset"]["x"] == pytest.approx((cam.u0 - 640) * 0.0053)
    assert lens["distortion"][0]["radial"] == [cam.k1, cam.k2, cam.k3]


def test_timestamp_is_the_exposure_in_tai() -> None:
    clock = TaiClock(utc_tai_offset_s=37)
    exposure_ns = time.monotonic_ns() - 40_000_000  # exposed 40 ms ago
    tai_ns = clock.to_tai_ns(exposure_ns)
    offset_s = clock.kernel_offset_s() or 37
    expected_ns = time.time_ns() - 40_000_000 + offset_s * 1_000_000_000
    assert abs(tai_ns - expected_ns) < 5_000_000


class _Collector(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.datagrams: asyncio.Queue[bytes] = asyncio.Queue()

    def datagram_received(self, data: bytes, addr: object) -> None:
        self.datagrams.put_nowait(data)


async def test_sender_on_loopback_carries_the_registered_pose() -> None:
    loop = asyncio.get_running_loop()
    transport, proto = await loop.create_datagram_endpoint(_Collector, local_addr=("127.0.0.1", 0))
    port = transport.get_extra_info("sockname")[1]
    out = OpenTrackIOSender(
        OpenTrackIOConfig(enabled=True, destinations=(f"127.0.0.1:{port}",), mtu_bytes=576),
        CameraModel(),
        fps=30.0,
    )
    await out.start()
    T = camera_pose(-20.0, 12.0, 0.5, at=(2500.0, 1200.0, 3950.0))
    try:
        sent = out.send(PoseSample(time.monotonic_ns(), T, "MOVING", 2500.0, 17))
        assert len(sent) > 1  # the first sample has the static block: more than 576 bytes
        joiner, payload = Reassembler(), None
        while payload is None:
            datagram = await asyncio.wait_for(proto.datagrams.get(), 5)
            payload = joiner.feed(decode_segment(datagram))
    finally:
        out.close()
        transport.close()
    sample = json.loads(payload)
    assert not list(VALIDATOR.iter_errors(sample))
    got = sample["transforms"][0]
    R = rot("z", got["rotation"]["pan"]) @ rot("x", got["rotation"]["tilt"])
    R = R @ rot("y", got["rotation"]["roll"])
    np.testing.assert_allclose(R, _axes(T), atol=1e-12)
    position_m = [got["translation"][k] for k in "xyz"]
    np.testing.assert_allclose(position_m, T[:3, 3] / 1000.0, atol=1e-12)
    assert sample["timing"]["sequenceNumber"] == 0
    assert out.stats() == {"sent": 1, "datagrams": len(sent), "errors": 0}


async def test_an_output_that_cannot_open_is_reported_not_fatal(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    async def unreachable(self: object) -> None:
        raise OSError("[Errno 101] Network is unreachable")

    first = loads_config('[outputs.opentrackio]\nenabled = true\ndestinations = ["127.0.0.1:9"]\n')
    moved = loads_config('[outputs.opentrackio]\nenabled = true\ndestinations = ["127.0.0.2:9"]\n')
    outputs = TrackingOutputs()
    try:
        await outputs.start(first)
        running = outputs.opentrackio
        assert running is not None
        monkeypatch.setattr("host.outputs.udp.UdpFanout.start", unreachable)
        await outputs.start(moved)  # a reload whose receiver cannot be opened
        assert outputs.opentrackio is running  # the running output stays in force
        stats = outputs.stats()
        assert stats["freed"] is None
        assert stats["opentrackio"]["error"] == "[Errno 101] Network is unreachable"
        assert stats["opentrackio"]["sent"] == 0
        outputs.close()
        await outputs.start(moved)  # a first start that cannot open: nothing runs, no raise
        assert outputs.opentrackio is None
        assert outputs.stats()["opentrackio"] == {"error": "[Errno 101] Network is unreachable"}
        outputs.send(PoseSample(0, np.eye(4), "READY"))  # nothing open: nothing raised
    finally:
        outputs.close()


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ('destinations = ["239.135.1.1:55555"]', "allow_multicast = true"),
        ('source_id = "not-a-uuid"', "outputs.opentrackio.source_id = 'not-a-uuid': not a UUID"),
        ('encoding = "xml"', "outputs.opentrackio.encoding"),
        ('camera_label = "  "', "camera_label: must not be blank"),
    ],
)
def test_bad_config_names_the_key(text: str, needle: str) -> None:
    with pytest.raises(ConfigError) as err:
        loads_config(f"[outputs.opentrackio]\nenabled = true\n{text}\n")
    assert needle in str(err.value)


def test_multicast_when_asked_for_and_uuid_normalised() -> None:
    config = loads_config(
        "[outputs.opentrackio]\nallow_multicast = true\n"
        'destinations = ["239.135.1.1:55555"]\n'
        'source_id = "urn:uuid:6BA7B810-9DAD-11D1-80B4-00C04FD430C8"\n'
    ).outputs.opentrackio
    assert config.destinations == ("239.135.1.1:55555",)
    assert config.source_id == "6ba7b810-9dad-11d1-80b4-00c04fd430c8"
