"""The host end of a link session: handshake, seq, ack/nak, retransmission, heartbeat, clock probes.

One `Session` sits on one transport. Reliable commands (`acked` in the message table) go out
with ACK_REQUESTED and are retransmitted with the same seq (and RETRANSMIT) until their reply
arrives, at most `rx_window` at a time; the RTO follows RFC 6298 with Karn's rule. Replies name
the command by `req_seq`; a reply for a seq no longer pending is a late duplicate, counted and
ignored. Requests are cancel-safe: the future is registered before the frame is sent and removed
in `finally`, whatever ends the wait. The session never reconnects by itself: it reports what it
sees (heartbeat silence, a controller reboot) through `on_event` and its owner decides.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from host.link.clocksync import ClockSync
from host.link.common import (
    BadIdentity,
    CommandTimeout,
    ControllerRejected,
    LinkDown,
    LinkEvent,
    LinkStats,
    ProtocolMismatch,
    decode_enum,
    note_unknown,
)
from host.link.probe_rate import ProbeRate
from host.transport.base import Transport, TransportError
from protocol import (
    PROTOCOL_VERSION,
    SCHEMA_HASH,
    Flag,
    FrameDecoder,
    Packet,
    encode_frame,
    spec_of,
)
from protocol.enums import Capability, NakCode, State
from protocol.messages import ClockSync as ClockSyncMsg
from protocol.messages import ClockSyncReply, Estop, Heartbeat, Hello, Identify, Nak, Stop

log = logging.getLogger(__name__)

SEQ_MOD = 1 << 16
U32_MOD = 1 << 32
# A frame with a tiny seq far from the expected one: the controller's counter restarted.
SEQ_RESTART_BELOW = 16
SEQ_RESTART_MIN_JUMP = 256
HOST_CAPABILITIES = int(Capability.BATCHED_TELEMETRY)  # Capability bits offered in HELLO
PROBE_ALIGN_MAX_S = 0.1  # a probe waits at most this long for a controller frame to follow
HEARTBEAT_MAX_S = 0.25  # 4 Hz costs an XBee 2.8 % of its air; 10 Hz cost 7 %
HEARTBEAT_SLACK_S = 0.002  # a wake-up this close to the heartbeat's time counts as on time
MAX_CLOCK_PROBES_IN_FLIGHT = 16  # older unanswered probes are forgotten
# G in RFC 6298, here the host's timer granularity: an asyncio loop on a busy PC wakes a few
# ms late. At 1 ms a link as regular as the emulated one drove RTTVAR to ~0, the RTO to
# SRTT + 1 ms, and any late wake-up into a spurious retransmit (air an XBee does not have).
RTO_CLOCK_GRANULARITY_S = 0.005
RTO_ALPHA = 1 / 8
RTO_BETA = 1 / 4
RTO_K = 4

_STOPS = (Stop, Estop)
_KNOWN_FLAGS = int(Flag.ACK_REQUESTED | Flag.RETRANSMIT)

EventHandler = Callable[[LinkEvent, str], None]
PacketHandler = Callable[[Packet], None]


@dataclass
class SessionConfig:
    """Timing of one session; the defaults suit a 115200 Bd serial link or an XBee radio."""

    # The shortest host heartbeat period; once the controller's WATCHDOG_MS is known the host
    # waits WATCHDOG_MS / 4 when that is longer (PROTOCOL.md §9): on a radio every heartbeat
    # is a packet of air (31 bytes at 10 Hz: 7 % of an XBee's), and a watchdog of seconds
    # needs no 10 Hz. It also paces the check for a silent controller.
    heartbeat_interval_s: float = 0.1
    dead_after_heartbeats: int = 10  # silence of this many intervals declares the link dead
    clock_sync_interval_s: float = 0.1  # 10 Hz probes; 0 disables clock sync
    # Once the fit has converged and its error stays small, probes go out this often instead
    # (host.link.probe_rate); a value ≤ clock_sync_interval_s keeps the steady rate.
    clock_sync_slow_interval_s: float = 1.0
    # A probe waits until the host has sent nothing for this long (at most one probe interval):
    # written behind another frame it would queue on the line, a delay on the way out only that
    # the estimator cannot tell from link asymmetry. The largest frame takes 7.3 ms at 115200 Bd.
    clock_probe_quiet_s: float = 0.01
    # σ of the legs' uneven split that the clock probes cannot see (ClockSync's
    # asymmetry_sigma_ns): what a stamp mapped through the clock is known to, beside its fit.
    clock_asymmetry_sigma_us: float = 0.0
    rto_initial_s: float = 0.25
    rto_min_s: float = 0.02
    rto_max_s: float = 2.0
    max_tries: int = 8  # transmissions of one command before CommandTimeout
    handshake_tries: int = 4
    # The controller keeps the replies of at least this many × rx_window commands (PROTOCOL.md,
    # "Duplicate suppression"). See Session._window_open for why the factor matters.
    reply_cache_factor: int = 2
    # Capability bits offered in HELLO; a feature is used when IDENTIFY offers it too.
    capabilities: int = HOST_CAPABILITIES


class RtoEstimator:
    """Retransmission timeout from RTT samples, per RFC 6298 (SRTT, RTTVAR, bounded backoff)."""

    def __init__(self, config: SessionConfig) -> None:
        self._cfg = config
        self.srtt_s: float | None = None
        self.rttvar_s: float | None = None
        self.rto_s = config.rto_initial_s

    def sample(self, rtt_s: float) -> None:
        """Fold in an RTT measured on a command sent once (Karn's rule is the caller's)."""
        if self.srtt_s is None or self.rttvar_s is None:
            self.srtt_s, self.rttvar_s = rtt_s, rtt_s / 2
        else:
            self.rttvar_s = (1 - RTO_BETA) * self.rttvar_s + RTO_BETA * abs(self.srtt_s - rtt_s)
            self.srtt_s = (1 - RTO_ALPHA) * self.srtt_s + RTO_ALPHA * rtt_s
        self.forget_backoff()

    def backoff(self) -> float:
        """Double the RTO after a timeout (bounded); returns the new value."""
        self.rto_s = self._clamp(self.rto_s * 2)
        return self.rto_s

    def forget_backoff(self) -> None:
        """Back to the estimate from the RTT samples, as if no timer had expired since.

        For timeouts that said nothing about the link: commands a rebooted controller never
        answered. Without samples yet, the configured initial value.
        """
        if self.srtt_s is None or self.rttvar_s is None:
            self.rto_s = self._cfg.rto_initial_s
            return
        raw = self.srtt_s + max(RTO_CLOCK_GRANULARITY_S, RTO_K * self.rttvar_s)
        self.rto_s = self._clamp(raw)

    def _clamp(self, rto_s: float) -> float:
        """Keep the RTO inside the configured bounds."""
        return min(max(rto_s, self._cfg.rto_min_s), self._cfg.rto_max_s)


@dataclass
class _Pending:
    """A reliable command waiting for its reply."""

    seq: int
    message: object
    name: str
    reply_name: str
    future: asyncio.Future[Packet]
    index: int = 0  # position among all commands, for the sliding window
    tries: int = 0
    first_sent_s: float = 0.0
    rto_s: float = 0.0
    timer: asyncio.TimerHandle | None = None


@dataclass
class _RxSeq:
    """Tracks the controller's seq to count frames lost on the way."""

    expected: int | None = None

    def see(self, seq: int, stats: LinkStats) -> bool:
        """Account for one received frame's seq; True if the seq restarted (a reboot?)."""
        if self.expected is None:
            self.expected = (seq + 1) % SEQ_MOD
            return False
        gap = (seq - self.expected) % SEQ_MOD
        if seq < SEQ_RESTART_BELOW and SEQ_RESTART_MIN_JUMP < gap < SEQ_MOD - SEQ_RESTART_MIN_JUMP:
            self.expected = (seq + 1) % SEQ_MOD  # a counter starting afresh, not a loss
            return True
        if gap < SEQ_MOD // 2:
            stats.rx_lost += gap
            self.expected = (seq + 1) % SEQ_MOD
        else:
            stats.rx_out_of_order += 1  # older than the newest: a repeat or a late frame
        return False


