"""Service-side costs: control-socket round trips, event fan-out, FreeD encoding, recording.

Run: python benchmarks/bench_service.py [--requests N] [--subscribers S] [--poses P]
Prints `metric: value` lines. Peers side by side: a status round trip over the Unix socket
beside a bare msgpack echo over the same kind of socket (the floor any client sees), recording
writes beside a plain msgpack dump of the same records into memory, and the daemon's memory
growth under a client that floods requests and never reads beside one that reads its replies.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import socket
import statistics
import tempfile
import threading
import time
from pathlib import Path

import msgpack

from host.config import ControlConfig
from host.control.api import PoseSample
from host.control.client import ControlClient
from host.control.ops import OpContext
from host.control.server import ControlServer
from host.control.wire import pack, read_message
from host.outputs.freed import encode_d1, pose_to_freed
from host.recording import RecordingReader, RecordingWriter
from tests.fakes import MemoryController

POSE = PoseSample(
    1, ((1.0, 0, 0, 1500.0), (0, 0, 1.0, 300.0), (0, -1.0, 0, 4000.0), (0, 0, 0, 1.0)), "MOVING"
)


async def _round_trips(server: ControlServer, n: int) -> list[float]:
    """Latencies of `status` requests, one at a time, in microseconds."""
    async with await ControlClient.connect_unix(server.config.socket_path) as client:
        out = []
        for _ in range(n):
            t0 = time.perf_counter()
            await client.request("status")
            out.append((time.perf_counter() - t0) * 1e6)
    return out


async def _echo_round_trips(path: str, n: int) -> list[float]:
    """The same framing against a server that only echoes: the socket's floor."""

    async def echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while (msg := await read_message(reader)) is not None:
            writer.write(pack(msg))
        writer.close()

    server = await asyncio.start_unix_server(echo, path=path)
    reader, writer = await asyncio.open_unix_connection(path)
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        writer.write(pack({"id": i, "op": "status", "args": {}}))
        await read_message(reader)
        out.append((time.perf_counter() - t0) * 1e6)
    writer.close()
    await writer.wait_closed()
    server.close()
    await server.wait_closed()
    return out


async def _fan_out(server: ControlServer, subscribers: int, poses: int) -> tuple[float, float]:
    """Publish cost per pose (µs, what the frame loop pays) and delivery rate (events/s)."""
    clients = [
        await ControlClient.connect_unix(server.config.socket_path) for _ in range(subscribers)
    ]
    for c in clients:
        await c.request("subscribe", topics=["pose"])
    data = POSE.to_dict()
    t0 = time.perf_counter()
    publish_s = 0.0
    for i in range(poses):
        p0 = time.perf_counter()
        server.publish("pose", data)
        publish_s += time.perf_counter() - p0
        if i % 64 == 0:
            await asyncio.sleep(0)  # let writers run, as the frame loop's awaits would
    for c in clients:
        while (await c.next_event(timeout_s=10))["topic"] != "pose":
            pass
    elapsed = time.perf_counter() - t0
    for c in clients:
        await c.close()
    return publish_s / poses * 1e6, poses * subscribers / elapsed


FLOOD_BYTES = 16 * 1024 * 1024
FLOOD_S = 5.0


