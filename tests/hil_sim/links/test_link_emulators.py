"""Link emulators on their own: fault statistics, baud pacing, XBee statuses, slcan commands."""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from pathlib import Path
from typing import Any

import pytest

from hil_sim.links.can_node import SlcanAdapter
from hil_sim.links.endpoint import FakeController, FrameSplitter, LoopbackEndpoint, build
from hil_sim.links.faults import FaultConfig, FaultInjector
from hil_sim.links.pacing import Line, PacedPipe
from hil_sim.links.pty_uart import PtyUart
from hil_sim.links.tcp import TcpLink
from hil_sim.links.xbee import (
    AIR_OVERHEAD_BYTES,
    AIR_RATE_BPS,
    CONTROLLER_ADDR64,
    SERIAL_BUFFER_BYTES,
    XBeeModule,
)
from host.transport import create_transport
from protocol import FrameDecoder, encode_frame
from protocol.messages import EncoderSample, Heartbeat
from protocol.xbee_frames import (
    ApiFrameDecoder,
    TransmitRequest,
    TransmitStatus,
    encode_api_frame,
)
from tests.transport.harness import Collector

UNITS = 20_000


def test_drop_rate_and_determinism() -> None:
    a = FaultInjector(FaultConfig(drop_rate=0.1, seed=3))
    b = FaultInjector(FaultConfig(drop_rate=0.1, seed=3))
    outs_a = [a.transmit(b"x") for _ in range(UNITS)]
    outs_b = [b.transmit(b"x") for _ in range(UNITS)]
    assert outs_a == outs_b
    assert a.counters.dropped == outs_a.count(None)
    assert 0.09 < a.counters.dropped / UNITS < 0.11


def test_bursts_have_the_configured_mean_length() -> None:
    inj = FaultInjector(FaultConfig(burst_rate=0.01, burst_length_mean=5.0, seed=5))
    for _ in range(UNITS * 5):
        inj.transmit(b"x")
    c = inj.counters
    assert c.bursts > 50
    assert 4.0 < c.burst_dropped / c.bursts < 6.0
    assert c.lost == c.burst_dropped


def test_bit_errors_are_counted_exactly() -> None:
    inj = FaultInjector(FaultConfig(bit_error_rate=1e-3, seed=9))
    data = bytes(100)
    flipped = 0
    for _ in range(2000):
        out = inj.transmit(data)
        assert out is not None
        flipped += sum(bin(b).count("1") for b in out)
    assert flipped == inj.counters.bits_flipped
    assert 0.8e-3 < flipped / (2000 * 800) < 1.2e-3


def test_latency_and_jitter_bounds() -> None:
    inj = FaultInjector(FaultConfig(latency_s=0.01, jitter_s=0.005, seed=1))
    delays = [inj.delay_s() for _ in range(1000)]
    assert min(delays) >= 0.01
    assert max(delays) <= 0.015
    assert inj.counters.delayed == 1000


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"drop_rate": 1.5}, "drop_rate"),
        ({"jitter_s": -1.0}, "jitter_s"),
        ({"burst_length_mean": 0.5}, "burst"),
    ],
)
def test_bad_fault_config_names_the_field(kwargs: dict[str, Any], key: str) -> None:
    with pytest.raises(ValueError, match=key):
        FaultConfig(**kwargs)


def test_frame_splitter() -> None:
    splitter = FrameSplitter(max_len=5)
    assert splitter.feed(b"\x00ab\x00cdefgh\x00ij") == [b"ab\x00"]
    assert splitter.oversize == 1
    assert splitter.feed(b"\x00") == [b"ij\x00"]


async def test_paced_pipe_keeps_order_under_jitter() -> None:
    got: list[int] = []
    pipe: PacedPipe[int] = PacedPipe(got.append, rate_bytes_s=1e6)
    pipe.start()
    inj = FaultInjector(FaultConfig(jitter_s=0.01, seed=2))
    for i in range(50):
        pipe.push(i, 10, inj.delay_s())
    await asyncio.sleep(0.05)
    await pipe.stop()
    assert got == list(range(50))


