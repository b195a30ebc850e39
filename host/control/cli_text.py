"""The terminal's words for the daemon's numbers: degrees, millimetres, named faults, ages.

`orbitar status` and `orbitar watch` print these; `--json` prints the raw results instead. The
daemon speaks radians and raw counters on the socket; people read degrees, millimetres at a
precision that means something, fault names, and how old each figure is.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import Any

STALE_AFTER_MS = 1000.0  # a figure older than this is marked stale
LABEL_WIDTH = 11
_RANGE = re.compile(r"(\w+)_rad = (\S+): outside \[(\S+), (\S+)\]")


def fmt(value: Any, digits: int = 1, unit: str = "") -> str:
    """A number at a fixed precision, or — when unknown."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return "—"
    return f"{value:.{digits}f}{unit}"


def deg(rad: Any, digits: int = 2) -> str:
    """Radians shown as degrees."""
    if not isinstance(rad, int | float) or isinstance(rad, bool):
        return "—"
    return fmt(math.degrees(rad), digits, "°")


def age(ms: Any) -> str:
    """How old a figure is: `12 ms old`, `3.4 s old (stale)`, or `age unknown`."""
    if not isinstance(ms, int | float) or isinstance(ms, bool) or not math.isfinite(ms):
        return "age unknown"
    text = f"{ms:.0f} ms old" if ms < 1000 else f"{ms / 1000:.1f} s old"
    return text + (" (stale)" if ms > STALE_AFTER_MS else "")


def duration(seconds: Any) -> str:
    """Uptime as `2 h 05 min`, `3 min 12 s` or `40 s`."""
    if not isinstance(seconds, int | float):
        return "—"
    s = int(seconds)
    if s >= 3600:
        return f"{s // 3600} h {s % 3600 // 60:02d} min"
    if s >= 60:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s} s"


def line(label: str, *parts: str) -> str:
    """`label      part · part · part`."""
    return f"{label:<{LABEL_WIDTH}} " + " · ".join(p for p in parts if p) + "\n"


def faults_text(controller: Mapping[str, Any]) -> str:
    """Latched faults by name (an unknown bit shows as its number)."""
    names = controller.get("fault_names")
    if names:
        return "FAULTS: " + ", ".join(str(n) for n in names)
    raw = controller.get("faults")
    if isinstance(raw, int) and raw:
        return f"FAULTS: 0x{raw:04x}"
    return "no faults"


def link_text(up: bool, link: Mapping[str, Any]) -> str:
    """The link line."""
    state = "up" if up else f"DOWN ({link.get('state', 'unknown')})"
    return line(
        "link",
        state,
        f"RTT {fmt(link.get('rtt_ms'), 1, ' ms')}",
        f"{link.get('retransmits', '—')} retransmits",
        f"{link.get('rx_lost', '—')} lost",
        f"clock σ {fmt(link.get('clock_sigma_us'), 0, ' µs')}",
    )


def controller_text(controller: Mapping[str, Any], link: Mapping[str, Any]) -> str:
    """The controller line: state, faults, position, homing, age."""
    homed = controller.get("homed", link.get("homed"))
    age_s = controller.get("age_s")
    return line(
        "controller",
        str(controller.get("state", "UNKNOWN")),
        faults_text(controller),
        f"position {fmt(controller.get('position_mm'), 1, ' mm')}",
        "" if homed is None else ("homed" if homed else "NOT HOMED"),
        age(age_s * 1e3 if isinstance(age_s, int | float) else None),
    )


def head_text(controller: Mapping[str, Any]) -> str:
    """Head angles in degrees."""
    head = controller.get("head_rad") or [None, None]
    return line("head", f"pan {deg(head[0])}", f"tilt {deg(head[1])}")


def pose_text(pose: Mapping[str, Any] | None, now_ns: int) -> str:
    """Where the camera is, and how old that is."""
    if not pose:
        return line("camera", "no pose yet")
    T = pose["T_w_c"]
    xyz = "  ".join(f"{axis} {T[i][3]:.1f}" for i, axis in enumerate("xyz"))
    return line(
        "camera",
        f"{xyz} mm",
        f"s {fmt(pose.get('s_mm'), 1, ' mm')}",
        age((now_ns - int(pose["t_ns"])) / 1e6),
    )


def drift_text(link: Mapping[str, Any]) -> str:
    """The drift filter, when references are configured."""
    if "chain_scale" not in link:
        return line("drift", "no references configured")
    return line(
        "drift",
        f"chain scale {fmt(link['chain_scale'], 6)}",
        f"{link.get('references_used', 0)} references used, "
        f"{link.get('references_rejected', 0)} rejected",
        f"{link.get('skips_detected', 0)} tooth skips",
        f"σ {fmt(link.get('position_sigma_mm'), 2, ' mm')}",
    )


def frames_text(service: Mapping[str, Any]) -> str:
    """The camera and the frame loop."""
    frames = service.get("frames")
    if not frames:
        return line("frames", "no camera", f"{fmt(service.get('fps'), 1, ' poses/s')}")
    source = frames.get("source", {})
    return line(
        "frames",
        f"{source.get('kind', 'camera')} {source.get('state', '')}".strip(),
        str(source.get("detail", "")),
        f"{fmt(service.get('fps'), 1, ' fps')}",
        f"{frames.get('dropped', 0)} dropped",
        f"latency p50 {fmt(frames.get('latency_ms_p50'), 0, ' ms')}",
        stamps_text(source.get("stamps")),
    )


def stamps_text(stamps: Mapping[str, Any] | None) -> str:
    """How the frames are stamped: as delivered, or on the camera's fitted clock."""
    if not stamps:
        return "stamps as delivered"
    return (
        f"stamps on the camera's clock ({stamps.get('smoothed', 0)} of "
        f"{stamps.get('frames', 0)}, ±{fmt(stamps.get('residual_us'), 0, ' µs')}, "
        f"{stamps.get('restarts', 0)} restarts)"
    )


def status_text(status: Mapping[str, Any], link: Mapping[str, Any], now_ns: int) -> str:
    """`orbitar status` for a person."""
    service = status.get("service", {})
    controller = status.get("controller", {})
    out = line(
        "daemon",
        str(service.get("phase", "?")),
        f"up {duration(service.get('uptime_s'))}",
        f"{service.get('clients', 0)} clients",
        f"link error: {service['link_error']}" if service.get("link_error") else "",
    )
    if service.get("drive_problem"):
        out += line("drive", f"controller built for another chain: {service['drive_problem']}")
    out += link_text(bool(status.get("link_up")), link)
    out += controller_text(controller, link)
    out += head_text(controller)
    out += pose_text(status.get("pose"), now_ns)
    out += drift_text(link)
    out += frames_text(service)
    return out


def head_error_in_degrees(message: str) -> str:
    """The daemon's radian range error for `head`, in the degrees the command was given in."""
    match = _RANGE.search(message)
    if not match:
        return message
    axis, value, lo, hi = match.groups()
    try:
        numbers = [math.degrees(float(v)) for v in (value, lo, hi)]
    except ValueError:
        return message
    value_deg, lo_deg, hi_deg = numbers
    return f"{axis} {value_deg:.2f}° is outside the head's limits [{lo_deg:.2f}°, {hi_deg:.2f}°]"
