"""The control socket server: Unix socket (operator) and optional TCP with tokens (docs/CONTROL.md).

Every client has a writer task fed by two queues: replies, which are never dropped, and events,
a bounded deque that drops the oldest event when the client reads too slowly. `publish` only
appends to deques, so the frame loop that calls it never waits on a client. Requests run as
tasks of their own, so a `stop` is not queued behind a long `home`.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import grp
import hmac
import logging
import os
import shutil
import socket
import stat
from collections import deque
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from host.config import ControlConfig
from host.control.ops import OPS, OpContext, OpError
from host.control.wire import WireError, error_reply, ok_reply, pack, read_message

log = logging.getLogger(__name__)

TOPICS = ("pose", "state", "link")
MAX_INFLIGHT_PER_CLIENT = 16
FLUSH_TIMEOUT_S = 1.0
REQUEST_GRACE_S = 5.0


class Role(enum.Enum):
    """What a client may do."""

    NONE = "none"  # TCP client before a successful hello
    VIEWER = "viewer"  # read-only ops and subscriptions
    OPERATOR = "operator"  # everything, motion included


class ControlServerError(RuntimeError):
    """The control socket cannot be set up (path in use, unknown group, …)."""


class ClientConnection:
    """One connected client: its role, subscriptions and outgoing queues."""

    def __init__(
        self,
        server: ControlServer,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        role: Role,
    ) -> None:
        self.server = server
        self.role = role
        self.topics: set[str] = set()
        self.dropped_total = 0
        self._dropped_unreported = 0
        self._reader = reader
        self._writer = writer
        self._replies: deque[dict[str, Any]] = deque()
        self._events: deque[dict[str, Any]] = deque(maxlen=server.queue_max)
        self._wake = asyncio.Event()
        self._closing = False
        self._aborted = False
        self._requests: set[asyncio.Task[None]] = set()

    def publish(self, event: dict[str, Any]) -> None:
        """Queue an event; a full queue drops its oldest entry and counts it."""
        if len(self._events) == self._events.maxlen:
            self.dropped_total += 1
            self._dropped_unreported += 1
            self.server.stats["events_dropped"] += 1
        self._events.append(event)
        self._wake.set()

    def reply(self, message: dict[str, Any]) -> None:
        """Queue a reply (never dropped)."""
        self._replies.append(message)
        self._wake.set()

    async def serve(self) -> None:
        """Read requests until the peer leaves, something unrecoverable arrives, or abort()."""
        writer_task = asyncio.create_task(self._write_loop())
        try:
            await self._read_loop()
            await self._finish_requests()
            self._closing = True
            self._wake.set()
            with contextlib.suppress(TimeoutError, ConnectionError, OSError):
                await asyncio.wait_for(asyncio.shield(writer_task), FLUSH_TIMEOUT_S)
        finally:
            for task in [writer_task, *self._requests]:
                task.cancel()
            await asyncio.gather(writer_task, *self._requests, return_exceptions=True)
            self._writer.close()

    def abort(self) -> None:
        """Hang up now (daemon shutdown): requests in flight are cancelled, not awaited."""
        self._aborted = True
        self._writer.close()

    async def _finish_requests(self) -> None:
        """Let requests in flight finish (an estop sent just before hanging up still counts)."""
        if self._requests and not self._aborted:
            await asyncio.wait(set(self._requests), timeout=REQUEST_GRACE_S)

    async def _read_loop(self) -> None:
        """Parse messages and start a task per request."""
        while True:
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
            self._start_request(message)

    def _start_request(self, message: dict[str, Any]) -> None:
        """Run one request as its own task, within the in-flight limit."""
        if len(self._requests) >= MAX_INFLIGHT_PER_CLIENT:
            self.reply(error_reply(message.get("id"), "busy", "too many requests in flight"))
            return
        task = asyncio.create_task(self._handle(message))
        self._requests.add(task)
        task.add_done_callback(self._requests.discard)

    async def _handle(self, message: dict[str, Any]) -> None:
        """Dispatch a request and queue its reply."""
        request_id = message.get("id")
        try:
            result = await self._dispatch(message)
        except OpError as exc:
            self.server.stats["errors"] += 1
            self.reply(error_reply(request_id, exc.code, str(exc)))
            return
        except Exception as exc:  # a controller failure must not take the connection down
            self.server.stats["errors"] += 1
            text = f"{type(exc).__name__}: {exc}"
            self.reply(error_reply(request_id, "failed", text))
            return
        self.reply(ok_reply(request_id, result))

    async def _dispatch(self, message: dict[str, Any]) -> Any:
        """Check the envelope and the role, then run the op."""
        op, args = message.get("op"), message.get("args", {})
        if "id" not in message or not isinstance(op, str) or not isinstance(args, dict):
            raise OpError("bad_request", 'a request needs "id", a string "op" and a map "args"')
        if op == "hello":
            return self._hello(args)
        if self.role is Role.NONE:
            raise OpError("unauthorized", 'send "hello" with a token first')
        if op in ("subscribe", "unsubscribe"):
            return self._subscription(op, args)
        if op not in OPS:
            raise OpError("unknown_op", f"unknown op {op!r}")
        handler, needs_operator = OPS[op]
        if needs_operator and self.role is not Role.OPERATOR:
            raise OpError("forbidden", f"{op!r} needs the operator role")
        self.server.stats["requests"] += 1
        return await handler(self.server.context, args)

    def _hello(self, args: Mapping[str, Any]) -> Any:
        """Authenticate a TCP client by token; on the Unix socket it just reports the role."""
        if self.server.is_tcp(self):
            role = self.server.role_for_token(args.get("token"))
            if role is Role.NONE:
                raise OpError("unauthorized", "unknown token")
            self.role = role
        return {"role": self.role.value, "topics": list(TOPICS)}

    def _subscription(self, op: str, args: Mapping[str, Any]) -> Any:
        """Add or remove topics."""
        topics = args.get("topics")
        if not isinstance(topics, list) or not all(t in TOPICS for t in topics):
            raise OpError("bad_args", f"topics must be a list drawn from {list(TOPICS)}")
        if op == "subscribe":
            self.topics.update(topics)
        else:
            self.topics.difference_update(topics)
        return {"topics": sorted(self.topics), "dropped": self.dropped_total}

    async def _write_loop(self) -> None:
        """Send replies first, then events, then any drop report."""
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self._replies or self._events or self._dropped_unreported:
                self._writer.write(self._encode(self._next_message()))
                await self._writer.drain()
            if self._closing:
                return

    def _next_message(self) -> dict[str, Any]:
        """The next outgoing message by priority."""
        if self._replies:
            return self._replies.popleft()
        if self._dropped_unreported:
            count, self._dropped_unreported = self._dropped_unreported, 0
            return {"topic": "overflow", "data": {"dropped": count, "total": self.dropped_total}}
        return self._events.popleft()

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
        self.stats = {"connections": 0, "requests": 0, "errors": 0, "bad_requests": 0}
        self.stats["events_dropped"] = 0
        self.tcp_port: int | None = None
        self._clients: dict[ClientConnection, asyncio.Task[Any] | None] = {}
        self._tcp_clients: set[ClientConnection] = set()
        self._servers: list[asyncio.Server] = []
        self._closed = False

    @property
    def client_count(self) -> int:
        """Clients connected now."""
        return len(self._clients)

    async def start(self) -> None:
        """Bind the Unix socket (and TCP if enabled)."""
        path = Path(self.config.socket_path)
        _clear_stale_socket(path)
        unix = await asyncio.start_unix_server(self._on_unix, path=str(path))
        self._servers.append(unix)
        _set_permissions(path, self.config.socket_mode, self.config.socket_group)
        if self.config.tcp_enabled:
            tcp = await asyncio.start_server(
                self._on_tcp, self.config.tcp_host, self.config.tcp_port
            )
            self._servers.append(tcp)
            self.tcp_port = int(tcp.sockets[0].getsockname()[1])
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

    def is_tcp(self, client: ClientConnection) -> bool:
        """True for a client that came in over TCP."""
        return client in self._tcp_clients

    async def _on_unix(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """A Unix-socket client: file permissions already vouched for it."""
        await self._serve(ClientConnection(self, reader, writer, Role.OPERATOR))

    async def _on_tcp(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """A TCP client: nothing but hello until it shows a token."""
        client = ClientConnection(self, reader, writer, Role.NONE)
        self._tcp_clients.add(client)
        await self._serve(client)

    async def _serve(self, client: ClientConnection) -> None:
        """Track a client for its lifetime."""
        self.stats["connections"] += 1
        if self._closed:
            client.abort()  # accepted in the instant close() ran
        self._clients[client] = asyncio.current_task()
        try:
            await client.serve()
        except asyncio.CancelledError:
            pass  # only close() cancels a client, and asyncio.streams logs a cancelled handler
        finally:
            self._clients.pop(client, None)
            self._tcp_clients.discard(client)


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
