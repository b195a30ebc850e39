"""Parameters in emulated flash, PERSIST, RESET and boot ids."""

from __future__ import annotations

from pathlib import Path

from firmware.storage import LoadResult, ParamStore
from hil_sim.client import FrameClient
from hil_sim.runner import Simulation
from hil_sim.scenario import Scenario
from protocol import Fault, NakCode, ParamId, State
from protocol.messages import (
    Ack,
    ClearFault,
    Hello,
    Identify,
    Nak,
    ParamGet,
    ParamPersist,
    ParamSet,
    ParamValue,
)
from protocol.messages import Reset as ResetCmd
from tests.firmware.conftest import Rig


def boot_id(client: FrameClient) -> int:
    """Current boot id via HELLO."""
    reply = client.request(Hello(1, 0))
    assert isinstance(reply, Identify)
    return reply.boot_id


def state_of(sim: Simulation) -> State:
    """The controller state (a call, so type narrowing does not stick across commands)."""
    return sim.firmware.state


def value(client: FrameClient, pid: ParamId) -> int:
    """A parameter via PARAM_GET."""
    reply = client.request(ParamGet(pid))
    assert isinstance(reply, ParamValue)
    return reply.value


def test_persisted_params_survive_reset_unpersisted_do_not(rig: Rig) -> None:
    c = rig.client
    first_boot = boot_id(c)
    c.request(ParamSet(ParamId.WATCHDOG_MS, 900))
    assert isinstance(c.request(ParamPersist()), Ack)
    c.request(ParamSet(ParamId.MAX_SPEED_UM_S, 123_000))  # RAM only
    assert isinstance(c.request(ResetCmd()), Ack)
    rig.sim.step(2)
    assert rig.sim.firmware.boots == 2
    assert boot_id(c) != first_boot
    assert value(c, ParamId.WATCHDOG_MS) == 900
    assert value(c, ParamId.MAX_SPEED_UM_S) == 500_000


def test_hardware_reset_hook_reboots_with_new_boot_id_and_unhomed(homed: Rig) -> None:
    c = homed.client
    before = boot_id(c)
    homed.sim.reset_controller()
    homed.sim.step(1)
    assert boot_id(c) != before
    assert homed.sim.firmware.state is State.IDLE
    assert not homed.sim.firmware.homed
    assert abs(homed.sim.firmware.enc_pos) <= 2  # counter restarted at the reset


def test_flash_in_a_file_survives_a_new_simulation(tmp_path: Path) -> None:
    sc = Scenario(flash_path=str(tmp_path / "flash.bin"))
    sim = Simulation(sc)
    c = FrameClient(sim)
    c.request(ParamSet(ParamId.FOLLOWING_ERROR_COUNTS, 321))
    c.request(ParamPersist())
    sim2 = Simulation(sc)
    assert value(FrameClient(sim2), ParamId.FOLLOWING_ERROR_COUNTS) == 321


def test_corrupt_flash_boots_defaults_with_flash_fault(tmp_path: Path) -> None:
    path = tmp_path / "flash.bin"
    store = ParamStore()
    store.set(ParamId.WATCHDOG_MS, 700)
    record = bytearray(store.encode())
    record[9] ^= 0x40
    path.write_bytes(bytes(record))
    sim = Simulation(Scenario(flash_path=str(path)))
    c = FrameClient(sim)
    assert sim.firmware.faults & Fault.FLASH
    assert sim.firmware.state is State.FAULT
    assert value(c, ParamId.WATCHDOG_MS) == 500
    assert isinstance(c.request(ClearFault()), Ack)
    assert state_of(sim) is State.IDLE


def test_flash_write_failure_is_nakked(rig: Rig) -> None:
    rig.sim.board.flash_fail = True
    reply = rig.client.request(ParamPersist())
    assert isinstance(reply, Nak)
    assert reply.code == NakCode.FLASH_ERROR


def test_record_round_trip_and_rejections() -> None:
    store = ParamStore()
    assert store.set(ParamId.HOME_OFFSET_UM, -5_000)
    record = store.encode()
    fresh = ParamStore()
    assert fresh.load(record) is LoadResult.LOADED
    assert fresh.values == store.values
    assert fresh.load(b"") is LoadResult.ERASED
    assert fresh.load(b"\xff" * 64) is LoadResult.ERASED
    assert fresh.load(record[:-1]) is LoadResult.CORRUPT
    assert fresh.get(ParamId.HOME_OFFSET_UM) == 0, "corrupt record leaves defaults"
    assert not store.set(ParamId.WATCHDOG_MS, 1), "below range"
    assert not store.set(999, 1), "unknown id"