async def test_paced_pipes_on_one_line_take_turns() -> None:
    line = Line()
    a: PacedPipe[int] = PacedPipe(lambda _: None, 1000.0, line)
    b: PacedPipe[int] = PacedPipe(lambda _: None, 1000.0, line)
    alone: PacedPipe[int] = PacedPipe(lambda _: None, 1000.0)
    start = time.monotonic()
    a_left = a.push(1, 100)  # 0.1 s on the line
    b_left = b.push(2, 50)  # waits for a's item: the line is theirs together
    alone_left = alone.push(3, 50)  # a line of its own is free
    assert a_left - start == pytest.approx(0.1, abs=0.02)
    assert b_left - a_left == pytest.approx(0.05)
    assert alone_left - start == pytest.approx(0.05, abs=0.02)


async def test_pty_uart_enforces_the_baud_rate(tmp_path: Path) -> None:
    baud = 19200
    uart = PtyUart(LoopbackEndpoint(), baud)
    await uart.start()
    transport = create_transport("serial", url=uart.path, baudrate=baud)
    rx = Collector()
    rx.attach(transport)
    await transport.open()
    try:
        payload = bytes(range(1, 201)) * 2 + b"\x00"  # 401 bytes: ~0.21 s each way at 19200
        start = time.monotonic()
        transport.send(payload)
        while sum(map(len, rx.chunks)) < len(payload) and time.monotonic() - start < 3.0:
            await asyncio.sleep(0.005)
        elapsed = time.monotonic() - start
        assert b"".join(rx.chunks) == payload
        # Both directions paced: the echo cannot beat two line times.
        assert elapsed >= 2 * len(payload) * 10 / baud * 0.9
    finally:
        await transport.close()
        await uart.stop()


async def test_bit_errors_on_a_pty_are_dropped_by_the_codec(tmp_path: Path) -> None:
    controller = FakeController()
    uart = PtyUart(controller, 115200, faults_to_host=FaultConfig(bit_error_rate=2e-3, seed=4))
    await uart.start()
    transport = create_transport("serial", url=uart.path)
    rx = Collector()
    rx.attach(transport)
    await transport.open()
    try:
        n = 200
        for i in range(n):
            controller.send_sample(i)
            await asyncio.sleep(0.001)
        corrupted = uart.to_host.counters.corrupted
        await rx.wait_packets(n - 2 * corrupted, timeout_s=10.0)
        await rx.settle(quiet_s=0.1)
        assert corrupted > 0
        good = len(rx.packets)
        # A flipped delimiter can take its neighbour down too; nothing corrupted gets through.
        assert n - 2 * corrupted <= good <= n - corrupted
        assert rx.decoder.drops.total() >= 1
    finally:
        await transport.close()
        await uart.stop()


async def test_xbee_statuses_report_retries_and_failures(tmp_path: Path) -> None:
    controller = FakeController()
    air = FaultConfig(drop_rate=0.5, seed=21)
    module = XBeeModule(controller, api_mode=2, air_faults=air, link_path=str(tmp_path / "xb"))
    await module.start()
    transport = create_transport(
        "xbee", url=module.path, dest_addr64=CONTROLLER_ADDR64, baudrate=115200, api_mode=2
    )
    await transport.open()
    try:
        n = 60
        for seq in range(n):
            transport.send(encode_frame(build(Heartbeat, seq), seq))
            # ~2 attempts of 31 bytes each take ~14 ms of air: faster, the module's buffer fills
            await asyncio.sleep(0.02)
        counters = module.counters
        extra = transport.stats.extra
        for _ in range(300):  # the air is slow with half the attempts lost
            if extra.get("xbee_delivered", 0) + extra.get("xbee_failed", 0) == n:
                break
            await asyncio.sleep(0.01)
        assert counters.delivered + counters.failed == n
        assert extra["xbee_delivered"] == counters.delivered == len(controller.received)
        assert extra.get("xbee_mac_ack_failure", 0) == counters.failed > 0
        assert extra["xbee_retries"] == counters.retries > 0
    finally:
        await transport.close()
        await module.stop()


