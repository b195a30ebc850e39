"""A serial link over TCP on 127.0.0.1, for pyserial's `socket://127.0.0.1:PORT`.

One host connection at a time (a second one is refused by closing it), bytes paced at an
optional baud rate and run through the shared fault injector. `disconnect` drops the current
connection, which the host sees as the peer going away.
"""

from __future__ import annotations

import asyncio

from hil_sim.links.endpoint import ByteEndpoint
from hil_sim.links.faults import FaultConfig, FaultInjector
from hil_sim.links.pacing import PacedPipe, uart_rate_bytes_s

LOOPBACK_HOST = "127.0.0.1"


class _Conn(asyncio.Protocol):
    """The accepted host connection."""

    def __init__(self, link: TcpLink) -> None:
        self._link = link
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        """Accept one client; refuse a second."""
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self._link._accept(self)

    def data_received(self, data: bytes) -> None:
        """Host bytes."""
        self._link._from_host(data)

    def connection_lost(self, exc: Exception | None) -> None:
        """Host gone."""
        self._link._forget(self)


class TcpLink:
    """A TCP server on the loopback interface serving one device endpoint."""

    def __init__(
        self,
        endpoint: ByteEndpoint,
        baud: int | None = None,
        faults_to_device: FaultConfig | None = None,
        faults_to_host: FaultConfig | None = None,
        port: int = 0,
    ) -> None:
        self.endpoint = endpoint
        self.to_device = FaultInjector(faults_to_device or FaultConfig())
        self.to_host = FaultInjector(faults_to_host or FaultConfig(seed=1))
        rate = uart_rate_bytes_s(baud) if baud else None
        self._down: PacedPipe[bytes] = PacedPipe(endpoint.write, rate)
        self._up: PacedPipe[bytes] = PacedPipe(self._to_host, rate)
        self._server: asyncio.Server | None = None
        self._conn: _Conn | None = None
        self._port = port
        self.refused = 0

    @property
    def port(self) -> int:
        """The bound TCP port."""
        return self._port

    @property
    def url(self) -> str:
        """What the host's serial transport opens."""
        return f"socket://{LOOPBACK_HOST}:{self._port}"

    async def start(self) -> None:
        """Listen on 127.0.0.1 and connect the device."""
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(lambda: _Conn(self), LOOPBACK_HOST, self._port)
        self._port = self._server.sockets[0].getsockname()[1]
        self._down.start()
        self._up.start()
        self.endpoint.set_sink(self._from_device)

    async def stop(self) -> None:
        """Drop the client and stop listening."""
        self.endpoint.set_sink(None)
        self._drop_client()
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None
        await self._down.stop()
        await self._up.stop()

    async def disconnect(self) -> None:
        """Cut the current connection; the server keeps listening for the next."""
        self.to_host.note_disconnect()
        self._drop_client()
        await asyncio.sleep(0)

    async def reconnect(self) -> None:
        """Nothing to plug back: the server never stopped listening."""
        await asyncio.sleep(0)

    def _drop_client(self) -> None:
        """Close the client connection if there is one."""
        if self._conn is not None and self._conn.transport is not None:
            self._conn.transport.close()
        self._conn = None

    def _accept(self, conn: _Conn) -> None:
        """First client wins."""
        if self._conn is not None:
            self.refused += 1
            assert conn.transport is not None
            conn.transport.close()
            return
        self._conn = conn

    def _forget(self, conn: _Conn) -> None:
        """The client went away."""
        if self._conn is conn:
            self._conn = None

    def _from_host(self, data: bytes) -> None:
        """Host bytes towards the device."""
        out = self.to_device.transmit(data)
        if out is not None:
            self._down.push(out, len(data), self.to_device.delay_s())

    def _from_device(self, data: bytes) -> None:
        """Device bytes towards the host."""
        out = self.to_host.transmit(data)
        if out is not None:
            self._up.push(out, len(data), self.to_host.delay_s())

    def _to_host(self, data: bytes) -> None:
        """Paced bytes onto the socket, if a host is connected."""
        if self._conn is not None and self._conn.transport is not None:
            self._conn.transport.write(data)
