"""The daemon's real parts: the controller link and the pose loop, built from the configuration.

`controller_factory` gives the daemon `host.link.Controller` on the transport named by `[link]`,
with the stream rates, the track window and the recording tap. `frame_loop_factory` builds
what turns the controller's samples into camera poses: a `PoseFeed` (encoder and head samples
into time-indexed buffers), a `PoseSource` on the configured rig, and either a camera frame loop
with per-frame registration or, without a camera, a fixed-rate pose publisher, so the pose
stream, FreeD and `orbitar watch` work on a rig (or an emulator) that has no camera attached.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from host.commissioning.frames import FrameTap as LatestFrameTap
from host.commissioning.frames import attach_range_tap
from host.config import Config
from host.control.api import ControllerLike, FrameLoopLike, PoseSample, PoseSink
from host.frames.loop import FrameLoop
from host.frames.registrar import Registrar, Registration
from host.frames.sources import Frame, FrameSource, VideoCaptureSource
from host.frames.stamps import SteadyClockSource
from host.fusion import rig_references
from host.fusion.chain_filter import ChainFilter, ChainFilterConfig
from host.fusion.range_fix import RangeFixer
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.model import Wireframe, load_model, manipulator_wireframe
from host.geometry.track import Track
from host.geometry.transforms import FloatArray
from host.link import Controller
from host.link.batches import plan_for
from host.link.common import LinkEvent
from host.link.limits import TrackWindow
from host.link.reconnect import BackoffConfig
from host.link.session import SessionConfig
from host.link.shedding import SheddingConfig
from host.recording.taps import FrameTap, attach_link_tap
from host.recording.writer import KIND_ENCODER, KIND_EVENT, KIND_HEAD, KIND_RANGE
from host.registration.pose_buffer import AngleBuffer, LookupStatus, PoseSource, SampleBuffer
from host.registration.track_feed import DEFAULT_CHAIN_PITCH_MM, PoseFeed
from host.rig import RigError, RigSpec, build_kinematics, current_rig
from host.rig import build_camera as build_camera_model
from host.rig import build_track as rig_build_track
from host.rig import workpiece_pose as rig_workpiece_pose
from host.service.daemon import RecordTap
from host.transport import Transport, TransportConfigError, create_transport
from protocol.enums import Stream

log = logging.getLogger(__name__)

# Telemetry each link carries comfortably (a 115200 Bd UART, a ~35 kbit/s radio, 500 kbit/s CAN),
# leaving room for commands, their replies and retransmissions.
#
# XBee budget. The air carries ~35 kbit/s = 4375 B/s for both directions (one half-duplex channel),
# and each wire frame is one RF packet with 18 bytes of air overhead. Alone, a sample costs its
# frame + 18 B: ENCODER_SAMPLE 26 + 18 = 44 B, so 100 Hz of it would nearly fill the air by itself.
# With batched telemetry (both sides offer it in the handshake) a packet carries a stream's samples
# of up to its batch age (host.link.batches.BATCH_AGES_MS): its first sample in full, then 9 B
# (encoder) or 5 B (range) per further one. At the rates below, per second: encoder 100 Hz, age 40
# ms, 5 a batch: 20 × (62 + 18) = 1600 B; range 50 Hz, age 60 ms, ~4 a batch: 612 B; head 10 Hz
# alone (its 100 ms step exceeds a record's 65 ms): 10 × (21 + 18) = 390 B; STATUS 2 × (27 + 18) =
# 90 B. The clock sync's probe pairs cost 2 × (23 + 18) = 82 B per Hz: 10 Hz until the fit
# converges, then 1 Hz (host.link.probe_rate). The host's HEARTBEAT (13 + 18 B) fills its silences
# every WATCHDOG_MS / 4 (not more often than `heartbeat_ms`, at least every 250 ms): 248 B/s at the
# default 500 ms watchdog, 155 B/s at a 200 ms `heartbeat_ms`, 124 B/s at a 2 s watchdog. Converged
# that is 2774 B/s + heartbeats = 63 % + 2.8–5.7 % of the air with ranging; converging, 17 % more
# for the first ~20 s (81–86 %), which the modules' buffers ride out at some loss; 4 Hz fast probes
# would fit the air, but were tried and left the demo's short run with fewer probes in its fit and a
# clock error no better (worse on most runs, under load). The rest carries commands (a full window
# of 8 MOVE_TO and their ACKs is ~0.6 kB, 0.14 s of air) and MAC retries;
# tests/service/test_stream_budget.py redoes the sum with the firmware's own batcher. Beyond the
# air's rate a module's 202-byte buffer overflows and loses replies as often as telemetry; the
# daemon then sheds telemetry on XBee (`XBEE_SHEDDING`), slowing the streams and lengthening the
# batch ages together.
# The price of batching is age. A sample's trip is store-and-forward: controller UART (115200
# Bd), air, module latency, host UART: ~21 ms for a 35-byte frame, +3.6 ms per further 9-byte
# record, plus waiting for the air. A batch of n encoder samples at 100 Hz holds its oldest
# (n − 1) × 10 ms, so the p95 age is about (n − 1) × 10 ms + the trip: 75 ms at age 40 (n = 5),
# ~57 ms at age 30, ~47 ms at age 20 (80 % of the air). A p95 within 40 ms needs n ≤ 2, i.e.
# 50 encoder packets a second, 2650 B/s of air for the encoder alone and ~97 % with the other
# streams: this radio cannot carry 100 + 50 Hz that young (benchmarks/bench_xbee_telemetry.py
# measures the trade, `--modes ages_E_R`). Ages are multiples of the sample period: one between
# two adds wait and saves no packet.
# A controller that does not batch gets the single-sample budget instead
# (host.link.batches.SINGLE_SAMPLE_RATES_HZ): without ranging 30 × 44 + 10 × 39 + 2 × 45 + 82
# = 1882 B/s = 43 %, with ranging 25 × 44 + 15 × 36 + 10 × 39 + 2 × 45 + 82 = 50 % (+ heartbeats;
# fast probes 17 % more while converging). The rates' floors: 25 Hz encoder keeps a sample
# within 40 ms of any instant (horizon 50 ms), 10 Hz head within 100 ms (horizon 150 ms); STATUS
# is also sent on every state change.
STREAM_RATES_HZ: dict[str, dict[Stream, int]] = {
    "serial": {Stream.ENCODER: 200, Stream.HEAD: 50, Stream.STATUS: 20},
    "xbee": {Stream.ENCODER: 100, Stream.HEAD: 10, Stream.STATUS: 2},
    "can": {Stream.ENCODER: 500, Stream.HEAD: 100, Stream.STATUS: 20},
}
# With surveyed surfaces every reading is a drift fix, and the sooner one follows a tooth skip
# the fewer frames carry it. The rangefinder takes what each link has room for:
# - serial: the encoder yields half its rate (100 Hz still interpolates a move to ~0.01 mm),
#   which leaves the line at ~67 % instead of ~74 % with 200 Hz encoder and 100 Hz range
#   (single samples; 5 ms batches take less);
# - XBee: 50 Hz beside 100 Hz encoder, in batches (budget above);
# - CAN (500 kbit/s): 250 + 250 Hz is ~55 % of the bus, where 500 + 500 Hz would saturate it.
RANGING_RATES_HZ: dict[str, dict[Stream, int]] = {
    "serial": {Stream.ENCODER: 100, Stream.RANGE: 200},
    "xbee": {Stream.ENCODER: 100, Stream.RANGE: 50},
    "can": {Stream.ENCODER: 250, Stream.RANGE: 250},
}

# How unevenly a link's legs may split a clock probe's round trip beyond what its fit sees (part
# of the clock's `uncertainty_ns`, the σ `calibrate latency` takes for the clock): on the radio the
# probes queue behind telemetry on the shared air, more on one leg than the other, and the
# daemon's clock was 84-712 µs off (median, per run) during the quick demo's latency calibration
# over three seeds (2026-12-03), ~430 µs RMS. A UART's or CAN's legs queue apart and the fit's
# own σ covers them.
CLOCK_ASYMMETRY_SIGMA_US: dict[str, float] = {"xbee": 500.0}

# On XBee the MAC retries every packet, so the controller's frames go missing mostly when a
# module's buffer overflows: then the daemon slows the streams until they fit the air again.
XBEE_SHEDDING = SheddingConfig()


def stream_rates(kind: str, ranging: bool, batched: bool = True) -> dict[Stream, int]:
    """Telemetry rates for a link kind, with the rangefinder when its readings are used.

    `batched`: whether the controller batches telemetry (the session agreed on it); a link whose
    single-sample budget differs has its own rates then (host.link.batches).
    """
    rates = dict(STREAM_RATES_HZ[kind])
    if ranging:
        rates.update(RANGING_RATES_HZ[kind])
    plan = plan_for(kind)
    return rates if batched or plan is None else plan.unbatched(rates)


# How long a frame may wait for the samples of its exposure (`registration.frame_wait_ms =
# "auto"`, host.frames.loop): about the longest a sample arrives after a frame stamped at the
# same instant. Over XBee a batch holds its oldest sample 40–60 ms and the trip and the air add
# 25–50 ms (the budget above); serial and CAN batches are 5 ms old.
FRAME_WAIT_MS: dict[str, float] = {"serial": 30.0, "xbee": 150.0, "can": 20.0}


def frame_wait_s(kind: str, configured: float | str = "auto") -> float:
    """The longest a frame waits for its samples on this link kind, in seconds."""
    return (FRAME_WAIT_MS[kind] if configured == "auto" else float(configured)) / 1000.0


ENCODER_HORIZON_NS = 50_000_000  # carry the trolley forward at most 50 ms past its last sample
HEAD_HORIZON_NS = 150_000_000  # head samples are slower and the head moves slowly
MAX_GAP_NS = 300_000_000
MIN_BUFFER_SAMPLES = 64
BUILTIN_MODEL = "builtin:manipulator"
NO_CAMERA_SOURCES = ("none", "sim")  # "sim" frames exist only inside the emulator's process
FPS_WINDOW_S = 2.0


class WiringError(ValueError):
    """The configuration names something that cannot be built (a model file, a transport)."""


# ---- the controller ------------------------------------------------------------------------


def build_transport(config: Config) -> Transport:
    """The transport `[link]` describes; WiringError names a bad option."""
    link = config.link
    try:
        if link.kind == "serial":
            return create_transport("serial", url=link.url, baudrate=link.baud)
        if link.kind == "xbee":
            return create_transport(
                "xbee",
                url=link.url,
                baudrate=link.baud,
                dest_addr64=link.xbee_address,
                api_mode=link.xbee_api_mode,
            )
        return create_transport(
            "can",
            interface=link.can_interface,
            channel=link.can_channel,
            node_id=link.node_id,
            bitrate=link.can_bitrate,
        )
    except TransportConfigError as exc:
        raise WiringError(f"[link]: {exc}") from exc


class RecordingSink:
    """A `SampleSink` that hands encoder and head samples to the daemon's recording tap."""

    def __init__(self, tap: RecordTap) -> None:
        self.tap = tap

    def on_encoder(self, t_host_ns: int, s_mm: float, velocity_mm_s: float, inputs: int) -> None:
        """One encoder sample."""
        self.tap(KIND_ENCODER, t_host_ns, {"s_mm": s_mm, "v_mm_s": velocity_mm_s, "inputs": inputs})

    def on_head(self, t_host_ns: int, pan_rad: float, tilt_rad: float) -> None:
        """One head sample."""
        self.tap(KIND_HEAD, t_host_ns, {"pan_rad": pan_rad, "tilt_rad": tilt_rad})

    def on_range(self, t_host_ns: int, distance_mm: float, quality: int) -> None:
        """A rangefinder sample (streamed only when surveyed surfaces make it a reference)."""
        self.tap(KIND_RANGE, t_host_ns, {"distance_mm": distance_mm, "quality": quality})

    def on_mark(self, t_host_ns: int, s_mm: float) -> None:
        """A reference mark passed: an event in the recording."""
        self.tap(KIND_EVENT, t_host_ns, {"ref_mark_mm": s_mm})