async def test_xbee_module_refuses_oversize_and_unknown_address(tmp_path: Path) -> None:
    module = XBeeModule(LoopbackEndpoint(), api_mode=1, link_path=str(tmp_path / "xb"))
    await module.start()
    fd = os.open(module.path, os.O_RDWR | os.O_NOCTTY)
    try:
        big = TransmitRequest(9, CONTROLLER_ADDR64, bytes(85)).frame_data()
        stranger = TransmitRequest(10, 0x1234, b"hi\x00").frame_data()
        os.write(fd, encode_api_frame(big, False) + encode_api_frame(stranger, False))
        statuses = await _read_statuses(fd, 2)
        assert statuses == [
            TransmitStatus(9, 0, 0x74),
            TransmitStatus(10, 3, 0x01),
        ]
        assert module.counters.too_large == 1
        assert module.counters.wrong_address == 1
    finally:
        os.close(fd)
        await module.stop()


async def _read_statuses(fd: int, n: int) -> list[TransmitStatus]:
    """Read API frames from a raw pty fd until n statuses arrived."""
    os.set_blocking(fd, False)
    decoder = ApiFrameDecoder(escaped=False)
    out: list[TransmitStatus] = []
    for _ in range(300):
        with contextlib.suppress(BlockingIOError):
            out += [TransmitStatus.parse(f) for f in decoder.feed(os.read(fd, 256))]
        if len(out) >= n:
            break
        await asyncio.sleep(0.01)
    return out


async def test_slcan_adapter_speaks_lawicel(tmp_path: Path) -> None:
    adapter = SlcanAdapter(LoopbackEndpoint(), link_path=str(tmp_path / "slcan"))
    await adapter.start()
    fd = os.open(adapter.path, os.O_RDWR | os.O_NOCTTY)
    os.set_blocking(fd, False)
    try:
        script = [
            (b"O\r", b"\x07"),  # no bitrate yet
            (b"S6\r", b"\r"),
            (b"V\r", b"V1013\r"),
            (b"N\r", b"NORB1\r"),
            (b"O\r", b"\r"),
            (b"S4\r", b"\x07"),  # bitrate is fixed while open
            (b"t2013C10102\r", b"z\r"),
            (b"F\r", b"F00\r"),
            (b"C\r", b"\r"),
            (b"t201\r", b"\x07"),  # closed, and malformed
        ]
        for command, reply in script:
            os.write(fd, command)
            assert await _read_until(fd, len(reply)) == reply, command
        assert adapter.bitrate_kbps == 500
        assert adapter.errors == 3
    finally:
        os.close(fd)
        await adapter.stop()


async def _read_until(fd: int, n: int) -> bytes:
    """Up to n bytes from a non-blocking fd, waiting briefly."""
    got = b""
    for _ in range(200):
        with contextlib.suppress(BlockingIOError):
            got += os.read(fd, n - len(got))
        if len(got) >= n:
            break
        await asyncio.sleep(0.005)
    return got


async def test_tcp_link_serves_one_host_at_a_time() -> None:
    link = TcpLink(LoopbackEndpoint())
    await link.start()
    try:
        _, w1 = await asyncio.open_connection("127.0.0.1", link.port)
        r2, w2 = await asyncio.open_connection("127.0.0.1", link.port)
        assert await asyncio.wait_for(r2.read(), 2.0) == b""  # closed at once
        assert link.refused == 1
        for writer in (w1, w2):
            writer.close()
            await writer.wait_closed()
    finally:
        await link.stop()


AIR_BYTES_S = AIR_RATE_BPS / 8
SAMPLE_AIR_BYTES = 26 + AIR_OVERHEAD_BYTES  # an ENCODER_SAMPLE frame in its RF packet


