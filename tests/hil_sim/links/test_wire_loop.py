"""A link emulator on its own loop moves bytes while the host's loop is busy."""

from __future__ import annotations

import os
import time
import tty

from hil_sim.links.endpoint import LoopbackEndpoint
from hil_sim.links.pty_uart import PtyUart
from hil_sim.links.wire_loop import WireLoop

BAUD = 115_200
PAYLOAD = bytes(range(1, 65))  # ~6 ms each way at 115200
HOST_BUSY_S = 0.3  # the host's loop blocked, as by a long render


def _echo_during_a_busy_host_loop(path: str) -> bytes:
    """Write to the pty, block this thread's loop, then read what came back meanwhile."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        tty.setraw(fd)
        os.write(fd, PAYLOAD)
        time.sleep(HOST_BUSY_S)  # deliberately blocking: nothing on this loop runs
        try:
            return os.read(fd, 4096)
        except BlockingIOError:
            return b""
    finally:
        os.close(fd)


async def test_the_echo_comes_back_while_the_host_loop_is_blocked() -> None:
    wire = WireLoop("test-wire")
    wire.start()
    uart = PtyUart(LoopbackEndpoint(), BAUD)
    try:
        await wire.run(uart.start())
        assert _echo_during_a_busy_host_loop(uart.path) == PAYLOAD
    finally:
        await wire.run(uart.stop())
        wire.stop()
    assert wire.loop.is_closed()


async def test_on_the_host_loop_the_same_echo_waits_for_it() -> None:
    """The control: what the wire loop is for (the emulator on the host's own loop)."""
    uart = PtyUart(LoopbackEndpoint(), BAUD)
    await uart.start()
    try:
        assert _echo_during_a_busy_host_loop(uart.path) == b""
    finally:
        await uart.stop()
