"""`[outputs.opentrackio]`: camera tracking as OpenTrackIO samples over UDP."""

from __future__ import annotations

import ipaddress
import uuid
from dataclasses import dataclass
from typing import Any

from host.config_fields import parse_destination, parse_vector3, spec

SYNC_SOURCES = ("none", "ptp", "ntp")
ENCODINGS = ("json", "cbor")
UTC_TAI_OFFSET_S = 37  # TAI - UTC since 2017-01-01; used where the kernel was not told


def parse_uuid(value: Any) -> str:
    """Empty (a new id at every start) or a UUID, stored in its canonical lower-case form."""
    if not isinstance(value, str):
        raise ValueError("expected a UUID string")
    if not value:
        return ""
    try:
        return str(uuid.UUID(value.removeprefix("urn:uuid:")))
    except ValueError:
        raise ValueError("not a UUID (e.g. 6ba7b810-9dad-11d1-80b4-00c04fd430c8)") from None


@dataclass(frozen=True)
class OpenTrackIOConfig:
    """OpenTrackIO output: destinations, encoding, axes, sensor size and the time source."""

    enabled: bool = spec(False, doc="switch this part on")
    destinations: tuple[str, ...] = spec(
        ("127.0.0.1:55555",), parse=parse_destination, each=True, doc='UDP "host:port" receivers'
    )
    allow_multicast: bool = spec(
        False, doc="permit multicast destinations (239.135.1.N:55555); off: unicast only"
    )
    encoding: str = spec("json", choices=ENCODINGS, doc='"json" or "cbor" payloads')
    mtu_bytes: int = spec(1500, lo=576, hi=65535, doc="largest datagram incl. IP/UDP headers")
    source_id: str = spec(
        "", parse=parse_uuid, doc="UUID naming this rig to receivers (empty: new at each start)"
    )
    source_number: int = spec(1, lo=0, hi=2**31 - 1, doc="stream index within the source")
    camera_label: str = spec("orbitar", doc="static.camera.label (non-blank)")
    origin_mm: tuple[float, float, float] = spec(
        (0.0, 0.0, 0.0), parse=parse_vector3, doc="stage origin in our world frame"
    )
    yaw_rad: float = spec(
        0.0, key="yaw_deg", deg=True, lo=-360.0, hi=360.0, doc="stage axes turned about world z"
    )
    pixel_pitch_um: float = spec(
        5.3, lo=0.01, hi=1000.0, doc="sensor pixel pitch: turns pixel intrinsics into mm"
    )
    static_interval_s: float = spec(2.0, lo=0.1, hi=3600.0, doc="seconds between static blocks")
    sync_source: str = spec(
        "none", choices=SYNC_SOURCES, doc='"ptp" when linuxptp disciplines the clock, "ntp", "none"'
    )
    utc_tai_offset_s: int = spec(
        UTC_TAI_OFFSET_S, lo=0, hi=100, doc="TAI - UTC used when the kernel's offset is unset"
    )


def opentrackio_problems(config: OpenTrackIOConfig) -> list[str]:
    """Rules across keys: multicast only when asked for, a non-blank label."""
    errors = []
    if not config.camera_label.strip():
        errors.append("outputs.opentrackio.camera_label: must not be blank")
    for i, destination in enumerate(config.destinations):
        host = destination.rpartition(":")[0].strip("[]")
        try:
            multicast = ipaddress.ip_address(host).is_multicast
        except ValueError:
            continue  # a host name: resolved when the output starts
        if multicast and not config.allow_multicast:
            errors.append(
                f"outputs.opentrackio.destinations[{i}] = {destination!r}: multicast needs "
                "outputs.opentrackio.allow_multicast = true"
            )
    return errors