def controller_factory(
    config: Config, record_tap: RecordTap, transport: Transport | None = None
) -> Controller:
    """The real controller on the configured link (or on `transport`, for an emulator)."""
    session = SessionConfig(
        heartbeat_interval_s=config.link.heartbeat_ms / 1000.0,
        clock_asymmetry_sigma_us=CLOCK_ASYMMETRY_SIGMA_US.get(config.link.kind, 0.0),
    )
    backoff = BackoffConfig(max_s=config.link.reconnect_max_s)

    def on_event(event: LinkEvent, detail: str) -> None:
        record_tap(KIND_EVENT, time.monotonic_ns(), {"link_event": event.value, "detail": detail})

    shedding = XBEE_SHEDDING if config.link.kind == "xbee" else None
    raw = attach_link_tap(transport or build_transport(config), record_tap)  # bytes recorded
    ctrl = Controller(
        raw,
        session,
        backoff,
        on_event=on_event,
        shedding=shedding,
        track_window=track_window(config),
        streams_hz=config_stream_rates(config),
        telemetry_plan=plan_for(config.link.kind),
    )
    ctrl.add_sink(RecordingSink(record_tap))
    ctrl.add_stats(lambda: clock_stats(ctrl))
    attach_range_tap(ctrl)  # the readings a workpiece or home survey averages
    log.info("controller link configured", extra={"kv": {"link": ctrl.transport.describe()}})
    return ctrl


