"""Fixtures for firmware tests: a lockstep rig driven through real frames."""

from __future__ import annotations

import copy
from dataclasses import dataclass

import pytest

from hil_sim.client import FrameClient
from hil_sim.runner import Simulation
from hil_sim.scenario import Scenario, TrackConfig
from protocol import State
from protocol.messages import Ack, Home

HOMING_TICKS_MAX = 30_000


@dataclass
class Rig:
    """A simulation and the client talking to it."""

    sim: Simulation
    client: FrameClient


def make_rig(seed: int = 7, start_s_mm: float = 300.0) -> Rig:
    """A fresh rig, not homed."""
    sim = Simulation(Scenario(seed=seed, track=TrackConfig(start_s_mm=start_s_mm)))
    return Rig(sim, FrameClient(sim))


def home(rig: Rig) -> None:
    """Home through real frames and wait for READY."""
    reply = rig.client.request(Home(0))
    assert isinstance(reply, Ack)
    for _ in range(HOMING_TICKS_MAX // 100):
        rig.client.run(100)
        if rig.sim.firmware.state is State.READY:
            return
    raise AssertionError(f"homing did not finish: {rig.sim.firmware.state!r}")


_HOMED: Rig | None = None


@pytest.fixture
def rig() -> Rig:
    """A fresh, unhomed rig."""
    return make_rig()


@pytest.fixture
def homed() -> Rig:
    """A homed rig (a copy of one homed once per session)."""
    global _HOMED
    if _HOMED is None:
        _HOMED = make_rig()
        home(_HOMED)
    return copy.deepcopy(_HOMED)