def _sample(n: int) -> bytes:
    """Encoder frame number n (its mcu_time carries n)."""
    return encode_frame(build(EncoderSample, n, n, n, 1000, 0), n & 0xFFFF)


async def _stream_up(controller: FakeController, rate_hz: float, duration_s: float) -> list[float]:
    """Send numbered encoder samples at rate_hz; returns each one's send time (loop clock)."""
    loop = asyncio.get_running_loop()
    sent: list[float] = []
    start = loop.time()
    while (now := loop.time()) - start < duration_s:
        while len(sent) < (now - start) * rate_hz:
            sent.append(loop.time())
            controller.send(build(EncoderSample, len(sent) - 1, 0, 0, 1000, 0))
        await asyncio.sleep(0.002)
    return sent


async def test_xbee_overload_loses_frames_instead_of_queueing_them(tmp_path: Path) -> None:
    """Offered twice what the air carries, the controller's module fills its buffer and drops:
    what arrives is never late by more than a buffer's worth of air time."""
    controller = FakeController()
    module = XBeeModule(controller, api_mode=2, link_path=str(tmp_path / "xb"))
    await module.start()
    transport = create_transport(
        "xbee", url=module.path, dest_addr64=CONTROLLER_ADDR64, baudrate=115200, api_mode=2
    )
    loop = asyncio.get_running_loop()
    arrived: dict[int, float] = {}  # sample number → arrival time
    decoder = FrameDecoder()
    rx = Collector()

    def on_bytes(data: bytes) -> None:
        rx.on_bytes(data)  # for settle()
        for packet in decoder.feed(data):
            arrived[int(getattr(packet.message, "mcu_time_us"))] = loop.time()  # noqa: B009

    transport.set_receiver(on_bytes, rx.on_lost)
    await transport.open()
    try:
        rate_hz = 2 * AIR_BYTES_S / SAMPLE_AIR_BYTES  # ~200 Hz against ~100 packets/s of air
        sent = await _stream_up(controller, rate_hz, 2.0)
        await rx.settle(quiet_s=0.3)
        counters = module.counters
        assert counters.up_overflow > len(sent) // 4
        assert len(arrived) + counters.up_overflow == len(sent)  # nothing else went missing
        assert module.up_buffer.peak <= SERIAL_BUFFER_BYTES
        buffer_air_s = SERIAL_BUFFER_BYTES / 26 * SAMPLE_AIR_BYTES / AIR_BYTES_S  # ~78 ms
        worst = max(arrived[n] - sent[n] for n in arrived)
        assert worst < buffer_air_s + 0.1, f"frames {worst:.2f} s late: the air queues"
    finally:
        await transport.close()
        await module.stop()


async def test_xbee_directions_share_one_channel(tmp_path: Path) -> None:
    """60 % of the air each way fits either way alone, not both at once: the channel is shared."""
    controller = FakeController()
    module = XBeeModule(controller, api_mode=1, link_path=str(tmp_path / "xb"))
    await module.start()
    transport = create_transport(
        "xbee", url=module.path, dest_addr64=CONTROLLER_ADDR64, baudrate=115200, api_mode=1
    )
    rx = Collector()
    rx.attach(transport)
    await transport.open()
    try:
        rate_hz = 0.6 * AIR_BYTES_S / SAMPLE_AIR_BYTES

        async def down() -> None:
            loop = asyncio.get_running_loop()
            start, n = loop.time(), 0
            while (now := loop.time()) - start < 2.0:
                while n < (now - start) * rate_hz:
                    transport.send(_sample(n))
                    n += 1
                await asyncio.sleep(0.002)

        sent_up, _ = await asyncio.gather(_stream_up(controller, rate_hz, 2.0), down())
        await rx.settle(quiet_s=0.3)
        counters = module.counters
        assert counters.up_overflow + counters.down_overflow > 0
        assert module.air_bytes <= AIR_BYTES_S * 2.5  # the air carried no more than it can
        assert len(rx.packets) + counters.up_overflow == len(sent_up)
    finally:
        await transport.close()
        await module.stop()