def clock_stats(ctrl: Controller) -> dict[str, Any]:
    """The clock sync's error and drift, for the station's and the terminal's status, and the
    drift the telemetry's one-way delays alone give (host.link.skew; None before ~10 s of
    telemetry): the fit leans on it, so the two differ by a few ppm at most once settled."""
    sync = ctrl.session.clock
    clock, skew = sync.estimate(), sync.skew()
    sigma_us = round(clock.sigma_ns / 1e3, 3) if clock.probes_used else None
    envelope_ppm = None
    if skew is not None:
        envelope_ppm = round((sync.nominal_ns_per_tick / skew.ns_per_tick - 1.0) * 1e6, 3)
    return {
        "clock_sigma_us": sigma_us,
        "clock_drift_ppm": round(clock.drift_ppm, 3),
        "clock_telemetry_drift_ppm": envelope_ppm,
    }


def config_stream_rates(config: Config) -> dict[Stream, int]:
    """The telemetry rates for the configured link (with ranging when surfaces are surveyed)."""
    return stream_rates(config.link.kind, bool(rig_spec(config).hall.surfaces))


# ---- rig, camera, model --------------------------------------------------------------------


def rig_spec(config: Config) -> RigSpec:
    """The rig description `[rig] path` names (the paper's rig when empty); WiringError if bad."""
    try:
        return current_rig(config.rig.path)
    except RigError as exc:
        raise WiringError("; ".join(exc.problems)) from exc


