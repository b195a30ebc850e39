"""Re-run the host's receive path on recorded link bytes: framing, clock sync, samples.

The live session stamps a CLOCK_SYNC probe and its reply with the transport's stamps (taken
just before the write, and as the chunk arrived), which are the times the transport tap records.
Fed in recorded order, this class decodes both directions, pairs every reply with its probe,
fits the controller clock with the same `ClockSync` estimator on the same numbers and converts
every sample to host time and units with the live controller's `host.link.samples.reading`: the
live sample times come back to the nanosecond, and a change to the clock sync (or to the drift
filter downstream) can be judged on a real recording. It never sends anything.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from host.link.batches import BATCH_TYPES, unpack
from host.link.clocksync import ClockSync
from host.link.samples import EncoderReading, SampleMessage, SampleSink, frame_arrived, reading
from host.link.snapshot import Identity
from protocol import FrameDecoder, Packet
from protocol.messages import ClockSync as ClockSyncMsg
from protocol.messages import (
    ClockSyncReply,
    EncoderSample,
    HeadSample,
    Identify,
    RangeSample,
    RefMark,
)

MAX_PROBES_IN_FLIGHT = 16  # as the session: older unanswered probes are forgotten
DEFAULT_MCU_CLOCK_HZ = 1_000_000


@dataclass
class LinkReplayStats:
    """What the replayed link saw."""

    rx_frames: int = 0
    tx_frames: int = 0
    handshakes: int = 0
    controller_resets: int = 0
    probes: int = 0
    probes_used: int = 0  # accepted by the clock fit
    unmatched_replies: int = 0
    samples: int = 0
    unsynced: int = 0  # samples before an IDENTIFY and a first probe: not convertible


class LinkReplay:
    """Recorded `link` bytes in, samples in host time out to a `SampleSink`."""

    def __init__(self, sink: SampleSink) -> None:
        self.sink = sink
        self.stats = LinkReplayStats()
        self.identity: Identity | None = None
        self.clock = ClockSync(DEFAULT_MCU_CLOCK_HZ)
        self.encoder_times_ns: deque[int] = deque(maxlen=4096)  # for comparing with the live
        self._rx = FrameDecoder()
        self._tx = FrameDecoder()
        self._probes: dict[int, tuple[int, int]] = {}

    @property
    def synced(self) -> bool:
        """True once samples can be converted (an IDENTIFY and an accepted probe)."""
        return self.identity is not None and self.clock.ready

    @property
    def chain_pitch_mm(self) -> float | None:
        """The controller's nominal chain pitch, once IDENTIFY was seen."""
        return self.identity.chain_pitch_mm if self.identity is not None else None

    def adopt_identity(self, fields: Mapping[str, Any]) -> bool:
        """A header's IDENTIFY constants, for a file that starts mid-session (before any seen)."""
        if self.identity is not None:
            return False
        names = {f.name for f in dataclasses.fields(Identity)}
        self.identity = Identity(**{k: v for k, v in fields.items() if k in names})
        self.clock = ClockSync(self.identity.mcu_clock_hz or DEFAULT_MCU_CLOCK_HZ)
        return True

    def feed(self, direction: str, t_ns: int, data: bytes) -> None:
        """One recorded chunk: "tx" frames the host sent, "rx" bytes it received."""
        if direction == "tx":
            for packet in self._tx.feed(data):
                self.stats.tx_frames += 1
                self._on_tx(packet, t_ns)
        elif direction == "rx":
            for packet in self._rx.feed(data):
                self.stats.rx_frames += 1
                self._on_rx(packet, t_ns)

    def _on_tx(self, packet: Packet, t_ns: int) -> None:
        """Note each clock probe's seq, token and send time."""
        msg = packet.message
        if isinstance(msg, ClockSyncMsg):
            self.stats.probes += 1
            self._probes[packet.seq] = (t_ns, msg.token)
            while len(self._probes) > MAX_PROBES_IN_FLIGHT:
                del self._probes[next(iter(self._probes))]

    def _on_rx(self, packet: Packet, t_ns: int) -> None:
        """Identity, clock replies and samples, as the session and the controller take them."""
        msg = packet.message
        if isinstance(msg, Identify):
            self._on_identify(msg)
        elif isinstance(msg, ClockSyncReply):
            probe = self._probes.pop(msg.req_seq, None)
            if probe is None or probe[1] != msg.token:
                self.stats.unmatched_replies += 1
            elif self.clock.add_probe(probe[0], msg.mcu_time_us, t_ns, msg.rx_time_us):
                self.stats.probes_used += 1
        elif isinstance(msg, EncoderSample | HeadSample | RangeSample | RefMark):
            self._on_frame(msg, [msg], t_ns)
        elif isinstance(msg, BATCH_TYPES):
            self._on_frame(msg, unpack(msg), t_ns)  # batched: each sample with its own MCU time

    def _on_frame(self, frame: object, samples: Sequence[SampleMessage], t_ns: int) -> None:
        """A telemetry frame, as the live controller takes it: arrival to the clock, samples."""
        frame_arrived(self.clock, frame, samples, t_ns)
        for sample in samples:
            self._on_sample(sample)

    def _on_identify(self, msg: Identify) -> None:
        """A handshake: a new boot id (or the first one) restarts the clock fit."""
        self.stats.handshakes += 1
        rebooted = self.identity is not None and self.identity.boot_id != msg.boot_id
        if rebooted or self.identity is None:
            self.clock = ClockSync(msg.mcu_clock_hz or DEFAULT_MCU_CLOCK_HZ)
        if rebooted:
            self.stats.controller_resets += 1
        self.identity = Identity.from_message(msg)

    def _on_sample(self, msg: SampleMessage) -> None:
        """Host time and units, then the sink (the same conversion as the live controller)."""
        sample = reading(msg, self.clock, self.identity)
        if sample is None:
            self.stats.unsynced += 1
            return
        self.stats.samples += 1
        if isinstance(sample, EncoderReading):
            self.encoder_times_ns.append(sample.t_ns)
        sample.to(self.sink)
