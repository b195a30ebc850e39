"""Serial link: wire frames as a delimited byte stream over pyserial, without blocking the loop.

Built on pyserial-asyncio-fast for devices and `socket://`: it watches the device's file
descriptor with the loop's `add_reader` (no thread, no polling) and hands `socket://` to asyncio's
own socket transport. Its POSIX path needs a descriptor, which pyserial's `loop://` and
`rfc2217://` handlers do not have; those are polled every millisecond instead. A read error
(unplugged adapter, pty closed, peer gone) becomes `_lost`.
"""

from __future__ import annotations

import asyncio
import functools
from typing import Any, ClassVar

import serial
import serial_asyncio_fast

from host.transport.base import Transport, TransportError

DEFAULT_BAUD = 115200
CLOSE_TIMEOUT_S = 2.0
URL_SCHEMES = ("socket://", "rfc2217://", "loop://", "spy://", "alt://", "hwgrep://")
POLLED_SCHEMES = ("loop://", "rfc2217://")  # pyserial handlers without a file descriptor
POLL_INTERVAL_S = 0.001


def check_url(url: object) -> str:
    """A device path or a pyserial URL; ValueError naming what is wrong."""
    if not isinstance(url, str) or not url:
        raise ValueError(f"url must be a device path or pyserial URL, got {url!r}")
    if url.startswith("/") or url.startswith(URL_SCHEMES):
        return url
    raise ValueError(f"url {url!r} is neither a device path (/dev/…) nor one of {URL_SCHEMES}")


def check_baud(baudrate: object) -> int:
    """A positive integer baud rate; ValueError otherwise."""
    if isinstance(baudrate, bool) or not isinstance(baudrate, int) or baudrate <= 0:
        raise ValueError(f"baudrate must be a positive integer, got {baudrate!r}")
    return baudrate


class _StreamProtocol(asyncio.Protocol):
    """Adapter from asyncio protocol callbacks to a byte sink and a lost handler."""

    def __init__(self, owner: ByteStream) -> None:
        self._owner = owner

    def data_received(self, data: bytes) -> None:
        """Bytes from the device."""
        self._owner.on_bytes(data)

    def connection_lost(self, exc: Exception | None) -> None:
        """The device is closed, by us or by the world."""
        self._owner.on_closed(exc)

    def pause_writing(self) -> None:
        """The device stopped draining (flow control, cut cable behind an adapter)."""
        self._owner.paused = True

    def resume_writing(self) -> None:
        """The device drains again."""
        self._owner.paused = False


class ByteStream:
    """A pyserial URL opened under asyncio; shared by the serial and XBee transports."""

    def __init__(self, url: str, baudrate: int, owner: Transport, options: dict[str, Any]) -> None:
        self.url = url
        self.baudrate = baudrate
        self._owner = owner
        self._options = options
        self._aio: asyncio.Transport | None = None
        self._closed: asyncio.Future[None] | None = None
        self.sink: Any = None  # Callable[[bytes], None], set by the owning transport
        self.paused = False

    async def open(self) -> None:
        """Open the URL; pyserial's errors become TransportError naming the device."""
        loop = asyncio.get_running_loop()
        self._closed = loop.create_future()
        if self.url.startswith(POLLED_SCHEMES):
            self._aio = await _PolledTransport.open(self, self.url, self.baudrate, self._options)
            return
        # A device path is locked (flock) so a second daemon cannot share it and fight over the
        # link; URL handlers (socket://, rfc2217://) have no file to lock.
        options = self._options if "://" in self.url else {"exclusive": True, **self._options}
        try:
            aio, _ = await serial_asyncio_fast.create_serial_connection(
                loop, lambda: _StreamProtocol(self), self.url, baudrate=self.baudrate, **options
            )
        except Exception as exc:  # pyserial raises SerialException, an OSError subclass, or worse
            raise TransportError(f"{self._owner.describe()}: {exc}") from exc
        self._aio = aio

    def write(self, data: bytes) -> None:
        """Queue bytes; the asyncio transport buffers what the device cannot take now."""
        if self._aio is None or self._aio.is_closing():
            raise OSError("device is closed")
        if self.paused:
            # Frames queued behind a stalled device are stale by the time it drains; the
            # session retransmits what matters, so drop and count instead of buffering forever.
            self._owner.stats.bump("tx_dropped_backpressure")
            return
        self._aio.write(data)

    async def close(self) -> None:
        """Release the device, dropping bytes it never accepted, and wait until it is free."""
        aio, closed = self._aio, self._closed
        self._aio = None
        if aio is None or closed is None:
            return
        if isinstance(aio, _PolledTransport):
            aio.close()
        else:
            # abort, not close: close would wait (tcdrain in a worker thread) for a stalled device
            # to drain, possibly forever. What the kernel already holds is still sent.
            aio.abort()
        if not closed.done():
            await asyncio.wait_for(asyncio.shield(closed), CLOSE_TIMEOUT_S)

    def on_bytes(self, data: bytes) -> None:
        """Protocol callback: route bytes to the owner."""
        if self.sink is not None:
            self.sink(data)

    def on_closed(self, exc: Exception | None) -> None:
        """Protocol callback: wake `close`, or report a link that died under us."""
        self.paused = False
        if self._closed is not None and not self._closed.done():
            self._closed.set_result(None)
        if self._aio is not None:
            self._aio = None
            self._owner._lost(exc if exc is not None else ConnectionError("device closed"))


