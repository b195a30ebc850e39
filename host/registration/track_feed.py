"""Link samples into pose buffers: the track arc length (drift-corrected) and the head angles.

Used by the daemon and by the demo alike: a `PoseFeed` is a `host.link.Controller` sample sink.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from host.fusion.chain_filter import ChainFilter, ChainFilterConfig
from host.fusion.range_fix import RangeFixer
from host.geometry.transforms import FloatArray
from host.registration.pose_buffer import AngleBuffer, Int64Array, SampleBuffer
from protocol.enums import Inputs

DEFAULT_CHAIN_PITCH_MM = 12.7  # ISO 08B / ANSI 40 roller chain, when the controller has not said
RAW_CAPACITY = 512  # uncorrected samples kept for late fixes (> 1 s at 500 Hz)
# A reading may be stamped after the newest encoder sample (another stream, same tick or later):
# the trolley is carried forward at most this far to place it; 50 Hz encoders need 20 ms.
RAW_HORIZON_NS = 50_000_000
# A frame waits for a reading after it only while readings flow: one this much older than the
# newest encoder sample says the rangefinder is off, aimed at nothing or lost.
RANGE_FLOWING_NS = 500_000_000
# A reading is a fix only if the head held still around it: the beam's direction comes from
# head samples (10 Hz over XBee) interpolated to the reading's stamp, and during a slew (1-2
# rad/s) a few milliseconds of that put the beam centimetres along a wall, which a fix reads
# as whole tooth skips. So a reading waits until the head's samples reach HEAD_STILL_NS past
# it, and is used only if the head turned less than HEAD_STILL_RAD over that span either side.
HEAD_STILL_NS = 20_000_000
HEAD_STILL_RAD = 2e-3
# A reading the head's samples have not reached after this long (the head stream stopped) is
# left unplaced; at most PENDING_RANGES wait at once (the oldest is then dropped, unplaced).
HEAD_WAIT_NS = 500_000_000
PENDING_RANGES = 256
# While the trolley drives a reading cannot wait: a frame waits for the reading after its
# exposure (a tooth skip shows in it), and over XBee the head's next sample comes up to 100 ms
# after the reading's batch. There the head is usually held (a drive looks ahead), so a reading
# the encoder reaches past is decided at once when the head held still over its last samples
# (HEAD_HELD_NS up to the newest, that one at most HEAD_CARRY_NS before the reading). A slew
# begun after the newest head sample is missed then; at rest, where the commissioning's slews
# happen, readings always wait. Moving: over MOVING_MM in the 50 ms before the reading.
HEAD_HELD_NS = 200_000_000
HEAD_CARRY_NS = 150_000_000
MOVING_NS = 50_000_000
MOVING_MM = 1.0


@dataclasses.dataclass
class PoseFeed:
    """A `SampleSink` filling the pose buffers: track arc length and head angles.

    The controller reports millimetres from its zero; the feed adds the surveyed `home_s_mm`.
    With absolute references configured — reference marks, or surveyed surfaces the rangefinder
    can read (`ranger`) — a `ChainFilter` maps the controller's millimetres to true ones (chain
    stretch, tooth skips) and the buffer holds the corrected arc length. A reference describes a
    past instant (the mark's edge, the reading's stamp): the samples buffered since then are
    corrected again, so frames registered after it arrives see it. The filter works relative to
    home, where its prior holds (the offset is small right after homing), so it starts afresh
    at every homing and ignores references while the controller is not homed.

    The controller's zero moves when the HOMED flag of its encoder samples changes (homing
    latches the index: the count jumps in the sample that first says HOMED; a reboot restarts
    it unhomed). Such a sample starts a new segment of the buffer, so no pose is made from the
    two sides of the jump, and the uncorrected samples kept for references are dropped: a
    reference stamped before the jump cannot be placed in the new coordinates.
    """

    encoder: SampleBuffer
    head: AngleBuffer
    home_s_mm: float = 0.0  # track arc length of the controller's zero
    marks_mm: tuple[float, ...] = ()  # surveyed mark positions (track arc length)
    lap_mm: float | None = None  # closed track: marks recur every lap
    pitch_mm: Callable[[], float | None] = lambda: None  # the controller's IDENTIFY, if known
    ranger: RangeFixer | None = None  # rangefinder readings of surveyed surfaces
    chain: ChainFilter | None = None
    raw_s_mm: float | None = None  # latest arc length before correction
    s_mm: float | None = None  # latest arc length pushed into the buffer
    marks_seen: int = 0  # REF_MARK events received
    marks_unhomed: int = 0  # of those, ignored: the controller's zero was not referenced yet
    ranges_seen: int = 0  # RANGE samples received
    # of those, not used: unhomed, no encoder/head sample around, or the head's samples never
    # reached past it (HEAD_WAIT_NS, a full queue, a new zero)
    ranges_unplaced: int = 0
    ranges_head_moving: int = 0  # of those, not used: the head turned around the reading
    homed: bool = False  # Inputs.HOMED of the latest encoder sample
    zero_resets: int = 0  # HOMED flag changes seen: the buffer is never bridged across them
    last_range_ns: int | None = None  # stamp of the newest RANGE sample decided (used or not)
    _raw: SampleBuffer = dataclasses.field(
        default_factory=lambda: SampleBuffer(1, RAW_CAPACITY, RAW_HORIZON_NS)
    )
    _agreed_ns: int | None = None  # stamp of the newest reference the filter took
    _skip_seen_ns: int | None = None  # first of the gated-out references pooled since
    # readings waiting for the head's samples past them: (stamp, distance, quality)
    _pending: deque[tuple[int, float, int]] = dataclasses.field(
        default_factory=lambda: deque(maxlen=PENDING_RANGES)
    )

    def __post_init__(self) -> None:
        if (self.marks_mm or self.ranger is not None) and self.chain is None:
            self.chain = ChainFilter(ChainFilterConfig(chain_pitch_mm=self._pitch()))

    def on_encoder(self, t_host_ns: int, s_mm: float, velocity_mm_s: float, inputs: int) -> None:
        """One encoder sample (controller mm from home) → the buffer, corrected when we can."""
        reset = self._follow_homing(bool(inputs & Inputs.HOMED))
        if reset and self.raw_s_mm is not None:
            self.zero_resets += 1
        self.raw_s_mm = self.home_s_mm + s_mm
        self.s_mm = self.raw_s_mm
        if self.chain is not None and self.homed:
            self.chain.predict(s_mm)
            self.s_mm = self.home_s_mm + self.chain.estimate(s_mm)[0]
        if reset:
            self._raw.clear()
        self._raw.push(t_host_ns, [s_mm])
        self.encoder.push(t_host_ns, [self.s_mm], after_reset=reset)
        if self._pending:
            self._decide_ranges()

    def raw_at(self, t_host_ns: int) -> float | None:
        """Track arc length at a time before the chain filter's corrections (home + controller
        mm), from the samples kept for late references; None outside them.

        What an offset in time is measured against: the corrected arc length moves by whole
        pitches when the filter takes a tooth skip, the controller's count never does.
        """
        enc = self._raw.lookup(t_host_ns)
        return None if enc.value is None else self.home_s_mm + float(enc.value[0])

    def covered_until(self) -> int | None:
        """The latest instant the samples in cover: the newest encoder sample, or, while
        rangefinder readings flow, the newest reading decided if it is older (a tooth skip
        before it shows in it; at rest, the newest reading in); None without encoder samples.
        The head is waited for only through the readings (each waits for the head's samples
        past it while the head may turn): its samples are sparse on a slow link (10 Hz over
        XBee), and it is steady or slow where the trolley is fast."""
        newest = self.encoder.newest_ns()
        last = self.last_range_ns
        if self._pending and not self._driving(self._pending[-1][0]):
            # at rest a frame's pose does not hang on readings waiting for the head's samples
            last = self._pending[-1][0]
        if newest is None or self.ranger is None or last is None:
            return newest
        return min(newest, last) if newest - last < RANGE_FLOWING_NS else newest

    def covers(self, t_host_ns: int) -> bool:
        """Whether the samples a pose at t is made from have come in (`covered_until`); with no
        stream at all (no link, or just re-homed) there is nothing to wait for."""
        until = self.covered_until()
        return until is None or t_host_ns <= until

    def on_head(self, t_host_ns: int, pan_rad: float, tilt_rad: float) -> None:
        """One head sample; it may reach past readings that waited for it."""
        self.head.push(t_host_ns, [pan_rad, tilt_rad])
        self._decide_ranges()

    def on_range(self, t_host_ns: int, distance_mm: float, quality: int) -> None:
        """A rangefinder reading: an absolute reference when it lands on a surveyed surface,
        decided once the head's samples reach past it (`HEAD_STILL_NS`)."""
        self.ranges_seen += 1
        if self.ranger is None or self.chain is None:
            self.last_range_ns = t_host_ns
            return
        if len(self._pending) == self._pending.maxlen:
            self._pending.popleft()  # the head stream stalled for longer than the queue lasts
            self.ranges_unplaced += 1
        self._pending.append((t_host_ns, distance_mm, quality))
        self._decide_ranges()

    def _decide_ranges(self) -> None:
        """Use or refuse, in order, the readings the head's samples now reach past (or, while
        the trolley drives with the head held, the encoder's)."""
        head_ns, enc_ns = self.head.newest_ns(), self.encoder.newest_ns()
        held = head_ns is not None and self._head_held(head_ns)
        while self._pending:
            t_ns, distance_mm, quality = self._pending[0]
            reached = head_ns is not None and head_ns >= t_ns + HEAD_STILL_NS
            driving = (
                held
                and head_ns is not None
                and t_ns - head_ns <= HEAD_CARRY_NS
                and enc_ns is not None
                and enc_ns >= t_ns
                and self._driving(t_ns)
            )
            given_up = enc_ns is not None and enc_ns > t_ns + HEAD_WAIT_NS
            if not (reached or driving or given_up):
                return
            self._pending.popleft()
            self.last_range_ns = t_ns
            if reached or driving:
                self._range_fix(t_ns, distance_mm, quality)
            else:
                self.ranges_unplaced += 1

    def _head_held(self, newest_ns: int) -> bool:
        """Whether the head's samples show it still over HEAD_HELD_NS up to the newest."""
        return self._turn(newest_ns - HEAD_HELD_NS, newest_ns) < HEAD_STILL_RAD

    def _driving(self, t_ns: int) -> bool:
        """Whether the controller's count moved over MOVING_MM in the MOVING_NS before t."""
        a, b = self._raw.lookup(t_ns - MOVING_NS), self._raw.lookup(t_ns)
        return (
            a.value is not None and b.value is not None and abs(b.value[0] - a.value[0]) > MOVING_MM
        )

    def _head_still(self, t_ns: int) -> bool:
        """Whether the head turned less than HEAD_STILL_RAD within HEAD_STILL_NS of t."""
        return self._turn(t_ns - HEAD_STILL_NS, t_ns + HEAD_STILL_NS) < HEAD_STILL_RAD

    def _turn(self, a_ns: int, b_ns: int) -> float:
        """The head's largest angle change between two instants; 0 without a sample at a (the
        head's own lookup at the reading decides then)."""
        before, after = self.head.lookup(a_ns), self.head.lookup(b_ns)
        if before.value is None or after.value is None:
            return 0.0
        turn = np.remainder(after.value - before.value + math.pi, 2.0 * math.pi) - math.pi
        return float(np.max(np.abs(turn)))

    def _range_fix(self, t_host_ns: int, distance_mm: float, quality: int) -> None:
        """One reading the head's samples reach past: a fix when it can be placed."""
        assert self.ranger is not None
        assert self.chain is not None
        enc = self._raw.lookup(t_host_ns)
        angles = self.head.lookup(t_host_ns)
        if not self.homed or enc.value is None or angles.value is None:
            self.ranges_unplaced += 1
            return
        if not self._head_still(t_host_ns):
            self.ranges_head_moving += 1
            return
        self._adopt_controller_pitch()
        rel = float(enc.value[0])
        predicted = self.home_s_mm + self.chain.estimate(rel)[0]
        pan, tilt = float(angles.value[0]), float(angles.value[1])
        fix = self.ranger.fix(predicted, pan, tilt, distance_mm if quality > 0 else None)
        if fix is None:
            return
        if fix.gradient is not None and len(fix.gradient) == self.chain.biases:
            # the filter holds the range model's parameters: the bias is weighed as shared
            self._reference(t_host_ns, rel, fix.s_mm - self.home_s_mm, fix.sigma_mm, fix.gradient)
        else:
            self._reference(t_host_ns, rel, fix.s_mm - self.home_s_mm, fix.total_sigma_mm)

    def on_mark(self, t_host_ns: int, s_mm: float) -> None:
        """A mark's captured encoder position: the nearest configured mark is the reference."""
        self.marks_seen += 1
        if self.chain is None or not self.marks_mm:
            return
        if not self.homed:
            self.marks_unhomed += 1
            return
        self._adopt_controller_pitch()
        predicted = self.home_s_mm + self.chain.estimate(s_mm)[0]
        mark = self.chain.associate(s_mm, self._candidates_rel(predicted))
        if mark is not None:
            self._reference(t_host_ns, s_mm, mark)

    def stats(self) -> dict[str, Any]:
        """Plain numbers for link statistics: raw and corrected position, the filter's state."""
        out: dict[str, Any] = {
            "track_s_mm": _rounded(self.s_mm),
            "raw_s_mm": _rounded(self.raw_s_mm),
            "marks_seen": self.marks_seen,
            "homed": self.homed,
            "zero_resets": self.zero_resets,
        }
        if self.chain is not None:
            rel_mm = 0.0 if self.raw_s_mm is None else self.raw_s_mm - self.home_s_mm
            sigma = self.chain.estimate(rel_mm)[1]
            out.update(
                chain_scale=round(float(self.chain.x[1]), 7),
                chain_offset_mm=round(float(self.chain.x[0]), 3),
                position_sigma_mm=round(sigma, 3),
                references_used=self.chain.stats.updates,
                references_rejected=self.chain.stats.rejected,
                marks_unhomed=self.marks_unhomed,
                marks_unassociated=self.chain.stats.unassociated,
                skips_detected=self.chain.stats.skips_detected,
            )
        if self.ranger is not None:
            out["ranges_seen"] = self.ranges_seen
            out["ranges_unplaced"] = self.ranges_unplaced
            out["ranges_head_moving"] = self.ranges_head_moving
            out["ranges_pending"] = len(self._pending)
            out.update({f"range_{k}": v for k, v in vars(self.ranger.stats).items()})
        return out

    def rehome(self, home_s_mm: float) -> None:
        """A new survey of the controller's zero: fresh buffer and filter."""
        self.home_s_mm = home_s_mm
        self.encoder.clear()
        self._raw.clear()
        self.ranges_unplaced += len(self._pending)  # stamped in the old zero's coordinates
        self._pending.clear()
        self._restart_filter()

    def _follow_homing(self, homed: bool) -> bool:
        """Whether the encoder's zero may have moved; a new homing voids what the filter learned."""
        if homed == self.homed:
            return False
        if homed:
            self._restart_filter()
        self.homed = homed
        return True

    def _reference(
        self,
        t_ns: int,
        enc_rel_mm: float,
        true_rel_mm: float,
        sigma_mm: float | None = None,
        gradient: FloatArray | None = None,
    ) -> None:
        """Apply one absolute reference stamped t_ns; if taken, re-correct the buffer from then.

        The encoder samples up to now have already been predicted through, hence no advance.
        """
        assert self.chain is not None
        skips = self.chain.stats.skips_detected
        if not self.chain.reference(enc_rel_mm, true_rel_mm, sigma_mm, False, gradient):
            # a gated-out reference the filter pools towards a skip: the skip came before it
            first = t_ns if self._skip_seen_ns is None else self._skip_seen_ns
            self._skip_seen_ns = first if self.chain.pooling else None
            return
        if self.chain.stats.skips_detected != skips and self._agreed_ns is not None:
            seen = t_ns if self._skip_seen_ns is None else self._skip_seen_ns
            self._correct_since(seen, ramp_from_ns=self._agreed_ns)
        else:
            self._correct_since(t_ns)
        self._agreed_ns, self._skip_seen_ns = t_ns, None

    def _correct_since(self, t_ns: int, ramp_from_ns: int | None = None) -> None:
        """Re-correct the buffered samples from t_ns on with the filter as it now stands.

        After a tooth skip, `ramp_from_ns` is the last reference that agreed with no skip: the
        skip happened at an instant between it and t_ns that no sensor saw. A sample there
        gets the correction times the chance that the skip came before it, (t - from) / (t_ns
        - from), the estimate with the least expected error for a frame exposed in between;
        with the whole correction from t_ns on such a frame carried the pitch whenever the skip
        came first (over XBee, with a reading every 20 ms, about one run in two).
        """
        chain = self.chain
        assert chain is not None
        t_raw, v_raw = self._raw.window()
        start = t_ns if ramp_from_ns is None else min(ramp_from_ns, t_ns)
        span = max(t_ns - start, 1)
        # the samples as corrected before this reference, for a ramp only (references come
        # often); read here, since `revise` calls `corrected` under the buffer's lock
        before = self.encoder.window() if start != t_ns else None

        def corrected(times: Int64Array) -> FloatArray:
            at = times.astype(np.float64)
            new = self.home_s_mm + chain.correct(
                np.interp(at, t_raw.astype(np.float64), v_raw[:, 0])
            )
            if before is None:
                return new[:, None]
            old = np.interp(at, before[0].astype(np.float64), before[1][:, 0])
            share = np.clip((at - start) / span, 0.0, 1.0)
            return (old + share * (new - old))[:, None]

        if len(t_raw):  # older samples than the raw ones kept cannot be recomputed
            self.encoder.revise(max(start, int(t_raw[0])), corrected)
            self.s_mm = self.home_s_mm + chain.estimate(float(v_raw[-1, 0]))[0]

    def _restart_filter(self) -> None:
        """Forget what the chain filter learned (same configuration)."""
        self._agreed_ns = self._skip_seen_ns = None
        if self.chain is not None:
            self.chain = ChainFilter(self.chain.config)

    def _pitch(self) -> float:
        """The controller's chain pitch if it has identified itself, else the nominal 12.7 mm."""
        return self.pitch_mm() or DEFAULT_CHAIN_PITCH_MM

    def _adopt_controller_pitch(self) -> None:
        """Until the first reference is taken, follow the pitch the controller reports."""
        assert self.chain is not None
        pitch = self._pitch()
        if self.chain.stats.updates == 0 and pitch != self.chain.config.chain_pitch_mm:
            config = dataclasses.replace(self.chain.config, chain_pitch_mm=pitch)
            self.chain = ChainFilter(config)

    def _candidates_rel(self, predicted_s_mm: float) -> tuple[float, ...]:
        """Mark positions relative to home; on a closed track, in the laps around the prediction."""
        if not self.lap_mm:
            return tuple(m - self.home_s_mm for m in self.marks_mm)
        lap = math.floor(predicted_s_mm / self.lap_mm)
        shifts = ((lap + k) * self.lap_mm - self.home_s_mm for k in (-1, 0, 1))
        return tuple(m + shift for shift in shifts for m in self.marks_mm)


def _rounded(value: float | None) -> float | None:
    """Millimetres to the micrometre, or None."""
    return None if value is None else round(value, 3)
