"""A frame waits for the samples of its exposure: what `PoseFeed.covers` says has come in.

Over XBee a batch arrives 50–100 ms after its first stamp, so a frame registered on arrival
is placed from old samples, and a tooth skip shows in it until a reading after the skip is in.
"""

from __future__ import annotations

import pytest

from host.config import loads_config
from host.config_fields import ConfigError
from host.fusion.chain_filter import ChainFilter, ChainFilterConfig
from host.fusion.range_fix import RangeFixer
from host.registration.pose_buffer import AngleBuffer, SampleBuffer
from host.registration.track_feed import RANGE_FLOWING_NS, PoseFeed
from host.service.wiring import (
    ENCODER_HORIZON_NS,
    FRAME_WAIT_MS,
    HEAD_HORIZON_NS,
    MAX_GAP_NS,
    frame_wait_s,
)
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
    # in, though not yet decided (the head's samples end at 50 ms): at rest the frame's pose
    # does not hang on it
    assert feed.covers(exposure)
    assert feed.stats()["ranges_pending"] == 1


def test_while_the_trolley_drives_with_the_head_held_a_reading_need_not_wait_for_the_head() -> None:
    """Over XBee the head's next sample (10 Hz) comes long after the reading's batch: a frame
    would wait for it. Driving, with the head still over its last samples, the encoder's
    samples past the reading decide it; at rest it waits (the previous test)."""
    feed = _feed(ranger=True)
    for k in range(31):  # 300 ms, head samples every 100 ms, driving at 200 mm/s
        feed.on_encoder(T0_NS + 10 * k * MS, 2.0 * k, 200.0, HOMED)
        if k % 10 == 0:
            feed.on_head(T0_NS + 10 * k * MS, *AHEAD)
    reading_ns = T0_NS + 305 * MS
    feed.on_range(reading_ns, _reading(HOME_S_MM + 61.0), 200)
    assert not feed.covers(reading_ns)  # the encoder has not reached past it yet
    feed.on_encoder(T0_NS + 310 * MS, 62.0, 200.0, HOMED)
    assert feed.covers(reading_ns)  # decided, 85 ms before the head's next sample
    assert feed.ranger is not None
    assert feed.ranger.stats.fixes == 1


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


# A radio-like schedule: each stream's samples arrive a fixed delay after their stamps (a batch's
# store-and-forward; range batches are older than encoder ones, as over XBee); frames arrive
# FRAME_DELIVERY_NS after their exposure.
SPEED_MM_S = 500.0
ENCODER_PERIOD_NS = 10 * MS
RANGE_PERIOD_NS = 20 * MS
FRAME_PERIOD_NS = 33 * MS
ENCODER_DELAY_NS = 60 * MS
RANGE_DELAY_NS = 80 * MS
FRAME_DELIVERY_NS = 20 * MS
# The chain jumps one tooth at 1010 ms. The first reading after it is stamped 1025 ms and in at
# 1105 ms; the frame exposed at 1031 ms has its encoder samples in by 1100 ms: waiting for the
# encoder alone would register it a pitch off.
SKIP_NS = T0_NS + 1_010 * MS
PITCH_MM = 12.7


def _true_s(t_ns: int) -> float:
    """Where the trolley is (track arc length); the encoder reads it without the skip."""
    s = HOME_S_MM + SPEED_MM_S * (t_ns - T0_NS) / 1e9
    return s + (PITCH_MM if t_ns >= SKIP_NS else 0.0)


