"""Runs the firmware mirror + plant on the test's event loop, paced to loop time, behind a
MemoryTransport: the host session talks to the real firmware with real frames."""

from __future__ import annotations

import asyncio
import contextlib

from firmware.config import TICK_US
from hil_sim.runner import Simulation
from hil_sim.scenario import Scenario
from host.transport.memory import Impairment, MemoryTransport

PACE_S = 0.001
MAX_BURST_TICKS = 200


class SimBridge:
    """Steps the simulation as loop time passes; bytes flow through a MemoryTransport."""

    def __init__(
        self,
        scenario: Scenario | None = None,
        tx: Impairment | None = None,
        rx: Impairment | None = None,
        seed: int = 0,
    ) -> None:
        self.sim = Simulation(scenario)
        self.transport = MemoryTransport(self._to_firmware, tx=tx, rx=rx, seed=seed, name="sim")
        self._inbound = bytearray()
        self._task: asyncio.Task[None] | None = None
        self._t0 = 0.0
        self._tick0 = 0

    def start(self) -> None:
        """Begin stepping on the running loop."""
        self._t0 = asyncio.get_running_loop().time()
        self._tick0 = self.sim.ticks
        self._task = asyncio.create_task(self._run(), name="sim-bridge")

    async def stop(self) -> None:
        """Stop stepping."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None

    def host_ns_of_mcu(self, mcu_us: int) -> int:
        """True host time (loop clock, ns) at which the MCU clock read `mcu_us` (64-bit)."""
        tick = (mcu_us - self.sim.scenario.clock.offset_us) // TICK_US
        dt_s: float = self.sim.dt_s
        return round((self._t0 + (tick - self._tick0) * dt_s) * 1e9)

    def _to_firmware(self, frame: bytes) -> None:
        self._inbound += frame

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            due = self._tick0 + int((loop.time() - self._t0) / self.sim.dt_s)
            for _ in range(min(due - self.sim.ticks, MAX_BURST_TICKS)):
                if self._inbound:
                    self.sim.send(bytes(self._inbound))
                    self._inbound.clear()
                self.sim.step(1)
                out = self.sim.receive()
                if out:
                    self.transport.inject(out)
            await asyncio.sleep(PACE_S)
