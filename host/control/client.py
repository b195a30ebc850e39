"""An asyncio client of the control socket, used by the CLI and the tests."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
from typing import Any

from host.control.wire import WireError, pack, read_message

DEFAULT_TIMEOUT_S = 30.0
EVENT_QUEUE_MAX = 1024


class ControlRequestError(Exception):
    """The daemon answered a request with an error."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


class ControlClient:
    """Requests with replies matched by id, and a queue of subscribed events."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._reader = reader
        self._writer = writer
        self._ids = itertools.count(1)
        self._pending: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self._events: asyncio.Queue[dict[str, Any]] = asyncio.Queue(EVENT_QUEUE_MAX)
        self._closed = asyncio.Event()
        self._task = asyncio.create_task(self._read_loop())
        self.unmatched: list[dict[str, Any]] = []  # replies with no request (id null)
        self._last_word: dict[str, Any] | None = None  # an id-null error: why the server closes

    @classmethod
    async def connect_unix(cls, path: str) -> ControlClient:
        """Connect to the daemon's Unix socket; ConnectionError if nobody listens there."""
        reader, writer = await asyncio.open_unix_connection(path)
        return cls(reader, writer)

    @classmethod
    async def connect_tcp(cls, host: str, port: int) -> ControlClient:
        """Connect to the daemon's TCP listener (send hello before anything else)."""
        reader, writer = await asyncio.open_connection(host, port)
        return cls(reader, writer)

    async def request(self, op: str, timeout_s: float = DEFAULT_TIMEOUT_S, **args: Any) -> Any:
        """Send one request and return its result; ControlRequestError on an error reply."""
        request_id = next(self._ids)
        future: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._pending[request_id] = future  # registered before sending: no lost fast reply
        if self._closed.is_set():
            self._fail(future)
        try:
            self._writer.write(pack({"id": request_id, "op": op, "args": args}))
            await self._writer.drain()
            reply = await asyncio.wait_for(future, timeout_s)
        finally:
            self._pending.pop(request_id, None)
            if future.done() and not future.cancelled():
                future.exception()  # a failed write raised first: the reader's verdict is read
            else:
                future.cancel()
        if not reply.get("ok"):
            error = reply.get("error") or {}
            raise ControlRequestError(str(error.get("code")), str(error.get("message")))
        return reply.get("result")

    async def send_raw(self, data: bytes) -> None:
        """Write bytes as they are (tests of malformed input)."""
        self._writer.write(data)
        await self._writer.drain()

    async def next_event(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> dict[str, Any]:
        """The next event; ConnectionError once the daemon has gone."""
        if self._events.empty() and self._closed.is_set():
            raise ConnectionError("control connection closed")
        getter = asyncio.ensure_future(self._events.get())
        closer = asyncio.ensure_future(self._closed.wait())
        try:
            await asyncio.wait({getter, closer}, timeout=timeout_s, return_when="FIRST_COMPLETED")
        finally:
            closer.cancel()
            if not getter.done():
                getter.cancel()
        if getter.done() and not getter.cancelled():
            return getter.result()
        if self._closed.is_set():
            raise ConnectionError("control connection closed")
        raise TimeoutError("no event within the timeout")

    @property
    def closed(self) -> bool:
        """True once the connection has ended."""
        return self._closed.is_set()

    async def close(self) -> None:
        """Close the connection and stop the reader."""
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)
        self._writer.close()
        with contextlib.suppress(ConnectionError, OSError):
            await self._writer.wait_closed()

    async def __aenter__(self) -> ControlClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _read_loop(self) -> None:
        """Route replies to their futures and events to the queue."""
        try:
            while (message := await read_message(self._reader)) is not None:
                self._route(message)
        except (WireError, ConnectionError, OSError):
            pass
        finally:
            self._closed.set()
            for future in self._pending.values():
                self._fail(future)

    def _fail(self, future: asyncio.Future[dict[str, Any]]) -> None:
        """End a request on a closed connection with the server's last word, if it said why."""
        if future.done():
            return
        if self._last_word is not None:  # e.g. too_many_clients: say that, not "closed"
            future.set_result(self._last_word)
        else:
            future.set_exception(ConnectionError("control connection closed"))

    def _route(self, message: dict[str, Any]) -> None:
        """One incoming message."""
        if "topic" in message:
            if self._events.full():
                self._events.get_nowait()  # keep the newest, like the server does
            self._events.put_nowait(message)
            return
        request_id = message.get("id")  # ours are ints; a raw request may have used anything
        future = None
        if isinstance(request_id, int) and not isinstance(request_id, bool):
            future = self._pending.get(request_id)
        if future is not None and not future.done():
            future.set_result(message)
        else:
            self.unmatched.append(message)
            if request_id is None and message.get("ok") is False:
                self._last_word = message
