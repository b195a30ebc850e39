"""Another drive: the simulator builds the firmware for the plant's chain, encoder and stepper.

The C takes the mechanics as build-time constants; the mirror takes them per instance, and the
simulator builds it for the scenario's drive, so a rig file with another chain runs end to end:
IDENTIFY reports the build, and MOVE_TO puts the trolley where it was sent.
"""

from __future__ import annotations

import pytest

from firmware.config import MECHANICS, Mechanics
from hil_sim.client import FrameClient
from hil_sim.runner import Simulation
from hil_sim.scenario import ChainConfig, EncoderConfig, Scenario, StepperConfig, TrackConfig
from protocol import State
from protocol.messages import Ack, Hello, Identify, MoveTo
from tests.firmware.conftest import Rig, home

ISO_10B = ChainConfig(sprocket_teeth=17, pitch_mm=15.875)


def other_drive() -> Rig:
    sc = Scenario(
        seed=3,
        chain=ISO_10B,
        encoder=EncoderConfig(lines=2500),
        stepper=StepperConfig(microsteps=8),
        track=TrackConfig(start_s_mm=300.0),
    )
    sim = Simulation(sc)
    return Rig(sim, FrameClient(sim))


def test_the_scenario_builds_the_firmware_for_its_drive() -> None:
    assert Scenario().firmware_build() == MECHANICS  # the paper's drive is the reference build
    assert other_drive().sim.firmware.mech == Mechanics(10_000, 1600, 17, 15_875)


def test_identify_reports_the_build_and_moves_land_where_sent() -> None:
    rig = other_drive()
    reply = rig.client.request(Hello(1, 0xBEEF))
    assert isinstance(reply, Identify)
    assert (reply.encoder_counts_per_rev, reply.steps_per_rev) == (10_000, 1600)
    assert (reply.sprocket_teeth, reply.chain_pitch_um) == (17, 15_875)
    home(rig)
    s0, pos0_mm = rig.sim.plant.truth().s_mm, rig.sim.firmware.position_um / 1000.0
    assert isinstance(rig.client.request(MoveTo(1_000_000, 300_000, 500_000)), Ack)
    for _ in range(100):
        rig.client.run(100)
        if rig.sim.firmware.state is State.READY:
            break
    assert rig.sim.firmware.state is State.READY
    # At 1 m by its encoder (the rotor stands a load angle behind its last step: ~0.15 mm of
    # chain at this friction), and the trolley truly went as far as the encoder says: a sprocket
    # turn is 17 × 15.875 mm here, not the reference build's 254 mm (which would put it 6 % off).
    pos_mm = rig.sim.firmware.position_um / 1000.0
    assert pos_mm == pytest.approx(1000.0, abs=0.3)
    travelled = rig.sim.plant.truth().s_mm - s0
    assert travelled == pytest.approx(pos_mm - pos0_mm, abs=0.1)  # chordal effect, one count


@pytest.mark.parametrize("bad", [{"sprocket_teeth": 0}, {"chain_pitch_um": -1}])
def test_a_build_for_no_drive_is_refused(bad: dict[str, int]) -> None:
    with pytest.raises(ValueError, match="positive"):
        Mechanics(**bad)
