"""FreeD D1 camera-tracking packets over UDP, for render engines (Unreal LiveLink, vMix, …).

The mapping from our world frame to FreeD's and the range handling are in docs/FREED.md. In
short: FreeD's Z is our world z (up); its axes are our world axes turned by `yaw_rad` about z,
its origin is `origin_mm`; pan is the compass angle of the optical axis, 0 along +Y and positive
towards +X (clockwise seen from above); tilt is the elevation of the optical axis, positive up;
roll is the turn of the camera about its optical axis, positive when the image top moves right.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from host.config import FreedConfig
from host.control.api import Matrix4
from host.outputs.udp import UdpFanout

log = logging.getLogger(__name__)

PACKET_BYTES = 29
MESSAGE_D1 = 0xD1
ANGLE_UNITS_PER_DEG = 32768
POSITION_UNITS_PER_MM = 64
INT24_MIN, INT24_MAX = -(1 << 23), (1 << 23) - 1
UINT24_MAX = (1 << 24) - 1
VERTICAL_EPS = 1e-9  # |horizontal part| of the optical axis below which pan comes from "up"

Vector3 = tuple[float, float, float]


@dataclass(frozen=True)
class FreedPose:
    """A camera pose in FreeD's terms: degrees and millimetres in FreeD's frame."""

    pan_deg: float
    tilt_deg: float
    roll_deg: float
    x_mm: float
    y_mm: float
    z_mm: float


@dataclass(frozen=True)
class FreedPacket:
    """A decoded D1 packet (raw zoom and focus)."""

    camera_id: int
    pose: FreedPose
    zoom: int
    focus: int


def _dot(a: Vector3, b: Vector3) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _column(T: Matrix4, j: int) -> Vector3:
    return (float(T[0][j]), float(T[1][j]), float(T[2][j]))


def _to_freed_frame(v: Vector3, yaw_rad: float) -> Vector3:
    """A world vector in FreeD's axes (turned by yaw about z)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return (c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2])


def wrap_deg(angle: float) -> float:
    """An angle in (-180, 180]."""
    wrapped = math.fmod(angle + 180.0, 360.0)
    wrapped = wrapped + 360.0 if wrapped <= 0.0 else wrapped
    return wrapped - 180.0


def pose_to_freed(
    T_w_c: Matrix4, origin_mm: Vector3 = (0.0, 0.0, 0.0), yaw_rad: float = 0.0
) -> FreedPose:
    """Pan, tilt, roll and position of camera pose T_w_c (camera looks along +z, image y down)."""
    d = _to_freed_frame(_column(T_w_c, 2), yaw_rad)  # optical axis
    up = _to_freed_frame(tuple(-x for x in _column(T_w_c, 1)), yaw_rad)  # type: ignore[arg-type]
    horizontal = math.hypot(d[0], d[1])
    tilt = math.atan2(d[2], horizontal)
    if horizontal < VERTICAL_EPS:
        # Straight down (up): the image top (bottom) points where the camera "faces".
        facing = up if d[2] < 0 else (-up[0], -up[1], -up[2])
        pan, roll = math.atan2(facing[0], facing[1]), 0.0
    else:
        pan = math.atan2(d[0], d[1])
        level_up = (
            -math.sin(tilt) * math.sin(pan),
            -math.sin(tilt) * math.cos(pan),
            math.cos(tilt),
        )
        level_right = (math.cos(pan), -math.sin(pan), 0.0)
        roll = math.atan2(_dot(up, level_right), _dot(up, level_up))
    p = _column(T_w_c, 3)
    rel = (p[0] - origin_mm[0], p[1] - origin_mm[1], p[2] - origin_mm[2])
    x, y, z = _to_freed_frame(rel, yaw_rad)
    return FreedPose(
        wrap_deg(math.degrees(pan)), math.degrees(tilt), wrap_deg(math.degrees(roll)), x, y, z
    )


