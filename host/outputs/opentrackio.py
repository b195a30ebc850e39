"""OpenTrackIO 1.0 camera tracking over UDP: a sample per registered frame, at its exposure time.

The mapping from our pose and camera model to OpenTrackIO's terms is in docs/OPENTRACKIO.md. In
short: the stage is our world frame turned by `yaw_deg` about z with its origin at `origin_mm`
(Z up, as ours); the camera's OpenTrackIO axes are X right, Y forward, Z up, so they are our
camera's x, z and -y; rotations are intrinsic Z-X-Y (pan, tilt, roll) in degrees; translations in
metres. The sample's timestamp is the exposure time, mapped from the host's monotonic clock to
TAI (PTP time) through the realtime clock.
"""

from __future__ import annotations

import json
import logging
import math
import time
import uuid
from collections.abc import Mapping
from typing import Any

import cbor2

from host.config_opentrackio import OpenTrackIOConfig
from host.control.api import Matrix4, PoseSample
from host.geometry.camera import CameraModel
from host.outputs.opentrackio_packet import Encoding, segment_payload
from host.outputs.udp import UdpFanout
from host.outputs.wallclock import monotonic_to_unix_ns

log = logging.getLogger(__name__)

PROTOCOL = {"name": "OpenTrackIO", "version": [1, 0, 1]}
TRACKER = {"make": "Orbitar", "model": "kinematic track rig"}
GIMBAL_EPS = 1e-9  # |cos tilt| below which pan and roll are not separable (camera looks up/down)
NS_PER_S = 1_000_000_000
Rotation = tuple[tuple[float, float, float], ...]


def _stage_rotation(T_w_c: Matrix4, yaw_rad: float) -> Rotation:
    """OpenTrackIO's camera axes (right, forward, up) in stage coordinates, as matrix columns."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)

    def stage(j: int, sign: float) -> tuple[float, float, float]:
        x, y, z = (sign * float(T_w_c[i][j]) for i in range(3))
        return (c * x + s * y, -s * x + c * y, z)

    right, forward, up = stage(0, 1.0), stage(2, 1.0), stage(1, -1.0)
    return tuple((right[i], forward[i], up[i]) for i in range(3))


def pan_tilt_roll_deg(R: Rotation) -> tuple[float, float, float]:
    """Intrinsic Z-X-Y Euler angles of R = Rz(pan) Rx(tilt) Ry(roll), degrees."""
    horizontal = math.hypot(R[0][1], R[1][1])
    tilt = math.atan2(R[2][1], horizontal)
    if horizontal < GIMBAL_EPS:  # looking straight up or down: put the whole turn into pan
        return math.degrees(math.atan2(R[1][0], R[0][0])), math.degrees(tilt), 0.0
    pan = math.atan2(-R[0][1], R[1][1])
    roll = math.atan2(-R[2][0], R[2][2])
    return math.degrees(pan), math.degrees(tilt), math.degrees(roll)


def transform(
    T_w_c: Matrix4, origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0), yaw_rad: float = 0.0
) -> dict[str, Any]:
    """The camera's OpenTrackIO transform relative to the stage origin (metres, degrees)."""
    pan, tilt, roll = pan_tilt_roll_deg(_stage_rotation(T_w_c, yaw_rad))
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    dx, dy, dz = (float(T_w_c[i][3]) - origin_mm[i] for i in range(3))
    return {
        "translation": {"x": (c * dx + s * dy) / 1000.0, "y": (-s * dx + c * dy) / 1000.0,
                        "z": dz / 1000.0},
        "rotation": {"pan": pan, "tilt": tilt, "roll": roll},
        "id": "camera",
    }  # fmt: skip


def lens(camera: CameraModel, pixel_pitch_um: float) -> dict[str, Any]:
    """Focal length, projection offset and distortion of the calibrated camera model."""
    pitch_mm = pixel_pitch_um / 1000.0
    return {
        "pinholeFocalLength": camera.fx * pitch_mm,
        "projectionOffset": {
            "x": (camera.u0 - camera.width / 2.0) * pitch_mm,
            "y": (camera.height / 2.0 - camera.v0) * pitch_mm,
        },
        "distortion": [
            {
                "model": "Brown-Conrady U-D",
                "radial": [camera.k1, camera.k2, camera.k3],
                "tangential": [camera.p1, camera.p2],
            }
        ],
    }


class TaiClock:
    """Maps host monotonic nanoseconds to PTP time (TAI seconds and nanoseconds)."""

    def __init__(self, utc_tai_offset_s: int) -> None:
        self.utc_tai_offset_s = utc_tai_offset_s

    def kernel_offset_s(self) -> int:
        """The kernel's TAI-UTC offset (0 where nothing such as phc2sys or chrony has set it)."""
        return round((time.clock_gettime_ns(time.CLOCK_TAI) - time.time_ns()) / NS_PER_S)

    def to_tai_ns(self, t_mono_ns: int) -> int:
        """TAI time of a host monotonic instant."""
        offset_s = self.kernel_offset_s() or self.utc_tai_offset_s
        return monotonic_to_unix_ns(t_mono_ns) + offset_s * NS_PER_S


