"""SimBoard: the firmware HAL implemented on the simulated plant.

It plays the MCU's peripherals: the step timer (steps issued this tick, read by the runner),
the encoder timer (reset to zero by a reset, 32-bit wrapping, index capture), GPIO, the UART's
RX ring (bounded, overruns counted, each received chunk stamped with the µs time it arrived) and
TX, the µs timer of the drifting crystal, the flash sector (in memory or a file), the head's
servo interface, the rangefinder and the RNG.
"""

from __future__ import annotations

import math
import os
import random
from collections import deque

from hil_sim.plant import MarkEvent, Plant
from hil_sim.scenario import Scenario

MASK32 = 0xFFFF_FFFF
RX_RING_BYTES = 4096  # UART DMA ring: bytes beyond it before the firmware reads are lost
TX_RING_BYTES = 256  # UART TX DMA buffer, when the board models its line rate
UNLIMITED_TX_ROOM = 1 << 30
QUALITY_BEST = 255


class SimBoard:
    """The firmware's `Hal` on a `Plant` (see firmware.hal.Hal for each call's contract)."""

    def __init__(self, plant: Plant, scenario: Scenario, rng: random.Random) -> None:
        self.plant = plant
        self.sc = scenario
        self.rng = rng
        self.steps = 0  # steps issued in the current tick, consumed by the runner
        self.mcu_us = scenario.clock.offset_us  # set by the runner at every tick
        # The RX ring as received: chunks with the µs time their last byte arrived.
        self.rx: deque[tuple[bytes, int]] = deque()
        self._rx_bytes = 0
        self.rx_overruns = 0
        self.tx = bytearray()
        # The UART's line rate, bytes/s; None: the link takes whatever is written (the default).
        self.link_tx_bytes_s: float | None = None
        self._tx_backlog = 0.0  # bytes written but not yet on the line
        self._tx_backlog_us = 0
        self.flash_fail = False  # fault hook: programming the sector fails
        self._flash = b""
        self._count_base = plant.count_abs
        self.resets = 0
        # The mark sensor's edge captures the encoder count (a timer input-capture channel).
        self._mark_capture: int | None = None
        plant.on_mark = self._on_mark

    # ---- Hal ------------------------------------------------------------------------------

    def step_out(self, steps: int) -> None:
        """Record the steps of this tick."""
        self.steps = steps

    def drive_enable(self, on: bool) -> None:
        """Energise or release the motor."""
        self.plant.set_drive(on)

    def encoder_read(self) -> int:
        """Shaft count since the last reset, wrapping at 32 bits."""
        return (self.plant.count_abs - self._count_base) & MASK32

    def encoder_index_latch(self) -> int | None:
        """Count captured at the last index edge, once."""
        edge = self.plant.index_abs
        if edge is None:
            return None
        self.plant.index_abs = None
        return (edge - self._count_base) & MASK32

    def inputs_read(self) -> int:
        """Closed switches."""
        return self.plant.switches()

    def mark_latch(self) -> int | None:
        """Count captured at the last reference-mark edge, once."""
        captured, self._mark_capture = self._mark_capture, None
        return captured

    def _on_mark(self, event: MarkEvent) -> None:
        """The plant reports a mark crossing: capture the count as the timer would."""
        self._mark_capture = (event.encoder_abs_count - self._count_base) & MASK32

    def link_read(self) -> tuple[bytes, int]:
        """The ring up to and including its first delimiter (else all of it), and its stamp."""
        rx = self.rx
        if not rx:
            return b"", 0
        parts = []
        while rx:
            chunk, at_us = rx.popleft()
            end = chunk.find(0) + 1
            if 0 < end < len(chunk):
                rx.appendleft((chunk[end:], at_us))  # the rest arrived with it
                chunk = chunk[:end]
            parts.append(chunk)
            if end:
                break
        data = b"".join(parts)
        self._rx_bytes -= len(data)
        return data, at_us & MASK32

    def link_write(self, data: bytes) -> None:
        """Bytes for the host."""
        self.tx += data
        if self.link_tx_bytes_s is not None:
            self.link_tx_room()  # bring the backlog up to now first
            self._tx_backlog += len(data)

    def link_tx_room(self) -> int:
        """Free bytes in the TX buffer: the backlog drains at the line rate."""
        if self.link_tx_bytes_s is None:
            return UNLIMITED_TX_ROOM
        elapsed_us = max(0, self.mcu_us - self._tx_backlog_us)
        self._tx_backlog_us = self.mcu_us
        self._tx_backlog = max(0.0, self._tx_backlog - elapsed_us * self.link_tx_bytes_s / 1e6)
        return max(0, int(TX_RING_BYTES - self._tx_backlog))

    def micros(self) -> int:
        """The MCU µs counter."""
        return self.mcu_us & MASK32

    def mcu_us_at(self, true_s: float) -> int:
        """The µs counter (unwrapped) at plant time `true_s`: the crystal's offset and drift."""
        clock = self.sc.clock
        return clock.offset_us + math.floor(true_s * 1e6 * (1.0 + clock.drift_ppm * 1e-6))

    def flash_read(self) -> bytes:
        """The parameter sector."""
        path = self.sc.flash_path
        if path is None:
            return self._flash
        if not os.path.exists(path):
            return b""
        with open(path, "rb") as f:
            return f.read()

    def flash_write(self, data: bytes) -> bool:
        """Program the sector (False when the fault hook says it fails)."""
        if self.flash_fail:
            return False
        if self.sc.flash_path is None:
            self._flash = bytes(data)
        else:
            with open(self.sc.flash_path, "wb") as f:
                f.write(data)
        return True

    def head_set(self, pan_urad: int, tilt_urad: int) -> None:
        """Servo targets."""
        self.plant.set_head_target(pan_urad * 1e-6, tilt_urad * 1e-6)

    def head_read(self) -> tuple[int, int]:
        """Measured head angles in µrad."""
        pan, tilt = self.plant.head_measure()
        return round(pan * 1e6), round(tilt * 1e6)

    def range_read(self) -> tuple[int, int]:
        """Distance in µm and a quality that falls with distance; (0, 0) without an echo."""
        d = self.plant.range_measure()
        if d is None:
            return 0, 0
        quality = QUALITY_BEST - int(200 * d / self.sc.rangefinder.max_mm)
        return min(MASK32, round(d * 1000)), max(1, quality)

    def system_reset(self) -> None:
        """Peripherals to reset state: encoder timer back to 0, RX ring emptied."""
        self.resets += 1
        self._count_base = self.plant.count_abs
        self.plant.index_abs = None
        self.rx.clear()
        self._rx_bytes = 0
        self.steps = 0

    def random_u32(self) -> int:
        """Hardware RNG (seeded, so runs repeat)."""
        return self.rng.getrandbits(32)

    # ---- the wire side (used by the runner) -----------------------------------------------

    def receive_from_host(self, data: bytes, at_us: int) -> None:
        """Bytes arriving on the UART when the µs counter reads `at_us` (unwrapped).

        The ring keeps the stamp with them, as the RX interrupt would; an overflowing ring loses
        the excess.
        """
        room = RX_RING_BYTES - self._rx_bytes
        if len(data) > room:
            self.rx_overruns += len(data) - room
            data = data[:room]
        if data:
            self.rx.append((bytes(data), at_us))
            self._rx_bytes += len(data)

    def take_for_host(self) -> bytes:
        """Bytes the firmware sent since the previous call."""
        if not self.tx:
            return b""
        data = bytes(self.tx)
        self.tx.clear()
        return data
