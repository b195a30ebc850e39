"""`orbitar demo --ui` as a newcomer runs it: a URL, a live page behind it, Ctrl-C ends it."""

from __future__ import annotations

import asyncio
import json
import signal
import sys
import time

import aiohttp

from tests.hil_rig import free_port


async def test_demo_ui_prints_a_url_serves_frames_and_ends_on_ctrl_c() -> None:
    port = free_port()
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "host.cli", "demo", "--ui", "--ui-port", str(port),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    assert proc.stdout is not None
    try:
        line = (await asyncio.wait_for(proc.stdout.readline(), 30.0)).decode()
        assert line.startswith("Orbitar station (operator): http://127.0.0.1:")
        url, token = line.split(": ", 1)[1].strip().split("#token=")
        async with aiohttp.ClientSession() as http:
            async with http.get(url) as page:
                assert page.status == 200
            async with http.ws_connect(url + "ws") as ws:
                await ws.send_json({"type": "hello", "token": token})
                hello = json.loads((await asyncio.wait_for(ws.receive(), 10.0)).data)
                assert hello["role"] == "operator"
                deadline = time.monotonic() + 20.0
                while time.monotonic() < deadline:  # the simulated camera's frames arrive
                    msg = await asyncio.wait_for(ws.receive(), 20.0)
                    if msg.type is aiohttp.WSMsgType.BINARY:
                        break
                else:
                    raise AssertionError("no frame from the demo")
        proc.send_signal(signal.SIGINT)
        assert await asyncio.wait_for(proc.wait(), 15.0) == 0
    finally:
        if proc.returncode is None:
            proc.kill()
        await proc.communicate()
