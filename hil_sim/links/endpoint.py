"""The device end of an emulated link, and two stand-ins for the firmware that plug into it.

A link emulator moves bytes between the host's device (a pty, a socket, a CAN bus) and a
`ByteEndpoint`: it calls `write` with what the host sent and registers a sink for what the
device sends. The firmware runner implements this for the real firmware mirror; tests use
`LoopbackEndpoint` (echoes bytes) or `FakeController` (a few protocol replies built from
`protocol`, no firmware).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any, Protocol

from protocol import PROTOCOL_VERSION, SCHEMA_HASH, FrameDecoder, Packet, encode_frame
from protocol.messages import EncoderSample, Heartbeat, Hello, Identify

ByteSink = Callable[[bytes], None]
DELIMITER = 0x00
FAKE_BOOT_ID = 0x0B0071D0
FAKE_FW_VERSION = 0x000100  # 0.1.0
RX_WINDOW = 8


def build(cls: type[Any], *fields: int) -> Any:
    """A message from positional fields (mypy cannot see the schema decorator's __init__)."""
    return cls(*fields)


class ByteEndpoint(Protocol):
    """What a link emulator needs from the device it serves."""

    def write(self, data: bytes) -> None:
        """Bytes that arrived from the host, in order."""

    def set_sink(self, sink: ByteSink | None) -> None:
        """Where the device's outgoing bytes go (None: nowhere)."""


class FirmwarePort(Protocol):
    """The simulator's thread-safe port (`hil_sim.runner.SimLinkPort`), as far as links care."""

    def write_to_firmware(self, data: bytes) -> None:
        """Queue bytes for the firmware's UART (any thread)."""

    def set_receiver(self, receiver: ByteSink | None) -> None:
        """Firmware bytes go to `receiver`, called on the simulator's thread."""


class SimPortEndpoint:
    """`ByteEndpoint` over the real-time runner's port, hopping firmware bytes onto our loop."""

    def __init__(self, port: FirmwarePort, loop: asyncio.AbstractEventLoop) -> None:
        self.port = port
        self._loop = loop
        self._sink: ByteSink | None = None

    def write(self, data: bytes) -> None:
        """Host bytes into the firmware's UART."""
        self.port.write_to_firmware(data)

    def set_sink(self, sink: ByteSink | None) -> None:
        """Route the firmware's bytes to `sink` on the emulator's loop."""
        self._sink = sink
        self.port.set_receiver(None if sink is None else self._from_sim_thread)

    def _from_sim_thread(self, data: bytes) -> None:
        """Called on the simulator thread: never touch the loop's objects from here."""
        if not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._on_loop, data)

    def _on_loop(self, data: bytes) -> None:
        """Back on the loop: hand over, unless disconnected meanwhile."""
        if self._sink is not None:
            self._sink(data)


class FrameSplitter:
    """Cut a byte stream at 0x00 delimiters into wire frames (delimiter kept)."""

    def __init__(self, max_len: int) -> None:
        self.max_len = max_len
        self.oversize = 0
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[bytes]:
        """Consume bytes; return each completed frame including its trailing 0x00."""
        out = []
        for byte in data:
            self._buf.append(byte)
            if byte == DELIMITER:
                frame, self._buf = bytes(self._buf), bytearray()
                if len(frame) > self.max_len:
                    self.oversize += 1
                elif len(frame) > 1:
                    out.append(frame)
        return out


class LoopbackEndpoint:
    """A device that sends back every byte it receives."""

    def __init__(self) -> None:
        self._sink: ByteSink | None = None
        self.bytes_in = 0

    def write(self, data: bytes) -> None:
        """Echo."""
        self.bytes_in += len(data)
        if self._sink is not None:
            self._sink(data)

    def set_sink(self, sink: ByteSink | None) -> None:
        """Where echoes go."""
        self._sink = sink


class FakeController:
    """Just enough controller for link tests: HELLO → IDENTIFY, HEARTBEAT echoed, telemetry."""

    def __init__(self, max_frame: int = 84) -> None:
        self.decoder = FrameDecoder()
        self.received: list[Packet] = []
        self.seq = 0
        self.max_frame = max_frame
        self.echo_all = False  # echo every good frame re-encoded (round-trip tests)
        self.echo_raw = False  # echo every delimited frame byte for byte, valid or not
        self._splitter = FrameSplitter(max_len=256)
        self._sink: ByteSink | None = None

    def write(self, data: bytes) -> None:
        """Bytes from the host: decode and answer."""
        if self.echo_raw:
            for frame in self._splitter.feed(data):
                if self._sink is not None:
                    self._sink(frame)
            return
        for packet in self.decoder.feed(data):
            self.received.append(packet)
            self._answer(packet)

    def set_sink(self, sink: ByteSink | None) -> None:
        """Where our frames go."""
        self._sink = sink

    def send(self, message: object) -> bytes:
        """Send one message with the next controller seq; returns the wire bytes."""
        wire = encode_frame(message, self.seq)
        self.seq = (self.seq + 1) & 0xFFFF
        if self._sink is not None:
            self._sink(wire)
        return wire

    def send_sample(self, mcu_time_us: int) -> bytes:
        """One encoder-telemetry frame, the link's most frequent message."""
        sample = build(EncoderSample, mcu_time_us & 0xFFFF_FFFF, mcu_time_us // 7, 0, 1000, 0)
        return self.send(sample)

    def _answer(self, packet: Packet) -> None:
        """The replies a real controller would give, minus everything else."""
        msg = packet.message
        if self.echo_all:
            self.send(msg)
        elif isinstance(msg, Hello):
            self.send(self._identify(packet.seq))
        elif isinstance(msg, Heartbeat):
            self.send(build(Heartbeat, msg.uptime_ms))

    def _identify(self, req_seq: int) -> Any:
        """IDENTIFY with the paper rig's constants."""
        return build(
            Identify,
            req_seq, PROTOCOL_VERSION, SCHEMA_HASH, FAKE_FW_VERSION, FAKE_BOOT_ID,
            4000, 3200, 20, 38100, 1_000_000, self.max_frame, RX_WINDOW, 0,
        )  # fmt: skip
