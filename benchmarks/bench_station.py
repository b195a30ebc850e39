"""Operator station: exposure-to-browser latency and the frame loop's cost of viewers.

Run: python benchmarks/bench_station.py [--seconds S] [--fps F] [--viewers N]
Prints `metric: value` lines. A synthetic 1280×1024 camera at 30 fps feeds the daemon's own
FrameLoop; each frame is registered (a fixed pose) and handed to the station, which draws the
overlay and encodes it. This process is the daemon's side only: the headless Debian Chromium
pages (driven by playwright) and the MJPEG peer (decoding each part with OpenCV) run in a child
process, so neither the driver's messages nor the peer's decoding run on the daemon's event
loop. The pages report exposure-to-drawn latency (their clock mapped to the daemon's by ping),
where it went, their ping round trips, and when their first frame came after navigation; the
MJPEG peer's latency is measured in the same window. The frame loop's fps is measured with 0
viewers, N acknowledging clients that do not decode, and the N pages.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiohttp
import cv2
import numpy as np

from host.config import Config, config_from_dict
from host.control.ops import OpContext
from host.frames.loop import FrameLoop
from host.frames.registrar import Registration
from host.frames.sources import Frame
from host.registration.pose_buffer import LookupStatus
from host.service.wiring import build_rig, workpiece_pose
from host.station.server import Station

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run"]  # fmt: skip
TOKEN = "bench-token-0123456"


class SyntheticCamera:
    """Frames of a textured 1280×1024 scene at a fixed rate, stamped at exposure."""

    def __init__(self, width: int, height: int, fps: float) -> None:
        rng = np.random.default_rng(3)
        self.base = rng.integers(40, 90, (height, width, 3), dtype=np.uint8)
        cv2.GaussianBlur(self.base, (0, 0), 3, dst=self.base)
        self.period_s = 1.0 / fps
        self._next = time.monotonic()
        self._index = 0
        self._closed = threading.Event()

    def read(self) -> Frame | None:
        """The next frame, on schedule (a camera never bursts)."""
        self._next += self.period_s
        delay = self._next - time.monotonic()
        if delay > 0 and self._closed.wait(delay):
            return None
        if self._closed.is_set():
            return None
        self._index += 1
        image = np.roll(self.base, self._index * 4, axis=1)  # a new buffer each frame
        return Frame(self._index, image, time.monotonic_ns())

    def close(self) -> None:
        """Stop."""
        self._closed.set()


RIG = """
[head]
tilt_max_deg = 80.0
[camera]
width = {width}
height = {height}
[camera.intrinsics]
u0 = {u0}
v0 = {v0}
fx = 1400.0
fy = 1400.0
[workpiece.frame]
matrix = [[1, 0, 0, -300.0], [0, 1, 0, -300.0], [0, 0, 1, 0], [0, 0, 0, 1]]
"""


def bench_config(width: int, height: int, directory: Path, **ui: Any) -> Config:
    """The paper's camera at full resolution (rig file in `directory`), the station on port 0."""
    rig = directory / "rig.toml"
    rig.write_text(RIG.format(width=width, height=height, u0=width / 2, v0=height / 2))
    return config_from_dict(
        {
            "camera": {"source": "none"},
            "rig": {"path": str(rig)},
            "ui": {"enabled": True, "port": 0, "operator_token": TOKEN, **ui},
        }
    )


def registrar(config: Config) -> Any:
    """A fixed pose aimed at the workpiece (registration's own cost is benchmarked elsewhere)."""
    rig = build_rig(config)
    target = workpiece_pose(config)[:3, 3] + [0.0, 0.0, 700.0]
    pan, tilt = rig.aim(150.0, target)
    T_w_c = rig.T_w_c(150.0, pan, tilt)

    def process(frame: Frame) -> Registration:
        return Registration(
            frame.index, frame.exposure_ns, LookupStatus.OK, T_w_c, 150.0, pan, tilt,
            None, 0, None, None, frame.image,
        )  # fmt: skip

    return process


