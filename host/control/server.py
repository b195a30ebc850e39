"""The control socket server: Unix socket (operator) and optional TCP with tokens (docs/CONTROL.md).

Every client has a writer task fed by two queues: replies, which are never dropped, and events,
a bounded deque that drops the oldest event when the client reads too slowly. `publish` only
appends to deques, so the frame loop that calls it never waits on a client. Requests run as
tasks of their own, so a `stop` is not queued behind a long `home`.

Nothing a client does may exhaust the daemon: a client whose replies pile up is not read until
they drain (its own sends then block in the kernel) and is cut off when they pass
`client_buffer_kb` or do not drain within `stall_timeout_s`; each listener has its own cap on
connections, so a TCP flood never takes the operator's Unix-socket slots; unauthenticated and
idle connections time out; failed hellos are throttled and logged a bounded number of times.
"""

from __future__ import annotations

import asyncio
import contextlib
import grp
import hmac
import logging
import os
import shutil
import socket
import stat
import time
from collections import deque
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from host.config import MIN_TOKEN_CHARS, ControlConfig
from host.control.limits import ThrottledLog, TokenBucket, ensure_fd_room
from host.control.ops import SAFETY_OPS, OpContext, OpError, Role, dispatch
from host.control.wire import WireError, error_reply, pack, read_message

__all__ = ["ClientConnection", "ControlServer", "ControlServerError", "Role"]

log = logging.getLogger(__name__)

TOPICS = ("pose", "state", "link")
MAX_INFLIGHT_PER_CLIENT = 16  # ordinary requests; stop and estop are not counted
MAX_SAFETY_INFLIGHT = 64  # beyond this many stops in flight the next one waits for a slot
FLUSH_TIMEOUT_S = 1.0
REQUEST_GRACE_S = 5.0
# asyncio accepts up to `backlog` connections in one go before any of them is refused, so the
# backlog bounds the descriptors a connection flood holds beyond the caps.
BACKLOG = 16
MAX_HELLO_FAILURES = 3  # per connection, then it is closed
HELLO_FAILURE_BURST = 20.0  # failed hellos tolerated at once over all connections …
HELLO_FAILURE_RATE_PER_S = 2.0  # … and refilled at this rate; beyond, the connection is closed


class ControlServerError(RuntimeError):
    """The control socket cannot be set up (path in use, unknown group, …)."""


