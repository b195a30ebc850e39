"""Serial backend details: a device that stops draining, and the loop:// handler."""

from __future__ import annotations

import os
import tty

from host.transport import TransportState, create_transport

FRAME = bytes(range(1, 26)) + b"\x00"


async def test_stalled_device_drops_and_counts_instead_of_buffering_forever() -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    transport = create_transport("serial", url=os.ttyname(slave))
    await transport.open()
    try:
        for _ in range(10_000):  # 260 kB: far past the pty buffer and the write high-water mark
            transport.send(FRAME)
        dropped = transport.stats.extra.get("tx_dropped_backpressure", 0)
        assert dropped > 0
        assert transport.state is TransportState.OPEN
        assert transport.stats.frames_out == 10_000
    finally:
        await transport.close()
        os.close(master)
        os.close(slave)