@dataclass
class Session:
    """Reliable commands, heartbeat and clock sync over one transport."""

    transport: Transport
    config: SessionConfig = field(default_factory=SessionConfig)
    on_packet: PacketHandler | None = None  # telemetry, STATUS, LOG: everything not a reply
    on_event: EventHandler | None = None
    on_lost: Callable[[Exception | None], None] | None = None  # the transport went away

    def __post_init__(self) -> None:
        self.stats = LinkStats()
        self.clock = self._new_clock(1_000_000)
        self.probe_rate = ProbeRate(
            self.config.clock_sync_interval_s, self.config.clock_sync_slow_interval_s
        )
        self.rto = RtoEstimator(self.config)
        self.identity: Identify | None = None
        self._decoder = FrameDecoder()
        self.stats.drops = self._decoder.drops
        # A random first seq: a restarted host is unlikely to repeat its predecessor's seqs
        # even towards a controller that kept its reply cache (PROTOCOL.md §6).
        self._tx_seq = random.randrange(SEQ_MOD)
        # Names this session in HELLO: the controller tells a repeated HELLO from a new host's.
        self._session_id = random.randrange(U32_MOD)
        self.capabilities = 0
        self._rx_seq = _RxSeq()
        self._inflight: dict[int, _Pending] = {}
        self._window = 1  # until IDENTIFY tells us rx_window
        self._cmd_index = 0
        self._slot_waiters: list[asyncio.Future[None]] = []
        self._probes: dict[int, int] = {}  # token → host send time, ns
        self._frame_in = asyncio.Event()  # a controller frame arrived (probes follow one)
        self._tokens = itertools.count(1)
        self._tasks: list[asyncio.Task[None]] = []
        self._running = False
        self._last_rx_s = 0.0
        self._last_tx_s = 0.0
        self.heartbeat_s = self.config.heartbeat_interval_s  # in force (follow_watchdog)
        self._peer_uptime_ms: int | None = None
        self._started_ns = time.monotonic_ns()

    # ---- life cycle ----------------------------------------------------------------------

    def start(self) -> None:
        """Begin on an open transport: route its bytes here, start heartbeat and probes."""
        self.transport.set_receiver(self._on_bytes, self.on_lost)
        # One delimiter first: the controller drops any partial frame it holds (PROTOCOL §7).
        with contextlib.suppress(TransportError):
            self.transport.send(b"\x00")
        self._decoder.reset()
        self.transport.resync()
        self._rx_seq = _RxSeq()
        self._running = True
        self.heartbeat_s = self.config.heartbeat_interval_s  # until this controller's is read
        self._last_rx_s = asyncio.get_running_loop().time()
        self._tasks = [asyncio.create_task(self._heartbeat_loop(), name="link-heartbeat")]
        if self.config.clock_sync_interval_s > 0:
            self._tasks.append(asyncio.create_task(self._clock_loop(), name="link-clocksync"))

    def halt(self, reason: str) -> None:
        """Stop at once (callable from callbacks): pending commands fail with LinkDown."""
        self._running = False
        for task in self._tasks:
            task.cancel()
        self._fail_pending(LinkDown(reason))
        self._probes.clear()

    async def stop(self, reason: str = "session closed") -> None:
        """Halt and wait for the background tasks to finish."""
        self.halt(reason)
        tasks, self._tasks = self._tasks, []
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task

    @property
    def running(self) -> bool:
        """True between start and halt."""
        return self._running

    # ---- requests ------------------------------------------------------------------------

    async def handshake(self) -> tuple[Identify, bool]:
        """HELLO → IDENTIFY; returns it and whether the boot id changed (controller reset)."""
        self._window = 1
        offered = self.config.capabilities
        hello = Hello(PROTOCOL_VERSION, SCHEMA_HASH, offered, self._session_id)
        packet = await self.request(hello, max_tries=self.config.handshake_tries)
        ident = packet.message
        assert isinstance(ident, Identify)
        if ident.protocol_version != PROTOCOL_VERSION or ident.schema_hash != SCHEMA_HASH:
            raise ProtocolMismatch(
                PROTOCOL_VERSION, SCHEMA_HASH, ident.protocol_version, ident.schema_hash
            )
        _check_identity(ident)
        rebooted = self.identity is not None and self.identity.boot_id != ident.boot_id
        if rebooted or self.identity is None:
            self.clock = self._new_clock(ident.mcu_clock_hz or 1_000_000)
            self.probe_rate.reset()
        if rebooted:
            self.stats.controller_resets += 1
        self.identity = ident
        # A feature is used only when both sides offer it (issue 16 negotiates with these bits).
        self.capabilities = offered & ident.capabilities
        cache = self.config.reply_cache_factor * ident.rx_window
        self._window = max(1, min(ident.rx_window, (cache + 1) // 2))
        self._peer_uptime_ms = None
        self.stats.handshakes += 1
        self._wake_next_waiter()
        return ident, rebooted

    async def request(self, message: object, *, max_tries: int | None = None) -> Packet:
        """Send a reliable command and return the reply packet; NAK raises ControllerRejected."""
        spec = spec_of(message)
        if not spec.acked or spec.reply is None:
            raise ValueError(f"{spec.name} is not an acknowledged command")
        if type(message) not in _STOPS:
            # STOP and ESTOP never wait for a window slot; the controller runs them on arrival.
            await self._acquire_slot()
        elif not self._running:
            raise LinkDown("session is not running")
        loop = asyncio.get_running_loop()
        entry = _Pending(self._next_seq(), message, spec.name, spec.reply, loop.create_future())
        entry.index = self._cmd_index
        self._cmd_index += 1
        self._inflight[entry.seq] = entry
        self._wake_next_waiter()  # the window may have room for more than this one
        try:
            self.stats.commands += 1
            entry.first_sent_s = loop.time()
            entry.rto_s = self.rto.rto_s
            self._transmit(entry, max_tries or self.config.max_tries)
        except BaseException:
            self._forget(entry)
            raise
        orphaned = False
        try:
            return await asyncio.shield(entry.future)
        except asyncio.CancelledError:
            if not entry.future.done():
                # Sent, so it holds its place in the controller's sequence: were its frame lost,
                # every later command would wait behind it. It goes on until its reply or its
                # last try, unheard; only then is its slot free.
                entry.future.add_done_callback(lambda _f: self._forget(entry))
                orphaned = True
            raise
        finally:
            if not orphaned:
                self._forget(entry)

    def send(self, message: object) -> int:
        """Send an unacknowledged frame (HEARTBEAT, CLOCK_SYNC); returns its seq.

        Only acked commands spend a seq (the controller runs them in seq order and waits for
        a gap to fill); an unacked frame carries the seq the next command will take.
        """
        if not self._running:
            raise LinkDown("session is not running")
        seq = self._tx_seq
        self._write(message, seq, Flag.NONE)
        return seq

    # ---- sending -------------------------------------------------------------------------

    def _next_seq(self) -> int:
        """The next u16 seq of the host direction."""
        seq = self._tx_seq
        self._tx_seq = (seq + 1) % SEQ_MOD
        return seq

    def _write(self, message: object, seq: int, flags: int) -> None:
        """Encode and hand one frame to the transport; a dead transport is LinkDown."""
        frame = encode_frame(message, seq, flags)
        try:
            self.transport.send(frame)
        except TransportError as exc:
            raise LinkDown(str(exc)) from exc
        self.stats.frames_out += 1
        self.stats.bytes_out += len(frame)
        self._last_tx_s = asyncio.get_running_loop().time()

    def _transmit(self, entry: _Pending, max_tries: int) -> None:
        """(Re)send a pending command and arm its retransmission timer."""
        if not self._running:
            raise LinkDown("session is not running")
        flags = Flag.ACK_REQUESTED | (Flag.RETRANSMIT if entry.tries else Flag.NONE)
        self._write(entry.message, entry.seq, flags)
        entry.tries += 1
        loop = asyncio.get_running_loop()
        entry.timer = loop.call_later(entry.rto_s, self._on_rto, entry, max_tries)

    def _on_rto(self, entry: _Pending, max_tries: int) -> None:
        """Timer: retransmit with a doubled timeout, or give up."""
        entry.timer = None
        if entry.future.done():
            return
        if entry.tries >= max_tries:
            self.stats.timeouts += 1
            msg = f"{entry.name} seq {entry.seq}: no reply after {entry.tries} tries"
            entry.future.set_exception(CommandTimeout(msg))
            if not isinstance(entry.message, Hello):
                # If none of its frames arrived, the controller holds every later command
                # behind its seq forever, though the link is up: only a HELLO restarts the
                # sequence (PROTOCOL.md §6). The handshake's own failures are the supervisor's.
                self._emit(LinkEvent.COMMAND_LOST, msg)
            return
        if entry.rto_s >= self.rto.rto_s:
            # One back-off per loss episode, as RFC 6298's single timer: the commands in flight
            # beside this one (held by the controller behind the same lost frame) time out at
            # about the same moment, and doubling the shared RTO for each of them pinned it at
            # rto_max_s, so a reconnect's HELLO and restore waited 2 s per lost frame.
            self.rto.backoff()
        entry.rto_s = min(entry.rto_s * 2, self.config.rto_max_s)
        self.stats.retransmits += 1
        try:
            self._transmit(entry, max_tries)
        except LinkDown as exc:
            # A transport may report the loss from inside send(), and the halt that follows
            # has already failed this command.
            if not entry.future.done():
                entry.future.set_exception(exc)

    async def _acquire_slot(self) -> None:
        """Wait, first come first served, until the window lets one more command out."""
        loop = asyncio.get_running_loop()
        while True:
            if not self._running:
                raise LinkDown("session is not running")
            if self._window_open() and not self._slot_waiters:
                return
            waiter: asyncio.Future[None] = loop.create_future()
            self._slot_waiters.append(waiter)
            try:
                await waiter
            except asyncio.CancelledError:
                if waiter.done() and not waiter.cancelled():
                    self._wake_next_waiter()  # woken, then cancelled: pass the turn on
                raise
            finally:
                if waiter in self._slot_waiters:
                    self._slot_waiters.remove(waiter)
            if self._running and self._window_open():
                return

    def _window_open(self) -> bool:
        """A sliding window over commands, not a count.

        PROTOCOL.md §6: at most rx_window consecutive seqs from the oldest unanswered command
        to the newest, so the controller can hold everything ahead of a lost command (never
        BUSY). The controller runs commands in seq order, so after X ran it has run at most
        span − 1 newer ones before X's retransmission arrives; a duplicate memory of
        factor × rx_window (≥ 2 × rx_window by the spec) always still holds X's reply. The span
        is also kept to (factor·rx_window + 1) // 2 so a smaller declared memory stays safe.
        """
        if not self._inflight:
            return True
        oldest = min(e.index for e in self._inflight.values())
        return self._cmd_index - oldest < self._window

    def _wake_next_waiter(self) -> None:
        """Give the turn to the oldest waiter if the window has room (one at a time: no herd)."""
        if not self._window_open():
            return
        while self._slot_waiters:
            waiter = self._slot_waiters.pop(0)
            if not waiter.done():
                waiter.set_result(None)
                return

    def _wake_slot_waiters(self) -> None:
        """Wake every waiter: the session stopped, they will all raise LinkDown."""
        waiters, self._slot_waiters = self._slot_waiters, []
        for waiter in waiters:
            if not waiter.done():
                waiter.set_result(None)

    def _forget(self, entry: _Pending) -> None:
        """A request ended (reply, error or cancellation): free its timer and window slot."""
        if entry.timer is not None:
            entry.timer.cancel()
            entry.timer = None
        if self._inflight.get(entry.seq) is entry:
            del self._inflight[entry.seq]
        if entry.future.done() and not entry.future.cancelled():
            entry.future.exception()  # a halt may have failed it while the send itself raised
        self._wake_next_waiter()

    def _fail_pending(self, exc: Exception) -> None:
        """Fail every pending command and window waiter."""
        for entry in list(self._inflight.values()):
            if entry.timer is not None:
                entry.timer.cancel()
                entry.timer = None
            if not entry.future.done():
                entry.future.set_exception(exc)
        self._wake_slot_waiters()

    # ---- receiving -----------------------------------------------------------------------

    def _on_bytes(self, data: bytes) -> None:
        """Transport receiver: decode and dispatch every complete frame."""
        self.stats.bytes_in += len(data)
        unknown_ids = self._decoder.drops.unknown_id
        for packet in self._decoder.feed(data):
            self.stats.frames_in += 1
            if packet.flags & ~_KNOWN_FLAGS:
                note_unknown("header flag bits", packet.flags & ~_KNOWN_FLAGS)
            if self._rx_seq.see(packet.seq, self.stats):
                self._emit(LinkEvent.RESET_SUSPECTED, f"controller seq restarted at {packet.seq}")
            self._last_rx_s = asyncio.get_running_loop().time()
            self._frame_in.set()
            self._dispatch(packet)
        if self._decoder.drops.unknown_id != unknown_ids:
            note_unknown("message id", self._decoder.last_unknown_id or 0)

    def _dispatch(self, packet: Packet) -> None:
        """Route one packet: replies to their requests, the rest to the owner."""
        msg = packet.message
        if isinstance(msg, ClockSyncReply):
            self._on_clock_reply(msg)
        elif hasattr(msg, "req_seq"):
            self._on_reply(packet)
        elif isinstance(msg, Heartbeat):
            self._on_heartbeat(msg)
        elif self.on_packet is not None:
            self.on_packet(packet)

    def _on_reply(self, packet: Packet) -> None:
        """Complete the command the reply names, or count it as a late duplicate."""
        msg: Any = packet.message
        entry = self._inflight.get(msg.req_seq)
        if entry is None or entry.future.done():
            self.stats.duplicate_replies += 1
            return
        if isinstance(msg, Nak):
            self.stats.naks += 1
            if msg.code == NakCode.BUSY:
                # Ahead of a gap the controller could not hold: the command did not run and the
                # retransmission timer resends it, same seq, once the gap has filled.
                self.stats.busy_naks += 1
                return
            code, state = decode_enum(NakCode, msg.code), decode_enum(State, msg.state)
            # Failed at once, whatever the code: a newer controller's refusal is still a refusal.
            entry.future.set_exception(ControllerRejected(entry.name, code, state))
            if msg.code == NakCode.HELLO_REQUIRED:
                # The controller rebooted since our HELLO: the supervisor re-handshakes.
                self._emit(LinkEvent.RESET_SUSPECTED, "controller asks for HELLO (it rebooted)")
            return
        if spec_of(msg).name != entry.reply_name:
            self.stats.unexpected_replies += 1
            return
        if entry.tries == 1:  # Karn: a retransmitted command's RTT is ambiguous
            self._rtt_sample(asyncio.get_running_loop().time() - entry.first_sent_s)
        entry.future.set_result(packet)

    def _rtt_sample(self, rtt_s: float) -> None:
        """Feed the RTO estimator and the statistics."""
        self.rto.sample(rtt_s)
        rtt = self.stats.rtt
        rtt.samples += 1
        rtt.last_s = rtt_s
        rtt.min_s = rtt_s if rtt.min_s is None else min(rtt.min_s, rtt_s)
        rtt.srtt_s, rtt.rttvar_s, rtt.rto_s = self.rto.srtt_s, self.rto.rttvar_s, self.rto.rto_s

    def _on_heartbeat(self, msg: Heartbeat) -> None:
        """Count it; uptime running backwards means the controller rebooted."""
        self.stats.heartbeats_in += 1
        previous, self._peer_uptime_ms = self._peer_uptime_ms, msg.uptime_ms
        if previous is not None and (msg.uptime_ms - previous) % U32_MOD >= U32_MOD // 2:
            self._emit(LinkEvent.RESET_SUSPECTED, f"uptime fell from {previous} ms")

    def _new_clock(self, mcu_clock_hz: int) -> ClockSync:
        """A fresh clock fit for a controller clock of that rate."""
        sigma_ns = self.config.clock_asymmetry_sigma_us * 1000.0
        return ClockSync(mcu_clock_hz, asymmetry_sigma_ns=sigma_ns)

    def _on_clock_reply(self, msg: ClockSyncReply) -> None:
        """Pair the reply with its probe and feed the estimator."""
        sent_ns = self._probes.pop(msg.token, None)
        if sent_ns is None:
            self.stats.duplicate_replies += 1
            return
        self.stats.clock_replies += 1
        t1_ns = self.transport.rx_time_ns or time.monotonic_ns()  # its chunk's arrival (recorded)
        self.probe_rate.check_reply(self.clock, sent_ns, msg.mcu_time_us, t1_ns)
        self.clock.add_probe(sent_ns, msg.mcu_time_us, t1_ns, msg.rx_time_us)

    def _emit(self, event: LinkEvent, detail: str) -> None:
        """Tell the owner; logging here so nothing goes unseen."""
        log.info("link event %s: %s", event.value, detail)
        if self.on_event is not None:
            self.on_event(event, detail)

    # ---- background ----------------------------------------------------------------------

    def follow_watchdog(self, watchdog_ms: int) -> None:
        """The controller's WATCHDOG_MS: heartbeat after WATCHDOG_MS / 4 of host silence.

        Any host frame feeds the watchdog, so HEARTBEAT fills only the silences; one or two
        lost frames still never trip it. Never shorter than the configured interval, nor longer
        than HEARTBEAT_MAX_S: a long watchdog is slack for a host that stalls, not air to save.
        """
        period_s = min(watchdog_ms / 4000, HEARTBEAT_MAX_S)
        self.heartbeat_s = max(self.config.heartbeat_interval_s, period_s)

    async def _heartbeat_loop(self) -> None:
        """Send HEARTBEAT when the host was silent; declare the link dead after a long silence."""
        cfg = self.config
        loop = asyncio.get_running_loop()
        while self._running:
            due_s = self._last_tx_s + self.heartbeat_s - loop.time()
            await asyncio.sleep(min(cfg.heartbeat_interval_s, max(due_s, HEARTBEAT_SLACK_S)))
            now = loop.time()
            if now - self._last_rx_s > cfg.heartbeat_interval_s * cfg.dead_after_heartbeats:
                self._emit(LinkEvent.HEARTBEAT_TIMEOUT, f"silent for {now - self._last_rx_s:.2f} s")
                return
            if now - self._last_tx_s >= self.heartbeat_s - HEARTBEAT_SLACK_S:
                uptime_ms = (time.monotonic_ns() - self._started_ns) // 1_000_000 % U32_MOD
                self._send_quietly(Heartbeat(uptime_ms=uptime_ms))
                self.stats.heartbeats_out += 1

    async def _clock_loop(self) -> None:
        """Probe the controller clock at a steady rate once the handshake is done."""
        cfg = self.config
        loop = asyncio.get_running_loop()
        while self._running:
            # Fast until the fit converges, slow while its error stays small (probe_rate).
            rate = self.probe_rate
            rate.fast_s, rate.slow_s = cfg.clock_sync_interval_s, cfg.clock_sync_slow_interval_s
            interval_s = rate.interval_s(self.clock, time.monotonic_ns())
            wake = loop.time() + interval_s
            while (left := wake - loop.time()) > 0 and self._running:
                await asyncio.sleep(min(left, cfg.clock_sync_interval_s))
                if not rate.slow:
                    break  # a controller reset restarted the fit: probe at once
            # Right after a controller frame arrived, its side of the link has just sent what it
            # had: the reply then likely finds the way back (a radio module's buffer) empty.
            # (Only while frames flow: a quiet link has nothing to wait for.)
            self._frame_in.clear()
            align_s = min(PROBE_ALIGN_MAX_S, cfg.clock_sync_interval_s)
            if loop.time() - self._last_rx_s < align_s:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._frame_in.wait(), align_s)
            # On a line just written to (the heartbeat loop wakes at the same rate), wait until
            # the host's previous frame has left.
            give_up = loop.time() + min(interval_s, cfg.clock_sync_interval_s)
            while (wait := self._last_tx_s + cfg.clock_probe_quiet_s - loop.time()) > 0:
                if loop.time() + wait > give_up:
                    break
                await asyncio.sleep(wait)
            if self.identity is None:
                continue
            token = next(self._tokens) % U32_MOD
            t0 = time.monotonic_ns()
            seq = self._send_quietly(ClockSyncMsg(token=token))
            if seq is not None:
                t0 = self.transport.tx_time_ns or t0  # taken just before the write (recorded)
                self.stats.clock_probes += 1
                self._probes[token] = t0
                while len(self._probes) > MAX_CLOCK_PROBES_IN_FLIGHT:
                    del self._probes[next(iter(self._probes))]

    def _send_quietly(self, message: object) -> int | None:
        """Background send: a dead link is reported by the transport, not raised here."""
        try:
            return self.send(message)
        except LinkDown:
            return None


_IDENTITY_POSITIVE = (
    "encoder_counts_per_rev",
    "steps_per_rev",
    "sprocket_teeth",
    "chain_pitch_um",
    "rx_window",
)


def _check_identity(ident: Identify) -> None:
    """Refuse constants that would divide by zero later (a misconfigured controller)."""
    bad = [name for name in _IDENTITY_POSITIVE if getattr(ident, name) <= 0]
    if bad:
        raise BadIdentity(f"IDENTIFY has non-positive {', '.join(bad)}: controller misconfigured")