def build_track(config: Config) -> Track:
    """The rig file's track, placed in the world."""
    try:
        return rig_build_track(rig_spec(config).track)
    except ValueError as exc:
        raise WiringError(f"track: {exc}") from exc


def track_window(config: Config) -> TrackWindow | None:
    """An open track's extent in controller millimetres (its zero is at the rig's home)."""
    track = build_track(config)
    if track.closed:
        return None
    home = rig_spec(config).track.home.value
    return TrackWindow(-home, track.length_mm - home)


def build_rig(config: Config) -> Rig:
    """Track, M_cr and the rangefinder mount (rotations made orthonormal)."""
    return build_kinematics(rig_spec(config))  # validated on load: the path builds


def build_references(
    config: Config, rig: Rig, pitch_mm: float | None
) -> tuple[RangeFixer | None, ChainFilter | None]:
    """The chain filter's references as the rig file describes them, with its σ: rangefinder
    fixes on its surveyed surfaces (their mount, placement and surface errors held as the
    filter's states) and its marks; no filter when it lists neither. The demo measures the
    drift correction with these very ones (host.fusion.rig_references)."""
    spec = rig_spec(config)
    ranger = rig_references.ranger(spec, rig)
    if ranger is None and not spec.track.marks.s_mm:
        return None, None
    pitch = pitch_mm or DEFAULT_CHAIN_PITCH_MM
    return ranger, ChainFilter(rig_references.chain_config(spec, pitch))


def build_camera(config: Config) -> CameraModel:
    """The rig file's camera intrinsics and resolution."""
    return build_camera_model(rig_spec(config))


def build_model(config: Config) -> Wireframe:
    """The workpiece wireframe: a file, or the built-in manipulator."""
    path = rig_spec(config).workpiece.model
    if path == BUILTIN_MODEL:
        return manipulator_wireframe()
    try:
        return load_model(path)
    except (OSError, ValueError) as exc:
        raise WiringError(f"workpiece.model = {path!r}: {exc}") from exc


# ---- samples → poses -----------------------------------------------------------------------


