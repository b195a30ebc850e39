"""Transport section of the link benchmark: per backend, round trip, telemetry rate, host CPU.

    python benchmarks/bench_link_transport.py                 # every transport
    python benchmarks/bench_link_transport.py --only serial_pty xbee_ap2
    python benchmarks/bench_link_transport.py --only xbee_ap2 --telemetry  # + XBee batching

`section_transport()` is the section `bench_link.py` runs beside the session figures; this file
also runs on its own. Prints `transport.<backend>.<metric>: value` lines, backends side by side,
with the codec's own decoding cost as the peer of every host CPU figure.

Each link emulator runs with a fake controller in a child process, so the host process's CPU
time is the host's alone; python-can's `virtual` bus exists only inside one process, so
`can_virtual` runs its emulator in-process and says so (`cpu_includes_emulator: 1`). Rates are
the realistic ones: serial 115200 baud through the pty (or TCP) emulator, XBee at 35 kbit/s air
rate behind a 115200-baud UART, CAN at 500 kbit/s.

The sustainable telemetry rate is the highest rate of the ladder at which at least 99 % of the
encoder frames streamed for 2 s reach the host no later than 0.1 s after the window: the wired
emulators queue rather than drop, so lateness is what overload looks like there; the XBee
modules' 202-byte buffers overflow and lose frames, as real ones do.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import statistics
import sys
import tempfile
import time
import uuid
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_xbee_telemetry import section_xbee_telemetry

from hil_sim.links.can_node import SlcanAdapter, VirtualCanNode
from hil_sim.links.endpoint import FakeController, build
from hil_sim.links.pty_uart import PtyUart
from hil_sim.links.tcp import TcpLink
from hil_sim.links.xbee import CONTROLLER_ADDR64, XBeeModule
from host.transport import Transport, create_transport
from protocol import FrameDecoder, encode_frame
from protocol.messages import EncoderSample, Heartbeat

UART_BAUD = 115200
RTT_SAMPLES = 200
RATE_WINDOW_S = 2.0
LATE_AFTER_S = 0.1
MAX_LOSS = 0.01
RATE_LADDER_HZ = (50, 75, 100, 150, 200, 300, 400, 500, 600, 800, 1000, 1250, 1600, 2000, 2500)
CPU_RATE_FRACTION = 0.8
TICK_S = 0.001
DRAIN_S = 0.3
TRANSPORTS = ("serial_pty", "serial_socket", "xbee_ap1", "xbee_ap2", "can_virtual", "can_slcan")


# ---- the device side (child process, or in-process for the virtual CAN bus) ----------------


def make_emulator(kind: str, controller: FakeController, tmp: str) -> Any:
    """The emulator of one transport, serving `controller`."""
    if kind == "serial_pty":
        return PtyUart(controller, UART_BAUD, link_path=f"{tmp}/tty")
    if kind == "serial_socket":
        return TcpLink(controller, baud=UART_BAUD)
    if kind.startswith("xbee_ap"):
        return XBeeModule(controller, int(kind[-1]), UART_BAUD, link_path=f"{tmp}/xbee")
    if kind == "can_slcan":
        return SlcanAdapter(controller, link_path=f"{tmp}/slcan")
    return VirtualCanNode(controller, f"bench-{uuid.uuid4().hex}")


def emulator_address(kind: str, emulator: Any) -> str:
    """Path, URL or channel the host transport opens."""
    if kind == "serial_socket":
        return str(emulator.url)
    if kind == "can_virtual":
        return str(emulator.channel)
    return str(emulator.path)


async def stream_telemetry(controller: FakeController, rate_hz: float, duration_s: float) -> int:
    """Send encoder samples at rate_hz for duration_s, catching up every tick; returns count."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    sent = 0
    while (elapsed := loop.time() - start) < duration_s:
        due = int(elapsed * rate_hz)
        while sent < due:
            controller.send(build(EncoderSample, sent, sent, sent, 1000, 0))
            sent += 1
        await asyncio.sleep(TICK_S)
    return sent


