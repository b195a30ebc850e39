"""FreeD D1: byte layout, checksum, the angle mapping for known poses, and the UDP sender."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from host.config import FreedConfig
from host.outputs.freed import (
    PACKET_BYTES,
    FreedPose,
    FreedSender,
    decode_d1,
    encode_d1,
    pose_to_freed,
    wrap_deg,
)

# Camera looking along world +Y, level, image top = world +Z: x_c = +X, y_c = -Z, z_c = +Y.
BASE = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])


def rot(axis: str, deg: float) -> np.ndarray:
    """A rotation about a coordinate axis."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def camera(
    pan: float, tilt: float, roll: float = 0.0, at: tuple[float, float, float] = (0, 0, 0)
) -> np.ndarray:
    """T_w_c built independently: clockwise pan about z, tilt up, roll about the optical axis."""
    T = np.eye(4)
    T[:3, :3] = rot("z", -pan) @ rot("x", tilt) @ BASE @ rot("z", roll)
    T[:3, 3] = at
    return T


def roundtrip(T: np.ndarray, **kw: object) -> FreedPose:
    """Map, encode and decode one pose."""
    packet, _ = encode_d1(7, pose_to_freed(T, **kw))  # type: ignore[arg-type]
    return decode_d1(packet).pose


def test_packet_layout_and_checksum() -> None:
    pose = FreedPose(10.0, -5.0, 1.5, 1000.0, -2000.0, 4000.0)
    packet, clamped = encode_d1(42, pose, zoom=0x123456, focus=7)
    assert len(packet) == PACKET_BYTES == 29
    assert packet[0] == 0xD1
    assert packet[1] == 42
    assert packet[2:5] == (10 * 32768).to_bytes(3, "big")
    assert packet[5:8] == (-5 * 32768 & 0xFFFFFF).to_bytes(3, "big")
    assert packet[11:14] == (1000 * 64).to_bytes(3, "big")
    assert packet[20:23] == b"\x12\x34\x56"
    assert packet[26:28] == b"\x00\x00"
    assert (0x40 - sum(packet[:28])) % 256 == packet[28]
    assert not clamped
    decoded = decode_d1(packet)
    assert (decoded.camera_id, decoded.zoom, decoded.focus) == (42, 0x123456, 7)
    assert decoded.pose == pose


def test_decode_rejects_bad_checksum_and_length() -> None:
    packet, _ = encode_d1(1, FreedPose(0, 0, 0, 0, 0, 0))
    with pytest.raises(ValueError, match="checksum"):
        decode_d1(packet[:-1] + bytes([(packet[-1] + 1) % 256]))
    with pytest.raises(ValueError, match="29-byte"):
        decode_d1(packet[:-2])


def test_level_along_plus_y_is_pan_zero_tilt_zero() -> None:
    got = roundtrip(camera(0, 0))
    assert (got.pan_deg, got.tilt_deg, got.roll_deg) == pytest.approx((0, 0, 0), abs=1e-4)


def test_along_plus_x_is_pan_plus_90() -> None:
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = (0, -1, 0), (0, 0, -1), (1, 0, 0)  # written out, no helper
    got = roundtrip(T)
    assert got.pan_deg == pytest.approx(90.0, abs=1e-4)
    assert got.tilt_deg == pytest.approx(0.0, abs=1e-4)


def test_looking_up_30_degrees_is_tilt_plus_30() -> None:
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    T = np.eye(4)
    T[:3, 0], T[:3, 2] = (1, 0, 0), (0, c, s)
    T[:3, 1] = np.cross(T[:3, 2], T[:3, 0])  # y = z × x keeps the frame right-handed
    got = roundtrip(T)
    assert got.tilt_deg == pytest.approx(30.0, abs=1e-4)
    assert got.pan_deg == pytest.approx(0.0, abs=1e-4)


def test_position_is_in_freed_frame_with_yaw_and_origin() -> None:
    T = camera(0, 0, at=(1500.0, 300.0, 4000.0))
    assert roundtrip(T) == FreedPose(0.0, 0.0, 0.0, 1500.0, 300.0, 4000.0)
    turned = roundtrip(T, origin_mm=(500.0, 300.0, 0.0), yaw_rad=math.radians(90))
    # FreeD +X is world +Y, FreeD +Y is world -X: the camera sits 1000 mm along world +X.
    assert (turned.x_mm, turned.y_mm, turned.z_mm) == pytest.approx((0.0, -1000.0, 4000.0))
    assert turned.pan_deg == pytest.approx(90.0, abs=1e-4)  # world +Y is FreeD +X


def test_straight_down_takes_pan_from_the_image_top() -> None:
    got = roundtrip(camera(40, -90))
    assert got.tilt_deg == pytest.approx(-90.0, abs=1e-4)
    assert got.pan_deg == pytest.approx(40.0, abs=1e-3)


def test_out_of_range_position_is_clamped_and_reported() -> None:
    packet, clamped = encode_d1(1, FreedPose(0, 0, 0, 200_000.0, 0, 0))
    assert clamped
    assert decode_d1(packet).pose.x_mm == pytest.approx(((1 << 23) - 1) / 64)


@given(
    st.floats(-179.0, 179.0),
    st.floats(-85.0, 85.0),
    st.floats(-179.0, 179.0),
)
def test_known_angles_come_back(pan: float, tilt: float, roll: float) -> None:
    got = roundtrip(camera(pan, tilt, roll))
    assert got.pan_deg == pytest.approx(pan, abs=1e-3)
    assert got.tilt_deg == pytest.approx(tilt, abs=1e-3)
    assert wrap_deg(got.roll_deg - roll) == pytest.approx(0.0, abs=1e-3)


def test_wrap_deg() -> None:
    assert wrap_deg(190.0) == pytest.approx(-170.0)
    assert wrap_deg(-180.0) == pytest.approx(180.0)
    assert wrap_deg(540.0) == pytest.approx(180.0)


class _Collector(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.packets: asyncio.Queue[bytes] = asyncio.Queue()

    def datagram_received(self, data: bytes, addr: object) -> None:
        self.packets.put_nowait(data)


async def test_sender_delivers_to_every_destination_on_loopback() -> None:
    loop = asyncio.get_running_loop()
    receivers = [
        await loop.create_datagram_endpoint(_Collector, local_addr=("127.0.0.1", 0))
        for _ in range(2)
    ]
    ports = [t.get_extra_info("sockname")[1] for t, _ in receivers]
    config = FreedConfig(enabled=True, destinations=tuple(f"127.0.0.1:{p}" for p in ports))
    sender = FreedSender(config)
    await sender.start()
    try:
        sender.send(camera(90, 10, at=(100.0, 200.0, 4000.0)))
        for _, proto in receivers:
            got = decode_d1(await asyncio.wait_for(proto.packets.get(), 5))
            assert got.camera_id == config.camera_id
            assert got.pose.pan_deg == pytest.approx(90.0, abs=1e-4)
            assert got.pose.tilt_deg == pytest.approx(10.0, abs=1e-4)
            assert got.pose.z_mm == pytest.approx(4000.0)
    finally:
        sender.close()
        for transport, _ in receivers:
            transport.close()
    assert sender.stats()["sent"] == 1
