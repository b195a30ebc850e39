"""Control-socket framing: a 4-byte big-endian length, then one msgpack map (docs/CONTROL.md)."""

from __future__ import annotations

import asyncio
import struct
from typing import Any

import msgpack

MAX_MESSAGE_BYTES = 64 * 1024
HEADER = struct.Struct(">I")


class WireError(Exception):
    """A message could not be read; `code` is the error code sent back to the peer."""

    def __init__(self, code: str, message: str, fatal: bool = False) -> None:
        super().__init__(message)
        self.code = code
        self.fatal = fatal  # the stream is out of step: reply, then close


def pack(message: dict[str, Any]) -> bytes:
    """One framed message; ValueError if it is larger than the limit."""
    body: bytes = msgpack.packb(message, use_bin_type=True)
    if len(body) > MAX_MESSAGE_BYTES:
        raise ValueError(f"message of {len(body)} bytes exceeds {MAX_MESSAGE_BYTES}")
    return HEADER.pack(len(body)) + body


def unpack_body(body: bytes) -> dict[str, Any]:
    """Decode one message body; WireError if it is not a msgpack map."""
    try:
        obj = msgpack.unpackb(body, raw=False)
    except Exception as exc:  # msgpack raises several unrelated types for bad input
        raise WireError("bad_request", f"not valid msgpack: {exc}") from exc
    if not isinstance(obj, dict):
        raise WireError("bad_request", f"expected a map, got {type(obj).__name__}")
    return obj


async def read_message(reader: asyncio.StreamReader) -> dict[str, Any] | None:
    """The next message, None at a clean end of stream; WireError for a bad one."""
    try:
        header = await reader.readexactly(HEADER.size)
    except asyncio.IncompleteReadError as exc:
        if exc.partial:
            raise WireError("bad_request", "stream ended inside a length prefix", True) from exc
        return None
    (length,) = HEADER.unpack(header)
    if length > MAX_MESSAGE_BYTES:
        # The body is not read, so the stream cannot be resynchronised: close after replying.
        raise WireError("too_large", f"{length} bytes exceeds {MAX_MESSAGE_BYTES}", fatal=True)
    try:
        body = await reader.readexactly(length)
    except asyncio.IncompleteReadError as exc:
        raise WireError("bad_request", "stream ended inside a message", True) from exc
    return unpack_body(body)


def error_reply(
    request_id: Any, code: str, message: str, detail: dict[str, Any] | None = None
) -> dict[str, Any]:
    """A failed reply; `detail` carries machine-readable facts (e.g. the watchdog period)."""
    error: dict[str, Any] = {"code": code, "message": message}
    if detail:
        error["detail"] = detail
    return {"id": request_id, "ok": False, "error": error}


def ok_reply(request_id: Any, result: Any) -> dict[str, Any]:
    """A successful reply."""
    return {"id": request_id, "ok": True, "result": result}