def build_pose_source(
    config: Config,
    rates_hz: Mapping[Stream, int],
    exposure_latency_ms: float = 0.0,
    pitch_mm: Callable[[], float | None] = lambda: None,
) -> tuple[PoseSource, PoseFeed]:
    """Buffers sized to the registration horizon at the stream rates, and the rig's pose source."""
    horizon_s = config.registration.horizon_ms / 1000.0
    enc_cap = max(MIN_BUFFER_SAMPLES, math.ceil(horizon_s * rates_hz.get(Stream.ENCODER, 1)))
    head_cap = max(MIN_BUFFER_SAMPLES, math.ceil(horizon_s * rates_hz.get(Stream.HEAD, 1)))
    spec = rig_spec(config)
    rig = build_rig(config)
    ranger, chain = build_references(config, rig, pitch_mm())
    feed = PoseFeed(
        SampleBuffer(1, enc_cap, ENCODER_HORIZON_NS, MAX_GAP_NS),
        AngleBuffer(2, head_cap, HEAD_HORIZON_NS, MAX_GAP_NS),
        home_s_mm=spec.track.home.value,
        marks_mm=spec.track.marks.s_mm,
        lap_mm=rig.track.length_mm if rig.track.closed else None,
        pitch_mm=pitch_mm,
        ranger=ranger,
        chain=chain,
    )
    latency_ns = round(exposure_latency_ms * 1e6)
    source = PoseSource(rig, feed.encoder, feed.head, exposure_latency_ns=latency_ns)
    return source, feed


def apply_rig(config: Config, poses: PoseSource, feed: PoseFeed, latency_ms: float) -> None:
    """Swap a changed rig file into a running pose pipeline (SIGHUP): samples keep flowing.

    The buffers keep their samples; those already pushed were placed with the old home and
    chain correction, which the next homing (or the next few samples, for a live trolley)
    replaces. The chain filter keeps its state unless the file changed what it rests on (the
    references' σ, the range model's states): then it starts afresh, as at a homing.
    """
    spec = rig_spec(config)
    rig = build_rig(config)
    poses.rig = rig
    poses.exposure_latency_ns = round(latency_ms * 1e6)
    feed.home_s_mm = spec.track.home.value
    feed.marks_mm = spec.track.marks.s_mm
    feed.lap_mm = rig.track.length_mm if rig.track.closed else None
    current = feed.chain.config.chain_pitch_mm if feed.chain is not None else feed.pitch_mm()
    feed.ranger, chain = build_references(config, rig, current)
    if chain is None or feed.chain is None or not _same_config(chain.config, feed.chain.config):
        feed.chain = chain


def _same_config(a: ChainFilterConfig, b: ChainFilterConfig) -> bool:
    """Equal filter configurations (the bias covariance, an array, is left out of `==`)."""
    a_cov, b_cov = a.bias_cov, b.bias_cov
    if a_cov is None or b_cov is None:
        return a == b and a_cov is b_cov
    return a == b and a_cov.shape == b_cov.shape and bool(np.array_equal(a_cov, b_cov))


def exposure_latency_ms(config: Config) -> float:
    """The rig file's calibrated time from mid-exposure to the frame's stamp."""
    return rig_spec(config).camera.latency.value


def workpiece_pose(config: Config) -> FloatArray:
    """T_w_p: the rig file's workpiece frame in the world (full 6-DoF)."""
    return rig_workpiece_pose(rig_spec(config))


class RateMeter:
    """Events per second over a sliding window."""

    def __init__(self, window_s: float = FPS_WINDOW_S) -> None:
        self.window_ns = round(window_s * 1e9)
        self._times: list[int] = []

    def tick(self, t_ns: int) -> None:
        """Count one event."""
        self._times.append(t_ns)
        cutoff = t_ns - self.window_ns
        while self._times and self._times[0] < cutoff:
            self._times.pop(0)

    def rate(self, now_ns: int | None = None) -> float:
        """Events per second over the window ending now (0 until two events, 0 when they stop)."""
        cutoff = (time.monotonic_ns() if now_ns is None else now_ns) - self.window_ns
        while self._times and self._times[0] < cutoff:
            self._times.pop(0)
        if len(self._times) < 2:
            return 0.0
        span_s = (self._times[-1] - self._times[0]) / 1e9
        return (len(self._times) - 1) / span_s if span_s > 0 else 0.0


def pose_sample(
    t_ns: int,
    T_w_c: FloatArray,
    snapshot: Mapping[str, Any],
    s_mm: float,
    index: int,
    head_rad: tuple[float, float],
) -> PoseSample:
    """A PoseSample with plain nested tuples (msgpack- and FreeD-ready), flagged when unhomed."""
    matrix = tuple(tuple(float(x) for x in row) for row in T_w_c)
    state = str(snapshot.get("state", "UNKNOWN"))
    head = (float(head_rad[0]), float(head_rad[1]))
    return PoseSample(t_ns, matrix, state, float(s_mm), index, bool(snapshot.get("homed")), head)


