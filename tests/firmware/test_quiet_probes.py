"""Quiet clock probes in the mirror (PROTOCOL.md §8, R-QUIET-1), tick by tick in lockstep."""

from __future__ import annotations

import itertools

import pytest

from firmware.link import CATCH_UP
from hil_sim.client import FrameClient
from protocol import PROTOCOL_VERSION, SCHEMA_HASH, Stream
from protocol.enums import Capability
from protocol.messages import ClockSync, ClockSyncReply, EncoderSample, Hello, StreamSet
from protocol.schema import QUIET_HOLD_US
from tests.firmware.conftest import Rig, make_rig

QUIET = int(Capability.QUIET_CLOCK_PROBES)
HOLD_TICKS = QUIET_HOLD_US // 1000


def _session(host_caps: int, fw_caps: int | None = None) -> Rig:
    """A rig in a session offering `host_caps`, its encoder stream at 500 Hz."""
    rig = make_rig()
    if fw_caps is not None:
        rig.sim.firmware.capabilities = fw_caps
    rig.client = FrameClient(rig.sim, handshake=False)
    rig.client.request(Hello(PROTOCOL_VERSION, SCHEMA_HASH, host_caps, 1))
    rig.client.request(StreamSet(int(Stream.ENCODER), 500))
    rig.client.run(20)
    return rig


def _timeline(rig: Rig, ticks: int, probe_at: dict[int, int]) -> list[tuple[int, object]]:
    """Step `ticks`, sending CLOCK_SYNC(token) at the ticks given; (tick, message) received."""
    out: list[tuple[int, object]] = []
    for i in range(ticks):
        if i in probe_at:
            rig.client.send(ClockSync(probe_at[i]))
        rig.sim.step(1)
        out.extend((i, p.message) for p in rig.client.poll())
    return out


def _sample_ticks(events: list[tuple[int, object]]) -> list[int]:
    return [t for t, m in events if isinstance(m, EncoderSample)]


def _reply_tick(events: list[tuple[int, object]], token: int) -> int:
    return next(t for t, m in events if isinstance(m, ClockSyncReply) and m.token == token)


def test_a_pair_holds_telemetry_between_its_probes_and_loses_none() -> None:
    rig = _session(QUIET)
    events = _timeline(rig, 80, {10: 1, 25: 2})
    first, second = _reply_tick(events, 1), _reply_tick(events, 2)
    samples = _sample_ticks(events)
    # Nothing but replies between the first probe's reply and the second's.
    assert not [t for t in samples if first <= t <= second]
    # Right after the second reply the held samples follow, then the stream at its rate.
    assert [t for t in samples if t > second][:1] == [second + 1]
    order = [m for _, m in events if isinstance(m, EncoderSample | ClockSyncReply)]
    times = [m.mcu_time_us for m in order if isinstance(m, EncoderSample)]
    assert times == sorted(times)
    steps = {b - a for a, b in itertools.pairwise(times)}
    assert steps == {2000}, "a sample was lost or doubled by the hold"
    assert rig.sim.firmware.counters.tx_dropped == 0


def test_a_lone_probe_holds_telemetry_no_longer_than_the_bound() -> None:
    # The second probe, or the first's reply, was lost: the controller sees the first alone.
    rig = _session(QUIET)
    events = _timeline(rig, 30 + 2 * HOLD_TICKS, {10: 1})
    reply = _reply_tick(events, 1)
    samples = _sample_ticks(events)
    resumed = min(t for t in samples if t > reply)
    assert HOLD_TICKS - 2 <= resumed - 10 <= HOLD_TICKS + 2
    # After it the stream flows again, a little faster than it is made until it has caught up
    # (firmware.link.TxQueue); then as made: the hold does not come back by itself.
    events = _timeline(rig, CATCH_UP * HOLD_TICKS, {})
    assert rig.sim.firmware.tx.delay_us() == 0
    assert {b - a for a, b in itertools.pairwise(_sample_ticks(events)[-10:])} == {2}
    # The next probe, later, starts a new hold of its own, again bounded.
    events = _timeline(rig, 2 * HOLD_TICKS, {0: 2})
    samples = _sample_ticks(events)
    assert min(t for t in samples if t > _reply_tick(events, 2)) <= HOLD_TICKS + 2


def test_what_a_hold_kept_leaves_with_its_spacing_not_in_a_burst() -> None:
    # A burst of a hold's frames overflowed the XBee module's 202-byte buffer.
    rig = _session(QUIET)
    events = _timeline(rig, 20 + CATCH_UP * HOLD_TICKS, {10: 1, 25: 2})
    second = _reply_tick(events, 2)
    after = [t for t in _sample_ticks(events) if t > second]
    assert len(after) == len(set(after)), "several held samples left in one tick"
    gaps = [b - a for a, b in itertools.pairwise(after)]
    # Made at one every 2 ticks, they leave no faster than CATCH_UP / (CATCH_UP - 1) times that.
    assert sum(gaps[:8]) >= 8 * 2 * (CATCH_UP - 1) // CATCH_UP
    assert rig.sim.firmware.counters.tx_dropped == 0


def test_a_second_probe_later_than_the_bound_holds_nothing() -> None:
    # Over a radio the first reply may wait behind the module's buffer: the second probe comes
    # after the hold ran out. It is its pair's late second, not a new first.
    late = HOLD_TICKS + 15
    rig = _session(QUIET)
    events = _timeline(rig, late + HOLD_TICKS + 10, {10: 1, 10 + late: 2})
    reply = _reply_tick(events, 2)
    samples = _sample_ticks(events)
    assert [t for t in samples if reply < t <= reply + 4], "a late second held telemetry"
    # The probe after it is a first again: it holds.
    events = _timeline(rig, 2 * HOLD_TICKS, {0: 3})
    reply = _reply_tick(events, 3)
    assert not [t for t in _sample_ticks(events) if reply < t < reply + HOLD_TICKS - 5]


@pytest.mark.parametrize(
    ("host_caps", "fw_caps"),
    [(0, None), (QUIET, int(Capability.BATCHED_TELEMETRY))],
    ids=["old-host", "old-controller"],
)
def test_without_both_offering_it_a_probe_holds_nothing(
    host_caps: int, fw_caps: int | None
) -> None:
    rig = _session(host_caps, fw_caps)
    events = _timeline(rig, 40, {10: 1})
    reply = _reply_tick(events, 1)
    samples = _sample_ticks(events)
    assert [t for t in samples if reply < t <= reply + 6], "telemetry waited for a probe"
    assert not rig.sim.firmware.quiet_probes
