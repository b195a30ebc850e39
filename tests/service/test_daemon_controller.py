"""The daemon against a controller emulator that sends what this host does not expect.

The daemon runs in this process with its real link controller and pose loop; the controller
is the scripted emulator of tests/link behind a MemoryTransport, which sends frames without
the encoder's range checks (a newer firmware, or a bit error the CRC let through).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sys
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
from protocol import PARAMS, ParamId
from protocol.enums import Fault, Inputs, State
from protocol.messages import EncoderSample, HeadSample, Status
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


def config_text(tmp_path: Path, extra: str = "", track: str = "") -> str:
    """No camera (poses at a fixed rate), the socket in tmp, a fast heartbeat; `track` is the
    rig file's track (the rig lives in its own file, [rig] path), `extra` more config."""
    rig = tmp_path / "rig.toml"
    rig.write_text("[camera]\nfps = 20.0\n" + track)
    return extra + (
        f'[control]\nsocket_path = "{tmp_path}/ctl.sock"\n'
        '[camera]\nsource = "none"\n'
        f'[rig]\npath = "{rig}"\n'
        "[link]\nheartbeat_ms = 50\n"
        "[systemd]\nready_grace_s = 0.2\nstatus_interval_s = 0.2\n"
    )


async def _heartbeats(emulator: FakeController) -> None:
    """Keep the link alive as a controller does."""
    while True:
        if not emulator.silent:  # a silent controller has hung: no heartbeat either
            emulator.send_heartbeat(int(HEARTBEAT_S * 1000))
        await asyncio.sleep(HEARTBEAT_S)


@contextlib.asynccontextmanager
async def serve(config: Config, tmp_path: Path) -> AsyncIterator[Served]:
    """The daemon on an emulated controller, until the block ends."""
    emulator = FakeController(state=State.IDLE)
    emulator.params.update({int(p.id): p.default for p in PARAMS})  # the firmware's defaults
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
        async with await served.client() as watcher:
            await watcher.request("subscribe", topics=["state"])
            for i in range(5):  # the controller keeps sending it, as a newer firmware would
                faults = UNKNOWN_FAULT_BIT | 0x0001
                served.emulator.send(Status(i, UNKNOWN_STATE, faults, HOMED, 1000 + i, 1000))
                await asyncio.sleep(0.15)  # several status periods and pose ticks
            pushed = (await watcher.next_event(timeout_s=2))["data"]  # pushed, as STATUS came
            assert pushed["state"] == UNKNOWN_STATE
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


async def test_a_latched_fault_is_logged_once_with_its_names_and_where(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)
    config = loads_config(config_text(tmp_path))
    async with serve(config, tmp_path) as served:
        for i in range(4):  # the controller repeats its STATUS while it stays latched
            served.emulator.send(Status(i, int(State.FAULT), int(Fault.WATCHDOG), HOMED, 2500, 1))
            await asyncio.sleep(0.15)
        served.emulator.send(Status(9, int(State.READY), 0, HOMED, 2500, 1))
        await asyncio.sleep(0.3)
    latched = [r for r in caplog.records if r.getMessage() == "controller latched"]
    assert len(latched) == 1, [r.getMessage() for r in caplog.records]
    kv = latched[0].kv  # type: ignore[attr-defined]
    assert (kv["state"], kv["faults"], kv["position_mm"]) == ("FAULT", "WATCHDOG", 2.5)
    assert latched[0].levelno == logging.WARNING
    assert sum(r.getMessage() == "controller latch cleared" for r in caplog.records) == 1


OPEN_TRACK = """[track.home]
value_mm = 100.0
[[track.segments]]
kind = "straight"
length_mm = 2000.0
"""
MM_PER_COUNT = 20 * 12.7 / 4000  # the emulator's IDENTIFY: 20 teeth, 12.7 mm pitch, 4000 counts


async def _sit_at(
    emulator: FakeController, position_mm: float, duration_s: float, inputs: int = HOMED
) -> None:
    """Encoder samples and STATUS of a (homed) trolley standing at a controller position."""
    loop = asyncio.get_running_loop()
    count = round(position_mm / MM_PER_COUNT)
    for _ in range(round(duration_s / 0.02)):
        mcu_us = (int(loop.time() * 1e6) + emulator.mcu_offset_us) % (1 << 32)
        emulator.send(EncoderSample(mcu_us, count, count, 0, inputs))
        emulator.send(HeadSample(mcu_us, 0, 0))
        state = int(State.READY if inputs & HOMED else State.IDLE)
        emulator.send(Status(mcu_us, state, 0, inputs, round(position_mm * 1000), 0))
        await asyncio.sleep(0.02)


