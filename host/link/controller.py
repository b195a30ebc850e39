"""The controller: async commands in mm, mm/s and radians, state snapshots, pushed changes.

This is the one controller surface: the daemon, the control operations and the outputs call it
directly. `start()` connects in the background and keeps the link up (host.link.reconnect);
`subscribe()` pushes a `ControllerChange` whenever the link state or the controller's STATUS
changes, so nobody polls. Commands return when the controller acknowledged them; a NAK raises
ControllerRejected; while the link is not up they raise LinkDown at once (naming the cause)
instead of waiting. Streams and parameters set through this API are remembered and re-applied
after every reconnect (parameters only after a controller reset: otherwise they are still in
force). Motions are never re-sent. On an open track, motion off the surveyed ends is refused
and the soft limits are kept inside it (host.link.limits). With a `SheddingConfig`, streams run
slower than asked while the link loses the controller's frames (`host.link.shedding`).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from host.link.batches import BATCH_TYPES, BatchStats, TelemetryPlan, plan_for, unpack
from host.link.common import (
    UM_PER_MM,
    LinkError,
    LinkEvent,
    LinkState,
    OutsideTrack,
    decode_enum,
    decode_flags,
    label,
)
from host.link.limits import (
    TrackWindow,
    check_jog,
    check_soft_limit,
    check_target,
    sync_soft_limits,
)
from host.link.reconnect import BackoffConfig, Supervisor
from host.link.samples import (
    URAD_PER_RAD,
    EncoderReading,
    HeadReading,
    SampleMessage,
    SampleSink,
    frame_arrived,
    reading,
)
from host.link.session import SEQ_MOD, Session, SessionConfig
from host.link.shedding import Shedder, SheddingConfig
from host.link.snapshot import ControllerChange, Identity, Listener, Snapshot
from host.transport.base import Transport
from protocol import Packet, ParamId
from protocol.enums import Capability, Fault, Inputs, State, Stream
from protocol.messages import (
    ClearFault,
    EncoderSample,
    Estop,
    HeadSample,
    HeadSet,
    Home,
    Identify,
    Jog,
    MoveTo,
    ParamGet,
    ParamPersist,
    ParamSet,
    ParamValue,
    RangeSample,
    RefMark,
    Status,
    Stop,
    StreamSet,
)

log = logging.getLogger(__name__)
RING_SAMPLES = 4096  # ~4 s of encoder samples at 1 kHz
STATUS_RATE_HZ = 20  # switched on at connect: motion completion is judged from STATUS
DEFAULT_SPEED_MM_S = 100.0  # the paper's camera speed, when a move names none
DEFAULT_ACCEL_MM_S2 = 500.0


class MotionFailed(LinkError):  # noqa: N818
    """A motion ended in FAULT or ESTOP instead of reaching its target."""


StatsProvider = Callable[[], Mapping[str, Any]]


@dataclass
class Motion:
    """Handle of an acknowledged motion; `await motion.done(timeout)` waits for its end."""

    controller: Controller
    ack_seq: int
    target_mm: float | None
    boot_id: int | None = None  # the controller that accepted it; a reboot ends the motion

    async def done(self, timeout_s: float = 60.0) -> None:
        """Return once STATUS shows rest (at this target, for MOVE_TO); MotionFailed on a fault."""
        await self.controller._wait_for_rest(self.ack_seq, self.target_mm, timeout_s, self.boot_id)


@dataclass
class _Status:
    """Latest STATUS, with the controller seq it arrived in."""

    seq: int
    msg: Status
    t_ns: int


@dataclass
class Controller:
    """Async API over one transport, with automatic reconnection and pushed state changes."""

    transport: Transport
    session_config: SessionConfig = field(default_factory=SessionConfig)
    backoff: BackoffConfig = field(default_factory=BackoffConfig)
    on_event: Callable[[LinkEvent, str], None] | None = None
    seed: int | None = None
    shedding: SheddingConfig | None = None  # None: the streams always run at the rates asked for
    track_window: TrackWindow | None = None  # an open track: limits motion and soft limits
    streams_hz: Mapping[Stream, int] = field(default_factory=dict)  # on at every handshake
    telemetry_plan: TelemetryPlan | None = None  # batch ages per link; None: by transport scheme

    def __post_init__(self) -> None:
        self.telemetry_plan = self.telemetry_plan or plan_for(self.transport.scheme)
        self.session = Session(self.transport, self.session_config, on_packet=self._on_packet)
        self.supervisor = Supervisor(
            self.session,
            self._restore,
            on_state=self._on_link_state,
            backoff=self.backoff,
            seed=self.seed,
        )
        self.supervisor.on_event = self._forward_event
        self.identity: Identity | None = None
        self.encoder_ring: deque[tuple[int, float, float, int]] = deque(maxlen=RING_SAMPLES)
        self.unsynced_samples = 0  # samples dropped before the clock sync had a probe
        self.sink_errors = 0  # samples a sink raised on (logged, then ignored)
        self.batch_stats = BatchStats()  # samples that came in batches (host.link.batches)
        self._sinks: list[SampleSink] = []
        self._streams: dict[Stream, int] = {Stream.STATUS: STATUS_RATE_HZ, **self.streams_hz}
        self._params: dict[int, int] = {}
        self._status: _Status | None = None
        self._status_changed = asyncio.Event()
        self._last_position_mm: float | None = None
        self._last_inputs = 0
        self._updated_ns: int | None = None
        self._head_rad: tuple[float, float] | None = None
        self._head_ns: int | None = None
        self._listeners: list[Listener] = []
        self._stats: list[StatsProvider] = []
        self._last_state_key: tuple[int, int, int, int, int] | None = None
        self.listener_errors = 0  # subscribers that raised (logged, then ignored)
        self.soft_limits_error: str | None = None  # why the soft limits do not match the track
        self.shedder = None if self.shedding is None else Shedder(self.shedding)
        self._shed_task: asyncio.Task[None] | None = None

    # ---- connection ----------------------------------------------------------------------

    async def connect(self) -> Identity:
        """Open the transport, handshake, switch on the streams; reconnects automatically after.

        The first attempt's error propagates (tools and tests want it); `start()` never raises.
        """
        await self.supervisor.connect()
        assert self.identity is not None
        self._start_shedding()
        return self.identity

    def start(self) -> None:
        """Connect in the background, retrying with capped backoff for ever; never raises.

        The daemon's way in: a controller that is absent at start is a link state (pushed to
        subscribers with its cause), not an error.
        """
        self.supervisor.start()
        self._start_shedding()

    @property
    def connected(self) -> bool:
        """True while the session is up."""
        return self.link_state is LinkState.UP

    @property
    def link_error(self) -> str:
        """Why the link is not up: the last failure (empty while up)."""
        return "" if self.connected else self.supervisor.last_error

    def subscribe(self, listener: Listener) -> Callable[[], None]:
        """Get every link and STATUS change pushed from now on; returns the unsubscriber."""
        self._listeners.append(listener)
        return lambda: self._listeners.remove(listener) if listener in self._listeners else None

    def add_stats(self, provider: StatsProvider) -> None:
        """Merge a component's counters into link_stats() (the pose feed's, for one)."""
        self._stats.append(provider)

    def chain_pitch_mm(self) -> float | None:
        """The chain pitch the controller reported in IDENTIFY, None before the first handshake."""
        return None if self.identity is None else self.identity.chain_pitch_mm

    def link_stats(self) -> dict[str, Any]:
        """The session counters and the components' counters, as plain numbers."""
        stats = self.session.stats
        out: dict[str, Any] = {"state": self.link_state.value, "detail": self.link_error}
        for key, value in vars(stats).items():
            if isinstance(value, int | float):
                out[key] = value
        out["drops"] = stats.drops.total()
        out["rtt_ms"] = None if stats.rtt.srtt_s is None else round(stats.rtt.srtt_s * 1e3, 3)
        out["unsynced_samples"] = self.unsynced_samples
        out["telemetry_scale"] = self.telemetry_scale
        out["soft_limits_error"] = self.soft_limits_error
        out["sink_errors"] = self.sink_errors
        for provider in self._stats:
            out.update(provider())
        return out

    def _start_shedding(self) -> None:
        """The shedding loop, once, when configured."""
        if self.shedder is not None and self._shed_task is None:
            self._shed_task = asyncio.create_task(self._shed_loop(self.shedder), name="link-shed")
            self._shed_task.add_done_callback(_shed_ended)

    async def close(self) -> None:
        """Stop everything; commands raise LinkDown afterwards."""
        task, self._shed_task = self._shed_task, None
        if task is not None:
            task.cancel()  # an earlier failure was logged when it happened (_shed_ended)
            await asyncio.gather(task, return_exceptions=True)
        await self.supervisor.close()

    @property
    def telemetry_scale(self) -> float:
        """Fraction of the requested stream rates in force (below 1 while shedding)."""
        return 1.0 if self.shedder is None else self.shedder.scale

    @property
    def link_state(self) -> LinkState:
        """Where the link is."""
        return self.supervisor.state

    async def identify(self) -> Identity:
        """The constants from the last IDENTIFY."""
        self.supervisor.require_up()
        assert self.identity is not None
        return self.identity

    def add_sink(self, sink: SampleSink) -> None:
        """Receive every converted sample from now on."""
        self._sinks.append(sink)

    @property
    def sinks(self) -> tuple[SampleSink, ...]:
        """The sample sinks, in the order they were added."""
        return tuple(self._sinks)

    def snapshot(self) -> Snapshot:
        """Current knowledge, without waiting (typed attributes; plain values as a mapping)."""
        st = self._status.msg if self._status is not None else None
        homed = bool(self._last_inputs & Inputs.HOMED)
        position = self._last_position_mm
        track = None
        if homed and position is not None:
            track = "on" if self.track_window is None else self.track_window.where(position)
        return Snapshot(
            self.link_state,
            decode_enum(State, st.state) if st is not None else None,
            decode_flags(Fault, st.faults) if st is not None else Fault.NONE,
            st.inputs if st is not None else 0,
            position,
            self._updated_ns,
            time.monotonic_ns(),
            homed,
            track,
            self._head_rad,
            self.link_error,
            self._head_ns,
        )

    # ---- commands ------------------------------------------------------------------------

    async def home(self, speed_mm_s: float = 0.0) -> Motion:
        """Seek home (0 = the controller's HOME_SPEED)."""
        return await self._motion(Home(speed_um_s=_um(speed_mm_s)), None)

    async def move_to(
        self, mm: float, speed_mm_s: float | None = None, accel_mm_s2: float | None = None
    ) -> Motion:
        """Move to an absolute arc length along a trapezoidal profile (on the track only)."""
        speed = speed_mm_s or DEFAULT_SPEED_MM_S
        msg = MoveTo(_um(mm), _um(speed), _um(accel_mm_s2 or DEFAULT_ACCEL_MM_S2))
        if self.track_window is not None:
            check_target(self.track_window, mm)
        return await self._motion(msg, mm)

    async def jog(self, mm_s: float, accel_mm_s2: float | None = None) -> Motion:
        """Run at a signed velocity until stop (0 ramps down); never further off a track's end."""
        msg = Jog(_um(mm_s), _um(accel_mm_s2 or DEFAULT_ACCEL_MM_S2))
        check_jog(self.snapshot().track, mm_s)
        return await self._motion(msg, None)

    async def stop(self) -> None:
        """Controlled stop."""
        await self._command(Stop())

    async def estop(self) -> None:
        """Emergency stop, latched until clear_fault."""
        await self._command(Estop())

    async def clear_fault(self) -> None:
        """Release latched faults and the e-stop."""
        await self._command(ClearFault())

    async def set_head(self, pan_rad: float, tilt_rad: float) -> None:
        """Point the head."""
        await self._command(
            HeadSet(_scaled(pan_rad, URAD_PER_RAD), _scaled(tilt_rad, URAD_PER_RAD))
        )

    async def set_streams(self, rates_hz: dict[Stream, int]) -> None:
        """Switch streams on (rate) or off (0); remembered across reconnects.

        While the link sheds telemetry the controller gets the scaled rate. The rate is noted
        before it is sent, so that a rescale meanwhile includes it; a scale that changed while
        the command was on its way means sending it again.
        """
        for stream, rate in rates_hz.items():
            previous = self._streams.get(stream)
            self._streams[stream] = int(rate)
            try:
                while True:
                    sent = self._stream_rate(int(rate))
                    await self._command(StreamSet(int(stream), sent))
                    if self._stream_rate(int(rate)) == sent:
                        break
            except BaseException:
                if previous is None:
                    del self._streams[stream]
                else:
                    self._streams[stream] = previous
                raise

    async def get_param(self, param_id: int) -> int:
        """Read a parameter."""
        return await self._param(ParamGet(int(param_id)))

    async def set_param(self, param_id: int, value: int) -> int:
        """Write a parameter; returns the value in force; re-applied after a controller reset."""
        if self.track_window is not None:
            check_soft_limit(self.track_window, int(param_id), int(value))
        in_force = await self._param(ParamSet(int(param_id), int(value)))
        self._params[int(param_id)] = int(value)
        if param_id == ParamId.WATCHDOG_MS:
            self.session.follow_watchdog(in_force)
        return in_force

    async def persist_params(self) -> None:
        """Write the parameters to flash."""
        await self._command(ParamPersist())

    async def wait_idle(self, timeout_s: float = 60.0) -> None:
        """Wait until the controller rests after everything sent so far."""
        await self._wait_for_rest(None, None, timeout_s)

    # ---- internals -----------------------------------------------------------------------

    async def _command(self, msg: object) -> Packet:
        """Refuse while down; otherwise send reliably and return the reply."""
        self.supervisor.require_up()
        return await self.session.request(msg)

    async def _motion(self, msg: object, target_mm: float | None) -> Motion:
        """A command whose completion can be awaited; on an open track, soft limits first."""
        self.supervisor.require_up()
        if self.soft_limits_error is not None:
            await self._sync_soft_limits()  # the controller refused them earlier: try again
            if self.soft_limits_error is not None:
                raise OutsideTrack(f"motion refused: {self.soft_limits_error}")
        reply = await self._command(msg)
        boot_id = self.identity.boot_id if self.identity is not None else None
        return Motion(self, reply.seq, target_mm, boot_id)

    async def _param(self, msg: object) -> int:
        """A parameter request; the reply carries the value in force."""
        reply = (await self._command(msg)).message
        assert isinstance(reply, ParamValue)
        return reply.value

    async def _restore(self, ident: Identify, rebooted: bool) -> None:
        """After each handshake: streams always, parameters after a controller reset."""
        self.identity = Identity.from_message(ident)
        self._status = None
        self._status_changed.set()  # wake motion waiters: a reboot ends their motions
        await self._plan_telemetry()
        for stream, rate in self._streams.items():
            await self.session.request(StreamSet(int(stream), self._stream_rate(rate)))
        if rebooted:
            for pid, value in self._params.items():
                await self.session.request(ParamSet(pid, value))
        await self._follow_watchdog()
        await self._sync_soft_limits()

    async def _follow_watchdog(self) -> None:
        """Heartbeats as often as the controller's watchdog needs (its value may be in flash)."""
        reply = (await self.session.request(ParamGet(int(ParamId.WATCHDOG_MS)))).message
        if isinstance(reply, ParamValue):
            self.session.follow_watchdog(reply.value)

    async def _plan_telemetry(self) -> None:
        """Batch ages when both sides batch (longer while shedding), else single-sample rates."""
        plan = self.telemetry_plan
        if plan is None:
            return
        if not self.session.capabilities & Capability.BATCHED_TELEMETRY:
            self._streams.update(plan.unbatched(self._streams))
            return
        scale = 1.0 if self.shedder is None else self.shedder.scale
        for pid, age_ms in plan.age_params(scale).items():
            await self.session.request(ParamSet(pid, age_ms))

    async def _sync_soft_limits(self) -> None:
        """Keep the controller's soft limits inside an open track; note why when it refuses."""
        if self.track_window is not None:
            self.soft_limits_error = await sync_soft_limits(self.session, self.track_window)

    def _stream_rate(self, requested_hz: int) -> int:
        """The rate the controller is asked for: as requested, or scaled while shedding."""
        return requested_hz if self.shedder is None else self.shedder.rate(requested_hz)

    async def _shed_loop(self, shedder: Shedder) -> None:
        """Each window: count the controller's frames received and lost; rescale the streams."""
        stats = self.session.stats
        seen: tuple[int, int] | None = None
        while True:
            await asyncio.sleep(shedder.config.window_s)
            if self.link_state is not LinkState.UP:
                seen = None  # a reconnect restarts the seq count: start a fresh window
                continue
            now = (stats.frames_in, stats.rx_lost)
            if seen is not None:
                received, lost = now[0] - seen[0], now[1] - seen[1]
                cuts = shedder.cuts
                if shedder.observe(received, lost):
                    level = logging.WARNING if shedder.cuts > cuts else logging.INFO
                    log.log(
                        level,
                        "telemetry at %.0f %% of its rates (%d of %d frames lost in %g s)",
                        shedder.scale * 100,
                        lost,
                        received + lost,
                        shedder.config.window_s,
                    )
                    await self._rescale_streams()
                    now = (stats.frames_in, stats.rx_lost)  # the change took a window of its own
            seen = now

    async def _rescale_streams(self) -> None:
        """Send every stream that is on its scaled rate, all at once (the window allows it)."""
        on = [(stream, rate) for stream, rate in self._streams.items() if rate > 0]
        results = await asyncio.gather(
            *(self._command(StreamSet(int(s), self._stream_rate(r))) for s, r in on),
            return_exceptions=True,
        )
        for (stream, _), result in zip(on, results, strict=True):
            if isinstance(result, LinkError):
                log.warning("could not rescale %s: %s", stream.name, result)
            elif isinstance(result, BaseException):
                raise result
        try:
            await self._plan_telemetry()  # batches wait longer while shedding: fewer packets
        except LinkError as exc:
            log.warning("could not rescale the batch ages: %s", exc)

    def _forward_event(self, event: LinkEvent, detail: str) -> None:
        """Pass link events to the user."""
        if self.on_event is not None:
            self.on_event(event, detail)

    def _on_link_state(self, state: LinkState, detail: str) -> None:
        """The supervisor moved the link: push it."""
        self._push("link")

    def _on_status(self, msg: Status) -> None:
        """Push a STATUS that changed the state, faults, inputs, position or target."""
        key = (msg.state, msg.faults, msg.inputs, msg.position_um, msg.target_um)
        if key != self._last_state_key:
            self._last_state_key = key
            self._push("state")

    def _push(self, topic: str) -> None:
        """Hand a change to every subscriber; one that raises is logged and ignored."""
        if not self._listeners:
            return
        change = ControllerChange(topic, self.snapshot())
        for listener in list(self._listeners):
            try:
                listener(change)
            except Exception:
                self.listener_errors += 1
                log.exception("a controller subscriber failed on %s", topic)

    async def _wait_for_rest(
        self, after_seq: int | None, target_mm: float | None, t: float, boot_id: int | None = None
    ) -> None:
        """Wait for a STATUS newer than `after_seq` showing rest (at target) or a fault."""
        async with asyncio.timeout(t):
            while True:
                self.supervisor.require_up()
                if boot_id is not None and self.identity and self.identity.boot_id != boot_id:
                    # Its seqs restarted and its profile is gone: this motion will never end.
                    raise MotionFailed("controller rebooted during the motion")
                if self._at_rest(after_seq, target_mm):
                    return
                self._status_changed.clear()
                await self._status_changed.wait()

    def _at_rest(self, after_seq: int | None, target_mm: float | None) -> bool:
        """True at rest; MotionFailed if the controller faulted."""
        st = self._status
        if st is None or (after_seq is not None and (st.seq - after_seq) % SEQ_MOD >= SEQ_MOD // 2):
            return False
        state = decode_enum(State, st.msg.state)
        if state in (State.FAULT, State.ESTOP):
            faults = decode_flags(Fault, st.msg.faults)
            raise MotionFailed(f"controller in {label(state)}, faults 0x{int(faults):04X}")
        if state not in (State.READY, State.IDLE):
            return False
        # The controller's own profile end, not the encoder (whether the trolley followed is the
        # firmware's following-error check); the firmware rounds the target to whole steps.
        return target_mm is None or abs(st.msg.target_um - _um(target_mm)) <= self._quantum_um()

    def _quantum_um(self) -> float:
        """Resolution of a target on the wire: the larger of one step and one encoder count."""
        ident = self.identity
        if ident is None:
            return 1.0
        per_rev_um = ident.sprocket_teeth * ident.chain_pitch_mm * UM_PER_MM
        return per_rev_um / min(ident.steps_per_rev, ident.encoder_counts_per_rev) + 1.0

    def _on_packet(self, packet: Packet) -> None:
        """Telemetry from the session."""
        msg = packet.message
        if isinstance(msg, Status):
            decode_enum(State, msg.state)  # an unknown value is logged once, here, on arrival
            decode_flags(Fault, msg.faults)
            self._status = _Status(packet.seq, msg, time.monotonic_ns())
            self._last_position_mm = msg.position_um / UM_PER_MM
            self._last_inputs = msg.inputs
            self._updated_ns = self._status.t_ns
            self._status_changed.set()
            self._on_status(msg)
        elif isinstance(msg, EncoderSample | HeadSample | RangeSample | RefMark):
            self._on_samples(msg, [msg])
        elif isinstance(msg, BATCH_TYPES):
            self._on_samples(msg, unpack(msg, self.batch_stats))  # each with its own MCU time

    def _on_samples(self, frame: object, samples: Sequence[SampleMessage]) -> None:
        """One telemetry frame: its arrival to the clock's rate, then each sample."""
        arrival_ns = self.session.transport.rx_time_ns or time.monotonic_ns()
        frame_arrived(self.session.clock, frame, samples, arrival_ns)
        for sample in samples:
            self._on_sample(sample)

    def _on_sample(self, msg: SampleMessage) -> None:
        """Convert to host time and units; a failing sink is logged, never the link's problem."""
        try:
            self._feed_sinks(msg)
        except Exception:
            self.sink_errors += 1
            log.exception("a sample sink failed on %s", type(msg).__name__)

    def _feed_sinks(self, msg: SampleMessage) -> None:
        """Convert to host time and units; feed the ring and the sinks."""
        sample = reading(msg, self.session.clock, self.identity)
        if sample is None:
            self.unsynced_samples += 1
            return
        if isinstance(sample, EncoderReading):
            t_ns, s_mm = sample.t_ns, sample.s_mm
            self.encoder_ring.append((t_ns, s_mm, sample.velocity_mm_s, sample.inputs))
            self._last_position_mm, self._updated_ns = s_mm, t_ns
            self._last_inputs = sample.inputs
        elif isinstance(sample, HeadReading):
            self._head_rad, self._head_ns = (sample.pan_rad, sample.tilt_rad), sample.t_ns
        for sink in self._sinks:
            sample.to(sink)


def _um(mm: float) -> int:
    """mm (or mm/s, mm/s²) → integer µm for the wire."""
    return _scaled(mm, UM_PER_MM)


def _scaled(value: float, factor: float) -> int:
    """value × factor rounded for the wire; ValueError (not OverflowError) for NaN or ±inf."""
    if not math.isfinite(value):
        raise ValueError(f"expected a finite number, got {value}")
    return round(value * factor)


def _shed_ended(task: asyncio.Task[None]) -> None:
    """Log a shedding loop that stopped by an error (the streams then stay at their scale)."""
    if not task.cancelled() and task.exception() is not None:
        log.error("telemetry shedding stopped", exc_info=task.exception())
