"""Garbage on the link never crashes the firmware and never moves the trolley."""

from __future__ import annotations

import copy

from hypothesis import given, settings
from hypothesis import strategies as st

from hil_sim.runner import Simulation
from protocol import Flag, State, encode_frame
from protocol.messages import Hello, Home, Jog, MoveTo
from tests.firmware.conftest import Rig, make_rig

_BASE: Rig | None = None
VALID = [
    encode_frame(Hello(1, 0), 1, Flag.ACK_REQUESTED),
    encode_frame(Home(0), 2, Flag.ACK_REQUESTED),
    encode_frame(Jog(100_000, 100_000), 3, Flag.ACK_REQUESTED),
    encode_frame(MoveTo(1000, 1000, 1000), 4, Flag.ACK_REQUESTED),
]


def base_sim() -> Simulation:
    """A fresh, idle simulation (copied per example)."""
    global _BASE
    if _BASE is None:
        _BASE = make_rig()
    return copy.deepcopy(_BASE.sim)


def corrupt(frame: bytes, pos: int, bit: int) -> bytes:
    """Flip one bit somewhere before the delimiter."""
    out = bytearray(frame)
    i = pos % (len(out) - 1)
    out[i] ^= 1 << bit
    return bytes(out)


@settings(max_examples=60, deadline=None)
@given(
    chunks=st.lists(
        st.one_of(
            st.binary(max_size=120),
            st.builds(
                corrupt,
                st.sampled_from(VALID),
                st.integers(0, 100),
                st.integers(0, 7),
            ),
        ),
        max_size=20,
    )
)
def test_garbage_and_corrupted_frames_change_nothing(chunks: list[bytes]) -> None:
    sim = base_sim()
    s0 = sim.truth().s_mm
    for chunk in chunks:
        sim.send(chunk)
        sim.step(3)
    sim.step(50)
    fw = sim.firmware
    assert fw.state is State.IDLE
    assert abs(sim.truth().s_mm - s0) < 0.1
    assert fw.profile.steps == 0
