"""The operator station: an aiohttp app in the daemon's event loop (page, WebSocket, MJPEG).

Everything the page needs is served from `static/` beside this module, so it works with no
internet. Its actions run the control socket's operations (`host.control.ops`: the same
validation, errors and roles). The daemon calls `on_registration` for each registered
camera frame and `on_pose` for each pose; without camera frames the view renders the model
from the registered pose over a plain background.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import math
import re
import secrets
import ssl
import time
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from aiohttp import web

from host.commissioning.coverage import MIN_PROGRESS
from host.commissioning.ops import COMMISSIONING_OPS
from host.config import Config
from host.config_ui import UiConfig
from host.control.api import PoseSample
from host.control.ops import OpContext, OpError, Role, dispatch
from host.frames.registrar import Registration
from host.geometry.track import Track
from host.geometry.transforms import FloatArray, invert_T
from host.station.hub import FrameHub
from host.station.parts import Parts, load_parts, sidecar_path
from host.station.render import ViewInput, ViewRenderer
from host.station.session import MAX_MESSAGE_BYTES, PageSession

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).with_name("static")
CAMERA_FRESH_NS = 1_000_000_000  # poses alone are drawn only when no frame came for this long
PLAN_STEP_MM = 50.0
LATENCY_WINDOW = 512
MJPEG_BOUNDARY = "orbitarframe"
SHUTDOWN_TIMEOUT_S = 1.0  # within the daemon's 2 s SIGTERM budget
SECURITY_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'self'; img-src 'self' blob: data:; connect-src 'self'; "
        "style-src 'self'; script-src 'self'; frame-ancestors 'none'"
    ),
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}
# A commissioning report (host.commissioning.report) is static HTML with its own inline style.
REPORT_HEADERS = {
    **SECURITY_HEADERS,
    "Content-Security-Policy": (
        "default-src 'none'; img-src 'self'; style-src 'unsafe-inline'; frame-ancestors 'none'"
    ),
}
REPORT_RUN = re.compile(r"[0-9A-Za-z][0-9A-Za-z._-]{0,120}")  # report.run_dir's names
REPORT_FILE = re.compile(r"index\.html|results\.json|figure[0-9]{1,3}\.png")
# The runs a page can start: every commissioning op but the two that follow and end them.
RUN_OPS = [
    op for op in COMMISSIONING_OPS if op not in ("commissioning_status", "commissioning_cancel")
]
StatusProvider = Callable[[], Mapping[str, Any]]


class Station:
    """The station's HTTP server, its frame hub and its pages."""

    def __init__(
        self,
        config: Config,
        context: OpContext,
        extra_status: StatusProvider = dict,
        ghost_offset_mm: Callable[[], float | None] = lambda: None,
        hall: Callable[[], list[dict[str, Any]] | None] = lambda: None,
    ) -> None:
        from host.service.wiring import build_track, rig_spec  # wiring imports the daemon, and us

        self.config = config.ui
        self.full_config = config
        self.context = context
        self.extra_status = extra_status
        self.ghost_offset_mm = ghost_offset_mm
        self.hall = hall  # the rigs of the hall on the bus, None without one
        self.track = build_track(config)
        self.parts = load_parts(
            sidecar_path(rig_spec(config).workpiece.model, config.ui.parts_path)
        )
        self.hub = FrameHub(self._renderer(config), config.ui.ghost)
        self.info = station_info(config, self.track, self.parts)
        self.stats = {"pages": 0, "refused": 0, "deadman_stops": 0, "mjpeg_clients": 0}
        self.stats["cut_off"] = 0
        self.latencies_ms: deque[float] = deque(maxlen=LATENCY_WINDOW)
        self.frame_rtt_ms: deque[float] = deque(maxlen=LATENCY_WINDOW)  # frame sent → its ack
        self.port: int | None = None
        # Report links carry this instead of a token: only pages that said hello are told it.
        self.reports_key = secrets.token_urlsafe(18)
        self.sessions: set[PageSession] = set()
        self._last_frame_ns = 0
        self._runner: web.AppRunner | None = None
        self._status_task: asyncio.Task[None] | None = None
        self._streams: set[asyncio.Task[Any]] = set()  # MJPEG handlers, ended at shutdown

    def _renderer(self, config: Config) -> ViewRenderer:
        """The view's drawing from the rig file: camera, model, workpiece pose."""
        from host.service.wiring import build_camera, build_model, workpiece_pose

        model, T_w_p = build_model(config), workpiece_pose(config)
        return ViewRenderer(build_camera(config), model, T_w_p, self.parts, config.ui.jpeg_quality)

    def apply_rig(self, config: Config) -> None:
        """A changed rig file (a calibration wrote it, or SIGHUP): draw with it, tell the pages."""
        from host.service.wiring import build_track

        self.full_config = config
        self.track = build_track(config)
        self.hub.renderer = self._renderer(config)  # the encoder takes it from its next frame
        self.info = station_info(config, self.track, self.parts)
        for session in self.sessions:
            session.push_info(self.info)

    @property
    def url(self) -> str:
        """Where the page is (the address it listens on)."""
        scheme = "https" if self.config.tls_cert else "http"
        host = self.config.host if ":" not in self.config.host else f"[{self.config.host}]"
        return f"{scheme}://{host}:{self.port}/"

    async def start(self) -> None:
        """Listen; OSError when the port is taken."""
        app = web.Application(middlewares=[_security_headers])
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._websocket)
        app.router.add_get("/mjpeg", self._mjpeg)
        app.router.add_get("/frame.jpg", self._snapshot)
        app.router.add_get("/reports/{key}/{run}/{name}", self._report)
        app.router.add_static("/static/", STATIC_DIR, follow_symlinks=False)
        app.on_shutdown.append(self._close_pages)
        self._runner = web.AppRunner(
            app, access_log=None, handle_signals=False, shutdown_timeout=SHUTDOWN_TIMEOUT_S
        )
        await self._runner.setup()
        ui = self.config
        site = web.TCPSite(self._runner, ui.host, ui.port, ssl_context=self._tls())
        await site.start()
        self.port = int(self._runner.addresses[0][1])
        self.hub.start()
        self._status_task = asyncio.create_task(self._status_loop(), name="station-status")
        log.info("operator station listening", extra={"kv": {"url": self.url}})

    async def close(self) -> None:
        """Close every page (their jogs stop) and the listener."""
        if self._status_task is not None:
            self._status_task.cancel()
            await asyncio.gather(self._status_task, return_exceptions=True)
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        await self.hub.close()

    def role_for_token(self, token: Any) -> Role:
        """Operator, viewer or none; empty configured tokens never match."""
        return role_for_token(token, self.config)

    async def dispatch(self, role: Role, op: str, args: Mapping[str, Any]) -> dict[str, Any]:
        """One op as the control socket runs it: {"ok", "result"} or {"ok": false, "error"}.

        The station's one addition is `move_track`: a tapped track position becomes a `move`.
        """
        if op == "move_track":
            if not role.allows(Role.OPERATOR):
                return OpError("forbidden", "'move_track' needs the operator role").reply()
            try:
                op, args = "move", self._track_move_args(args)
            except OpError as exc:
                return exc.reply()
        return await dispatch(self.context, role, op, args)

    def on_registration(self, reg: Registration) -> None:
        """A registered camera frame (frame loop output, event loop)."""
        self._last_frame_ns = time.monotonic_ns()
        T = reg.T_w_c
        ghost = self._ghost(T, reg.s_mm)
        self.hub.submit(ViewInput(reg.index, reg.exposure_ns, reg.frame, T, ghost, reg.s_mm))

    def on_pose(self, sample: PoseSample) -> None:
        """A pose; drawn over a plain background when no camera frame came recently."""
        if time.monotonic_ns() - self._last_frame_ns < CAMERA_FRESH_NS:
            return
        T = np.asarray(sample.T_w_c, dtype=np.float64)
        ghost = self._ghost(T, sample.s_mm)
        self.hub.submit(ViewInput(sample.frame_index, sample.t_ns, None, T, ghost, sample.s_mm))

    async def status(self) -> dict[str, Any]:
        """Everything the status panel shows, through the same ops as `orbitar status`."""
        status = await self.dispatch(Role.VIEWER, "status", {})
        link = await self.dispatch(Role.VIEWER, "link_stats", {})
        return {
            "type": "status",
            "host_ms": time.monotonic_ns() / 1e6,
            "status": status.get("result") or {},
            "link": link.get("result") or {},
            "frames": dict(self.extra_status()),
            "station": self.station_stats(),
            "hall": self.hall(),
            "commissioning": await self.commissioning(),
        }

    async def commissioning(self) -> dict[str, Any]:
        """The current (or last) commissioning run, with a link to its report once written."""
        body = await self.dispatch(Role.VIEWER, "commissioning_status", {})
        if not body["ok"]:
            return {"state": "unavailable", "reason": (body.get("error") or {}).get("message")}
        run = dict(body.get("result") or {})
        result = run.get("result")
        if isinstance(result, dict) and isinstance(result.get("report"), str):
            run["report_url"] = self._report_url(result["report"])
        return run

    def _report_url(self, path: str) -> str | None:
        """The station's address of a report page written under the report root, else None."""
        root = getattr(getattr(self.context, "commissioning", None), "report_root", None)
        if root is None:
            return None
        page = Path(path).resolve()
        if page.parent.parent != Path(root).resolve() or not REPORT_FILE.fullmatch(page.name):
            return None
        return f"/reports/{self.reports_key}/{page.parent.name}/{page.name}"

    def station_stats(self) -> dict[str, Any]:
        """The station's own counters."""
        hub = self.hub.stats
        ordered = sorted(self.latencies_ms)
        return {
            **self.stats,
            "viewers": self.hub.viewer_count,
            "encoded": hub.encoded,
            "encode_fps": round(hub.fps(), 2),
            "encode_dropped": hub.dropped,
            "encode_cpu_ms": round(hub.cpu_ms_mean(), 2),
            "jpeg_ready_ms_p50": _quantile(sorted(hub.ready_ms), 0.5),
            "latency_ms_p50": _quantile(ordered, 0.5),
            "latency_ms_p95": _quantile(ordered, 0.95),
            "frame_rtt_ms_p50": _quantile(sorted(self.frame_rtt_ms), 0.5),
        }

    def _ghost(self, T_w_c: FloatArray | None, s_mm: float | None) -> FloatArray | None:
        """The encoder-only pose: the same view moved back by the drift correction."""
        offset = self.ghost_offset_mm()
        if T_w_c is None or s_mm is None or offset is None or not math.isfinite(s_mm):
            return None
        track = self.track
        if not track.closed and not 0.0 <= s_mm + offset <= track.length_mm:
            return None
        T_w_t = track.pose(s_mm)
        out: FloatArray = track.pose(s_mm + offset) @ invert_T(T_w_t) @ T_w_c
        return out

    def _track_move_args(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """A tapped track position → the controller's target, the short way round a loop."""
        target = args.get("track_s_mm")
        if isinstance(target, bool) or not isinstance(target, int | float):
            raise OpError("bad_args", f"track_s_mm = {target!r}: expected a number")
        if not math.isfinite(target) or not 0 <= target <= self.track.length_mm:
            raise OpError(
                "out_of_range", f"track_s_mm = {target!r}: outside [0, {self.track.length_mm:.1f}]"
            )
        ctrl = self.context.controller
        snap = ctrl.snapshot() if ctrl is not None else {}
        position = snap.get("position_mm")
        stats = ctrl.link_stats() if ctrl is not None else {}
        here = stats.get("track_s_mm")
        from host.service.wiring import rig_spec  # wiring imports the daemon, which imports us

        home = rig_spec(self.full_config).track.home.value
        if not isinstance(position, int | float) or not isinstance(here, int | float):
            position_mm = float(target) - home
        else:
            delta = float(target) - float(here)
            if self.track.closed:
                delta = math.remainder(delta, self.track.length_mm)
            position_mm = float(position) + delta
        out: dict[str, Any] = {"position_mm": round(position_mm, 3)}
        if args.get("speed_mm_s") is not None:
            out["speed_mm_s"] = args["speed_mm_s"]
        return out

    def _tls(self) -> ssl.SSLContext | None:
        """A server TLS context from the configured certificate and key."""
        if not self.config.tls_cert:
            return None
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.load_cert_chain(self.config.tls_cert, self.config.tls_key)
        return context

    async def _status_loop(self) -> None:
        """Push the status to every page at `[ui] status_hz`."""
        period_s = 1.0 / self.config.status_hz
        while True:
            await asyncio.sleep(period_s)
            if not self.sessions:
                continue
            try:
                status = await self.status()
            except Exception:
                log.exception("station status failed")
                continue
            for session in self.sessions:
                session.push_status(status)

    async def _index(self, request: web.Request) -> web.StreamResponse:
        """The page."""
        return web.FileResponse(STATIC_DIR / "index.html")

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        """A page's live connection."""
        # liveness: the page's pings; no permessage-deflate: frames are JPEG, deflating them
        # costs the daemon and the browser CPU for nothing (benchmarks/bench_station.py)
        ws = web.WebSocketResponse(max_msg_size=MAX_MESSAGE_BYTES, compress=False)
        await ws.prepare(request)
        session = PageSession(self, ws)
        self.sessions.add(session)
        self.stats["pages"] += 1
        try:
            await session.run()
        finally:
            self.sessions.discard(session)
            with contextlib.suppress(Exception):
                await ws.close()
        return ws

    def _request_role(self, request: web.Request) -> Role:
        """The role of a plain HTTP request: `?token=` or `Authorization: Bearer`."""
        token = request.query.get("token")
        auth = request.headers.get("Authorization", "")
        if token is None and auth.startswith("Bearer "):
            token = auth[len("Bearer ") :]
        return self.role_for_token(token)

    async def _mjpeg(self, request: web.Request) -> web.StreamResponse:
        """multipart/x-mixed-replace JPEG stream for other tools (newest frame only)."""
        if self._request_role(request) is Role.NONE:
            self.stats["refused"] += 1
            raise web.HTTPUnauthorized(text="unknown token")
        response = web.StreamResponse(
            headers={"Content-Type": f"multipart/x-mixed-replace; boundary={MJPEG_BOUNDARY}"}
        )
        await response.prepare(request)
        ghost = {"1": True, "0": False}.get(request.query.get("ghost", ""))  # else `[ui] ghost`
        slot = self.hub.attach(ghost)
        self.stats["mjpeg_clients"] += 1
        task = asyncio.current_task()
        if task is not None:
            self._streams.add(task)
        try:
            while True:
                frame = await slot.take()
                head = (
                    f"--{MJPEG_BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                    f"Content-Length: {len(frame.jpeg)}\r\n"
                    f"X-Exposure-Ms: {frame.exposure_ns / 1e6:.3f}\r\n\r\n"
                ).encode()
                await response.write(head + frame.jpeg + b"\r\n")
        except ConnectionError:
            pass  # the reader went away (aiohttp's ClientConnectionResetError is one)
        finally:
            self.hub.detach(slot)
            self._streams.discard(task)
        return response

    async def _snapshot(self, request: web.Request) -> web.StreamResponse:
        """The latest JPEG, once."""
        if self._request_role(request) is Role.NONE:
            raise web.HTTPUnauthorized(text="unknown token")
        frame = self.hub.latest
        if frame is None:
            raise web.HTTPServiceUnavailable(text="no frame yet (frames are drawn while watched)")
        return web.Response(body=frame.jpeg, content_type="image/jpeg")

    async def _report(self, request: web.Request) -> web.StreamResponse:
        """A commissioning report's page, figure or results (the key stands for a token)."""
        key, run, name = (request.match_info[k] for k in ("key", "run", "name"))
        if not hmac.compare_digest(key.encode(), self.reports_key.encode()):
            raise web.HTTPNotFound()
        root = getattr(getattr(self.context, "commissioning", None), "report_root", None)
        if root is None or not REPORT_RUN.fullmatch(run) or not REPORT_FILE.fullmatch(name):
            raise web.HTTPNotFound()
        path = Path(root) / run / name
        if not path.is_file():
            raise web.HTTPNotFound()
        return web.FileResponse(path)

    async def _close_pages(self, app: web.Application) -> None:
        """Daemon shutdown: close the pages (each stops its own jog) and the MJPEG streams."""
        for task in list(self._streams):
            task.cancel()
        for session in list(self.sessions):
            with contextlib.suppress(Exception):
                await session.ws.close(code=1001, message=b"daemon stopping")


@web.middleware
async def _security_headers(request: web.Request, handler: Any) -> web.StreamResponse:
    """No third-party anything: the page may load only from this daemon."""
    response: web.StreamResponse = await handler(request)
    if not response.prepared:
        reports = request.path.startswith("/reports/")
        response.headers.update(REPORT_HEADERS if reports else SECURITY_HEADERS)
    return response


def role_for_token(token: Any, ui: UiConfig) -> Role:
    """Operator, viewer or none (constant-time comparison; empty tokens never match)."""
    if not isinstance(token, str) or not token:
        return Role.NONE
    for role, secret in ((Role.OPERATOR, ui.operator_token), (Role.VIEWER, ui.viewer_token)):
        if secret and hmac.compare_digest(token.encode(), secret.encode()):
            return role
    return Role.NONE


def station_info(config: Config, track: Track, parts: Parts) -> dict[str, Any]:
    """What the page needs once: the camera size, the track plan, limits, the parts."""
    from host.service.wiring import build_camera, rig_spec  # wiring imports the daemon, and us

    n = max(2, math.ceil(track.length_mm / PLAN_STEP_MM) + 1)
    s = np.linspace(0.0, track.length_mm, n)
    xy = track.position(s)[:, :2]
    spec = rig_spec(config)
    marks = [
        {"s_mm": m, "xy": [round(float(v), 1) for v in track.position(m)[:2]]}
        for m in spec.track.marks.s_mm
    ]
    head = spec.head
    cam = build_camera(config)  # the calibrated intrinsics: a drag turns the head by its angle
    return {
        "camera": {
            "width": spec.camera.width,
            "height": spec.camera.height,
            **{k: round(float(getattr(cam, k)), 4) for k in ("fx", "fy", "u0", "v0")},
        },
        "ghost": config.ui.ghost,
        "runs": RUN_OPS,
        "coverage_min": dict(MIN_PROGRESS),  # what an intrinsics verdict asks of each bar
        "track": {
            "length_mm": round(track.length_mm, 3),
            "closed": track.closed,
            "home_s_mm": spec.track.home.value,
            "plan_s_mm": [round(float(v), 1) for v in s],
            "plan_xy_mm": [[round(float(x), 1), round(float(y), 1)] for x, y in xy],
            "marks": marks,
        },
        "head_deg": {
            "pan": [math.degrees(head.pan_min_rad), math.degrees(head.pan_max_rad)],
            "tilt": [math.degrees(head.tilt_min_rad), math.degrees(head.tilt_max_rad)],
        },
        "deadman_ms": config.ui.deadman_ms,
        "parts": parts.to_dict(),
    }


def _quantile(ordered: list[float], q: float) -> float | None:
    """A quantile of sorted values (None when empty)."""
    if not ordered:
        return None
    return round(ordered[min(len(ordered) - 1, int(q * len(ordered)))], 2)