def loop_fps(loop: FrameLoop[Any], seconds: float) -> float:
    """Frames the loop processed per second over the next `seconds` (blocking wait)."""
    n0, t0 = loop.stats.processed, time.monotonic()
    time.sleep(seconds)
    return (loop.stats.processed - n0) / (time.monotonic() - t0)


async def mjpeg_client(url: str, settle_s: float, seconds: float, out: list[float]) -> int:
    """Read the MJPEG stream, decode each part, keep exposure-to-decode latencies after settle_s.

    Runs in a process of its own, on the daemon's monotonic clock (the same machine); prints
    `connected` once the stream is open.
    """
    frames = 0
    async with aiohttp.ClientSession() as http, http.get(url) as reply:
        print("connected", flush=True)
        reader = aiohttp.MultipartReader.from_response(reply)
        start = time.monotonic() + settle_s
        while time.monotonic() < start + seconds:
            part = await reader.next()
            if part is None:
                break
            assert isinstance(part, aiohttp.BodyPartReader)
            exposure_ms = float(part.headers["X-Exposure-Ms"])
            data = np.frombuffer(await part.read(), np.uint8)
            cv2.imdecode(data, cv2.IMREAD_COLOR)
            if time.monotonic() >= start:
                out.append(time.monotonic_ns() / 1e6 - exposure_ms)
                frames += 1
    return frames


async def ws_clients(url: str, count: int, seconds: float) -> None:
    """Viewers that acknowledge every frame at once (no decoding): the daemon's side alone."""

    async def one(http: aiohttp.ClientSession) -> None:
        async with http.ws_connect(url) as ws:
            await ws.send_json({"type": "hello", "token": TOKEN})
            deadline = time.monotonic() + seconds
            while time.monotonic() < deadline:
                msg = await ws.receive(timeout=5.0)
                if msg.type is aiohttp.WSMsgType.BINARY:
                    await ws.send_json({"type": "ack"})

    async with aiohttp.ClientSession() as http:
        await asyncio.gather(*(one(http) for _ in range(count)))


async def child(*args: str) -> asyncio.subprocess.Process:
    """This script in another process (its output piped back)."""
    return await asyncio.create_subprocess_exec(
        sys.executable, __file__, *args, stdout=asyncio.subprocess.PIPE
    )


async def daemon_side_fps(loop: FrameLoop[Any], ws_url: str, count: int, seconds: float) -> float:
    """Frame loop fps while `count` light viewers in another process take every frame."""
    proc = await child("--clients", ws_url, "--viewers", str(count), "--seconds", str(seconds + 2))
    await asyncio.sleep(1.0)
    fps = await asyncio.to_thread(loop_fps, loop, seconds)
    await proc.wait()
    return fps


SETTLE_S = 2.0
RESET = "orbitar.latencies = []; orbitar.frames = 0; orbitar.timing = []"  # pings: the last 10