class _PolledTransport(asyncio.Transport):
    """Minimal asyncio transport over a pyserial handler with no descriptor: a 1 ms poll task."""

    def __init__(self, stream: ByteStream, port: serial.SerialBase) -> None:
        super().__init__()
        self._stream = stream
        self._port = port
        self._closing = False
        self._task = asyncio.get_running_loop().create_task(self._poll())

    @classmethod
    async def open(
        cls, stream: ByteStream, url: str, baudrate: int, options: dict[str, Any]
    ) -> _PolledTransport:
        """Open in an executor thread (rfc2217 negotiates) and start polling."""
        opener = functools.partial(
            serial.serial_for_url, url, baudrate=baudrate, timeout=0, **options
        )
        try:
            port = await asyncio.get_running_loop().run_in_executor(None, opener)
        except Exception as exc:
            raise TransportError(f"{stream._owner.describe()}: {exc}") from exc
        return cls(stream, port)

    def write(self, data: bytes | bytearray | memoryview) -> None:
        """Hand bytes to the handler (its own queue or socket)."""
        self._port.write(bytes(data))

    def is_closing(self) -> bool:
        """True once close was asked."""
        return self._closing

    def close(self) -> None:
        """Stop polling; the poll task closes the port and reports."""
        self._closing = True
        self._task.cancel()

    async def _poll(self) -> None:
        """Read whatever waits, every millisecond, until closed or failed."""
        exc: Exception | None = None
        try:
            while True:
                waiting = self._port.in_waiting
                if waiting:
                    self._stream.on_bytes(self._port.read(waiting))
                await asyncio.sleep(POLL_INTERVAL_S)
        except serial.SerialException as err:
            exc = err
        finally:
            self._port.close()
            self._stream.on_closed(exc)


class SerialTransport(Transport):
    """Wire frames over a serial port, a pty, a TCP socket or pyserial's loop://."""

    scheme: ClassVar[str] = "serial"

    def __init__(self, url: str, baudrate: int = DEFAULT_BAUD, **serial_options: Any) -> None:
        super().__init__()
        self._stream = ByteStream(check_url(url), check_baud(baudrate), self, serial_options)
        self._stream.sink = self._deliver

    def describe(self) -> str:
        """E.g. 'serial /dev/ttyUSB0 @115200'."""
        return f"serial {self._stream.url} @{self._stream.baudrate}"

    async def _open(self) -> None:
        """Open the device."""
        await self._stream.open()

    def _write(self, frame: bytes) -> None:
        """Queue the frame's bytes."""
        self._stream.write(frame)

    async def _close(self) -> None:
        """Release the device."""
        await self._stream.close()