def _ptp_time(tai_ns: int) -> dict[str, int]:
    """TAI nanoseconds as OpenTrackIO's PTP timestamp."""
    return {"seconds": tai_ns // NS_PER_S, "nanoseconds": tai_ns % NS_PER_S}


def _rational(rate_hz: float) -> dict[str, int]:
    """A frame rate as OpenTrackIO's rational (29.97 → 30000/1001)."""
    for denom in (1, 1001):
        num = rate_hz * denom
        if abs(num - round(num)) < 1e-3 * denom:
            return {"num": round(num), "denom": denom}
    return {"num": round(rate_hz * 1000), "denom": 1000}


class OpenTrackIOSender:
    """Builds and sends one OpenTrackIO sample per registered pose."""

    def __init__(self, config: OpenTrackIOConfig, camera: CameraModel, fps: float) -> None:
        self.config = config
        self.camera = camera
        self.fps = fps
        self.clock = TaiClock(config.utc_tai_offset_s)
        self.source_id = f"urn:uuid:{config.source_id or uuid.uuid4()}"
        self.sent = 0
        self.datagrams = 0
        self.sequence = 0
        self._last_static_ns: int | None = None
        self._udp = UdpFanout(config.destinations)

    @property
    def errors(self) -> int:
        """Send errors the OS reported (ICMP port unreachable and the like)."""
        return self._udp.errors

    async def start(self) -> None:
        """Open the UDP endpoints."""
        await self._udp.start()

    def close(self) -> None:
        """Close the UDP endpoints."""
        self._udp.close()

    def sample(self, pose: PoseSample, now_ns: int | None = None) -> dict[str, Any]:
        """The OpenTrackIO sample of one registered pose (static block every static_interval_s)."""
        cfg = self.config
        tai_ns = self.clock.to_tai_ns(pose.t_ns)
        sample: dict[str, Any] = {
            "protocol": PROTOCOL,
            "sampleId": f"urn:uuid:{uuid.uuid4()}",
            "sourceId": self.source_id,
            "sourceNumber": cfg.source_number,
            "timing": {
                "mode": "internal",
                "sampleRate": _rational(self.fps),
                "sampleTimestamp": _ptp_time(tai_ns),
                "sequenceNumber": self.sequence,
            },
            "tracker": {"status": _status(pose), "recording": False},
            "transforms": [transform(pose.T_w_c, cfg.origin_mm, cfg.yaw_rad)],
            "lens": lens(self.camera, cfg.pixel_pitch_um),
        }
        if cfg.sync_source != "none":
            sample["timing"]["synchronization"] = {"source": cfg.sync_source, "locked": True}
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        due = self._last_static_ns is None or now_ns - self._last_static_ns >= round(
            cfg.static_interval_s * NS_PER_S
        )
        if due:
            sample["static"] = self._static()
            self._last_static_ns = now_ns
        return sample

    def send(self, pose: PoseSample) -> list[bytes]:
        """Encode the pose's sample, segment it to the MTU and send it to every destination."""
        sample = self.sample(pose)
        datagrams = segment_payload(
            self.encoding, self.sequence, self.encode(sample), self.config.mtu_bytes
        )
        for datagram in datagrams:
            self._udp.send(datagram)
        self.sequence = (self.sequence + 1) & 0xFFFF
        self.sent += 1
        self.datagrams += len(datagrams)
        return datagrams

    @property
    def encoding(self) -> Encoding:
        """The configured payload encoding."""
        return Encoding.CBOR if self.config.encoding == "cbor" else Encoding.JSON

    def encode(self, sample: Mapping[str, Any]) -> bytes:
        """The sample's payload bytes in the configured encoding."""
        if self.encoding is Encoding.CBOR:
            return bytes(cbor2.dumps(sample))
        return json.dumps(sample, separators=(",", ":")).encode()

    def stats(self) -> dict[str, int]:
        """Counters for the status op."""
        return {"sent": self.sent, "datagrams": self.datagrams, "errors": self.errors}

    def _static(self) -> dict[str, Any]:
        """What does not change from frame to frame: the sensor and the tracker."""
        pitch_mm = self.config.pixel_pitch_um / 1000.0
        width, height = self.camera.width, self.camera.height
        return {
            "camera": {
                "label": self.config.camera_label,
                "captureFrameRate": _rational(self.fps),
                "activeSensorResolution": {"width": width, "height": height},
                "activeSensorPhysicalDimensions": {
                    "width": width * pitch_mm,
                    "height": height * pitch_mm,
                },
            },
            "tracker": dict(TRACKER),
        }


def _status(pose: PoseSample) -> str:
    """Tracker status text: the controller state when the pose was computed, and if unhomed."""
    state = pose.state or "unknown"
    return state if pose.homed else f"{state}, not homed"