# ---- the loops ---------------------------------------------------------------------------


# Without a camera the poses follow the link's lag: the longest of the last second, at most
# LAG_CAP_NS (past it the link has stalled, and a pose for now is stale, not an old one re-sent).
LAG_WINDOW_NS = 1_000_000_000
LAG_CAP_NS = 250_000_000


class PosePublisher:
    """Without a camera: poses at a fixed rate from the buffers, each for the latest instant
    the link's samples reliably cover and stamped with it.

    Over a slow link a pose for the current instant would be carried past the newest sample,
    beyond the buffer's horizon most of the time: XBee batches arrive 20–100 ms after their
    stamps, and such poses were stale on 69 % of the ticks. Each pose is made for now less the
    longest lag of the last second instead (a few ms on serial and CAN).
    """

    def __init__(
        self,
        poses: PoseSource,
        controller: Controller,
        sink: PoseSink,
        rate_hz: float,
        feed: PoseFeed | None = None,
    ) -> None:
        self.poses = poses
        self.feed = feed
        self.rig: RigSpec | None = None  # the rig file's content the poses are computed with
        self.controller = controller
        self.sink = sink
        self.period_ns = round(1e9 / rate_hz)
        self.published = 0
        self.stale = 0  # ticks without a usable pose (no samples yet, or the stream stalled)
        self.off_track = 0  # of those, ticks with the trolley outside the surveyed open track
        self._meter = RateMeter()
        self._lags: deque[tuple[int, int]] = deque()  # (tick, now − covered instant)
        self._last_t_ns = 0

    @property
    def fps(self) -> float:
        """Poses published per second, recently."""
        return self._meter.rate()

    async def run(self) -> None:
        """Publish until cancelled, on a drift-free schedule."""
        next_ns = time.monotonic_ns()
        while True:
            next_ns += self.period_ns
            now = time.monotonic_ns()
            if next_ns < now:  # fell behind (a stalled loop): skip, do not burst
                next_ns = now + self.period_ns
            await asyncio.sleep((next_ns - now) / 1e9)
            t_ns = self.pose_time(time.monotonic_ns())
            if t_ns > self._last_t_ns:  # a lag that grew would go back in time: wait instead
                self._last_t_ns = t_ns
                self.publish(t_ns)

    def pose_time(self, now_ns: int) -> int:
        """The instant to publish at `now_ns`: now less the link's recent lag."""
        until = self.feed.covered_until() if self.feed is not None else None
        lag = 0 if until is None else now_ns - until
        self._lags.append((now_ns, lag if 0 < lag <= LAG_CAP_NS else 0))
        while self._lags[0][0] < now_ns - LAG_WINDOW_NS:
            self._lags.popleft()
        return now_ns - max(held for _, held in self._lags)

    def apply_rig(self, config: Config) -> None:
        """A changed rig file (SIGHUP): the poses from now on use it."""
        if self.feed is not None:
            apply_rig(config, self.poses, self.feed, 0.0)
        self.rig = rig_spec(config)

    def publish(self, t_ns: int) -> bool:
        """One pose at t_ns to the sink; False (counted) when the buffers cannot give one."""
        pose = self.poses.pose_at(t_ns)
        if not pose.ok or pose.T_w_c is None:
            self.stale += 1
            self.off_track += pose.status is LookupStatus.OFF_TRACK
            return False
        self.published += 1
        self._meter.tick(t_ns)
        snapshot = self.controller.snapshot()
        head = (pose.pan_rad, pose.tilt_rad)
        self.sink(pose_sample(t_ns, pose.T_w_c, snapshot, pose.s_mm, self.published, head))
        return True


