"""A frame waits for the samples of its exposure: what `PoseFeed.covers` says has come in.

Over XBee a batch arrives 50–100 ms after its first stamp, so a frame registered on arrival
is placed from old samples, and a tooth skip shows in it until a reading after the skip is in.
"""

from __future__ import annotations

import pytest

from host.config import loads_config
from host.config_fields import ConfigError
from host.fusion.range_fix import RangeFixer
from host.registration.pose_buffer import AngleBuffer, SampleBuffer
from host.registration.track_feed import RANGE_FLOWING_NS, PoseFeed
from host.service.wiring import FRAME_WAIT_MS, frame_wait_s
from protocol.enums import Inputs
from tests.fusion.test_range_fix import AHEAD, HALL, RIG, _reading

MS = 1_000_000
T0_NS = 1_000 * MS
HOME_S_MM = 1000.0
HOMED = int(Inputs.HOMED)


def _feed(ranger: bool) -> PoseFeed:
    return PoseFeed(
        SampleBuffer(1, 512),
        AngleBuffer(2, 512),
        home_s_mm=HOME_S_MM,
        ranger=RangeFixer(RIG, HALL) if ranger else None,
    )


def _encoder(feed: PoseFeed, t_ns: int, s_mm: float = 0.0) -> None:
    feed.on_encoder(t_ns, s_mm, 0.0, HOMED)
    feed.on_head(t_ns, *AHEAD)


def test_a_frame_waits_for_an_encoder_sample_at_or_after_its_exposure() -> None:
    feed = _feed(ranger=False)
    assert feed.covers(T0_NS)  # no stream at all: nothing will come to wait for
    _encoder(feed, T0_NS)
    assert feed.covers(T0_NS)
    assert not feed.covers(T0_NS + 1)
    _encoder(feed, T0_NS + 10 * MS)
    assert feed.covers(T0_NS + 10 * MS)


def test_while_readings_flow_a_frame_waits_for_a_reading_after_it_too() -> None:
    feed = _feed(ranger=True)
    for k in range(6):
        _encoder(feed, T0_NS + 10 * k * MS)
    feed.on_range(T0_NS + 20 * MS, _reading(HOME_S_MM), 200)
    exposure = T0_NS + 30 * MS
    assert not feed.covers(exposure)  # encoder in, but no reading after the exposure yet
    feed.on_range(T0_NS + 40 * MS, _reading(HOME_S_MM), 200)
    assert feed.covers(exposure)


def test_a_rangefinder_that_went_quiet_is_not_waited_for() -> None:
    feed = _feed(ranger=True)
    feed.on_range(T0_NS, _reading(HOME_S_MM), 200)
    _encoder(feed, T0_NS)
    late = T0_NS + RANGE_FLOWING_NS
    _encoder(feed, late)
    assert feed.covers(late)  # its last reading is as old as the flow's bound: not flowing


def test_the_link_decides_the_wait_unless_the_config_says() -> None:
    assert frame_wait_s("xbee") == pytest.approx(FRAME_WAIT_MS["xbee"] / 1000.0)
    assert FRAME_WAIT_MS["xbee"] > FRAME_WAIT_MS["serial"] > FRAME_WAIT_MS["can"]
    config = loads_config("[registration]\nframe_wait_ms = 0\n")
    assert frame_wait_s("xbee", config.registration.frame_wait_ms) == 0.0
    assert loads_config("").registration.frame_wait_ms == "auto"


@pytest.mark.parametrize("value", ['"soon"', "-1", "1001", "true", "nan"])
def test_a_bad_wait_names_the_key(value: str) -> None:
    with pytest.raises(ConfigError) as err:
        loads_config(f"[registration]\nframe_wait_ms = {value}\n")
    assert "registration.frame_wait_ms" in str(err.value)
