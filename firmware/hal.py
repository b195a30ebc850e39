"""The hardware abstraction boundary: everything the firmware touches on the board.

The STM32 build implements these calls with timers, GPIO, the UART/CAN driver and the flash
controller; the simulator implements them on the plant (`hil_sim.board.SimBoard`). The
firmware never reaches past this interface, so the same control code runs on both.
"""

from __future__ import annotations

from typing import Protocol


class Hal(Protocol):
    """Board services, called from the 1 kHz control tick (no call may block)."""

    def step_out(self, steps: int) -> None:
        """Issue `abs(steps)` step pulses this tick, forward if positive, evenly spaced."""

    def drive_enable(self, on: bool) -> None:
        """Energise (True) or release (False) the stepper driver."""

    def encoder_read(self) -> int:
        """Quadrature counter, 32-bit wrapping, zero at reset."""

    def encoder_index_latch(self) -> int | None:
        """Counter value captured at the last index pulse since the previous call, else None."""

    def mark_latch(self) -> int | None:
        """Counter value captured at the last reference-mark edge since the previous call.

        On the STM32 the mark sensor drives a timer input-capture channel of the encoder timer.
        """

    def inputs_read(self) -> int:
        """Digital inputs as `protocol.Inputs` bits: HOME, LIMIT_MIN, LIMIT_MAX, ESTOP_IN."""

    def link_read(self) -> tuple[bytes, int]:
        """Received bytes up to the next frame delimiter, and the µs time the last one arrived.

        Returns the RX ring's bytes up to and including the next 0x00 (all of them when no
        delimiter is pending) with the `micros()` value captured when the last of those bytes
        arrived, or (b"", 0) when the ring is empty; bytes not ending in 0x00 emptied it. On the
        STM32 the UART's character-match interrupt on 0x00 (on CAN, the RX interrupt of a
        frame's last segment) stores the timer and the ring position in a small FIFO beside the
        DMA ring, so the stamp is the frame's arrival, not the tick that gets to it.
        """

    def link_write(self, data: bytes) -> None:
        """Queue bytes for the host on the link's byte stream."""

    def link_tx_room(self) -> int:
        """Bytes the transmit path can take now without waiting (free space in the UART's TX
        DMA buffer, or the CAN mailboxes' worth). The firmware writes no more than this per tick
        and keeps the rest queued, dropping the oldest telemetry when its queue is full."""

    def micros(self) -> int:
        """Free-running microsecond timer, 32-bit wrapping."""

    def flash_read(self) -> bytes:
        """The parameter sector's contents (empty or all 0xFF when erased)."""

    def flash_write(self, data: bytes) -> bool:
        """Erase the parameter sector and program `data`; False if programming failed."""

    def head_set(self, pan_urad: int, tilt_urad: int) -> None:
        """Command the pan/tilt head's servo targets."""

    def head_read(self) -> tuple[int, int]:
        """Measured pan and tilt in µrad."""

    def range_read(self) -> tuple[int, int]:
        """Latest rangefinder reading: distance in µm (0 if invalid) and quality 0–255."""

    def system_reset(self) -> None:
        """Return the peripherals to their reset state (encoder counter zero, RX ring empty)."""

    def random_u32(self) -> int:
        """A word from the hardware random generator (boot ids)."""