async def serve(kind: str, conn: Connection) -> None:
    """Child main: run the emulator and obey ('stream', rate, duration) / ('stop',)."""
    controller = FakeController()
    with tempfile.TemporaryDirectory() as tmp:
        emulator = make_emulator(kind, controller, tmp)
        await emulator.start()
        conn.send(emulator_address(kind, emulator))
        loop = asyncio.get_running_loop()
        while True:
            command = await loop.run_in_executor(None, conn.recv)
            if command[0] == "stop":
                break
            conn.send(await stream_telemetry(controller, command[1], command[2]))
        await emulator.stop()


def child_main(kind: str, conn: Connection) -> None:
    """Process entry point of the device side."""
    asyncio.run(serve(kind, conn))


class Device:
    """The emulator, in a child process or (virtual CAN) in this one, behind one interface."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.in_process = kind == "can_virtual"
        self._proc: Any = None
        self._conn: Connection | None = None
        self._emulator: Any = None
        self._controller = FakeController()
        self._tmp = tempfile.TemporaryDirectory()

    async def start(self) -> str:
        """Start and return the address for the host."""
        if self.in_process:
            self._emulator = make_emulator(self.kind, self._controller, self._tmp.name)
            await self._emulator.start()
            return emulator_address(self.kind, self._emulator)
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=child_main, args=(self.kind, child), daemon=True)
        self._proc.start()
        return str(await self._recv())

    async def stream(self, rate_hz: float, duration_s: float) -> int:
        """Have the controller stream telemetry; returns frames sent."""
        if self.in_process:
            return await stream_telemetry(self._controller, rate_hz, duration_s)
        assert self._conn is not None
        self._conn.send(("stream", rate_hz, duration_s))
        return int(await self._recv())

    async def stop(self) -> None:
        """Stop the emulator and reap the child."""
        if self.in_process:
            await self._emulator.stop()
        elif self._conn is not None:
            self._conn.send(("stop",))
            await asyncio.get_running_loop().run_in_executor(None, self._proc.join, 5.0)
        self._tmp.cleanup()

    async def _recv(self) -> Any:
        """A reply from the child without blocking the loop."""
        assert self._conn is not None
        return await asyncio.get_running_loop().run_in_executor(None, self._conn.recv)


# ---- the host side -------------------------------------------------------------------------


def host_transport(kind: str, address: str) -> Transport:
    """The host transport for one benchmark kind."""
    if kind in ("serial_pty", "serial_socket"):
        return create_transport("serial", url=address, baudrate=UART_BAUD)
    if kind.startswith("xbee_ap"):
        return create_transport(
            "xbee", url=address, dest_addr64=CONTROLLER_ADDR64, baudrate=UART_BAUD,
            api_mode=int(kind[-1]),
        )  # fmt: skip
    if kind == "can_slcan":
        return create_transport("can", interface="slcan", channel=address, sleep_after_open=0)
    return create_transport("can", interface="virtual", channel=address)


class HostSide:
    """Decode what arrives and timestamp it."""

    def __init__(self) -> None:
        self.decoder = FrameDecoder()
        self.arrivals: list[tuple[float, object]] = []
        self.event = asyncio.Event()

    def on_bytes(self, data: bytes) -> None:
        """Receiver callback."""
        now = time.perf_counter()
        for packet in self.decoder.feed(data):
            self.arrivals.append((now, packet.message))
        self.event.set()


async def measure_rtt(transport: Transport, host: HostSide) -> list[float]:
    """Sequential HEARTBEAT → HEARTBEAT round trips, in ms."""
    out = []
    for seq in range(RTT_SAMPLES):
        host.arrivals.clear()
        host.event.clear()
        start = time.perf_counter()
        transport.send(encode_frame(build(Heartbeat, seq), seq))
        while not host.arrivals:
            try:
                await asyncio.wait_for(host.event.wait(), 1.0)
            except TimeoutError:
                break
            host.event.clear()
        if host.arrivals:
            out.append((host.arrivals[0][0] - start) * 1000.0)
    return out


async def run_rate(device: Device, host: HostSide, rate_hz: float) -> tuple[int, int, float]:
    """(sent, received in time, host CPU s) for one window at rate_hz."""
    await asyncio.sleep(DRAIN_S)
    host.arrivals.clear()
    cpu0 = time.process_time()
    start = time.perf_counter()
    sent = await device.stream(rate_hz, RATE_WINDOW_S)
    deadline = start + RATE_WINDOW_S + LATE_AFTER_S
    await asyncio.sleep(max(0.0, deadline - time.perf_counter()))
    cpu = time.process_time() - cpu0
    on_time = sum(1 for t, m in host.arrivals if t <= deadline and isinstance(m, EncoderSample))
    return sent, on_time, cpu


async def highest_rate(device: Device, host: HostSide) -> float:
    """Climb the ladder until more than 1 % arrives late or never."""
    best = 0.0
    for rate in RATE_LADDER_HZ:
        sent, got, _ = await run_rate(device, host, rate)
        if sent == 0 or got < sent * (1 - MAX_LOSS):
            break
        best = rate
    return best


async def bench_backend(kind: str) -> dict[str, float | int]:
    """All figures of one transport."""
    device = Device(kind)
    address = await device.start()
    transport = host_transport(kind, address)
    host = HostSide()
    transport.set_receiver(host.on_bytes)
    await transport.open()
    try:
        rtts = await measure_rtt(transport, host)
        best = await highest_rate(device, host)
        _, got, cpu = await run_rate(device, host, max(best, 50) * CPU_RATE_FRACTION)
    finally:
        await transport.close()
        await device.stop()
    return {
        "rtt_median_ms": statistics.median(rtts) if rtts else float("nan"),
        "rtt_p99_ms": _p99(rtts),
        "rtt_lost": RTT_SAMPLES - len(rtts),
        "max_telemetry_rate_hz": best,
        "host_cpu_us_per_1000_frames": cpu / got * 1e9 if got else float("nan"),
        "cpu_includes_emulator": int(device.in_process),
    }


def codec_cost_us(n: int = 20_000) -> float:
    """CPU µs per 1000 telemetry frames for `FrameDecoder.feed`, one frame per call."""
    frames = [encode_frame(build(EncoderSample, i, i, i, 1000, 0), i & 0xFFFF) for i in range(n)]
    decoder = FrameDecoder()
    cpu0 = time.process_time()
    for frame in frames:
        decoder.feed(frame)
    return (time.process_time() - cpu0) / n * 1e9


def _p99(values: list[float]) -> float:
    """99th percentile (nearest rank)."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))]


