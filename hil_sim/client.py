"""A minimal lockstep host: real frames to and from the simulated controller, for tests.

It is deliberately not the host's session layer: no retransmission or clock sync, just seq
numbering, encoding with `protocol.encode_frame`, decoding with `protocol.FrameDecoder`, and
stepping the simulation until a reply arrives.
"""

from __future__ import annotations

from typing import TypeVar

from hil_sim.runner import Simulation
from protocol import (
    PROTOCOL_VERSION,
    SCHEMA_HASH,
    Flag,
    FrameDecoder,
    Packet,
    encode_frame,
    spec_of,
)
from protocol.messages import Heartbeat, Hello

REPLY_FIELD = "req_seq"
MessageT = TypeVar("MessageT")


class FrameClient:
    """Talks to a lockstep Simulation through its link bytes."""

    def __init__(self, sim: Simulation, handshake: bool = True) -> None:
        self.sim = sim
        self.seq = 0
        self.decoder = FrameDecoder()
        self.received: list[Packet] = []  # every packet, replies and telemetry, in order
        if handshake:  # the controller refuses commands until a HELLO, as on the real link
            self.request(Hello(PROTOCOL_VERSION, SCHEMA_HASH))

    def send(self, msg: object, flags: int | None = None, seq: int | None = None) -> int:
        """Encode and send a message; ACK_REQUESTED when the schema says acked. Returns its seq."""
        if flags is None:
            flags = Flag.ACK_REQUESTED if spec_of(msg).acked else Flag.NONE
        if seq is None:
            # Acked commands are numbered consecutively; other frames carry the next one's seq
            # without spending it (PROTOCOL.md §6).
            seq = self.seq
            if flags & Flag.ACK_REQUESTED:
                self.seq = (self.seq + 1) & 0xFFFF
        self.sim.send(encode_frame(msg, seq, flags))
        return seq

    def poll(self) -> list[Packet]:
        """Decode what the firmware has sent; also kept in `received`."""
        packets = self.decoder.feed(self.sim.receive())
        self.received.extend(packets)
        return packets

    def wait_reply(self, seq: int, max_ticks: int = 50) -> object:
        """Step until the reply to `seq` arrives; TimeoutError after max_ticks."""
        for _ in range(max_ticks):
            self.sim.step(1)
            for p in self.poll():
                if getattr(p.message, REPLY_FIELD, None) == seq:
                    return p.message
        raise TimeoutError(f"no reply to seq {seq} within {max_ticks} ticks")

    def request(self, msg: object, max_ticks: int = 50) -> object:
        """Send a command and return its reply."""
        return self.wait_reply(self.send(msg), max_ticks)

    def run(self, ticks: int, heartbeat_ms: int = 100) -> list[Packet]:
        """Step with heartbeats keeping the watchdog fed; return the packets received."""
        out: list[Packet] = []
        for i in range(ticks):
            if i % heartbeat_ms == 0:
                self.send(Heartbeat(self.sim.ticks & 0xFFFF_FFFF))
            self.sim.step(1)
            out.extend(self.poll())
        return out

    def of_type(self, cls: type[MessageT]) -> list[MessageT]:
        """Messages of one type among everything received so far."""
        return [p.message for p in self.received if isinstance(p.message, cls)]
