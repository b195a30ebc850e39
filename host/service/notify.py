"""sd_notify(3) with the stdlib: datagrams to $NOTIFY_SOCKET, and the watchdog period.

Outside systemd (no NOTIFY_SOCKET) every call is a cheap no-op, so the daemon runs the same way
from a terminal. Send errors are counted, never raised: the service manager going away must not
take the daemon down with it.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)


class Notifier:
    """Sends `KEY=value` lines to the service manager's notification socket."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self.address = _socket_address(env.get("NOTIFY_SOCKET", ""))
        self.watchdog_usec = _watchdog_usec(env)
        self.sent = 0
        self.errors = 0
        self._sock: socket.socket | None = None

    @property
    def enabled(self) -> bool:
        """True when a notification socket was given."""
        return self.address is not None

    @property
    def watchdog_interval_s(self) -> float | None:
        """How often to ping: half of WATCHDOG_USEC, as sd_watchdog_enabled(3) advises."""
        return None if self.watchdog_usec is None else self.watchdog_usec / 2e6

    def notify(self, **fields: str | int) -> bool:
        """Send one datagram, e.g. notify(READY=1, STATUS="link up"); False if not delivered."""
        if self.address is None:
            return False
        payload = "\n".join(f"{k}={v}" for k, v in fields.items()).encode()
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                # Never block the event loop: a manager that stops reading fills the datagram
                # queue (10 deep on Linux), and a blocking send would then hang the daemon.
                self._sock.setblocking(False)
            self._sock.sendto(payload, self.address)
        except OSError as exc:
            self.errors += 1
            log.debug("sd_notify failed", extra={"kv": {"error": exc}})
            return False
        self.sent += 1
        return True

    def ready(self, status: str) -> bool:
        """READY=1 with a STATUS line."""
        return self.notify(READY=1, STATUS=status)

    def status(self, text: str) -> bool:
        """A STATUS= line shown by `systemctl status`."""
        return self.notify(STATUS=text)

    def watchdog(self) -> bool:
        """WATCHDOG=1: the event loop is alive."""
        return self.notify(WATCHDOG=1)

    def stopping(self, status: str = "stopping") -> bool:
        """STOPPING=1 at the start of shutdown."""
        return self.notify(STOPPING=1, STATUS=status)

    def close(self) -> None:
        """Close the datagram socket."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _socket_address(value: str) -> str | bytes | None:
    """A filesystem path, or an abstract-namespace name written with a leading `@`."""
    if not value:
        return None
    if value.startswith("@"):
        return b"\0" + value[1:].encode()
    if value.startswith("/"):
        return value
    log.warning("ignoring NOTIFY_SOCKET that is neither a path nor @abstract")
    return None


def _watchdog_usec(env: Mapping[str, str]) -> int | None:
    """WATCHDOG_USEC if it is meant for this process (WATCHDOG_PID unset or ours)."""
    pid = env.get("WATCHDOG_PID")
    if pid and pid != str(os.getpid()):
        return None
    try:
        usec = int(env.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    return usec if usec > 0 else None
