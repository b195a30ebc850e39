"""One page on one WebSocket: its role, its requests, its frames, and the jog dead-man.

Messages from the page are JSON: `hello` (the token, first), `op` (a control operation, run
as for the control socket, through `Station.dispatch`), `hold` (the jog dead-man's
heartbeat), `ack` (the page decoded a frame: send the next), `ping` (clock offset), `view`
(this page's view choices: the ghost on or off; not an operation, it moves nothing). To the page:
JSON replies and status, and binary frames: a 4-byte big-endian header length, a JSON header
(index, exposure time, feature points in view) and the JPEG.

One writer task sends, replies first, then the newest status, then the newest frame once the
previous one is acknowledged: a slow page receives fewer frames, never an older one, and holds
no queue. A jog from this page runs only while hold messages arrive: when they pause for the
dead-man time, or the WebSocket closes, the station stops the trolley.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import struct
import time
from collections import deque
from typing import TYPE_CHECKING, Any

from aiohttp import WSMsgType, web

from host.control.ops import Role
from host.station.hub import ViewerSlot
from host.station.render import EncodedView

if TYPE_CHECKING:
    from host.station.server import Station

log = logging.getLogger(__name__)

HELLO_TIMEOUT_S = 5.0
SILENCE_TIMEOUT_S = 10.0  # pages ping every 2 s: a silent one is gone (no FIN on a dead network)
ACK_TIMEOUT_S = 1.0  # a page that never acknowledges still gets a frame a second
MAX_MESSAGE_BYTES = 64 * 1024
CLOSE_UNAUTHORIZED = 4401  # application close code: bad or missing token
MAX_INFLIGHT = 16  # requests running for one page (STOP and E-STOP are never refused)
MAX_UNSENT_REPLIES = 256  # a page that sends but never reads is cut off, not buffered for
STOPPING_OPS = frozenset({"stop", "estop"})
# Requests that replace a jog once they succeed (the head turns independently of the trolley).
REPLACING_OPS = frozenset({"jog", "move", "move_track", "home", *STOPPING_OPS})


def frame_message(frame: EncodedView, sent_ns: int) -> bytes:
    """The binary frame message: header length, JSON header, JPEG."""
    header = json.dumps(
        {
            "index": frame.index,
            "exposure_ms": frame.exposure_ns / 1e6,
            "sent_ms": sent_ns / 1e6,
            "age_at_send_ms": round((sent_ns - frame.exposure_ns) / 1e6, 2),
            "width": frame.width,
            "height": frame.height,
            "registered": frame.registered,
            "ghost": frame.ghost,
            "points": frame.points_uv,
        }
    ).encode()
    return struct.pack(">I", len(header)) + header + frame.jpeg


class PageSession:
    """Serves one connected page."""

    def __init__(self, station: Station, ws: web.WebSocketResponse) -> None:
        self.station = station
        self.ws = ws
        self.role = Role.NONE
        self.jogging = False  # the dead-man is armed
        self._motion_seq = 0  # motion requests so far: only the newest may disarm
        self.last_hold_s = 0.0
        self.last_heard_s = time.monotonic()
        self.deadman_stops = 0
        self.frames_sent = 0
        self._replies: deque[dict[str, Any]] = deque()
        self._status: dict[str, Any] | None = None
        self._slot: ViewerSlot | None = None
        self._awaiting_ack = False
        self._sent_at_s = 0.0
        self._wake = asyncio.Event()
        self._tasks: set[asyncio.Task[Any]] = set()
        self._closer: asyncio.Task[None] | None = None

    async def run(self) -> None:
        """Authenticate, then serve until the page goes; a jog in progress is stopped."""
        if not await self._hello():
            return
        self._slot = self.station.hub.attach()
        self._slot.on_offer = self._wake.set
        writer = asyncio.create_task(self._write_loop())
        deadman = asyncio.create_task(self._deadman_loop())
        try:
            await self._read_loop()
        finally:
            writer.cancel()
            deadman.cancel()
            self.station.hub.detach(self._slot)
            if self.jogging:
                await self._deadman_stop("page disconnected")
            closer = [self._closer] if self._closer is not None else []
            await asyncio.gather(writer, deadman, *self._tasks, *closer, return_exceptions=True)

    def push_info(self, info: dict[str, Any]) -> None:
        """The rig changed: what the page was told at hello, again (never dropped)."""
        self._reply({"type": "info", **info})

    def push_status(self, status: dict[str, Any]) -> None:
        """The newest status replaces one not yet sent."""
        self._status = status
        self._wake.set()

    async def _hello(self) -> bool:
        """The first message must carry a known token; otherwise close with 4401."""
        try:
            msg = await self.ws.receive(timeout=HELLO_TIMEOUT_S)
            data = json.loads(msg.data) if msg.type is WSMsgType.TEXT else None
        except (TimeoutError, ValueError):
            data = None
        hello = isinstance(data, dict) and data.get("type") == "hello"
        token = data.get("token") if hello and isinstance(data, dict) else None
        self.role = self.station.role_for_token(token)
        if self.role is Role.NONE:
            self.station.stats["refused"] += 1
            with contextlib.suppress(ConnectionError, RuntimeError):
                await self.ws.send_json({"type": "error", "code": "unauthorized"})
                await self.ws.close(code=CLOSE_UNAUTHORIZED, message=b"unknown token")
            return False
        try:
            await self.ws.send_json({"type": "hello", "role": self.role.value, **self.station.info})
        except ConnectionError:  # the page left while we answered
            return False
        return True

    async def _read_loop(self) -> None:
        """Handle the page's messages until it closes."""
        async for msg in self.ws:
            self.last_heard_s = time.monotonic()
            if msg.type is not WSMsgType.TEXT:
                continue
            try:
                data = json.loads(msg.data)
            except ValueError:
                self._reply({"type": "error", "code": "bad_request", "message": "not JSON"})
                continue
            if isinstance(data, dict):
                self._handle(data)

    def _handle(self, data: dict[str, Any]) -> None:
        """Dispatch one message by type."""
        kind = data.get("type")
        if kind == "hold":
            self.last_hold_s = time.monotonic()
        elif kind == "ack":
            self._on_ack(data)
        elif kind == "ping":
            self._reply({"type": "pong", "t": data.get("t"), "host_ms": time.monotonic_ns() / 1e6})
        elif kind == "op":
            self._start_op(data)
        elif kind == "view":
            self._on_view(data)
        else:
            self._reply({"type": "error", "code": "bad_request", "message": f"type {kind!r}"})

    def _start_op(self, data: dict[str, Any]) -> None:
        """Run an op as its own task, so a STOP never waits behind a slow request."""
        op, args = data.get("op"), data.get("args", {})
        if not isinstance(op, str) or not isinstance(args, dict):
            self._reply({"type": "reply", "id": data.get("id"), "ok": False, "code": "bad_request"})
            return
        if len(self._tasks) >= MAX_INFLIGHT and op not in STOPPING_OPS:
            self._reply({"type": "reply", "id": data.get("id"), "op": op, "ok": False,
                         "code": "busy", "message": "too many requests in flight"})  # fmt: skip
            return
        motion_seq = self._motion_seq
        if op in REPLACING_OPS:
            self._motion_seq = motion_seq = motion_seq + 1
            velocity = args.get("velocity_mm_s")
            if op == "jog" and self.role is Role.OPERATOR and velocity != 0:
                # Armed with the request, not its acknowledgement; only a success disarms.
                self.jogging = True
                self.last_hold_s = time.monotonic()
        task = asyncio.create_task(self._op(data.get("id"), op, args, motion_seq))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _op(self, request_id: Any, op: str, args: dict[str, Any], motion_seq: int) -> None:
        """Run one op and queue its reply; a jog-ending success disarms the dead-man."""
        body = await self.station.dispatch(self.role, op, args)
        reply: dict[str, Any] = {"type": "reply", "id": request_id, "op": op, "ok": body["ok"]}
        if body["ok"]:
            reply["result"] = body.get("result")
        else:
            error = body.get("error") or {}
            reply.update(code=error.get("code"), message=error.get("message"))
        ends_jog = op != "jog" or args.get("velocity_mm_s") == 0
        if body["ok"] and op in REPLACING_OPS and ends_jog and motion_seq == self._motion_seq:
            self.jogging = False  # a failure keeps it armed: a needless STOP is harmless
        self._reply(reply)

    def _reply(self, message: dict[str, Any]) -> None:
        """Queue a message that is never dropped; a page that does not read them is cut off."""
        if len(self._replies) >= MAX_UNSENT_REPLIES:
            self.station.stats["cut_off"] += 1
            self._replies.clear()
            if self._closer is None:
                self._closer = asyncio.create_task(self._cut_off())
            return
        self._replies.append(message)
        self._wake.set()

    async def _cut_off(self) -> None:
        """Close a page that does not read what it asked for."""
        log.warning("station page cut off: it does not read its replies")
        await self.ws.close(code=1008, message=b"replies not read")

    def _on_view(self, data: dict[str, Any]) -> None:
        """The page's choice of what its frames show (any role: it changes only this page)."""
        ghost = data.get("ghost")
        if not isinstance(ghost, bool) or self._slot is None:
            self._reply({"type": "error", "code": "bad_request", "message": "view: ghost = bool"})
            return
        self._slot.ghost = ghost
        self._reply({"type": "view", "ghost": ghost})

    def _on_ack(self, data: dict[str, Any]) -> None:
        """The page has drawn the frame: record its latency, allow the next."""
        if self._awaiting_ack:
            self.station.frame_rtt_ms.append((time.monotonic() - self._sent_at_s) * 1e3)
        self._awaiting_ack = False
        latency = data.get("latency_ms")
        if isinstance(latency, int | float) and 0 <= latency < 60_000:
            self.station.latencies_ms.append(float(latency))
        self._wake.set()

    async def _deadman_loop(self) -> None:
        """Stop a jog whose hold messages have paused for the dead-man time; drop silent pages."""
        limit_s = self.station.config.deadman_ms / 1000.0
        while True:
            await asyncio.sleep(limit_s / 5)
            now = time.monotonic()
            if self.jogging and now - self.last_hold_s > limit_s:
                await self._deadman_stop("hold messages stopped")
            if now - self.last_heard_s > SILENCE_TIMEOUT_S:
                await self.ws.close(code=1001, message=b"page silent")
                return

    async def _deadman_stop(self, why: str) -> None:
        """Stop the trolley on the page's behalf."""
        self.jogging = False
        self.deadman_stops += 1
        self.station.stats["deadman_stops"] += 1
        log.warning("station dead-man: stopping the jog", extra={"kv": {"why": why}})
        body = await self.station.dispatch(Role.OPERATOR, "stop", {})
        if not body["ok"]:  # the firmware's own watchdog is the next line of defence
            log.error("dead-man stop failed", extra={"kv": {"error": body.get("error")}})
        self._reply({"type": "deadman", "why": why})

    async def _write_loop(self) -> None:
        """Replies, then status, then a frame once the last one was acknowledged."""
        while True:
            timeout = None
            if self._awaiting_ack:
                timeout = max(0.0, self._sent_at_s + ACK_TIMEOUT_S - time.monotonic())
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), timeout)
            self._wake.clear()
            if self._awaiting_ack and time.monotonic() - self._sent_at_s >= ACK_TIMEOUT_S:
                self._awaiting_ack = False
            await self._flush()

    async def _flush(self) -> None:
        """Send everything that may go now."""
        while True:
            if self._replies:
                message = self._replies.popleft()
                if message.get("type") == "pong":  # its time in this queue is not network delay
                    message["sent_ms"] = time.monotonic_ns() / 1e6
                await self.ws.send_json(message)
            elif self._status is not None:
                status, self._status = self._status, None
                await self.ws.send_json(status)
            elif not self._awaiting_ack and self._slot is not None and self._slot.frame:
                frame, self._slot.frame = self._slot.frame, None
                self._awaiting_ack = True
                self._sent_at_s = time.monotonic()
                await self.ws.send_bytes(frame_message(frame, time.monotonic_ns()))
                self.frames_sent += 1
            else:
                return