def _int24(value: float, scale: int) -> tuple[bytes, bool]:
    """Signed 24-bit big-endian of value*scale, clamped; True if it had to be clamped."""
    raw = round(value * scale)
    clamped = min(max(raw, INT24_MIN), INT24_MAX)
    return (clamped & UINT24_MAX).to_bytes(3, "big"), clamped != raw


def _uint24(value: int) -> bytes:
    """Unsigned 24-bit big-endian, clamped."""
    return min(max(value, 0), UINT24_MAX).to_bytes(3, "big")


def checksum(body: bytes) -> int:
    """FreeD checksum: 0x40 minus the sum of all preceding bytes, modulo 256."""
    return (0x40 - sum(body)) % 256


def encode_d1(camera_id: int, pose: FreedPose, zoom: int = 0, focus: int = 0) -> tuple[bytes, bool]:
    """A 29-byte D1 packet, and whether any field was clamped to its 24-bit range."""
    fields = [
        _int24(pose.pan_deg, ANGLE_UNITS_PER_DEG),
        _int24(pose.tilt_deg, ANGLE_UNITS_PER_DEG),
        _int24(pose.roll_deg, ANGLE_UNITS_PER_DEG),
        _int24(pose.x_mm, POSITION_UNITS_PER_MM),
        _int24(pose.y_mm, POSITION_UNITS_PER_MM),
        _int24(pose.z_mm, POSITION_UNITS_PER_MM),
    ]
    body = bytes([MESSAGE_D1, camera_id & 0xFF]) + b"".join(f for f, _ in fields)
    body += _uint24(zoom) + _uint24(focus) + b"\x00\x00"
    return body + bytes([checksum(body)]), any(c for _, c in fields)


def decode_d1(packet: bytes) -> FreedPacket:
    """Parse a D1 packet; ValueError for a wrong length, type or checksum."""
    if len(packet) != PACKET_BYTES or packet[0] != MESSAGE_D1:
        raise ValueError(f"not a 29-byte D1 packet: {packet[:2].hex()}… ({len(packet)} bytes)")
    if checksum(packet[:-1]) != packet[-1]:
        raise ValueError("FreeD checksum mismatch")

    def s24(i: int, scale: int) -> float:
        return int.from_bytes(packet[i : i + 3], "big", signed=True) / scale

    pose = FreedPose(
        s24(2, ANGLE_UNITS_PER_DEG),
        s24(5, ANGLE_UNITS_PER_DEG),
        s24(8, ANGLE_UNITS_PER_DEG),
        s24(11, POSITION_UNITS_PER_MM),
        s24(14, POSITION_UNITS_PER_MM),
        s24(17, POSITION_UNITS_PER_MM),
    )
    zoom = int.from_bytes(packet[20:23], "big")
    focus = int.from_bytes(packet[23:26], "big")
    return FreedPacket(packet[1], pose, zoom, focus)


class FreedSender:
    """Sends a D1 packet per pose to every configured destination."""

    def __init__(self, config: FreedConfig) -> None:
        self.config = config
        self.sent = 0
        self.clamped = 0
        self._udp = UdpFanout(config.destinations)

    @property
    def errors(self) -> int:
        """Send errors the OS reported (ICMP port unreachable and the like)."""
        return self._udp.errors

    async def start(self) -> None:
        """Open one UDP endpoint per destination."""
        await self._udp.start()

    def send(self, T_w_c: Matrix4) -> bytes:
        """Encode the pose and send it (never blocks: UDP datagrams are queued by the OS)."""
        pose = pose_to_freed(T_w_c, self.config.origin_mm, self.config.yaw_rad)
        packet, clamped = encode_d1(
            self.config.camera_id, pose, self.config.zoom, self.config.focus
        )
        self.clamped += clamped
        self._udp.send(packet)
        self.sent += 1
        return packet

    def close(self) -> None:
        """Close every endpoint."""
        self._udp.close()

    def stats(self) -> dict[str, int]:
        """Counters for the status op."""
        return {"sent": self.sent, "errors": self.errors, "clamped": self.clamped}
