"""The bus under a hall's load: N rigs publishing poses to S subscribers on loopback, beside the
control socket's pose events (the path `orbitar watch` reads) carrying the same poses.

Run: python benchmarks/bench_bus.py [--rigs 10] [--rate 500] [--subscribers 5] [--seconds 5]

Two processes: the rigs (each a real BusPublisher with its own Zenoh session listening on
127.0.0.1, multicast scouting off, plus one ControlServer on a Unix socket for the peer path)
and the subscribers (S Zenoh sessions connected to every rig, then S control-socket clients).
Latency is publish to callback on the shared monotonic clock. A 30 Hz frame-loop stand-in
(projection of 10,000 points per frame) runs in the rigs' process; its fps is measured idle,
under the bus load and under the control-socket load. Prints `metric: value` lines.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import multiprocessing as mp
import tempfile
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

PHASE_SETTLE_S = 1.0
FRAME_HZ = 30.0
POSE_T = ((1.0, 0, 0, 1500.0), (0, 0, 1.0, 300.0), (0, -1.0, 0, 4000.0), (0, 0, 0, 1.0))


def _ports(n: int) -> list[int]:
    """N free TCP ports on 127.0.0.1."""
    import socket

    probes = [socket.socket() for _ in range(n)]
    for probe in probes:
        probe.bind(("127.0.0.1", 0))
    ports = [int(p.getsockname()[1]) for p in probes]
    for probe in probes:
        probe.close()
    return ports


class FrameLoopStandIn:
    """30 Hz of registration-sized work; counts the frames it manages."""

    def __init__(self) -> None:
        self.frames = 0
        self._points = np.random.default_rng(1).normal(size=(10_000, 3)) + np.array([0.0, 0.0, 5.0])

    async def run(self) -> None:
        period = 1.0 / FRAME_HZ
        next_s = time.monotonic()
        while True:
            p = self._points
            _ = (p[:, :2] / p[:, 2:3]) * 3676.0 + 640.0  # a frame's projection
            self.frames += 1
            next_s += period
            await asyncio.sleep(max(0.0, next_s - time.monotonic()))
            next_s = max(next_s, time.monotonic() - period)  # no bursts after a stall


async def _paced(rate_hz: float, seconds: float, emit: Any) -> int:
    """Call emit(t_ns) rate_hz times a second for `seconds`, catching up on late ticks."""
    start = time.monotonic()
    sent = 0
    while (elapsed := time.monotonic() - start) < seconds:
        due = int(elapsed * rate_hz) + 1
        while sent < due:
            emit(time.monotonic_ns())
            sent += 1
        await asyncio.sleep(0.001)
    return sent


async def _fps_during(loop_stand_in: FrameLoopStandIn, job: Any) -> tuple[float, Any]:
    """The stand-in's fps while `job` runs, and the job's result."""
    frames0, t0 = loop_stand_in.frames, time.monotonic()
    result = await job
    return (loop_stand_in.frames - frames0) / (time.monotonic() - t0), result


async def _rigs_main(
    args: argparse.Namespace, ports: list[int], sock: str, pipe: Connection
) -> None:
    from host.bus.publisher import BusPublisher
    from host.config import ControlConfig
    from host.config_bus import BusConfig
    from host.control.api import PoseSample
    from host.control.ops import OpContext
    from host.control.server import ControlServer

    async def nothing() -> dict[str, Any]:
        return {}

    buses = [
        BusPublisher(
            BusConfig(enabled=True, rig_id=f"rig{i}", listen=(f"tcp/127.0.0.1:{port}",)),
            status=nothing, rig=nothing, stats=dict,
        )
        for i, port in enumerate(ports)
    ]  # fmt: skip
    tasks = [asyncio.create_task(bus.run()) for bus in buses]
    queue = int(args.rate * args.rigs)  # a second of events: the peer never drops for want of room
    server = ControlServer(OpContext(None), ControlConfig(socket_path=sock, queue_max=queue))
    await server.start()
    stand_in = FrameLoopStandIn()
    tasks.append(asyncio.create_task(stand_in.run()))
    while not all(bus.up for bus in buses):
        await asyncio.sleep(0.05)
    fps_idle, _ = await _fps_during(stand_in, asyncio.sleep(args.seconds / 2))
    loop = asyncio.get_running_loop()
    await loop.run_in_executor(None, pipe.send, {"fps_idle": fps_idle})

    def bus_emit(t_ns: int) -> None:
        for bus in buses:
            bus.publish_pose(PoseSample(t_ns, POSE_T, "MOVING", 1500.0))

    def control_emit(t_ns: int) -> None:
        for _ in range(args.rigs):
            server.publish("pose", PoseSample(t_ns, POSE_T, "MOVING", 1500.0).to_dict())

    for phase in ("bus", "control"):
        assert await loop.run_in_executor(None, pipe.recv) == phase
        cpu0 = time.process_time()
        emit = bus_emit if phase == "bus" else control_emit
        fps, sent = await _fps_during(stand_in, _paced(args.rate, args.seconds, emit))
        cpu_s = time.process_time() - cpu0
        await asyncio.sleep(PHASE_SETTLE_S)  # the last messages arrive
        result = {"fps": fps, "sent": sent * args.rigs, "cpu_s": cpu_s}
        result["dropped"] = server.stats["events_dropped"] if phase == "control" else 0
        await loop.run_in_executor(None, pipe.send, result)
    assert await loop.run_in_executor(None, pipe.recv) == "quit"
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    for bus in buses:
        await bus.close()
    await server.close()


def _rigs_process(args: argparse.Namespace, ports: list[int], sock: str, pipe: Connection) -> None:
    asyncio.run(_rigs_main(args, ports, sock, pipe))


def _subscribers_process(
    args: argparse.Namespace, ports: list[int], sock: str, pipe: Connection
) -> None:
    import msgpack
    import zenoh

    from host.bus.session import zenoh_config

    endpoints = [f"tcp/127.0.0.1:{port}" for port in ports]
    latencies: list[int] = []

    def on_pose(sample: zenoh.Sample) -> None:
        t_ns = msgpack.unpackb(sample.payload.to_bytes())["t_ns"]
        latencies.append(time.monotonic_ns() - t_ns)

    assert pipe.recv() == "connect"
    sessions = [
        zenoh.open(zenoh_config("peer", [], endpoints, False)) for _ in range(args.subscribers)
    ]
    subs = [s.declare_subscriber("orbitar/*/pose", on_pose) for s in sessions]
    time.sleep(PHASE_SETTLE_S)  # subscriptions propagate to every rig
    cpu0 = time.process_time()
    pipe.send("ready")
    assert pipe.recv() == "report"
    pipe.send({"latencies": list(latencies), "cpu_s": time.process_time() - cpu0})
    for sub in subs:
        sub.undeclare()
    for session in sessions:
        session.close()
    asyncio.run(_control_subscribers(args, sock, pipe))


async def _control_subscribers(args: argparse.Namespace, sock: str, pipe: Connection) -> None:
    from host.control.wire import pack, read_message

    latencies: list[int] = []
    streams = [await asyncio.open_unix_connection(sock) for _ in range(args.subscribers)]
    for i, (reader, writer) in enumerate(streams):
        writer.write(pack({"id": i, "op": "subscribe", "args": {"topics": ["pose"]}}))
        await read_message(reader)

    async def drain(reader: asyncio.StreamReader) -> None:
        while (msg := await read_message(reader)) is not None:
            if msg.get("topic") == "pose":
                latencies.append(time.monotonic_ns() - msg["data"]["t_ns"])

    readers = [asyncio.create_task(drain(reader)) for reader, _ in streams]
    loop = asyncio.get_running_loop()
    cpu0 = time.process_time()
    await loop.run_in_executor(None, pipe.send, "ready")
    assert await loop.run_in_executor(None, pipe.recv) == "report"
    await loop.run_in_executor(
        None, pipe.send, {"latencies": latencies, "cpu_s": time.process_time() - cpu0}
    )
    for task in readers:
        task.cancel()
    for _, writer in streams:
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()


def _report(name: str, path: dict[str, Any], rigs: dict[str, Any], subscribers: int) -> None:
    """Latency, delivery and CPU of one path."""
    lat_ms = sorted(x / 1e6 for x in path["latencies"])
    got, expected = len(lat_ms), int(rigs["sent"]) * subscribers

    def quantile(q: float) -> float:
        return lat_ms[min(got - 1, int(q * got))] if got else float("nan")

    print(f"{name}_latency_p50_ms: {quantile(0.50):.3f}")
    print(f"{name}_latency_p99_ms: {quantile(0.99):.3f}")
    print(f"{name}_delivered_per_s: {got / rigs['seconds']:.0f}")
    print(f"{name}_lost: {expected - got} of {expected}")
    cpu_us = (rigs["cpu_s"] + path["cpu_s"]) / max(got, 1) * 1e6
    print(f"{name}_cpu_per_delivered_message_us: {cpu_us:.1f}")
    print(f"{name}_frame_loop_fps: {rigs['fps']:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rigs", type=int, default=10)
    parser.add_argument("--rate", type=float, default=500.0, help="poses per second per rig")
    parser.add_argument("--subscribers", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    ports = _ports(args.rigs)
    ctx = mp.get_context("spawn")
    with tempfile.TemporaryDirectory() as tmp:
        sock = f"{tmp}/control.sock"
        rigs_pipe, rigs_end = ctx.Pipe()
        subs_pipe, subs_end = ctx.Pipe()
        procs = [
            ctx.Process(target=_rigs_process, args=(args, ports, sock, rigs_end)),
            ctx.Process(target=_subscribers_process, args=(args, ports, sock, subs_end)),
        ]
        for proc in procs:
            proc.start()
        fps_idle = rigs_pipe.recv()["fps_idle"]
        subs_pipe.send("connect")
        results = {}
        for phase in ("bus", "control"):
            assert subs_pipe.recv() == "ready"
            rigs_pipe.send(phase)
            rigs = rigs_pipe.recv() | {"seconds": args.seconds}
            subs_pipe.send("report")
            results[phase] = (subs_pipe.recv(), rigs)
        rigs_pipe.send("quit")
        for proc in procs:
            proc.join(30)
    print(f"load: {args.rigs} rigs x {args.rate:g} Hz poses -> {args.subscribers} subscribers")
    print(f"frame_loop_fps_idle: {fps_idle:.2f}")
    _report("bus", *results["bus"], args.subscribers)
    _report("control_socket", *results["control"], args.subscribers)
    print(f"control_socket_events_dropped: {results['control'][1]['dropped']}")


if __name__ == "__main__":
    main()
