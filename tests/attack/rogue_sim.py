"""The emulator with two additions for attack tests: its truth in a file, and injected frames.

`python -m tests.attack.rogue_sim --link-path P --truth T [emulator options]` runs the same
emulator as `python -m hil_sim` and writes the plant's true position and head angles (and the
true place of the controller's zero) to T every 50 ms, so a test can see whether the trolley
moved without asking the host. Lines on stdin inject controller frames behind the firmware's
back: `status N STATE FAULTS` sends N STATUS frames, `log N` N LOG frames, `encoder N [COUNT
VELOCITY MCU_US]` N encoder samples, `head N PAN TILT` N head samples (µrad), as a misbehaving
controller would; `mute S both|to_host|to_firmware` drops the link's bytes for S seconds, as a
pulled cable does.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import struct
import sys
import threading
import time

from hil_sim.cli import (
    add_arguments,
    make_emulator,
    make_runner,
    options_from_args,
    say,
    stop_on_signals,
)
from hil_sim.runner import RealtimeRunner
from protocol import PROTOCOL_VERSION, cobs, encode_frame
from protocol.codec import spec_of
from protocol.crc import crc16
from protocol.messages import EncoderSample, HeadSample, Log, Status
from protocol.schema import HEADER_FORMAT

TRUTH_PERIOD_S = 0.05


def write_truth(runner: RealtimeRunner, path: str, stop: threading.Event) -> None:
    """The plant's true position, atomically replaced every TRUTH_PERIOD_S; and where on the
    track the controller's zero truly is (its position and the plant's at the same instant)."""
    while not stop.wait(TRUTH_PERIOD_S):
        with runner.lock:
            truth = runner.sim.truth()
            zero_mm = truth.s_mm - runner.sim.firmware.position_um / 1000.0
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            pose = {"s_wrapped_mm": truth.s_wrapped_mm, "pan_rad": truth.pan_rad}
            pose["tilt_rad"] = truth.tilt_rad
            json.dump({"s_mm": truth.s_mm, "time_s": truth.time_s, "zero_mm": zero_mm, **pose}, f)
        os.replace(tmp, path)


def frames(command: str) -> list[bytes]:
    """The frames one stdin line asks for."""
    words = command.split()
    kind, count = words[0], int(words[1])
    out = []
    for i in range(count):
        seq = (40000 + i) % 65536
        if kind == "status":
            out.append(raw_status(seq, i * 1000, int(words[2]), int(words[3])))
            continue
        if kind == "log":
            message: object = Log(2, f"flood {i} " + "x" * 40)
        elif kind == "encoder":  # encoder N [COUNT VELOCITY MCU_US]
            count, velocity, mcu_us = (int(w) for w in (words[2:5] if len(words) > 4 else "000"))
            message = EncoderSample(mcu_us + i * 1000, count, count, velocity, 0)
        else:  # head N PAN_URAD TILT_URAD
            message = HeadSample(i * 1000, int(words[2]), int(words[3]))
        out.append(encode_frame(message, seq))
    return out


def raw_status(seq: int, mcu_us: int, state: int, faults: int) -> bytes:
    """A STATUS frame with any state and faults, past the encoder's range checks."""
    spec = spec_of(Status(0, 0, 0, 0, 0, 0))
    payload = struct.pack(spec.struct_format, mcu_us, state, faults, 0, 0, 0)
    raw = struct.pack(HEADER_FORMAT, PROTOCOL_VERSION, 0, seq, spec.id) + payload
    return cobs.encode(raw + crc16(raw).to_bytes(2, "big")) + b"\x00"


class Mute:
    """Drops the link's bytes in one or both directions until a deadline (a cable pulled)."""

    def __init__(self, runner: RealtimeRunner) -> None:
        self.to_host_until = self.to_firmware_until = 0.0
        port = runner.port
        deliver, write = port.deliver, port.write_to_firmware

        def muted_deliver(data: bytes) -> None:
            if time.monotonic() >= self.to_host_until:
                deliver(data)

        def muted_write(data: bytes) -> None:
            if time.monotonic() >= self.to_firmware_until:
                write(data)

        port.deliver = muted_deliver  # type: ignore[method-assign]
        port.write_to_firmware = muted_write  # type: ignore[method-assign]

    def apply(self, words: list[str]) -> None:
        """`mute SECONDS both|to_host|to_firmware`."""
        until = time.monotonic() + float(words[1])
        if words[2] in ("both", "to_host"):
            self.to_host_until = until
        if words[2] in ("both", "to_firmware"):
            self.to_firmware_until = until


def inject(runner: RealtimeRunner, stop: threading.Event) -> None:
    """Read injection commands from stdin and hand their frames to the link."""
    mute = Mute(runner)
    for line in sys.stdin:
        if stop.is_set() or not line.strip():
            continue
        if line.startswith("mute"):
            mute.apply(line.split())
            say(sys.stdout, f"injected {line.strip()}")
            continue
        try:
            for frame in frames(line):
                runner.port.deliver(frame)
        except (ValueError, IndexError) as exc:  # a bad command line: say so, keep serving
            say(sys.stdout, f"injected nothing: {exc}")
            continue
        say(sys.stdout, f"injected {line.strip()}")


async def serve(args: argparse.Namespace) -> int:
    """The emulator of `python -m hil_sim`, plus truth and injection threads."""
    options = options_from_args(args)
    stop = asyncio.Event()
    restore = stop_on_signals(stop)
    runner = make_runner(options)
    emulator = make_emulator(options, runner)
    done = threading.Event()
    threads = [
        threading.Thread(target=write_truth, args=(runner, args.truth, done), daemon=True),
        threading.Thread(target=inject, args=(runner, done), daemon=True),
    ]
    try:
        await emulator.start()
        runner.start()
        for thread in threads:
            thread.start()
        say(sys.stdout, "press Ctrl-C (or send SIGTERM) to stop")
        await stop.wait()
    finally:
        done.set()
        await emulator.stop()
        runner.stop()
        restore()
    return 0


def main() -> int:
    """Parse the emulator's options and --truth, then serve."""
    parser = argparse.ArgumentParser(prog="python -m tests.attack.rogue_sim")
    add_arguments(parser)
    parser.add_argument("--truth", required=True, help="file to write the true position to")
    return asyncio.run(serve(parser.parse_args()))


if __name__ == "__main__":
    sys.exit(main())
