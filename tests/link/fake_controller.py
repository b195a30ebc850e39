"""A scripted controller built from `protocol`, behind a MemoryTransport, for session tests."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import struct
from collections import Counter, OrderedDict
from dataclasses import dataclass, field

from host.transport.memory import Impairment, MemoryTransport
from protocol import PROTOCOL_VERSION, SCHEMA_HASH, Flag, FrameDecoder, cobs, spec_of
from protocol.crc import crc16
from protocol.enums import State, Stream
from protocol.messages import (
    Ack,
    ClockSync,
    ClockSyncReply,
    EncoderSample,
    Heartbeat,
    Hello,
    Identify,
    MoveTo,
    Nak,
    ParamGet,
    ParamSet,
    ParamValue,
    Status,
    StreamSet,
)
from protocol.schema import HEADER_FORMAT


@dataclass
class FakeController:
    """Answers HELLO, ACKs commands once per seq, streams samples; can drop, delay and reboot."""

    boot_id: int = 0x1234
    protocol_version: int = PROTOCOL_VERSION
    schema_hash: int = SCHEMA_HASH
    rx_window: int = 4
    mcu_offset_us: int = 1_000_000
    counts_per_rev: int = 4000
    reply_delay_s: float = 0.0
    silent: bool = False  # swallow everything: a hung controller
    nak_next: tuple[int, int] | None = None  # (code, state): may be values we do not know
    executions: Counter[int] = field(default_factory=Counter)  # seq → times executed
    executed: list[object] = field(default_factory=list)
    streams: dict[int, int] = field(default_factory=dict)
    params: dict[int, int] = field(default_factory=dict)
    state: State = State.READY
    position_um: int = 0
    max_inflight_seen: int = 0

    def __post_init__(self) -> None:
        self.transport: MemoryTransport | None = None
        self._decoder = FrameDecoder()
        self._seq = 0
        self._replies: OrderedDict[int, object] = OrderedDict()
        self._uptime_ms = 0
        self._pending_replies = 0
        self._tasks: set[asyncio.Task[None]] = set()

    def wire(self, tx: Impairment | None = None, rx: Impairment | None = None) -> MemoryTransport:
        """A host-side transport whose peer is this controller."""
        self.transport = MemoryTransport(self.receive, tx=tx, rx=rx, seed=7)
        return self.transport

    def receive(self, data: bytes) -> None:
        """Bytes from the host."""
        for packet in self._decoder.feed(data):
            if not self.silent:
                self._handle(packet.seq, packet.flags, packet.message)

    def reboot(self, new_boot_id: int) -> None:
        """Lose all RAM state, as a reset does."""
        self.boot_id = new_boot_id
        self.streams.clear()
        self.params.clear()
        self._replies.clear()
        self._seq = 0
        self._uptime_ms = 0
        self.state = State.IDLE

    def send(self, message: object) -> None:
        """Emit one frame towards the host with the next controller seq."""
        assert self.transport is not None
        frame = unchecked_frame(message, self._seq)
        self._seq = (self._seq + 1) % 65536
        self.transport.inject(frame)

    def send_heartbeat(self, advance_ms: int = 100) -> None:
        """One HEARTBEAT with a growing uptime."""
        self._uptime_ms += advance_ms
        self.send(Heartbeat(uptime_ms=self._uptime_ms))

    def send_encoder(self, mcu_time_us: int, count: int, velocity: int = 0) -> None:
        """One ENCODER_SAMPLE."""
        self.send(EncoderSample(mcu_time_us, count, count, velocity, 0x10))

    def send_status(self, state: State, position_um: int, target_um: int) -> None:
        """One STATUS."""
        self.state = state
        self.send(Status(0, int(state), 0, 0x10, position_um, target_um))

    async def close(self) -> None:
        """Wait out delayed replies."""
        for task in list(self._tasks):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    def _handle(self, seq: int, flags: int, msg: object) -> None:
        """One host frame."""
        if isinstance(msg, ClockSync):
            now_us = int(asyncio.get_running_loop().time() * 1e6) + self.mcu_offset_us
            self.send(ClockSyncReply(seq, msg.token, now_us % (1 << 32), now_us % (1 << 32)))
            return
        if not flags & Flag.ACK_REQUESTED:
            return
        cached = self._replies.get(seq)
        if cached is None:
            cached = self._execute(seq, msg)
            self._replies[seq] = cached
            while len(self._replies) > 2 * self.rx_window:  # the least the protocol allows
                self._replies.popitem(last=False)
        self._reply(cached)

    def _reply(self, reply: object) -> None:
        """Send now, or after the scripted delay."""
        if self.reply_delay_s <= 0:
            self.send(reply)
            return
        self._pending_replies += 1
        self.max_inflight_seen = max(self.max_inflight_seen, self._pending_replies)
        task = asyncio.get_running_loop().create_task(self._later(reply))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _later(self, reply: object) -> None:
        await asyncio.sleep(self.reply_delay_s)
        self._pending_replies -= 1
        self.send(reply)

    def _execute(self, seq: int, msg: object) -> object:
        """Run a command once and build its reply."""
        if isinstance(msg, Hello):
            return self._identify(seq)
        if self.nak_next is not None:
            code, state = self.nak_next
            self.nak_next = None
            return Nak(seq, int(code), int(state))
        self.executions[seq] += 1
        self.executed.append(msg)
        if isinstance(msg, StreamSet):
            self.streams[msg.stream] = msg.rate_hz
        elif isinstance(msg, ParamSet):
            self.params[msg.param_id] = msg.value
            return ParamValue(seq, msg.param_id, msg.value)
        elif isinstance(msg, ParamGet):
            return ParamValue(seq, msg.param_id, self.params.get(msg.param_id, 0))
        elif isinstance(msg, MoveTo):
            self.state = State.MOVING
        return Ack(seq, int(self.state))

    def _identify(self, seq: int) -> Identify:
        return Identify(
            seq,
            self.protocol_version,
            self.schema_hash,
            0x000100,
            self.boot_id,
            self.counts_per_rev,
            3200,
            20,
            12_700,
            1_000_000,
            84,
            self.rx_window,
            int(self.state),
        )


def unchecked_frame(message: object, seq: int) -> bytes:
    """Wire bytes for a message without the encoder's range checks: what a newer firmware (or a
    bit error the CRC misses) may send, such as a state or NAK code this host does not know."""
    spec = spec_of(message)
    values = [getattr(message, f.name) for f in dataclasses.fields(message)]  # type: ignore[arg-type]
    raw = struct.pack(HEADER_FORMAT, PROTOCOL_VERSION, 0, seq, spec.id)
    raw += struct.pack(spec.struct_format, *values)
    raw += crc16(raw).to_bytes(2, "big")
    return bytes(cobs.encode(raw)) + b"\x00"


ENCODER = int(Stream.ENCODER)
