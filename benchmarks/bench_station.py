"""Operator station: exposure-to-browser latency and the frame loop's cost of viewers.

Run: python benchmarks/bench_station.py [--seconds S] [--fps F] [--viewers N]
Prints `metric: value` lines. A synthetic 1280×1024 camera at 30 fps feeds the daemon's own
FrameLoop; each frame is registered (a fixed pose) and handed to the station, which draws the
overlay and encodes it. Headless Debian Chromium pages receive the WebSocket frames and report
exposure-to-decode latency (their clock mapped to the host's by ping); beside them, in the same
run, a client of the MJPEG endpoint decodes each part with OpenCV and reports its latency.
The frame loop's fps is measured with 0 and with N viewers.
"""

from __future__ import annotations

import argparse
import asyncio
import os
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


async def mjpeg_client(url: str, seconds: float, out: list[float]) -> int:
    """Read the MJPEG stream, decode each part, keep exposure-to-decode latencies."""
    frames = 0
    deadline = time.monotonic() + seconds
    async with aiohttp.ClientSession() as http, http.get(url) as reply:
        reader = aiohttp.MultipartReader.from_response(reply)
        while time.monotonic() < deadline:
            part = await reader.next()
            if part is None:
                break
            assert isinstance(part, aiohttp.BodyPartReader)
            exposure_ms = float(part.headers["X-Exposure-Ms"])
            data = await part.read()
            cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
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


async def daemon_side_fps(loop: FrameLoop[Any], ws_url: str, count: int, seconds: float) -> float:
    """Frame loop fps while `count` light viewers in another process take every frame."""
    import sys

    proc = await asyncio.create_subprocess_exec(
        sys.executable, __file__, "--clients", ws_url, "--viewers", str(count),
        "--seconds", str(seconds + 2.0),
    )  # fmt: skip
    await asyncio.sleep(1.0)
    fps = await asyncio.to_thread(loop_fps, loop, seconds)
    await proc.wait()
    return fps


# The live view compared side by side for one viewer: the station as it was (WebSocket
# permessage-deflate on, as aiohttp offers it and Chromium accepts, quality 80) beside it
# without compression, at quality 80 and 70. Each is its own station on the same frame loop; a
# station nobody watches draws nothing.
VARIANTS: dict[str, dict[str, Any]] = {
    "before_deflate_q80": {"compress": True, "jpeg_quality": 80},
    "after_q80": {"compress": False, "jpeg_quality": 80},
    "after_q70": {"compress": False, "jpeg_quality": 70},
    "tried_ack_on_arrival_q80": {"compress": False, "jpeg_quality": 80, "page": "ack_on_arrival"},
}
# Tried, not shipped: the page acknowledges a frame on arrival, so the daemon sends the next
# during the decode; the page decodes the newest it has (one waiting at most).
ACK_ON_ARRIVAL_JS = """(() => {
  let decoding = false; let waiting = null; let last = null;
  async function drawWaiting() {
    decoding = true;
    while (waiting) {
      const { header, blob, receivedMs } = waiting; waiting = null;
      const bitmap = await createImageBitmap(blob); const decodedMs = performance.now();
      const canvas = document.getElementById("view");
      if (canvas.width !== bitmap.width || canvas.height !== bitmap.height) {
        canvas.width = bitmap.width; canvas.height = bitmap.height;
      }
      canvas.getContext("2d", { alpha: false }).drawImage(bitmap, 0, 0); bitmap.close();
      last = drawn(header, receivedMs, decodedMs);
    }
    decoding = false;
  }
  orbitar.ws.onmessage = (ev) => {
    if (typeof ev.data === "string") { onJson(JSON.parse(ev.data)); return; }
    const receivedMs = performance.now(); const buffer = ev.data;
    const headLen = new DataView(buffer).getUint32(0);
    const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, headLen)));
    const blob = new Blob([new Uint8Array(buffer, 4 + headLen)], { type: "image/jpeg" });
    orbitar.ws.send(JSON.stringify({ type: "ack", index: header.index, latency_ms: last }));
    last = null; waiting = { header, blob, receivedMs };
    if (!decoding) drawWaiting();
  };
})()"""
Measured = tuple[list[float], list[dict[str, float]], float]


async def latency_variants(
    browser: Any, stations: dict[str, Station], seconds: float, rounds: int
) -> dict[str, Measured]:
    """One viewer per variant in turn, interleaved over `rounds` (the machine's load drifts)."""
    out: dict[str, Measured] = {k: ([], [], 0.0) for k in stations}
    for _ in range(rounds):
        for name, station in stations.items():
            page = await browser.new_page(viewport={"width": 1600, "height": 1100}, bypass_csp=True)
            await page.goto(f"http://127.0.0.1:{station.port}/#token={TOKEN}")
            await page.wait_for_function("orbitar.frames > 0", timeout=10_000)
            if VARIANTS[name].get("page") == "ack_on_arrival":
                await page.evaluate(ACK_ON_ARRIVAL_JS)
            await asyncio.sleep(2.5)  # clock offsets settle (pings every 2 s)
            await page.evaluate("orbitar.latencies = []; orbitar.frames = 0; orbitar.timing = []")
            await asyncio.sleep(seconds)
            lat, timing, frames = out[name]
            lat += [float(v) for v in await page.evaluate("orbitar.latencies")]
            timing += await page.evaluate("orbitar.timing")
            out[name] = (lat, timing, frames + float(await page.evaluate("orbitar.frames")))
            await page.close()
    return out