def _rss_kb() -> int:
    """This process's resident set size, kB (Linux)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def _drain(sock: socket.socket) -> None:
    """Read and discard until the socket ends."""
    while True:
        try:
            if not sock.recv(65536):
                return
        except TimeoutError:
            continue
        except OSError:
            return


def _flood(path: str, read_replies: bool, out: dict[str, float]) -> None:
    """Send `status` requests for FLOOD_BYTES or FLOOD_S; read the replies or never read them."""
    sock = socket.socket(socket.AF_UNIX)
    sock.connect(path)
    sock.settimeout(0.2)
    if read_replies:
        threading.Thread(target=_drain, args=(sock,), daemon=True).start()
    chunk = b"".join(pack({"id": i, "op": "status"}) for i in range(2000))
    sent, t0 = 0, time.perf_counter()
    try:
        while sent < FLOOD_BYTES and time.perf_counter() - t0 < FLOOD_S:
            try:
                sock.sendall(chunk)
                sent += len(chunk)
            except TimeoutError:
                continue  # the server stopped reading us: back-pressure
    except (BrokenPipeError, ConnectionResetError):
        out["cut_off_s"] = time.perf_counter() - t0
    out["sent_mb"] = sent / 2**20
    sock.close()


async def _flood_growth(path: str, read_replies: bool) -> dict[str, float]:
    """Peak RSS growth of this process (the server's side) while one client floods it."""
    out: dict[str, float] = {}
    before = _rss_kb()
    peak = before
    flood = asyncio.ensure_future(asyncio.to_thread(_flood, path, read_replies, out))
    while not flood.done():
        peak = max(peak, _rss_kb())
        await asyncio.sleep(0.02)
    await flood
    out["growth_mb"] = (peak - before) / 1024
    return out


async def _flood_metrics() -> None:
    """A client that never reads beside one that reads, against the same server."""
    with tempfile.TemporaryDirectory() as tmp:
        config = ControlConfig(socket_path=f"{tmp}/f.sock", stall_timeout_s=1.0)
        server = ControlServer(OpContext(None), config)
        await server.start()
        reading = await _flood_growth(config.socket_path, read_replies=True)
        silent = await _flood_growth(config.socket_path, read_replies=False)
        await server.close()
    print(f"control_nonreading_client_rss_growth_mb: {silent['growth_mb']:.1f}")
    print(f"control_nonreading_client_sent_mb: {silent['sent_mb']:.1f}")
    print(f"control_nonreading_client_cut_off_s: {silent.get('cut_off_s', float('nan')):.2f}")
    print(f"peer_reading_client_rss_growth_mb: {reading['growth_mb']:.1f}")
    print(f"peer_reading_client_sent_mb: {reading['sent_mb']:.1f}")


async def _socket_metrics(args: argparse.Namespace) -> None:
    """Everything that needs the event loop."""
    with tempfile.TemporaryDirectory() as tmp:
        fake = MemoryController()
        await fake.connect()
        config = ControlConfig(socket_path=f"{tmp}/c.sock", queue_max=args.poses)
        server = ControlServer(OpContext(fake, latest_pose=lambda: POSE), config)
        await server.start()
        rtt = await _round_trips(server, args.requests)
        echo = await _echo_round_trips(f"{tmp}/echo.sock", args.requests)
        publish_us, delivered = await _fan_out(server, args.subscribers, args.poses)
        await server.close()
    print(f"control_status_rtt_median_us: {statistics.median(rtt):.1f}")
    print(f"control_status_rtt_p99_us: {sorted(rtt)[int(len(rtt) * 0.99) - 1]:.1f}")
    print(f"peer_msgpack_echo_rtt_median_us: {statistics.median(echo):.1f}")
    print(f"pose_publish_cost_us_{args.subscribers}_subscribers: {publish_us:.2f}")
    print(f"pose_events_delivered_per_s: {delivered:.0f}")


def _freed_rate(n: int) -> float:
    """Poses mapped and encoded per second."""
    t0 = time.perf_counter()
    for _ in range(n):
        encode_d1(1, pose_to_freed(POSE.T_w_c))
    return n / (time.perf_counter() - t0)


def _recording_rates(n: int) -> tuple[float, float, float]:
    """Records written/s to rotating files, read back/s, and a plain in-memory dump/s."""
    data = POSE.to_dict()
    with tempfile.TemporaryDirectory() as tmp:
        writer = RecordingWriter(Path(tmp), rotate_mb=8, keep_files=100, drop_when_full=False)
        writer.open()
        t0 = time.perf_counter()
        for i in range(n):
            writer.write("pose", i, data)
        writer.close()
        write_rate = n / (time.perf_counter() - t0)
        t0 = time.perf_counter()
        count = sum(1 for _ in RecordingReader([tmp]))
        read_rate = count / (time.perf_counter() - t0)
    buf, packer = io.BytesIO(), msgpack.Packer(use_bin_type=True)
    t0 = time.perf_counter()
    for i in range(n):
        buf.write(packer.pack({"k": "pose", "t": i, "d": data}))
    return write_rate, read_rate, n / (time.perf_counter() - t0)


def main() -> None:
    """Run every measurement and print the metrics."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--requests", type=int, default=2000)
    parser.add_argument("--subscribers", type=int, default=4)
    parser.add_argument("--poses", type=int, default=3000)
    args = parser.parse_args()
    asyncio.run(_socket_metrics(args))
    asyncio.run(_flood_metrics())
    print(f"freed_poses_encoded_per_s: {_freed_rate(50_000):.0f}")
    write_rate, read_rate, peer_rate = _recording_rates(100_000)
    print(f"recording_pose_writes_per_s: {write_rate:.0f}")
    print(f"recording_records_read_per_s: {read_rate:.0f}")
    print(f"peer_msgpack_dump_to_memory_per_s: {peer_rate:.0f}")


if __name__ == "__main__":
    main()
