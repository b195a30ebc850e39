"""Keep a session up: connect, detect a dead link, back off, reopen, re-handshake, restore.

The only reconnect loop of the host: the daemon starts it (`start()`, which retries the first
connection too) and follows its state changes through `on_state`; `last_error` keeps the real
cause (the transport's error, the heartbeat silence) while the link is not up.

The states follow aioesphomeapi's reconnect_logic (the code is ours): a drop fails every pending
command with LinkDown at once (nothing is re-sent after a reconnect: nothing moves that was not
asked for), then the supervisor waits a capped exponential delay with jitter and tries again.
A controller reset seen on a live link is handled the same way without closing the transport.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from host.link.common import LinkDown, LinkError, LinkEvent, LinkState
from host.link.session import Session
from host.transport.base import TransportError
from protocol.messages import Identify

log = logging.getLogger(__name__)

RestoreHook = Callable[[Identify, bool], Awaitable[None]]
StateHook = Callable[[LinkState, str], None]


@dataclass(frozen=True)
class BackoffConfig:
    """Delays between reconnection attempts."""

    initial_s: float = 0.1
    max_s: float = 5.0
    jitter: float = 0.25  # each delay is cut by up to this fraction, so peers do not align

    def delay_s(self, attempt: int, rng: random.Random) -> float:
        """Delay before attempt number `attempt` (0 = the first retry)."""
        base = min(self.max_s, self.initial_s * 2.0**attempt)
        return base * (1.0 - self.jitter * rng.random())


class Supervisor:
    """Owns the session's life: connect, watch, reconnect, close."""

    def __init__(
        self,
        session: Session,
        restore: RestoreHook,
        on_state: StateHook | None = None,
        backoff: BackoffConfig | None = None,
        seed: int | None = None,
    ) -> None:
        self.session = session
        self.state = LinkState.DISCONNECTED
        self.attempts = 0
        self.last_error = "not connected yet"  # why the link is not up (kept through BACKOFF)
        self._restore = restore
        self._on_state = on_state
        self._backoff = backoff or BackoffConfig()
        self._rng = random.Random(seed)
        self._wake = asyncio.Event()
        self._reopen = True
        self._task: asyncio.Task[None] | None = None
        self.on_event: Callable[[LinkEvent, str], None] | None = None
        session.on_event = self._on_session_event
        session.on_lost = self._on_transport_lost

    async def connect(self) -> Identify:
        """First connection: errors propagate; afterwards reconnection is automatic."""
        ident = await self._attempt(reopen=True)
        self._task = asyncio.create_task(self._watch(), name="link-supervisor")
        return ident

    def start(self) -> None:
        """Connect in the background, with backoff from the first failure on; never raises."""
        if self._task is None:
            self._task = asyncio.create_task(self._run(), name="link-supervisor")

    async def _run(self) -> None:
        """The first connection (retried like any reconnection), then the watch."""
        await self._reconnect(first=True)
        await self._watch()

    async def close(self) -> None:
        """Stop reconnecting, stop the session, close the transport."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        await self.session.stop("link closed by the user")
        await self.session.transport.close()
        self.last_error = "closed"
        self._set_state(LinkState.DISCONNECTED, "closed")

    def drop(self, reason: str, reopen: bool = True) -> None:
        """Declare the link down now (callable from callbacks)."""
        if self.state is not LinkState.UP:
            return
        self.session.halt(reason)
        self.session.stats.link_downs += 1
        self.last_error = reason
        self._reopen = reopen
        self._set_state(LinkState.DOWN, reason)
        self._wake.set()

    async def _watch(self) -> None:
        """Wait for a drop, then retry with backoff until up again; forever."""
        while True:
            await self._wake.wait()
            self._wake.clear()
            await self._reconnect()

    async def _reconnect(self, first: bool = False) -> None:
        """Attempts with growing delays until one succeeds (the first one at once if `first`)."""
        reopen, self._reopen = self._reopen, True
        attempt = 0
        last = ""
        while True:
            if (reopen and not first) or attempt:
                delay = self._backoff.delay_s(attempt, self._rng)
                self._set_state(LinkState.BACKOFF, f"retry in {delay:.2f} s: {self.last_error}")
                await asyncio.sleep(delay)
            try:
                await self._attempt(reopen=reopen or attempt > 0)
                return
            except (LinkError, TransportError, OSError) as exc:
                # OSError: a serial device that is not there (yet) raises it from open().
                # The same failure again and again (a controller unplugged for hours) is
                # logged when it starts and every 100th time, not at every attempt.
                repeated = attempt > 0 and str(exc) == last
                level = logging.DEBUG if repeated and attempt % 100 else logging.WARNING
                log.log(level, "connection attempt %d failed: %s", attempt + 1, exc)
                last = str(exc)
                attempt += 1
            except Exception:
                # Anything else is a bug, but the supervisor must outlive it or the link stays
                # down for good: log it and keep retrying with backoff.
                log.exception("connection attempt %d failed unexpectedly", attempt + 1)
                attempt += 1

    async def _attempt(self, reopen: bool) -> Identify:
        """Open (if asked), handshake and restore; leaves the state UP or raises."""
        self.attempts += 1
        self._set_state(LinkState.CONNECTING, "opening" if reopen else "re-handshaking")
        await self.session.stop("reconnecting")
        try:
            if reopen:
                await self.session.transport.close()
                await self.session.transport.open()
            self.session.start()
            ident, rebooted = await self.session.handshake()
            if rebooted:
                self._notify(LinkEvent.CONTROLLER_RESET, f"new boot id 0x{ident.boot_id:08X}")
            await self._restore(ident, rebooted)
        except BaseException as exc:
            await self.session.stop("connection attempt failed")
            self.last_error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            self._set_state(LinkState.DOWN, f"attempt failed: {self.last_error}")
            raise
        self.last_error = ""
        self._set_state(LinkState.UP, f"boot id 0x{ident.boot_id:08X}")
        return ident

    def _on_session_event(self, event: LinkEvent, detail: str) -> None:
        """Heartbeat silence and resets seen by the session."""
        self._notify(event, detail)
        if event is LinkEvent.HEARTBEAT_TIMEOUT:
            self.drop(f"heartbeat timeout: {detail}")
        elif event is LinkEvent.RESET_SUSPECTED:
            # Commands pending now went to a controller that may have forgotten them: fail
            # them, re-handshake; the boot id then tells whether it really rebooted. Their
            # timeouts were the reboot's, not the link's: the HELLO starts from the measured
            # RTO, not one backed off towards rto_max_s (2 s lost per unanswered try).
            if self.state is LinkState.UP:
                self.session.rto.forget_backoff()
            self.drop(f"controller reset suspected: {detail}", reopen=False)
        elif event is LinkEvent.COMMAND_LOST:
            # The controller may hold every later command behind the lost one's seq: HELLO
            # starts a new sequence, and restore puts the streams and parameters back.
            self.drop(f"command lost: {detail}", reopen=False)

    def _on_transport_lost(self, exc: Exception | None) -> None:
        """The transport reports the device gone."""
        self.drop(f"transport lost: {exc}")

    def _notify(self, event: LinkEvent, detail: str) -> None:
        """Forward an event to whoever listens to state changes."""
        log.warning("link %s: %s", event.value, detail)
        if self.on_event is not None:
            self.on_event(event, detail)

    def _set_state(self, state: LinkState, detail: str) -> None:
        """Record and announce a state change."""
        if state is self.state:
            return
        self.state = state
        log.info("link %s (%s)", state.value, detail)
        if self._on_state is not None:
            self._on_state(state, detail)

    def require_up(self) -> None:
        """Raise LinkDown unless the link is up: commands are refused, never queued."""
        if self.state is not LinkState.UP:
            cause = f": {self.last_error}" if self.last_error else ""
            raise LinkDown(f"link is {self.state.value}{cause}")