def _registrations(wait: bool) -> dict[int, float]:
    """Each frame's fused arc length minus the truth at its exposure, registered on arrival
    or once `covers` says its samples are in."""
    from host.fusion.range_fix import RangeFixConfig

    feed = PoseFeed(  # the daemon's horizons: the encoder carried at most 50 ms forward
        SampleBuffer(1, 2048, ENCODER_HORIZON_NS, MAX_GAP_NS),
        AngleBuffer(2, 2048, HEAD_HORIZON_NS, MAX_GAP_NS),
        home_s_mm=HOME_S_MM,
        ranger=RangeFixer(RIG, HALL, RangeFixConfig(noise_mm=0.2)),
    )
    events: list[tuple[int, int, str, int]] = []  # (arrives, order, kind, stamp)
    end = T0_NS + 2_000 * MS
    for t in range(T0_NS, end, ENCODER_PERIOD_NS):
        events.append((t + ENCODER_DELAY_NS, 0, "encoder", t))
    for t in range(T0_NS + 5 * MS, end, RANGE_PERIOD_NS):
        events.append((t + RANGE_DELAY_NS, 1, "range", t))
    for t in range(T0_NS + 305 * MS, end - 300 * MS, FRAME_PERIOD_NS):
        events.append((t + FRAME_DELIVERY_NS, 2, "frame", t))
    errors: dict[int, float] = {}
    held: list[int] = []
    for _, _, kind, t in sorted(events):
        if kind == "encoder":
            s_ctrl = SPEED_MM_S * (t - T0_NS) / 1e9
            feed.on_encoder(t, s_ctrl, SPEED_MM_S, HOMED)
            feed.on_head(t, *AHEAD)
        elif kind == "range":
            feed.on_range(t, _reading(_true_s(t)), 200)
        else:
            held.append(t)
        for exposure in [e for e in held if not wait or feed.covers(e)]:
            looked = feed.encoder.lookup(exposure)
            assert looked.value is not None
            errors[exposure] = float(looked.value[0]) - _true_s(exposure)
            held.remove(exposure)
    assert feed.chain is not None
    assert feed.chain.stats.skips_detected == 1
    return errors


def test_a_frame_that_waits_for_the_reading_after_a_skip_shows_it_put_right() -> None:
    on_arrival, waited = _registrations(wait=False), _registrations(wait=True)
    first_reading = next(t for t in range(T0_NS + 5 * MS, SKIP_NS + 100 * MS, RANGE_PERIOD_NS)
                         if t >= SKIP_NS)  # fmt: skip
    # from the first encoder sample after that reading: the one before it is not corrected
    after = [t for t in waited if t >= first_reading + ENCODER_PERIOD_NS // 2]
    # Registered on arrival, the frames of the next ~80 ms carry the whole pitch: the reading
    # that shows the skip is still on the way.
    wrong_on_arrival = [t for t in after if abs(on_arrival[t]) > PITCH_MM / 2]
    assert len(wrong_on_arrival) >= 2
    # Waiting for a reading after the exposure, every frame from then on is right (one between
    # the skip and that reading cannot be: nothing had seen the skip yet).
    assert all(abs(waited[t]) < 0.5 for t in after)
    before = [e for t, e in waited.items() if SKIP_NS - 300 * MS <= t < SKIP_NS]  # settled
    assert before
    assert all(abs(e) < 0.5 for e in before)


def test_after_a_skip_the_samples_since_the_last_agreeing_reference_get_its_likely_share() -> None:
    """The skip came between a mark that agreed (200 ms) and the next, which showed it (574.6
    ms): a sample in between gets the pitch times the chance the skip came before it, so a
    frame exposed there is off by less on average than with the pitch from the second mark on
    (all of it whenever the skip came first), and a sample before the first gets none."""
    chain = ChainFilter(ChainFilterConfig(scale_sigma0=1e-4))  # a chain known to 0.01 %
    marks = (1100.0, 1300.0)
    feed = PoseFeed(SampleBuffer(1, 512), AngleBuffer(2, 512), HOME_S_MM, marks, chain=chain)
    for k in range(121):  # 500 mm/s, samples every 5 ms; the chain jumps a tooth at 210 ms
        feed.on_encoder(k * 5 * MS, 2.5 * k, 500.0, HOMED)
        if k == 40:
            feed.on_mark(200 * MS, 100.0)  # at 1100 mm, where the encoder says: no skip yet
        if k == 116:
            feed.on_mark(574_600_000, 287.3)  # at 1300 mm: 12.7 mm further than it reads
    assert feed.chain is not None
    assert feed.chain.stats.skips_detected == 1

    def correction(t_ms: int) -> float:
        value = feed.encoder.lookup(t_ms * MS).value
        assert value is not None
        return float(value[0]) - (HOME_S_MM + 0.5 * t_ms)

    assert correction(195) == pytest.approx(0.0, abs=0.05)
    assert correction(500) == pytest.approx(300 / 374.6 * PITCH_MM, abs=0.1)
    assert correction(580) == pytest.approx(PITCH_MM, abs=0.05)
