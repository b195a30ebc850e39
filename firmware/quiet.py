"""Quiet clock probes in the controller: when telemetry is held for a probe pair (PROTOCOL.md §8).

In a session where both sides offered Capability.QUIET_CLOCK_PROBES, the first CLOCK_SYNC of a
pair holds telemetry so that the host's second probe and its reply cross quiet air; the second
ends the hold, and a hold ends by itself QUIET_HOLD_US after the first arrived (R-QUIET-1).

A radio's round trip can be longer than the bound: over XBee the first reply waits behind what
the controller's module still holds (up to 202 bytes, ~50 ms of air), so the second probe may
arrive after the hold ran out. Taken for a new first, it would hold telemetry for another full
bound, and the two holds' backlog overflowed the module. So a probe that arrives within
QUIET_HOLD_US after a hold ran out is its pair's late second: answered, nothing held.
All times are the controller's wrapping 32-bit µs.
"""

from __future__ import annotations

from protocol.schema import QUIET_HOLD_US

_U32 = 0xFFFF_FFFF


class QuietHold:
    """The hold of one session: started by a pair's first probe, ended by its second or the bound.

    As in the C: a few words in the controller's static struct, no allocation.
    """

    __slots__ = ("_from_us", "_paired", "_ran_out", "_until_us", "active")

    def __init__(self) -> None:
        self.active = False  # telemetry is held now
        self._from_us = 0  # the first probe's arrival
        self._until_us = 0  # the hold ends at this time: the bound, or just after the second
        self._paired = False  # the running hold's second probe arrived
        self._ran_out = False  # the last hold ended at its bound: its second may still come

    def clear(self) -> None:
        """No hold (a new session, a reset)."""
        self.active = self._ran_out = False

    def probe(self, rx_us: int) -> None:
        """A CLOCK_SYNC arrived at `rx_us` (handled in this tick, before the TX queue drains)."""
        if self.active:
            self._paired = True
            self._until_us = (rx_us + 1) & _U32  # this tick still holds: its reply goes first
        elif self._ran_out and (rx_us - self._from_us) & _U32 <= 2 * QUIET_HOLD_US:
            self._ran_out = False  # its pair's late second: it starts nothing
        else:
            self.active, self._paired, self._ran_out = True, False, False
            self._from_us = rx_us
            self._until_us = (rx_us + QUIET_HOLD_US) & _U32

    def tick(self, now_us: int) -> int:
        """At the start of a tick: end a hold whose time is up; the µs it lasted, else 0."""
        if not self.active or 0 < (self._until_us - now_us) & _U32 <= QUIET_HOLD_US:
            return 0
        self.active = False
        self._ran_out = not self._paired
        return max(1, (now_us - self._from_us) & _U32)
