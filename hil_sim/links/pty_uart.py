"""A UART on a pty: the host opens `/dev/pts/N` with pyserial, the emulator serves the master.

`PtyPort` is the pty itself (raw mode, non-blocking master watched by the loop, an optional
stable symlink that follows the pty across reconnects so the host can reopen the same path).
`PtyUart` joins a port to a `ByteEndpoint` through two paced pipes that carry no more than
baud/10 bytes per second each way, with fault injection on both.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import tty
from collections.abc import Callable

from hil_sim.links.endpoint import ByteEndpoint
from hil_sim.links.faults import FaultConfig, FaultInjector
from hil_sim.links.pacing import PacedPipe, uart_rate_bytes_s

READ_CHUNK_BYTES = 4096
_RETRY_ERRNOS = (errno.EAGAIN, errno.EWOULDBLOCK, errno.EINTR)


class PtyPort:
    """One pty pair served on the running loop; `path` is what the host opens."""

    def __init__(self, on_bytes: Callable[[bytes], None], link_path: str | None = None) -> None:
        self._on_bytes = on_bytes
        self.link_path = link_path
        self._master: int | None = None
        self._slave: int | None = None
        self._pts = ""
        self._out = bytearray()
        self.bytes_in = 0
        self.bytes_out = 0

    @property
    def path(self) -> str:
        """The path the host should open: the stable symlink if any, else /dev/pts/N."""
        return self.link_path or self._pts

    @property
    def is_open(self) -> bool:
        """True while the pty exists."""
        return self._master is not None

    def open(self) -> None:
        """Create the pty (raw, so no echo or line editing) and watch its master."""
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave, self._pts = master, slave, os.ttyname(slave)
        if self.link_path:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.link_path)
            os.symlink(self._pts, self.link_path)
        asyncio.get_running_loop().add_reader(master, self._readable)

    def close(self) -> None:
        """Destroy the pty: a host holding the slave sees a read error, as on an unplug."""
        master, slave = self._master, self._slave
        self._master = self._slave = None
        self._out.clear()
        if master is None:
            return
        loop = asyncio.get_running_loop()
        loop.remove_reader(master)
        loop.remove_writer(master)
        os.close(master)
        if slave is not None:
            os.close(slave)

    def remove_link(self) -> None:
        """Remove the stable symlink (at the end of the emulator's life)."""
        if self.link_path:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.link_path)

    def write(self, data: bytes) -> None:
        """Bytes to the host; what the pty cannot take now waits for writability."""
        if self._master is None:
            return
        if self._out:
            self._out += data
            return
        sent = self._try_write(data)
        if sent < len(data):
            self._out += data[sent:]
            asyncio.get_running_loop().add_writer(self._master, self._writable)

    def _try_write(self, data: bytes) -> int:
        """Non-blocking write; how many bytes went."""
        assert self._master is not None
        try:
            sent = os.write(self._master, data)
        except OSError as exc:
            if exc.errno in _RETRY_ERRNOS:
                return 0
            raise
        self.bytes_out += sent
        return sent

    def _writable(self) -> None:
        """Flush what was waiting."""
        if self._master is None:
            return
        sent = self._try_write(bytes(self._out))
        del self._out[:sent]
        if not self._out:
            asyncio.get_running_loop().remove_writer(self._master)

    def _readable(self) -> None:
        """Bytes from the host."""
        if self._master is None:
            return
        try:
            data = os.read(self._master, READ_CHUNK_BYTES)
        except OSError as exc:
            if exc.errno in _RETRY_ERRNOS or exc.errno == errno.EIO:
                return  # EIO: no slave open right now; the host may come back
            raise
        self.bytes_in += len(data)
        self._on_bytes(data)


class PtyUart:
    """A serial cable at `baud` between a pty and a device endpoint, with faults."""

    def __init__(
        self,
        endpoint: ByteEndpoint,
        baud: int = 115200,
        faults_to_device: FaultConfig | None = None,
        faults_to_host: FaultConfig | None = None,
        link_path: str | None = None,
    ) -> None:
        self.endpoint = endpoint
        self.baud = baud
        self.to_device = FaultInjector(faults_to_device or FaultConfig())
        self.to_host = FaultInjector(faults_to_host or FaultConfig(seed=1))
        rate = uart_rate_bytes_s(baud)
        self.port = PtyPort(self._from_host, link_path)
        self._down: PacedPipe[bytes] = PacedPipe(endpoint.write, rate)
        self._up: PacedPipe[bytes] = PacedPipe(self.port.write, rate)

    @property
    def path(self) -> str:
        """What the host opens."""
        return self.port.path

    async def start(self) -> None:
        """Create the pty and connect the device."""
        self.port.open()
        self._down.start()
        self._up.start()
        self.endpoint.set_sink(self._from_device)

    async def stop(self) -> None:
        """Disconnect the device and destroy the pty."""
        self.endpoint.set_sink(None)
        await self._down.stop()
        await self._up.stop()
        self.port.close()
        self.port.remove_link()

    async def disconnect(self) -> None:
        """Unplug: the pty disappears (the host's read fails) and bytes in flight are lost."""
        self.to_host.note_disconnect()
        await self._down.stop()
        await self._up.stop()
        self.port.close()

    async def reconnect(self) -> None:
        """Plug back in: a new pty behind the same symlink."""
        self.port.open()
        self._down.start()
        self._up.start()

    def _from_host(self, data: bytes) -> None:
        """Host bytes onto the line towards the device."""
        _push(self._down, self.to_device, data)

    def _from_device(self, data: bytes) -> None:
        """Device bytes onto the line towards the host."""
        _push(self._up, self.to_host, data)


def _push(pipe: PacedPipe[bytes], faults: FaultInjector, data: bytes) -> None:
    """Through the faults, then onto the paced line (at the original size: it was sent)."""
    out = faults.transmit(data)
    if out is not None:
        pipe.push(out, len(data), faults.delay_s())