async def section_transport(only: list[str] | None = None) -> None:
    """Transport figures, one block per backend."""
    wire = len(encode_frame(build(EncoderSample, 0, 0, 0, 0, 0), 0))
    print(f"transport.telemetry_frame_bytes: {wire}")
    # The peer of every host CPU figure: what decoding alone costs, with no link at all.
    print(f"transport.codec_only.decode_cpu_us_per_1000_frames: {codec_cost_us():.1f}")
    for kind in only or TRANSPORTS:
        for name, value in (await bench_backend(kind)).items():
            shown = f"{value:.3f}" if isinstance(value, float) else str(value)
            print(f"transport.{kind}.{name}: {shown}", flush=True)


def main(argv: list[str] | None = None) -> int:
    """Run the transport section."""
    parser = argparse.ArgumentParser(description="transport figures of the link benchmark")
    parser.add_argument("--only", nargs="*", choices=TRANSPORTS, help="transports to run")
    parser.add_argument(
        "--telemetry",
        action="store_true",
        help="also XBee telemetry, single samples beside batches (bench_xbee_telemetry.py)",
    )
    args = parser.parse_args(argv)
    asyncio.run(section_transport(args.only))
    if args.telemetry:
        asyncio.run(section_xbee_telemetry())
    return 0


if __name__ == "__main__":
    sys.exit(main())
