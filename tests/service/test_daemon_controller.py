"""The daemon against a controller emulator that sends what this host does not expect.

The daemon runs in this process with its real link controller and pose loop; the controller
is the scripted emulator of tests/link behind a MemoryTransport, which sends frames without
the encoder's range checks (a newer firmware, or a bit error the CRC let through).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from host.config import Config, loads_config
from host.control.client import ControlClient, ControlRequestError
from host.link import common
from host.service import wiring
from host.service.daemon import Daemon
from host.service.notify import Notifier
from protocol.enums import Inputs, State
from protocol.messages import Status
from tests.link.fake_controller import FakeController

HEARTBEAT_S = 0.05
UNKNOWN_STATE = 77
UNKNOWN_FAULT_BIT = 0x8000
UNKNOWN_NAK = 99
HOMED = int(Inputs.HOMED)


@dataclass
class Served:
    """A running daemon, its emulated controller and the daemon's task."""

    daemon: Daemon
    emulator: FakeController
    task: asyncio.Task[int]
    socket: str

    async def client(self) -> ControlClient:
        """A control connection, once the socket is there."""
        for _ in range(100):
            with contextlib.suppress(OSError):
                return await ControlClient.connect_unix(self.socket)
            await asyncio.sleep(0.02)
        raise TimeoutError(self.socket)

    async def status(self) -> dict[str, Any]:
        """One `status` request."""
        async with await self.client() as client:
            result: dict[str, Any] = await client.request("status")
            return result


def config_text(tmp_path: Path, track: str = "") -> str:
    """No camera (poses at a fixed rate), the socket in tmp, a fast heartbeat."""
    return (
        f'[control]\nsocket_path = "{tmp_path}/ctl.sock"\n'
        '[camera]\nsource = "none"\nfps = 20.0\n'
        "[link]\nheartbeat_ms = 50\n"
        "[systemd]\nready_grace_s = 0.2\nstatus_interval_s = 0.2\n" + track
    )


async def _heartbeats(emulator: FakeController) -> None:
    """Keep the link alive as a controller does."""
    while True:
        emulator.send_heartbeat(int(HEARTBEAT_S * 1000))
        await asyncio.sleep(HEARTBEAT_S)


@contextlib.asynccontextmanager
async def serve(config: Config, tmp_path: Path) -> AsyncIterator[Served]:
    """The daemon on an emulated controller, until the block ends."""
    emulator = FakeController(state=State.IDLE)
    transport = emulator.wire()
    daemon = Daemon(
        config,
        lambda cfg, tap: wiring.controller_factory(cfg, tap, transport=transport),
        wiring.frame_loop_factory,
        notifier=Notifier({}),
    )
    beats = asyncio.create_task(_heartbeats(emulator))
    task = asyncio.create_task(daemon.run())
    served = Served(daemon, emulator, task, config.control.socket_path)
    try:
        await wait_link_up(served)
        yield served
    finally:
        daemon.request_stop()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(asyncio.shield(task), 5.0)
        beats.cancel()
        await asyncio.gather(beats, return_exceptions=True)
        await emulator.close()


async def wait_link_up(served: Served, timeout_s: float = 5.0) -> None:
    """Until the daemon's status says the link is up."""
    async with asyncio.timeout(timeout_s):
        while not (await served.status())["link_up"]:
            await asyncio.sleep(0.05)


@pytest.fixture(autouse=True)
def _fresh_unknown_log(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test sees the first report of every unknown value (the log-once set is global)."""
    monkeypatch.setattr(common, "_unknown_noted", set())


async def test_unknown_state_fault_and_nak_are_numbers_not_a_crash(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    config = loads_config(config_text(tmp_path))
    async with serve(config, tmp_path) as served:
        for i in range(5):  # the controller keeps sending it, as a newer firmware would
            faults = UNKNOWN_FAULT_BIT | 0x0001
            served.emulator.send(Status(i, UNKNOWN_STATE, faults, HOMED, 1000, 1000))
            await asyncio.sleep(0.15)  # several status periods and pose ticks
        assert not served.task.done(), "the daemon stopped on an unknown controller value"
        shown = (await served.status())["controller"]
        assert shown["state"] == UNKNOWN_STATE
        assert shown["fault_names"] == ["WATCHDOG", "0x8000"]
        served.emulator.nak_next = (UNKNOWN_NAK, UNKNOWN_STATE)
        async with await served.client() as client:
            with pytest.raises(ControlRequestError) as refused:
                await client.request("home")
        assert refused.value.code == "failed"
        assert "rejected: 99 in state 77" in str(refused.value)
        assert not served.task.done()
    assert await served.task == 0
    notes = [r.getMessage() for r in caplog.records if "unknown" in r.getMessage()]
    assert sum("State 77" in n for n in notes) == 1  # logged once, however often it came
    assert sum("Fault bit 32768" in n for n in notes) == 1
    assert sum("NAK code 99" in n for n in notes) == 1
