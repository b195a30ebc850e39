"""The daemon's side of the bus: publish poses, state, statistics and events; answer queries.

Publishing happens on the event loop and never waits (Zenoh's put with congestion control DROP
only queues). Queries and Zenoh's own callbacks run on Zenoh's threads: a status query is handed
to the event loop and answered from its result, bounded by QUERY_TIMEOUT_S. The session opens
off the loop and is retried while it cannot open, so a bus that is down never stops the daemon.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable, Mapping
from typing import Any

import zenoh
import zenoh.ext

from host.bus.fleet import Fleet
from host.bus.messages import ALIVE, QUERIES, TOPICS, key, pack, pose_body, stamped
from host.bus.session import open_session
from host.config_bus import BusConfig, rig_name
from host.control.api import PoseSample

log = logging.getLogger(__name__)

QUERY_TIMEOUT_S = 1.0
RETRY_S = 5.0

Provider = Callable[[], Awaitable[Mapping[str, Any]]]


class BusPublisher:
    """One rig's presence on the bus."""

    def __init__(
        self,
        config: BusConfig,
        *,
        status: Provider,
        rig: Provider,
        stats: Callable[[], Mapping[str, Any]],
    ) -> None:
        self.config = config
        self.rig = rig_name(config)
        self._providers = {"status": status, "rig": rig}
        self._stats = stats
        self._session: zenoh.Session | None = None
        self._publishers: dict[str, zenoh.Publisher | zenoh.ext.AdvancedPublisher] = {}
        self._entities: list[Any] = []  # queryables and the liveliness token
        self._loop: asyncio.AbstractEventLoop | None = None
        self._fleet: Fleet | None = None  # the other rigs of the hall, seen on this session
        self._last_state: dict[str, Any] | None = None
        self.error = "not started"
        self.counts = dict.fromkeys(TOPICS, 0) | {"queries": 0, "errors": 0}

    @property
    def up(self) -> bool:
        """True once the session is open."""
        return self._session is not None

    async def run(self) -> None:
        """Open the session (retrying), then publish statistics until cancelled."""
        self._loop = asyncio.get_running_loop()
        while self._session is None:
            try:
                await self._loop.run_in_executor(None, self._open)
            except Exception as exc:  # zenoh.ZError and OSError: a bus down is not fatal
                self.error = str(exc)
                log.warning("bus not open, retrying", extra={"kv": {"error": exc}})
                await asyncio.sleep(RETRY_S)
        while True:
            self._put("stats", stamped(self._stats(), time.monotonic_ns()))
            await asyncio.sleep(self.config.stats_interval_s)

    def hall(self) -> list[dict[str, Any]] | None:
        """Every rig seen on the bus (this one included, flagged `self`); None while down."""
        if self._fleet is None:
            return None
        return [{**row, "self": row["rig"] == self.rig} for row in self._fleet.rows()]

    def publish_pose(self, sample: PoseSample) -> None:
        """A registered camera pose."""
        self._put("pose", pose_body(sample))

    def publish_state(self, snapshot: Mapping[str, Any]) -> None:
        """The controller's state, when it differs from the last one published."""
        state = dict(snapshot)
        if state != self._last_state:
            self._last_state = state
            self._put("state", stamped(state, time.monotonic_ns()))

    def publish_event(self, event: str, detail: str = "") -> None:
        """Something that happened (link up or down, reload, a fault)."""
        self._put("event", stamped({"event": event, "detail": detail}, time.monotonic_ns()))

    async def close(self) -> None:
        """Withdraw the liveliness token and close the session."""
        session, self._session = self._session, None
        if session is None:
            return
        fleet, self._fleet = self._fleet, None
        if fleet is not None:
            with contextlib.suppress(Exception):
                fleet.close()
        for entity in self._entities:
            with contextlib.suppress(Exception):
                entity.undeclare()
        self._entities.clear()
        self._publishers.clear()
        await asyncio.get_running_loop().run_in_executor(None, session.close)

    def stats(self) -> dict[str, Any]:
        """Counters for the status op."""
        return {"rig": self.rig, "up": self.up, "error": "" if self.up else self.error,
                **self.counts}  # fmt: skip

    def _open(self) -> None:
        """Open the session and declare everything (runs on an executor thread)."""
        session = open_session(self.config)
        drop = zenoh.CongestionControl.DROP
        self._publishers = {
            topic: session.declare_publisher(key(self.rig, topic), congestion_control=drop)
            for topic in TOPICS
            if topic != "state"
        }
        # State is published on change only: its last sample stays in a cache that a fleet
        # joining later asks for, or it would show "?" until the controller's next change.
        self._publishers["state"] = zenoh.ext.declare_advanced_publisher(
            session, key(self.rig, "state"), congestion_control=drop,
            cache=zenoh.ext.CacheConfig(1), publisher_detection=True,
        )  # fmt: skip
        self._entities = [
            session.declare_queryable(key(self.rig, name), self._answerer(name)) for name in QUERIES
        ]
        self._entities.append(session.liveliness().declare_token(key(self.rig, ALIVE)))
        fleet = Fleet(session)
        fleet.start()
        self._fleet = fleet
        self._session = session
        log.info("bus open", extra={"kv": {"rig": self.rig, "zid": str(session.zid())}})

    def _put(self, topic: str, body: Mapping[str, Any]) -> None:
        """Publish if the session is open; a failure is counted, never raised."""
        publisher = self._publishers.get(topic)
        if publisher is None:
            return
        try:
            publisher.put(pack(self.rig, body))
            self.counts[topic] += 1
        except Exception as exc:  # an output must never break the frame loop
            self.counts["errors"] += 1
            if self.counts["errors"] <= 3:
                log.warning("bus put failed", extra={"kv": {"topic": topic, "error": exc}})

    def _answerer(self, name: str) -> Callable[[zenoh.Query], None]:
        """A queryable callback (Zenoh thread) answering from the event loop's provider."""
        provider = self._providers[name]
        reply_key = key(self.rig, name)

        def answer(query: zenoh.Query) -> None:
            self.counts["queries"] += 1
            loop = self._loop
            try:
                if loop is None or loop.is_closed():
                    raise RuntimeError("the daemon is stopping")
                body = asyncio.run_coroutine_threadsafe(_call(provider), loop).result(
                    QUERY_TIMEOUT_S
                )
                query.reply(reply_key, pack(self.rig, {name: body}))
            except Exception as exc:
                query.reply_err(pack(self.rig, {"error": f"{type(exc).__name__}: {exc}"}))

        return answer


async def _call(provider: Provider) -> Mapping[str, Any]:
    """Await a provider (a coroutine for run_coroutine_threadsafe)."""
    return await provider()