async def drive(port: int, viewers: int, seconds: float) -> dict[str, Any]:
    """The browsers' side (its own process): open the pages, then measure with an MJPEG peer.

    Prints `measuring` when the window starts, so the daemon measures its frame loop in it.
    """
    from playwright.async_api import async_playwright

    url = f"http://127.0.0.1:{port}/#token={TOKEN}"
    async with async_playwright() as pw:
        browser = await pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        pages, first_wall_s, first_page_ms = [], [], []
        for _ in range(viewers):
            page = await browser.new_page(viewport={"width": 1600, "height": 1100},
                                          bypass_csp=True)  # fmt: skip
            t0 = time.monotonic()
            await page.goto(url)
            await page.wait_for_function("orbitar.frames > 0", timeout=10_000)
            first_wall_s.append(time.monotonic() - t0)
            first_page_ms.append(await page.evaluate("orbitar.marks"))
            pages.append(page)
        peer = await child("--mjpeg", str(port), "--seconds", str(seconds))
        assert peer.stdout is not None
        await peer.stdout.readline()  # connected: it settles as the pages do
        await asyncio.sleep(SETTLE_S)  # and the pages' clock offsets settle (pings every 2 s)
        for page in pages:
            await page.evaluate(RESET)
        print("measuring", flush=True)
        await asyncio.sleep(seconds)
        out: dict[str, Any] = {"lat": [], "delivered": [], "timing": [], "rtt": [], "err": []}
        out["held"] = []
        for page in pages:
            out["lat"] += await page.evaluate("orbitar.latencies")
            out["delivered"].append(float(await page.evaluate("orbitar.frames")) / seconds)
            out["timing"] += await page.evaluate("orbitar.timing")
            out["rtt"] += await page.evaluate("orbitar.pings.map((p) => p.rtt)")
            out["held"] += await page.evaluate("orbitar.pings.map((p) => p.held ?? null)")
            out["err"].append(await page.evaluate("orbitar.offsetErrMs"))
        await browser.close()
    mjpeg = json.loads(await peer.stdout.read())
    await peer.wait()
    out.update(mjpeg=mjpeg, first_wall_s=first_wall_s)
    out["first_page_ms"] = first_page_ms
    return out


def pct(values: list[float], q: float) -> float:
    """A percentile (nan when empty)."""
    return float(np.percentile(values, q)) if values else float("nan")


