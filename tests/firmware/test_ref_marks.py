"""Reference marks: the encoder count captured at each mark's edge reaches the host."""

from __future__ import annotations

from hil_sim.client import FrameClient
from hil_sim.runner import Simulation
from hil_sim.scenario import Scenario, TrackConfig
from protocol import Stream
from protocol.messages import Ack, Jog, RefMark, StreamSet

MARKS_MM = (600.0, 900.0)
COUNTS_PER_MM = 4000 / (20 * 12.7)


def _pass_marks(stream_on: bool) -> tuple[Simulation, list[RefMark], int]:
    """Jog from 500 mm past both marks; return the REF_MARK messages and the start count."""
    sim = Simulation(
        Scenario(seed=3, track=TrackConfig(start_s_mm=500.0, reference_marks_mm=MARKS_MM))
    )
    client = FrameClient(sim)
    if stream_on:
        assert isinstance(client.request(StreamSet(Stream.ENCODER, 100)), Ack)
    start = sim.firmware.enc_pos
    assert isinstance(client.request(Jog(200_000, 500_000)), Ack)
    packets = client.run(3000)
    return sim, [p.message for p in packets if isinstance(p.message, RefMark)], start


def test_each_mark_is_reported_once_with_the_count_at_its_edge() -> None:
    sim, marks, start = _pass_marks(stream_on=True)
    assert len(marks) == len(MARKS_MM) == len(sim.plant.mark_events)
    for msg, mark_mm in zip(marks, MARKS_MM, strict=True):
        travelled_mm = (msg.encoder_count - start) / COUNTS_PER_MM
        # No stretch here: the captured count equals the true travel within one count (and the
        # sub-millimetre chordal wobble of the sprocket).
        assert abs(500.0 + travelled_mm - mark_mm) < 0.2


def test_marks_are_not_sent_without_the_encoder_stream() -> None:
    _, marks, _ = _pass_marks(stream_on=False)
    assert marks == []