class CameraPoseLoop:
    """With a camera: the frame loop registers each frame and publishes its pose."""

    def __init__(
        self,
        source: FrameSource,
        registrar: Callable[[Frame], Registration],
        controller: Controller,
        sink: PoseSink,
        record_tap: RecordTap,
        poses: tuple[PoseSource, PoseFeed] | None = None,
        max_wait_s: float = 0.0,
    ) -> None:
        self.frame_tap = LatestFrameTap(source)  # the newest frame, for calibration runs
        self.source: FrameSource = self.frame_tap
        self.poses = poses  # what apply_rig swaps a changed rig file into
        self.rig: RigSpec | None = None  # the rig file's content the frames are registered with
        self.controller = controller
        self.sink = sink
        self.record_tap = record_tap
        self.unregistered = 0  # frames whose exposure had no usable pose
        self.loop: FrameLoop[Registration] = FrameLoop(
            self.source, registrar, [self._publish], self._samples_in, max_wait_s
        )
        self._meter = RateMeter()

    @property
    def fps(self) -> float:
        """Frames registered per second, recently."""
        return self._meter.rate()

    def apply_rig(self, config: Config) -> None:
        """A changed rig file (SIGHUP): camera model, workpiece and kinematics from now on."""
        if self.poses is not None:
            poses, feed = self.poses
            apply_rig(config, poses, feed, exposure_latency_ms(config))
            T_w_p = workpiece_pose(config)
            registrar = Registrar(
                poses, build_camera(config), build_model(config), lambda t_ns: T_w_p, draw=False
            )
            self.loop.process = FrameTap(registrar, self.record_tap)  # the next frame uses it
        self.rig = rig_spec(config)

    async def run(self) -> None:
        """Run the frame loop until cancelled or the source ends; release the camera after."""
        try:
            await self.loop.run()
        finally:
            self.loop.stop()
            self.source.close()

    def _samples_in(self, frame: Frame) -> bool:
        """Whether the link has delivered the samples of the frame's exposure."""
        if self.poses is None:
            return True
        poses, feed = self.poses
        return feed.covers(frame.exposure_ns - poses.exposure_latency_ns)

    def _publish(self, reg: Registration) -> None:
        """A registered frame (recorded by its FrameTap) → a PoseSample if it has a pose."""
        if reg.T_w_c is None:
            self.unregistered += 1
            return
        self._meter.tick(time.monotonic_ns())
        snapshot = self.controller.snapshot()
        head = (reg.pan_rad, reg.tilt_rad)
        self.sink(pose_sample(reg.exposure_ns, reg.T_w_c, snapshot, reg.s_mm, reg.index, head))


def open_camera(config: Config) -> FrameSource | None:
    """The configured camera, or None for "none"/"sim" or when it cannot be opened (logged)."""
    source, cam = config.camera.source, rig_spec(config).camera
    if isinstance(source, str) and source.lower() in NO_CAMERA_SOURCES:
        return None
    try:
        return VideoCaptureSource(source, cam.width, cam.height, cam.fps)
    except OSError as exc:
        log.error(
            "camera unavailable, publishing poses without frames", extra={"kv": {"error": exc}}
        )
        return None


def frame_loop_factory(
    config: Config,
    controller: ControllerLike,
    pose_sink: PoseSink,
    record_tap: RecordTap,
    camera: FrameSource | None = None,
) -> FrameLoopLike:
    """The pose loop on the controller's samples: per camera frame, or at a fixed rate.

    `camera` overrides `[camera] source` (the demo's simulated camera lives in its process).
    """
    if not isinstance(controller, Controller):
        raise WiringError("the pose loop needs the link controller built by controller_factory")
    model = build_model(config)  # checked even without a camera: a bad path shows at start
    camera = camera or open_camera(config)
    if camera is not None and config.camera.stamps == "steady":
        camera = SteadyClockSource(camera)
    latency_ms = exposure_latency_ms(config) if camera is not None else 0.0
    poses, feed = build_pose_source(
        config, config_stream_rates(config), latency_ms, controller.chain_pitch_mm
    )
    controller.add_sink(feed)
    controller.add_stats(feed.stats)
    if camera is None:
        publisher = PosePublisher(poses, controller, pose_sink, rig_spec(config).camera.fps, feed)
        publisher.rig = rig_spec(config)
        return publisher
    T_w_p = workpiece_pose(config)  # fixed: measured at set-up, the workpiece does not move
    registrar = Registrar(poses, build_camera(config), model, lambda t_ns: T_w_p, draw=False)
    recorded = FrameTap(registrar, record_tap)  # frames and their images to the recording
    wait_s = frame_wait_s(config.link.kind, config.registration.frame_wait_ms)
    camera_loop = CameraPoseLoop(
        camera, recorded, controller, pose_sink, record_tap, (poses, feed), wait_s
    )
    camera_loop.rig = rig_spec(config)
    return camera_loop