async def test_open_track_homed_below_zero_is_a_state_not_a_crash(tmp_path: Path) -> None:
    config = loads_config(config_text(tmp_path, track=OPEN_TRACK))
    async with serve(config, tmp_path) as served:
        emulator = served.emulator
        # Set from the track on connect: [0, 2000] mm of track is [-100, 1900] mm of controller.
        assert emulator.params[ParamId.SOFT_LIMIT_MIN_UM] == -100_000
        assert emulator.params[ParamId.SOFT_LIMIT_MAX_UM] == 1_900_000
        await _sit_at(emulator, -150.0, 0.6)  # homing ran toward negative s, past the start
        assert not served.task.done(), "the daemon stopped on a position off the open track"
        shown = (await served.status())["controller"]
        assert shown["homed"] is True
        assert shown["track"] == "below_start"
        before = len(emulator.executed)
        async with await served.client() as client:
            for op, args in (
                ("move", {"position_mm": 5000.0}),
                ("move", {"position_mm": -120.0}),
                ("jog", {"velocity_mm_s": -10.0}),
                ("param_set", {"param": "SOFT_LIMIT_MIN_UM", "value": -500_000}),
            ):
                with pytest.raises(ControlRequestError, match=r"outside|below_start"):
                    await client.request(op, **args)
            assert len(emulator.executed) == before  # nothing reached the controller
            await client.request("jog", velocity_mm_s=10.0)  # back onto the track: allowed
            await client.request("move", position_mm=500.0)
        assert [type(m).__name__ for m in emulator.executed[before:]] == ["Jog", "MoveTo"]
        await _sit_at(emulator, 500.0, 0.3)
        shown = await served.status()
        assert shown["controller"]["track"] == "on"
        assert shown["pose"]["s_mm"] == pytest.approx(600.0, abs=0.1)  # poses again, on the track
    assert await served.task == 0


class _Udp(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.packets: list[bytes] = []

    def datagram_received(self, data: bytes, addr: object) -> None:
        self.packets.append(data)


async def _orbitar_status(socket_path: str) -> int:
    """`orbitar status` as the operator types it; its exit code."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "host.cli", "status", "--socket", socket_path,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL,
    )  # fmt: skip
    return await asyncio.wait_for(proc.wait(), 20.0)


async def test_unhomed_poses_flagged_freed_held_and_a_down_link_is_not_fresh(
    tmp_path: Path,
) -> None:
    loop = asyncio.get_running_loop()
    udp, receiver = await loop.create_datagram_endpoint(_Udp, local_addr=("127.0.0.1", 0))
    port = udp.get_extra_info("sockname")[1]
    freed = f'[outputs.freed]\nenabled = true\ndestinations = ["127.0.0.1:{port}"]\n'
    config = loads_config(config_text(tmp_path, freed))
    try:
        async with serve(config, tmp_path) as served:
            async with await served.client() as client:
                await client.request("subscribe", topics=["pose"])
                await _sit_at(served.emulator, 100.0, 0.4, inputs=0)  # powered up, not homed
                unhomed = (await client.next_event(timeout_s=2))["data"]
                assert unhomed["homed"] is False
                held = (await served.status())["service"]["freed"]["held_unhomed"]
                assert held > 0
                assert not receiver.packets  # FreeD holds an unreferenced pose
                await _sit_at(served.emulator, 100.0, 0.4)
                assert receiver.packets  # homed: FreeD flows
                while not (await client.next_event(timeout_s=2))["data"]["homed"]:
                    pass
            watcher = await served.client()
            await watcher.request("subscribe", topics=["link"])
            served.emulator.silent = True  # the controller hangs: no frames, no heartbeats
            async with asyncio.timeout(3.0):  # the change is pushed, with its cause
                while (link := (await watcher.next_event(timeout_s=3))["data"])["up"]:
                    pass
            assert "heartbeat" in link["error"]
            with pytest.raises(ControlRequestError, match="heartbeat"):
                await watcher.request("home")  # refused, naming the cause
            await watcher.close()
            shown = await served.status()
            assert not shown["link_up"]
            assert shown["controller"]["link"] != "up"
            assert shown["controller"]["age_s"] >= 0.4  # the last STATUS is that old
            assert shown["service"]["pose_age_s"] >= 0.4
            assert await _orbitar_status(served.socket) == 3  # not "ok": the data is stale
            async with asyncio.timeout(4.0):  # the frame rate falls to 0 (2 s window)
                while (await served.status())["service"]["fps"] > 0:
                    await asyncio.sleep(0.1)
    finally:
        udp.close()
