"""UDP fan-out for the tracking outputs (FreeD, OpenTrackIO): one endpoint per destination."""

from __future__ import annotations

import asyncio
from collections.abc import Sequence


def parse_destination(text: str) -> tuple[str, int]:
    """`host:port` or `[v6]:port` into a (host, port) pair."""
    host, _, port = text.rpartition(":")
    return host.strip("[]"), int(port)


class _ErrorCounter(asyncio.DatagramProtocol):
    """Counts send errors reported by the OS (ICMP port unreachable and the like)."""

    def __init__(self, fanout: UdpFanout) -> None:
        self.fanout = fanout

    def error_received(self, exc: Exception) -> None:
        self.fanout.errors += 1


class UdpFanout:
    """Sends each datagram to every destination; never blocks (the OS queues datagrams)."""

    def __init__(self, destinations: Sequence[str]) -> None:
        self.destinations = tuple(destinations)
        self.errors = 0
        self._transports: list[asyncio.DatagramTransport] = []

    async def start(self) -> None:
        """Open one UDP endpoint per destination."""
        loop = asyncio.get_running_loop()
        for destination in self.destinations:
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _ErrorCounter(self), remote_addr=parse_destination(destination)
            )
            self._transports.append(transport)

    def send(self, datagram: bytes) -> None:
        """Queue the datagram to every open endpoint."""
        for transport in self._transports:
            transport.sendto(datagram)

    def close(self) -> None:
        """Close every endpoint."""
        for transport in self._transports:
            transport.close()
        self._transports.clear()
