"""The attack tests' rig: the shared HIL rig with tests.attack.rogue_sim as its emulator.

rogue_sim writes the plant's true position to dir/truth.json, so a test sees whether the
trolley moved without asking the host, and injects frames on request (`Rig.inject`).
"""

from __future__ import annotations

import json
import time

from tests.hil_rig import HilRig


class Rig(HilRig):
    """The emulator (with truth and injection) and the daemon of one attack."""

    sim_module = "tests.attack.rogue_sim"

    def sim_args(self) -> list[str]:
        return [*super().sim_args(), "--truth", str(self.dir / "truth.json")]

    def start_sim(self, timeout_s: float = 20.0) -> None:
        """The emulator, once it is ready and has written its first truth."""
        super().start_sim(timeout_s)
        deadline = time.monotonic() + 5.0
        while not (self.dir / "truth.json").exists() and time.monotonic() < deadline:
            time.sleep(0.02)

    def inject(self, line: str) -> None:
        """Tell the emulator to send frames of its own (see rogue_sim)."""
        self.tell_sim(line)
        self.wait_sim_says(b"injected", 10.0)

    def truth_s_mm(self) -> float:
        """The trolley's true position now (the emulator's plant, not the host's view)."""
        value: float = json.loads((self.dir / "truth.json").read_text())["s_mm"]
        return value

    def truth(self) -> dict[str, float]:
        """The emulator's last truth: s_mm, s_wrapped_mm, pan_rad, tilt_rad, zero_mm, time_s."""
        value: dict[str, float] = json.loads((self.dir / "truth.json").read_text())
        return value

    def truth_zero_mm(self) -> float:
        """Where on the track the controller's zero truly is (scoring a home survey)."""
        value: float = json.loads((self.dir / "truth.json").read_text())["zero_mm"]
        return value
