"""What keeps one client from exhausting the daemon: log throttling, hello throttling, fd room.

A flood of connections or bad hellos must cost the daemon a bounded number of log lines and file
descriptors, so the operator's CLI, the serial port and the camera keep working (issue 14).
"""

from __future__ import annotations

import logging
import resource
import time
from dataclasses import dataclass, field

FD_RESERVE = 64  # descriptors kept for the link, the camera, logs and the recording


@dataclass
class ThrottledLog:
    """At most one line per key per interval; the lines held back are counted into the next."""

    logger: logging.Logger
    interval_s: float = 10.0
    _last: dict[str, float] = field(default_factory=dict)
    _held: dict[str, int] = field(default_factory=dict)

    def warning(self, key: str, message: str, **kv: object) -> None:
        """Log `message` with `kv` unless `key` was logged within the interval."""
        now = time.monotonic()
        if now - self._last.get(key, -self.interval_s) < self.interval_s:
            self._held[key] = self._held.get(key, 0) + 1
            return
        held = self._held.pop(key, 0)
        if held:
            kv["similar_since_last"] = held
        self._last[key] = now
        self.logger.warning(message, extra={"kv": kv})


@dataclass
class TokenBucket:
    """`burst` events at once, refilled at `rate_per_s`: how many failed hellos are tolerated."""

    burst: float
    rate_per_s: float
    _tokens: float = -1.0
    _t: float = 0.0

    def take(self) -> bool:
        """Spend one token; False when none is left (the caller refuses)."""
        now = time.monotonic()
        if self._tokens < 0:
            self._tokens, self._t = self.burst, now
        self._tokens = min(self.burst, self._tokens + (now - self._t) * self.rate_per_s)
        self._t = now
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True


def ensure_fd_room(connections: int) -> tuple[int, int]:
    """Raise the soft RLIMIT_NOFILE to fit the connection caps (and a reserve) if the hard allows.

    Returns (soft limit now, descriptors wanted); the caller warns when the first is smaller.
    """
    wanted = connections + FD_RESERVE
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < wanted:
        new_soft = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (new_soft, hard))
            soft = new_soft
        except (ValueError, OSError):
            pass
    return soft, wanted