class ClientConnection:
    """One connected client: its role, subscriptions, outgoing queues and limits."""

    def __init__(
        self,
        server: ControlServer,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        role: Role,
        listener: str,
    ) -> None:
        self.server = server
        self.role = role
        self.listener = listener  # "unix" or "tcp"
        self.peer = str(writer.get_extra_info("peername") or listener)
        self.topics: set[str] = set()
        self.dropped_total = 0
        self._dropped_unreported = 0
        self._reader = reader
        self._writer = writer
        self._replies: deque[bytes] = deque()  # encoded, so their size is known
        self._reply_bytes = 0
        self._events: deque[dict[str, Any]] = deque(maxlen=server.queue_max)
        self._wake = asyncio.Event()
        self._room = asyncio.Event()  # set whenever the output backlog is below the resume mark
        self._closing = False
        self._aborted = False
        self._ended = False
        self._read_task: asyncio.Task[None] | None = None
        self._requests: set[asyncio.Task[None]] = set()
        self._ordinary = 0  # requests in flight that count against the cap
        self._safety = 0
        self._hello_failures = 0
        self._close_after_reply = False
        self._shutdown = False
        self._t_connect = self._last_rx = time.monotonic()
        limit = server.config.client_buffer_kb * 1024
        self._limit_bytes = limit
        self._pause_bytes = limit // 8  # stop reading requests above this backlog …
        self._resume_bytes = limit // 16  # … until it is below this
        # drain() then waits whenever the kernel-side buffer alone passes the resume mark, so an
        # idle writer always leaves the backlog below it and a paused reader is always woken.
        writer.transport.set_write_buffer_limits(self._resume_bytes, self._resume_bytes // 4)

    def publish(self, event: dict[str, Any]) -> None:
        """Queue an event; a full queue drops its oldest entry and counts it."""
        if self._ended:
            return
        if len(self._events) == self._events.maxlen:
            self.dropped_total += 1
            self._dropped_unreported += 1
            self.server.stats["events_dropped"] += 1
        self._events.append(event)
        self._wake.set()

    def reply(self, message: dict[str, Any]) -> None:
        """Queue a reply (never dropped while the client is connected and reading)."""
        if self._aborted:
            return
        data = self._encode(message)
        self._replies.append(data)
        self._reply_bytes += len(data)
        self._wake.set()
        if self.backlog_bytes() > self._limit_bytes:
            self.end("overrun", f"over {self._limit_bytes} bytes of replies unread", abort=True)

    def backlog_bytes(self) -> int:
        """Bytes queued for this client and not yet taken by the kernel."""
        return self._writer.transport.get_write_buffer_size() + self._reply_bytes

    async def serve(self) -> None:
        """Read requests until the peer leaves, something unrecoverable arrives, or end()."""
        writer_task = asyncio.create_task(self._write_loop())
        watch_task = asyncio.create_task(self._watch_timeouts())
        self._read_task = asyncio.create_task(self._read_loop())
        try:
            await asyncio.wait({self._read_task})
            await self._finish_requests()
            self._closing = True
            self._wake.set()
            if not self._aborted:
                with contextlib.suppress(TimeoutError, ConnectionError, OSError):
                    await asyncio.wait_for(asyncio.shield(writer_task), FLUSH_TIMEOUT_S)
        finally:
            for task in [self._read_task, watch_task, writer_task, *self._requests]:
                task.cancel()
            await asyncio.gather(
                self._read_task, watch_task, writer_task, *self._requests, return_exceptions=True
            )
            self._hang_up()

    def abort(self) -> None:
        """Hang up now (daemon shutdown): requests in flight are cancelled, not awaited."""
        self._shutdown = self._aborted = True
        self._hang_up()
        if self._read_task is not None:
            self._read_task.cancel()  # it may be waiting for output room, not for the peer

    def _hang_up(self) -> None:
        """Close; with bytes still unsent, abort, since a close would wait on them for ever."""
        if self._writer.transport.get_write_buffer_size():
            self._writer.transport.abort()
        else:
            self._writer.close()

    def end(self, code: str, message: str, abort: bool = False) -> None:
        """Cut this client off: tell it why (unless it does not read anyway) and stop reading."""
        if self._ended:
            return
        self._ended = True
        self.server.stats["cut_off"] += 1
        self.server.throttled.warning(
            f"cut:{code}", "control client cut off", code=code, reason=message, peer=self.peer
        )
        if abort:
            self._aborted = True
            self._replies.clear()
            self._reply_bytes = 0
            self._writer.transport.abort()  # drop what it never read: the memory comes back now
        else:
            self._replies.append(self._encode(error_reply(None, code, message)))
            self._wake.set()
        self._room.set()
        if self._read_task is not None:
            self._read_task.cancel()

    async def _finish_requests(self) -> None:
        """Let requests in flight finish (an estop sent just before hanging up still counts)."""
        if self._requests and not self._shutdown:
            await asyncio.wait(set(self._requests), timeout=REQUEST_GRACE_S)

    async def _read_loop(self) -> None:
        """Parse messages and start a task per request, while the client reads its replies."""
        while await self._output_room():
            try:
                message = await read_message(self._reader)
            except WireError as exc:
                self.server.stats["bad_requests"] += 1
                self.reply(error_reply(None, exc.code, str(exc)))
                if exc.fatal:
                    return
                continue
            except (ConnectionError, OSError):
                return
            if message is None:
                return
            self._last_rx = time.monotonic()
            await self._start_request(message)
            await asyncio.sleep(0)  # its first step (the frame to the controller) goes first

    async def _output_room(self) -> bool:
        """Wait while the backlog is over the pause mark; cut off a client that stays stalled."""
        if self._ended:
            return False
        if self.backlog_bytes() <= self._pause_bytes:
            return True
        self.server.stats["read_pauses"] += 1
        stall_s = self.server.config.stall_timeout_s
        deadline = time.monotonic() + stall_s
        while self.backlog_bytes() > self._resume_bytes and not self._ended:
            self._room.clear()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                text = f"{self.backlog_bytes()} bytes of replies not read within {stall_s} s"
                self.end("stalled", text, abort=True)
                break
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._room.wait(), remaining)
        return not self._ended

    async def _start_request(self, message: dict[str, Any]) -> None:
        """Run one request as its own task; stop and estop bypass the in-flight cap."""
        op = message.get("op")
        safety = isinstance(op, str) and op in SAFETY_OPS and self.role is not Role.NONE
        if safety:
            while self._safety >= MAX_SAFETY_INFLIGHT:  # stops in flight are already stopping it
                await asyncio.wait(set(self._requests), return_when="FIRST_COMPLETED")
        elif self._ordinary >= MAX_INFLIGHT_PER_CLIENT:
            text = f"{MAX_INFLIGHT_PER_CLIENT} requests already in flight"
            self.reply(error_reply(message.get("id"), "busy", text))
            return
        task = asyncio.create_task(self._handle(message))
        self._requests.add(task)
        if safety:
            self._safety += 1
        else:
            self._ordinary += 1
        task.add_done_callback(lambda t: self._request_done(t, safety))

    def _request_done(self, task: asyncio.Task[None], safety: bool) -> None:
        """Free the request's slot."""
        self._requests.discard(task)
        if safety:
            self._safety -= 1
        else:
            self._ordinary -= 1

    async def _handle(self, message: dict[str, Any]) -> None:
        """Dispatch a request and queue its reply."""
        request_id = message.get("id")
        op, args = message.get("op"), message.get("args", {})
        if "id" not in message or not isinstance(op, str) or not isinstance(args, dict):
            body = OpError("bad_request", 'a request needs "id", a string "op", a map "args"')
            self._answer(request_id, body.reply())
            return
        if op == "hello":
            self._answer(request_id, self._hello(args))
            if self._close_after_reply:
                self.end("unauthorized", "too many failed hellos; connection closed")
        elif op in ("subscribe", "unsubscribe") and self.role is not Role.NONE:
            self._answer(request_id, self._subscription(op, args))
        else:
            self.server.stats["requests"] += 1
            self._answer(request_id, await dispatch(self.server.context, self.role, op, args))

    def _answer(self, request_id: Any, body: dict[str, Any]) -> None:
        """Queue a reply body under the request's id."""
        if not body.get("ok"):
            self.server.stats["errors"] += 1
        self.reply({"id": request_id, **body})

    def _hello(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Authenticate a TCP client by token; on the Unix socket it just reports the role."""
        if self.listener == "tcp":
            role = self.server.role_for_token(args.get("token"))
            if role is Role.NONE:
                return self._failed_hello()
            self.role = role
        return {"ok": True, "result": {"role": self.role.value, "topics": list(TOPICS)}}

    def _failed_hello(self) -> dict[str, Any]:
        """Count, log (throttled) and, past the limits, close after the reply."""
        self._hello_failures += 1
        self.server.stats["hello_failures"] += 1
        allowed = self.server.hello_failures.take()
        self.server.throttled.warning("hello", "failed hello on the control socket", peer=self.peer)
        self._close_after_reply = self._hello_failures >= MAX_HELLO_FAILURES or not allowed
        return OpError("unauthorized", "unknown token").reply()

    def _subscription(self, op: str, args: Mapping[str, Any]) -> dict[str, Any]:
        """Add or remove topics."""
        topics = args.get("topics")
        if not isinstance(topics, list) or not all(t in TOPICS for t in topics):
            text = f"topics must be a list drawn from {list(TOPICS)}"
            return OpError("bad_args", text).reply()
        if op == "subscribe":
            self.topics.update(topics)
        else:
            self.topics.difference_update(topics)
        result = {"topics": sorted(self.topics), "dropped": self.dropped_total}
        return {"ok": True, "result": result}

    async def _watch_timeouts(self) -> None:
        """Cut off a TCP client that never says hello, and any client idle for too long."""
        cfg = self.server.config
        period_s = min(max(min(cfg.hello_timeout_s, cfg.idle_timeout_s) / 4, 0.05), 5.0)
        while not self._ended:
            await asyncio.sleep(period_s)
            now = time.monotonic()
            if self.role is Role.NONE and now - self._t_connect >= cfg.hello_timeout_s:
                text = f"no successful hello within {cfg.hello_timeout_s} s"
                self.end("timeout", text + " (control.hello_timeout_s)")
            quiet = not self.topics and not self._requests
            if quiet and now - self._last_rx >= cfg.idle_timeout_s:
                text = f"no request and no subscription for {cfg.idle_timeout_s} s"
                self.end("timeout", text + " (control.idle_timeout_s)")

    async def _write_loop(self) -> None:
        """Send replies first, then events, then any drop report."""
        while True:
            await self._wake.wait()
            self._wake.clear()
            while (data := self._next_bytes()) is not None:
                self._writer.write(data)
                await self._writer.drain()
                if self.backlog_bytes() <= self._resume_bytes:
                    self._room.set()
            self._room.set()
            if self._closing:
                return

    def _next_bytes(self) -> bytes | None:
        """The next outgoing message by priority, encoded; None when there is nothing to send."""
        if self._replies:
            data = self._replies.popleft()
            self._reply_bytes -= len(data)
            return data
        if self._dropped_unreported:
            count, self._dropped_unreported = self._dropped_unreported, 0
            report = {"dropped": count, "total": self.dropped_total}
            return self._encode({"topic": "overflow", "data": report})
        if self._events:
            return self._encode(self._events.popleft())
        return None

    @staticmethod
    def _encode(message: dict[str, Any]) -> bytes:
        """Frame a message; a result too big to send becomes an error reply."""
        try:
            return pack(message)
        except (ValueError, TypeError) as exc:
            return pack(error_reply(message.get("id"), "too_large", str(exc)))


class ControlServer:
    """Serves the control protocol on a Unix socket and, optionally, on TCP."""

    def __init__(self, context: OpContext, config: ControlConfig) -> None:
        self.context = context
        self.config = config
        self.queue_max = config.queue_max
        self.stats = dict.fromkeys(
            ("connections", "requests", "errors", "bad_requests", "events_dropped"), 0
        )
        self.stats.update(refused=0, cut_off=0, hello_failures=0, read_pauses=0)
        context.control_stats = lambda: self.stats  # `status` shows refusals and cut-offs
        self.tcp_port: int | None = None
        self.throttled = ThrottledLog(log)
        self.hello_failures = TokenBucket(HELLO_FAILURE_BURST, HELLO_FAILURE_RATE_PER_S)
        self._clients: dict[ClientConnection, asyncio.Task[Any] | None] = {}
        self._servers: list[asyncio.Server] = []
        self._closed = False

    @property
    def client_count(self) -> int:
        """Clients connected now."""
        return len(self._clients)

    async def start(self) -> None:
        """Bind the Unix socket (and TCP if enabled)."""
        self._check_tokens()
        path = Path(self.config.socket_path)
        _clear_stale_socket(path)
        unix = await asyncio.start_unix_server(self._on_unix, path=str(path), backlog=BACKLOG)
        self._servers.append(unix)
        _set_permissions(path, self.config.socket_mode, self.config.socket_group)
        caps = self.config.max_unix_connections + BACKLOG
        if self.config.tcp_enabled:
            tcp = await asyncio.start_server(
                self._on_tcp, self.config.tcp_host, self.config.tcp_port, backlog=BACKLOG
            )
            self._servers.append(tcp)
            self.tcp_port = int(tcp.sockets[0].getsockname()[1])
            caps += self.config.max_tcp_connections + BACKLOG
        soft, wanted = ensure_fd_room(caps)
        if soft < wanted:
            kv = {"nofile": soft, "wanted": wanted}
            log.warning("open-file limit below the connection caps", extra={"kv": kv})
        log.info("control socket listening", extra={"kv": {"path": path, "tcp": self.tcp_port}})

    async def close(self) -> None:
        """Stop listening and disconnect every client."""
        self._closed = True
        for server in self._servers:
            server.close()
        for client in list(self._clients):
            client.abort()
        tasks = [t for t in self._clients.values() if t is not None]
        if tasks:
            _, stuck = await asyncio.wait(tasks, timeout=FLUSH_TIMEOUT_S)
            for task in stuck:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        for server in self._servers:
            await server.wait_closed()
        self._servers.clear()
        with contextlib.suppress(FileNotFoundError):
            Path(self.config.socket_path).unlink()

    def publish(self, topic: str, data: Any) -> None:
        """Send an event to every subscriber of `topic` without waiting."""
        event = {"topic": topic, "data": data}
        for client in self._clients:
            if topic in client.topics:
                client.publish(event)

    def role_for_token(self, token: Any) -> Role:
        """Operator, viewer or none; empty configured tokens never match."""
        if not isinstance(token, str) or not token:
            return Role.NONE
        for role, secret in (
            (Role.OPERATOR, self.config.operator_token),
            (Role.VIEWER, self.config.viewer_token),
        ):
            if secret and hmac.compare_digest(token.encode(), secret.encode()):
                return role
        return Role.NONE

    def connections(self, listener: str) -> int:
        """Clients connected now on one listener ("unix" or "tcp")."""
        return sum(1 for c in self._clients if c.listener == listener)

    def _check_tokens(self) -> None:
        """Refuse tokens short enough to guess (config check says the same, naming the key)."""
        for key in ("operator_token", "viewer_token"):
            if 0 < (n := len(getattr(self.config, key))) < MIN_TOKEN_CHARS:
                text = f"control.{key}: {n} characters, need {MIN_TOKEN_CHARS} or more"
                raise ControlServerError(text)

    async def _on_unix(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """A Unix-socket client: file permissions already vouched for it."""
        cap = self.config.max_unix_connections
        if self._admit(writer, "unix", cap, "control.max_unix_connections"):
            await self._serve(ClientConnection(self, reader, writer, Role.OPERATOR, "unix"))

    async def _on_tcp(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """A TCP client: nothing but hello until it shows a token."""
        cap = self.config.max_tcp_connections
        if self._admit(writer, "tcp", cap, "control.max_tcp_connections"):
            await self._serve(ClientConnection(self, reader, writer, Role.NONE, "tcp"))

    def _admit(self, writer: asyncio.StreamWriter, listener: str, cap: int, key: str) -> bool:
        """Below the listener's cap: True; else tell the client why, hang up and return False."""
        if self.connections(listener) < cap and not self._closed:
            return True
        self.stats["refused"] += 1
        text = f"{cap} clients already connected on {listener} ({key})"
        self.throttled.warning(f"refused:{listener}", "control client refused", reason=text)
        with contextlib.suppress(ConnectionError, OSError):
            writer.write(pack(error_reply(None, "too_many_clients", text)))
        writer.close()
        return False

    async def _serve(self, client: ClientConnection) -> None:
        """Track a client for its lifetime."""
        self.stats["connections"] += 1
        self._clients[client] = asyncio.current_task()
        try:
            await client.serve()
        except asyncio.CancelledError:
            pass  # only close() cancels a client, and asyncio.streams logs a cancelled handler
        except Exception as exc:  # a bug must cost one client and a few log lines, not the daemon
            self.throttled.warning("client_error", "control client failed", error=repr(exc))
        finally:
            self._clients.pop(client, None)


def _clear_stale_socket(path: Path) -> None:
    """Remove a socket file left by a crashed daemon; refuse if a live one answers."""
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        return
    if not stat.S_ISSOCK(path.stat().st_mode):
        raise ControlServerError(f"{path}: exists and is not a socket")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.connect(str(path))
    except OSError:
        path.unlink()
        return
    finally:
        probe.close()
    raise ControlServerError(f"{path}: another daemon is listening there")


def _set_permissions(path: Path, mode: int, group: str) -> None:
    """chmod the socket, and chgrp it when a group is configured."""
    os.chmod(path, mode)
    if not group:
        return
    try:
        grp.getgrnam(group)
        shutil.chown(path, group=group)
    except (KeyError, LookupError, PermissionError) as exc:
        raise ControlServerError(f"{path}: cannot give it to group {group!r}: {exc}") from exc