async def run(seconds: float, fps: float, viewers: int, width: int, height: int) -> None:
    """The whole measurement: this process is the daemon's side only."""
    directory = Path(tempfile.mkdtemp(prefix="bench-station-"))
    config = bench_config(width, height, directory)
    station = Station(config, OpContext(None))
    await station.start()
    source = SyntheticCamera(width, height, fps)
    outputs: list[Callable[[Registration], None]] = [station.on_registration]
    loop: FrameLoop[Registration] = FrameLoop(source, registrar(config), outputs)
    frames_task = asyncio.create_task(loop.run())
    try:
        await asyncio.sleep(1.0)
        fps0 = await asyncio.to_thread(loop_fps, loop, seconds)
        ws_url = f"http://127.0.0.1:{station.port}/ws"
        fps_light = await daemon_side_fps(loop, ws_url, viewers, seconds)
        driver = await child("--driver", str(station.port), "--viewers", str(viewers),
                             "--seconds", str(seconds))  # fmt: skip
        assert driver.stdout is not None
        while (line := await driver.stdout.readline()) and line.strip() != b"measuring":
            pass
        cpu0, hub0 = os.times(), station.hub.stats.encoded
        fps_n = await asyncio.to_thread(loop_fps, loop, seconds)
        cpu1, hub1 = os.times(), station.hub.stats.encoded
        got = json.loads((await driver.stdout.read()).decode().strip().splitlines()[-1])
        await driver.wait()
    finally:
        loop.stop()
        source.close()
        await frames_task
        await station.close()
    encoded = max(1, hub1 - hub0)
    cpu_s = (cpu1.user - cpu0.user) + (cpu1.system - cpu0.system)
    lat = got["lat"]
    print(f"resolution: {width}x{height}")
    print(f"camera_fps: {fps:.1f}")
    print(f"viewers: {viewers}")
    print(f"ws_latency_ms_p50: {pct(lat, 50):.1f}")
    print(f"ws_latency_ms_p95: {pct(lat, 95):.1f}")
    breakdown("ws", got["timing"])
    print(f"ws_ping_rtt_ms_min: {pct(got['rtt'], 0):.1f}")
    print(f"ws_ping_rtt_ms_p50: {pct(got['rtt'], 50):.1f}")
    held = [h for h in got["held"] if h is not None]
    print(f"ws_pong_held_ms_p50: {pct(held, 50):.1f}  # in the daemon: ping read to pong written")
    print(f"ws_pong_held_ms_max: {max(held, default=math.nan):.1f}")
    errors = [e for e in got["err"] if e is not None]  # None: a page that does not say
    print(f"ws_clock_offset_error_ms_max: {max(errors, default=math.nan):.1f}  # ± on latency")
    print(f"ws_frame_rtt_ms_p50: {station.station_stats().get('frame_rtt_ms_p50')}  # sent, acked")
    print(f"mjpeg_latency_ms_p50: {pct(got['mjpeg'], 50):.1f}")
    print(f"mjpeg_latency_ms_p95: {pct(got['mjpeg'], 95):.1f}")
    print(f"ws_delivered_fps_per_viewer: {np.mean(got['delivered']):.1f}")
    print(f"mjpeg_delivered_fps: {len(got['mjpeg']) / seconds:.1f}")
    marks = [m or {} for m in got["first_page_ms"]]
    for mark in ("open", "hello", "frame_in", "frame"):
        worst = max(m.get(mark) or float("nan") for m in marks)
        print(f"first_{mark}_ms_max: {worst:.0f}  # from navigation start, in the page")
    print(f"first_frame_s_max: {max(got['first_wall_s']):.2f}  # goto to frames > 0, driver side")
    print(f"encode_cpu_ms_per_frame: {station.hub.stats.cpu_ms_mean():.2f}")
    print(f"daemon_cpu_ms_per_frame: {cpu_s * 1e3 / encoded:.2f}  # includes the camera, loop")
    print(f"frame_loop_fps_0_viewers: {fps0:.2f}")
    print(f"frame_loop_fps_{viewers}_viewers: {fps_n:.2f}")
    print(f"frame_loop_fps_cost_pct: {100.0 * (fps0 - fps_n) / fps0:.2f}  # browsers share the CPU")
    print(f"frame_loop_fps_{viewers}_light_viewers: {fps_light:.2f}  # acking clients, no decode")
    print(f"frame_loop_fps_cost_pct_light: {100.0 * (fps0 - fps_light) / fps0:.2f}")
    ready = station.station_stats()["jpeg_ready_ms_p50"]
    print(f"jpeg_ready_ms_p50: {ready}  # exposure to encoded JPEG, in the daemon")
    print(f"registration_latency_ms_p50: {loop.stats.latency_ms(0.5):.1f}  # exposure to pose")
    print(f"frames_dropped_by_loop: {loop.stats.dropped}")
    print(f"encoder_dropped: {station.hub.stats.dropped}")


def breakdown(prefix: str, timing: list[dict[str, float]]) -> None:
    """Where the time went: exposure to send (daemon), send to receipt, decode, draw."""
    for part in ("daemon", "transit", "decode", "draw"):
        values = [float(t[part]) for t in timing if t.get(part) is not None]
        print(f"{prefix}_{part}_ms_p50: {pct(values, 50):.1f}")
        print(f"{prefix}_{part}_ms_p95: {pct(values, 95):.1f}")


def main() -> None:
    """Parse arguments and run."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--viewers", type=int, default=4)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=1024)
    parser.add_argument("--clients", metavar="WS_URL", help=argparse.SUPPRESS)
    parser.add_argument("--driver", metavar="PORT", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--mjpeg", metavar="PORT", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.clients:
        asyncio.run(ws_clients(args.clients, args.viewers, args.seconds))
        return
    if args.mjpeg:
        latencies: list[float] = []
        url = f"http://127.0.0.1:{args.mjpeg}/mjpeg?token={TOKEN}"
        asyncio.run(mjpeg_client(url, SETTLE_S, args.seconds, latencies))
        print(json.dumps(latencies))
        return
    if args.driver:
        print(json.dumps(asyncio.run(drive(args.driver, args.viewers, args.seconds))))
        return
    asyncio.run(run(args.seconds, args.fps, args.viewers, args.width, args.height))


if __name__ == "__main__":
    main()
