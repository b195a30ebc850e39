"""A control server in a process of its own, so tests can measure its memory and descriptors.

Run: python -m tests.control.server_process '<ControlConfig fields as JSON>'
Prints one JSON line ({"pid", "tcp_port"}) once listening; stops at EOF on stdin or SIGTERM.
It serves without a controller (`status` still answers), which is all a flood test needs.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import sys
from pathlib import Path

from host.config import ControlConfig
from host.control.ops import OpContext
from host.control.server import ControlServer


def rss_kb(pid: int) -> int:
    """Resident set size of a process, kB (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for pid {pid}")


def fd_count(pid: int) -> int:
    """Open file descriptors of a process (Linux /proc)."""
    return len(os.listdir(f"/proc/{pid}/fd"))


async def _serve(fields: dict[str, object]) -> None:
    """Listen until stdin ends or SIGTERM arrives."""
    server = ControlServer(OpContext(None), ControlConfig(**fields))  # type: ignore[arg-type]
    await server.start()
    print(json.dumps({"pid": os.getpid(), "tcp_port": server.tcp_port}), flush=True)
    loop = asyncio.get_running_loop()
    done = asyncio.Event()
    loop.add_signal_handler(signal.SIGTERM, done.set)
    stdin = asyncio.StreamReader()
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(stdin), sys.stdin)
    eof = asyncio.create_task(stdin.read())
    stop = asyncio.create_task(done.wait())
    await asyncio.wait({eof, stop}, return_when=asyncio.FIRST_COMPLETED)
    eof.cancel()
    stop.cancel()
    await server.close()


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(levelname)s %(message)s")
    asyncio.run(_serve(json.loads(sys.argv[1])))
