"""The daemon's stream rates fit their links with room left for commands.

Frame sizes come from the codec (COBS adds a fixed byte or two, whatever the values), the
XBee air's rate and per-packet overhead from its emulator, the clock-sync rate from the session.
"""

from __future__ import annotations

import pytest

from hil_sim.links.endpoint import build
from hil_sim.links.pacing import uart_rate_bytes_s
from hil_sim.links.xbee import AIR_OVERHEAD_BYTES, AIR_RATE_BPS
from host.link.session import SessionConfig
from host.service.wiring import stream_rates
from protocol import encode_frame
from protocol.enums import Stream
from protocol.messages import ClockSync, ClockSyncReply, EncoderSample, HeadSample, RangeSample
from protocol.messages import Status as StatusMsg

MAX_SHARE = 0.70  # the rest is for commands, their replies, retransmissions and MAC retries
SAMPLES = {
    Stream.ENCODER: build(EncoderSample, 0, 0, 0, 0, 0),
    Stream.RANGE: build(RangeSample, 0, 0, 0),
    Stream.HEAD: build(HeadSample, 0, 0, 0),
    Stream.STATUS: build(StatusMsg, 0, 0, 0, 0, 0, 0),
}
PROBE_HZ = 1.0 / SessionConfig().clock_sync_interval_s


def _frame(message: object) -> int:
    """Wire bytes of one frame, delimiter included."""
    return len(encode_frame(message, 0))


@pytest.mark.parametrize("ranging", [False, True])
def test_xbee_streams_leave_a_third_of_the_air(ranging: bool) -> None:
    """One half-duplex channel for both ways; every frame is an RF packet with its overhead."""

    def packet(message: object) -> int:
        return _frame(message) + AIR_OVERHEAD_BYTES

    rates = stream_rates("xbee", ranging)
    load: float = sum(rate * packet(SAMPLES[stream]) for stream, rate in rates.items())
    load += PROBE_HZ * (packet(build(ClockSync, 0)) + packet(build(ClockSyncReply, 0, 0, 0, 0)))
    share = load / (AIR_RATE_BPS / 8)
    assert share <= MAX_SHARE, f"XBee streams take {share:.0%} of the air"


@pytest.mark.parametrize("ranging", [False, True])
def test_serial_streams_leave_a_third_of_the_line(ranging: bool) -> None:
    """Full duplex: the controller's direction carries the telemetry and the clock replies."""
    rates = stream_rates("serial", ranging)
    load: float = sum(rate * _frame(SAMPLES[stream]) for stream, rate in rates.items())
    load += PROBE_HZ * _frame(build(ClockSyncReply, 0, 0, 0, 0))
    share = load / uart_rate_bytes_s(115200)
    assert share <= MAX_SHARE, f"serial streams take {share:.0%} of the line"