def pct(values: list[float], q: float) -> float:
    """A percentile (nan when empty)."""
    return float(np.percentile(values, q)) if values else float("nan")


async def run(seconds: float, fps: float, viewers: int, width: int, height: int) -> None:
    """The whole measurement."""
    from playwright.async_api import async_playwright

    directory = Path(tempfile.mkdtemp(prefix="bench-station-"))
    config = bench_config(width, height, directory)
    station = Station(config, OpContext(None))
    await station.start()
    others = {}
    for name, variant in VARIANTS.items():
        other = Station(
            bench_config(width, height, directory, jpeg_quality=variant["jpeg_quality"]),
            OpContext(None),
        )
        other.ws_compress = bool(variant["compress"])
        await other.start()
        others[name] = other
    source = SyntheticCamera(width, height, fps)
    outputs: list[Callable[[Registration], None]] = [station.on_registration]
    outputs += [o.on_registration for o in others.values()]
    loop: FrameLoop[Registration] = FrameLoop(source, registrar(config), outputs)
    frames_task = asyncio.create_task(loop.run())
    url = f"http://127.0.0.1:{station.port}/#token={TOKEN}"
    try:
        await asyncio.sleep(1.0)
        fps0 = await asyncio.to_thread(loop_fps, loop, seconds)
        ws_url = f"http://127.0.0.1:{station.port}/ws"
        fps_light = await daemon_side_fps(loop, ws_url, viewers, seconds)
        async with async_playwright() as pw:
            browser = await pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            pages, first_frame_s = [], []
            for _ in range(viewers):
                page = await browser.new_page(viewport={"width": 1600, "height": 1100},
                                              bypass_csp=True)  # fmt: skip
                t0 = time.monotonic()
                await page.goto(url)
                await page.wait_for_function("orbitar.frames > 0", timeout=10_000)
                first_frame_s.append(time.monotonic() - t0)
                pages.append(page)
            await asyncio.sleep(2.0)  # clock offsets settle (pings every 2 s)
            for page in pages:
                await page.evaluate(
                    "orbitar.latencies = []; orbitar.frames = 0; orbitar.timing = []"
                )
            cpu0, hub0 = os.times(), station.hub.stats.encoded
            mjpeg: list[float] = []
            mjpeg_url = f"http://127.0.0.1:{station.port}/mjpeg?token={TOKEN}"
            mjpeg_task = asyncio.create_task(mjpeg_client(mjpeg_url, seconds, mjpeg))
            fps_n = await asyncio.to_thread(loop_fps, loop, seconds)
            mjpeg_frames = await mjpeg_task
            cpu1, hub1 = os.times(), station.hub.stats.encoded
            lat: list[float] = []
            delivered = []
            timing: list[dict[str, float]] = []
            for page in pages:
                lat += [float(v) for v in await page.evaluate("orbitar.latencies")]
                delivered.append(float(await page.evaluate("orbitar.frames")) / seconds)
                timing += await page.evaluate("orbitar.timing")
            variants = await latency_variants(browser, others, seconds, 2)
            await browser.close()
    finally:
        loop.stop()
        source.close()
        await frames_task
        for st in (station, *others.values()):
            await st.close()
    encoded = max(1, hub1 - hub0)
    cpu_s = (cpu1.user - cpu0.user) + (cpu1.system - cpu0.system)
    print(f"resolution: {width}x{height}")
    print(f"camera_fps: {fps:.1f}")
    print(f"viewers: {viewers}")
    print(f"ws_latency_ms_p50: {pct(lat, 50):.1f}")
    print(f"ws_latency_ms_p95: {pct(lat, 95):.1f}")
    breakdown("ws", timing)
    for name, (v_lat, v_timing, v_frames) in variants.items():
        print(f"one_viewer_{name}_latency_ms_p50: {pct(v_lat, 50):.1f}")
        print(f"one_viewer_{name}_latency_ms_p95: {pct(v_lat, 95):.1f}")
        print(f"one_viewer_{name}_delivered_fps: {v_frames / (2 * seconds):.1f}")
        print(f"one_viewer_{name}_encode_cpu_ms: {others[name].hub.stats.cpu_ms_mean():.2f}")
        breakdown(f"one_viewer_{name}", v_timing)
    print(f"mjpeg_latency_ms_p50: {pct(mjpeg, 50):.1f}")
    print(f"mjpeg_latency_ms_p95: {pct(mjpeg, 95):.1f}")
    print(f"ws_delivered_fps_per_viewer: {np.mean(delivered):.1f}")
    print(f"mjpeg_delivered_fps: {mjpeg_frames / seconds:.1f}")
    print(f"first_frame_s_max: {max(first_frame_s):.2f}")
    print(f"encode_cpu_ms_per_frame: {station.hub.stats.cpu_ms_mean():.2f}")
    print(f"process_cpu_ms_per_frame: {cpu_s * 1e3 / encoded:.2f}  # includes the camera, loop")
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
    args = parser.parse_args()
    if args.clients:
        asyncio.run(ws_clients(args.clients, args.viewers, args.seconds))
        return
    asyncio.run(run(args.seconds, args.fps, args.viewers, args.width, args.height))


if __name__ == "__main__":
    main()
