"""Lockstep simulator speed: firmware mirror + plant at the 1 kHz tick.

Prints `metric: value` lines. The headline is `sim_realtime_factor` (simulated seconds per wall
second) with the trolley jogging at the paper's 0.1 m/s and the ENCODER stream at 500 Hz (every
frame encoded and drained from the link each tick); peers show the same run with the host's
decoder attached, with no telemetry, and the plant alone.
"""

from __future__ import annotations

import argparse
import random
import time

from hil_sim.client import FrameClient
from hil_sim.plant import Plant
from hil_sim.runner import Simulation
from hil_sim.scenario import Scenario, TrackConfig
from protocol import FrameDecoder, State, Stream, encode_frame
from protocol.messages import Heartbeat, Jog, StreamSet

TICK_S = 1e-3
PAPER_SPEED_UM_S = 100_000
ACCEL_UM_S2 = 500_000
HEARTBEAT_TICKS = 100


def moving_sim(encoder_hz: int) -> Simulation:
    """A rig jogging at 0.1 m/s with the encoder stream at encoder_hz."""
    sim = Simulation(Scenario(track=TrackConfig(start_s_mm=1000.0)))
    client = FrameClient(sim)
    if encoder_hz:
        client.request(StreamSet(Stream.ENCODER, encoder_hz))
    client.request(Jog(PAPER_SPEED_UM_S, ACCEL_UM_S2))
    client.run(500)
    return sim


def time_ticks(sim: Simulation, ticks: int, decode: bool) -> tuple[float, int]:
    """Run ticks, draining the link each tick; (wall seconds, frames seen)."""
    decoder = FrameDecoder()
    frames = 0
    step, receive, send = sim.step, sim.receive, sim.send
    heartbeat = encode_frame(Heartbeat(0), 0xFFFF)  # keeps the watchdog fed, as a host would
    t0 = time.perf_counter()
    for i in range(ticks):
        if i % HEARTBEAT_TICKS == 0:
            send(heartbeat)
        step(1)
        data = receive()
        if decode and data:
            frames += len(decoder.feed(data))
    wall = time.perf_counter() - t0
    if sim.firmware.state is not State.MOVING:
        raise RuntimeError(f"the trolley stopped during the run: {sim.firmware.state!r}")
    return wall, frames


def plant_only(ticks: int) -> float:
    """Wall seconds for the plant alone at a constant step rate."""
    p = Plant(Scenario(), random.Random(1))
    t0 = time.perf_counter()
    for i in range(ticks):
        p.advance(1 + (i & 3 == 0), TICK_S)
    return time.perf_counter() - t0


def main() -> None:
    """Run the benchmark and print the figures."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per run")
    args = ap.parse_args()
    ticks = round(args.seconds / TICK_S)
    wall, _ = time_ticks(moving_sim(500), ticks, decode=False)
    print(f"sim_realtime_factor: {ticks * TICK_S / wall:.1f}")
    print(f"ticks_per_s: {ticks / wall:.0f}")
    print(f"tick_us: {wall / ticks * 1e6:.1f}")
    wall_dec, frames = time_ticks(moving_sim(500), ticks, decode=True)
    print(f"sim_realtime_factor_with_host_decode: {ticks * TICK_S / wall_dec:.1f}")
    print(f"encoder_frames_per_sim_s: {frames / (ticks * TICK_S):.0f}")
    wall_quiet, _ = time_ticks(moving_sim(0), ticks, decode=False)
    print(f"sim_realtime_factor_no_telemetry: {ticks * TICK_S / wall_quiet:.1f}")
    print(f"plant_only_ticks_per_s: {ticks / plant_only(ticks):.0f}")


if __name__ == "__main__":
    main()
