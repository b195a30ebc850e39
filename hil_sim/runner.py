"""Running firmware and plant together: lockstep (deterministic, fast) or paced to wall clock.

Lockstep: `Simulation.step(n)` runs n controller ticks as fast as Python goes; a test talks to
the firmware with `send()` / `receive()` (raw link bytes) or through `hil_sim.client.FrameClient`.

Real time: `RealtimeRunner(sim)` runs the same ticks in a background thread paced to the wall
clock, and exchanges link bytes through a thread-safe `SimLinkPort`, the endpoint the link
emulators (pty, TCP, XBee, CAN) bridge to.
"""

from __future__ import annotations

import queue
import random
import threading
import time
from collections.abc import Callable

from firmware.config import TICK_US
from firmware.controller import Firmware
from hil_sim.board import SimBoard
from hil_sim.plant import Plant, Truth
from hil_sim.scenario import Scenario
from host.geometry.track import Track, runway
from host.geometry.transforms import FloatArray

FirmwareBytes = Callable[[bytes], None]
MAX_CATCHUP_TICKS = 200  # after a stall, run at most this many ticks before yielding
MIN_SLEEP_NS = 20_000  # below this a sleep costs more than it waits: run the next tick now
MAX_WAKE_LEAD_NS = 300_000  # cap on how early the thread aims to wake (its measured overshoot)
WAKE_LEAD_GAIN = 1 / 16  # smoothing of the measured overshoot: a GIL stall is one sample of many


class Simulation:
    """Firmware + board + plant, advanced one 1 ms controller tick at a time."""

    def __init__(self, scenario: Scenario | None = None) -> None:
        self.scenario = sc = scenario or Scenario()
        rng = random.Random(sc.seed)
        self.plant = Plant(sc, random.Random(rng.getrandbits(64)))
        self.board = SimBoard(self.plant, sc, random.Random(rng.getrandbits(64)))
        self.firmware = Firmware(self.board, mechanics=sc.firmware_build())
        self.ticks = 0
        # The tick timer runs off the MCU crystal: a fast crystal makes ticks shorter in true time.
        self.dt_s = TICK_US * 1e-6 / (1.0 + sc.clock.drift_ppm * 1e-6)
        self._mcu_base_us = sc.clock.offset_us
        self._track: Track | None = None

    def step(self, n_ticks: int = 1) -> None:
        """Run n controller ticks, each followed by the plant's integration over one tick."""
        board, tick, advance, dt = self.board, self.firmware.tick, self.plant.advance, self.dt_s
        t = self.ticks
        base = self._mcu_base_us
        for _ in range(n_ticks):
            # Tick t samples the plant as it is at true time t·dt and stamps it t·TICK_US.
            board.mcu_us = base + t * TICK_US
            tick()
            advance(board.steps, dt)
            t += 1
        self.ticks = t

    def run_for(self, seconds: float) -> None:
        """Run for a span of MCU time."""
        self.step(round(seconds * 1e6 / TICK_US))

    def send(self, data: bytes, at_s: float | None = None) -> None:
        """Bytes from the host to the firmware's UART, read at the next tick.

        They arrived at plant time `at_s`, by default now (the instant the next tick runs): the
        board stamps them with the MCU clock of that moment, as the UART's RX interrupt would.
        """
        if at_s is None:
            at_us = self._mcu_base_us + self.ticks * TICK_US
        else:
            at_us = self.board.mcu_us_at(at_s)
        self.board.receive_from_host(data, at_us)

    def receive(self) -> bytes:
        """Bytes the firmware has sent since the previous call."""
        return self.board.take_for_host()

    def truth(self) -> Truth:
        """The plant's ground truth now."""
        return self.plant.truth()

    def truth_at(self, time_s: float) -> Truth | None:
        """The plant's ground truth at a recent instant (`Plant.truth_at`)."""
        return self.plant.truth_at(time_s)

    def trolley_pose(self) -> FloatArray:
        """True T_w_t of the trolley now, on the scenario's track (host.geometry.track)."""
        if self._track is None:
            self._track = self.scenario.track.path or runway()
        return self._track.pose(self.plant.truth().s_wrapped_mm)

    @property
    def time_s(self) -> float:
        """True (plant) time since power-on."""
        return self.plant.time_s

    @property
    def mcu_time_us(self) -> int:
        """The MCU clock now, as the firmware reads it (32-bit wrapping)."""
        return self.board.micros()

    # ---- fault hooks ----------------------------------------------------------------------

    def reset_controller(self) -> None:
        """Hardware reset of the MCU (brown-out, watchdog reset, reset button)."""
        self.firmware.request_reboot()

    def inject_tooth_skip(self, teeth: int = 1) -> None:
        """The chain jumps teeth on the sprocket."""
        self.plant.inject_tooth_skip(teeth)

    def inject_missed_steps(self, steps: int) -> None:
        """The motor loses steps."""
        self.plant.inject_missed_steps(steps)

    def set_elongation(self, elongation: float) -> None:
        """Chain stretch from now on (0.005 = 0.5 %)."""
        self.plant.set_elongation(elongation)

    def press_estop(self, pressed: bool = True) -> None:
        """The e-stop mushroom."""
        self.plant.estop_pressed = pressed


class SimLinkPort:
    """Thread-safe byte-stream endpoint of the simulated controller's link.

    `write_to_firmware` may be called from any thread; it stamps the bytes with the host
    monotonic time (`clock_ns`) at which they arrive, so the runner can give the firmware their
    true arrival time even when they arrive between ticks. Bytes from the firmware go to the
    receiver set with `set_receiver` (called on the simulator's thread: hop to your own
    loop with `loop.call_soon_threadsafe`), or, with no receiver, into a queue read with
    `read_from_firmware`.
    """

    def __init__(self, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self._clock_ns = clock_ns
        self._lock = threading.Lock()
        self._inbound: list[tuple[bytes, int]] = []
        self._outbound: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self._receiver: FirmwareBytes | None = None

    def write_to_firmware(self, data: bytes) -> None:
        """Queue bytes for the firmware's UART, stamped with the time they arrive."""
        if not data:
            return
        at_ns = self._clock_ns()
        with self._lock:
            self._inbound.append((bytes(data), at_ns))

    def set_receiver(self, receiver: FirmwareBytes | None) -> None:
        """Deliver firmware bytes to this callable (None: queue them instead)."""
        with self._lock:
            self._receiver = receiver

    def read_from_firmware(self, timeout_s: float = 0.0) -> bytes:
        """Bytes from the firmware, waiting up to timeout_s for the first chunk; b"" if none."""
        chunks = []
        try:
            chunks.append(
                self._outbound.get(timeout=timeout_s)
                if timeout_s > 0
                else self._outbound.get_nowait()
            )
            while True:
                chunks.append(self._outbound.get_nowait())
        except queue.Empty:
            pass
        return b"".join(chunks)

    def take_inbound(self) -> list[tuple[bytes, int]]:
        """Simulator side: the chunks written to the firmware since the previous call.

        In order, each with the host monotonic ns at which it arrived.
        """
        with self._lock:
            chunks, self._inbound = self._inbound, []
        return chunks

    def deliver(self, data: bytes) -> None:
        """Simulator side: hand firmware bytes to the receiver or the queue."""
        with self._lock:
            receiver = self._receiver
        if receiver is not None:
            receiver(data)
        else:
            self._outbound.put(data)


class RealtimeRunner:
    """Runs a Simulation in a background thread paced to the wall clock (`speed` × real time).

    Use `with runner.lock:` to read ground truth or inject faults from another thread.
    """

    def __init__(self, sim: Simulation, speed: float = 1.0, port: SimLinkPort | None = None):
        self.sim = sim
        self.speed = speed
        self.port = port or SimLinkPort()
        self.lock = threading.Lock()
        self.late_ticks = 0  # ticks run behind schedule (the host machine could not keep up)
        # (wall-clock ns, true time s) when pacing began: tick k is due at the wall time that
        # maps to its true time, so `wall_ns_at` converts plant time to host monotonic time.
        self.epoch: tuple[int, float] | None = None
        self._start_tick = sim.ticks
        self._tick_ns = sim.dt_s / speed * 1e9
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._held: list[tuple[bytes, float]] = []  # arrived after the running tick was due

    def wall_ns_at(self, true_s: float) -> int:
        """Host monotonic ns at which plant time `true_s` is (or was) due."""
        if self.epoch is None:
            raise RuntimeError("runner not started")
        t0_ns, true0_s = self.epoch
        return t0_ns + round((true_s - true0_s) / self.speed * 1e9)

    def true_s_at(self, wall_ns: int) -> float:
        """Plant time due at host monotonic time `wall_ns` (the inverse of `wall_ns_at`)."""
        if self.epoch is None:
            raise RuntimeError("runner not started")
        t0_ns, true0_s = self.epoch
        return true0_s + (wall_ns - t0_ns) * self.speed / 1e9

    def start(self) -> None:
        """Start the simulator thread."""
        if self._thread is not None:
            raise RuntimeError("runner already started")
        self._stop.clear()
        self._set_epoch(time.monotonic_ns())
        self._thread = threading.Thread(target=self._run, name="hil-sim", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop and join the simulator thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def __enter__(self) -> RealtimeRunner:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def run_due(self, now_ns: int) -> int:
        """Run every tick due by host time `now_ns`; return ns until the next one is due.

        The pacing step of the thread, public so that a test can drive it with a fake clock
        (the first call then sets the epoch). Tick k is due at `wall_ns_at(k · dt)`, the time
        its MCU stamp stands for, so its link output leaves when the stamp says it does.
        """
        if self.epoch is None:
            self._set_epoch(now_ns)
        backlog = self._ticks_due(now_ns) - self.sim.ticks
        if backlog > 1:
            self.late_ticks += backlog - 1
        for _ in range(min(backlog, MAX_CATCHUP_TICKS)):
            self._run_tick()
        return self._next_due_ns() - now_ns

    def _set_epoch(self, now_ns: int) -> None:
        """Pin the current tick to host time `now_ns`."""
        with self.lock:
            self.epoch = (now_ns, self.sim.time_s)
            self._start_tick = self.sim.ticks
        self._tick_ns = self.sim.dt_s / self.speed * 1e9

    def _ticks_due(self, now_ns: int) -> int:
        """Tick count once every tick due at or before `now_ns` has run."""
        assert self.epoch is not None
        elapsed_ns = now_ns - self.epoch[0]
        if elapsed_ns < 0:
            return self._start_tick
        # The tick due exactly at the epoch counts too: tick k runs at its due time, not a
        # tick later, or every reply would leave one tick after the time it is stamped with.
        return self._start_tick + int(elapsed_ns // self._tick_ns) + 1

    def _next_due_ns(self) -> int:
        """Host time at which the next tick to run is due."""
        assert self.epoch is not None
        return self.epoch[0] + round((self.sim.ticks - self._start_tick) * self._tick_ns)

    def _run_tick(self) -> None:
        """One tick under the lock, its link bytes in before and out after.

        Bytes that arrived since the previous tick enter the UART stamped with the MCU time of
        their arrival, not this tick's: the firmware's clock-sync replies tell the host how long
        a probe waited for the tick.
        """
        sim, port = self.sim, self.port
        with self.lock:
            # A tick that runs late finds bytes that arrived after it was due: in plant time
            # they came after this tick, so they wait for the next one, stamped as they came.
            arrived = self._held + [(d, self.true_s_at(at_ns)) for d, at_ns in port.take_inbound()]
            self._held = [(d, at_s) for d, at_s in arrived if at_s > sim.time_s]
            for data, at_s in arrived:
                if at_s <= sim.time_s:
                    sim.send(data, at_s)
            sim.step(1)
            out = sim.receive()
        if out:
            port.deliver(out)

    def _run(self) -> None:
        """Pace ticks: run those due, then sleep until the next is due."""
        lead_ns = 0.0  # how late the OS wakes us (timer slack, GIL): aim that much earlier
        while not self._stop.is_set():
            now_ns = time.monotonic_ns()
            wait_ns = self.run_due(now_ns + round(lead_ns))
            if wait_ns < MIN_SLEEP_NS:
                continue
            # Each tick's output leaves when it runs and carries the time it was due: waking late
            # by the OS overshoot would delay every reply past its own stamp, a clock-sync bias.
            time.sleep(wait_ns / 1e9)
            overshoot_ns = min(time.monotonic_ns() - now_ns - wait_ns, MAX_WAKE_LEAD_NS)
            lead_ns += WAKE_LEAD_GAIN * (overshoot_ns - lead_ns)
