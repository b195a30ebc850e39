"""Attacks from the controller's side of the link on the real daemon (issue 14, tester's run).

The emulator (tests.attack.rogue_sim) drops the link's bytes as a pulled cable does, and its
plant's true position shows what the trolley really did.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import threading
import time
from typing import Any

import pytest

from tests.attack.rig import Rig
from tests.hil_rig import Rigs, request

HOME_SPEED_UM_S = 150_000


@pytest.fixture
def rig(hil_rig: Rigs) -> Rig:
    rig = hil_rig(Rig)
    rig.start()
    return rig


def home(rig: Rig) -> None:
    """Home quickly and wait until READY."""
    assert rig.request("param_set", param="HOME_SPEED_UM_S", value=HOME_SPEED_UM_S)["ok"]
    assert rig.request("home")["ok"]
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline:
        state = rig.request("status")["result"]["controller"]
        if state.get("homed") and state["state"] == "READY":
            return
        time.sleep(0.2)
    raise AssertionError(f"not homed: {state}")


def test_a_move_whose_ack_is_lost_says_it_may_be_running(rig: Rig) -> None:
    # On main the operator got "failed: LinkDown: heartbeat timeout" while the trolley drove on
    # to the target: nothing said the command had reached the controller.
    home(rig)
    start_mm = rig.truth_s_mm()
    rig.inject("mute 3 to_host")  # the controller hears us; we hear nothing
    reply: dict[str, Any] = {}

    def move() -> None:
        reply.update(rig.request("move", timeout_s=20.0, position_mm=200.0, speed_mm_s=200.0))

    thread = threading.Thread(target=move)
    thread.start()
    thread.join(25.0)
    assert abs(rig.truth_s_mm() - start_mm) > 100.0  # the trolley did move
    assert reply["ok"] is False
    error = reply["error"]
    assert error["code"] == "failed"
    assert "may have reached the controller" in error["message"]
    assert error["detail"] == {"acked": False, "may_have_run": True}
    rig.wait_link_up()
    stop = rig.request("stop")
    assert stop["result"] == {"sent": True, "acked": True}


def test_sigterm_while_our_frames_are_lost_says_who_stops_the_trolley(rig: Rig) -> None:
    # On main the log said `stop not acknowledged error=""`: the timeout had no text.
    home(rig)
    assert rig.request("jog", velocity_mm_s=100.0)["ok"]
    time.sleep(0.3)
    rig.inject("mute 5 to_firmware")  # the controller no longer hears us, the stop included
    assert rig.daemon is not None
    rig.daemon.send_signal(signal.SIGTERM)
    assert rig.daemon.wait(2.0) == 0
    log = rig.log_tail(20000)
    assert "stop not acknowledged error=TimeoutError" in log
    assert "the controller's own watchdog stops the trolley" in log
    time.sleep(1.0)  # WATCHDOG_MS (500 ms by default) after our last frame …
    stopped_at_mm = rig.truth_s_mm()
    time.sleep(0.5)
    assert abs(rig.truth_s_mm() - stopped_at_mm) < 0.5  # … the trolley stands


def test_a_second_daemon_on_the_same_device_cannot_take_the_link(rig: Rig) -> None:
    # The control socket's lock stops a second daemon on the same socket; one started with
    # another socket_path but the same serial device used to open it too, and the two fought
    # over the link (re-handshakes, LinkDown). The device is now locked (flock) when opened.
    second = rig.dir / "second.toml"
    second.write_text(rig.config.read_text().replace("ctl.sock", "ctl2.sock"))
    with open(rig.dir / "second.log", "wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "host.service", "daemon", "--config", str(second)],
            stdout=subprocess.DEVNULL, stderr=log,
        )  # fmt: skip
    try:
        # Until the second daemon says its link failed (its status), or it took the link.
        deadline = time.monotonic() + 20.0
        second_status: dict[str, Any] = {}
        while time.monotonic() < deadline and rig.request("link_stats")["result"]["handshakes"] < 2:
            assert proc.poll() is None, (rig.dir / "second.log").read_text()
            with contextlib.suppress(OSError):
                second_status = request(str(rig.dir / "ctl2.sock"), "status", 2.0)["result"]
                if second_status["service"]["link_error"]:
                    break
            time.sleep(0.1)
        assert second_status["link_up"] is False, second_status
        assert second_status["service"]["link_error"], second_status
        stats = rig.request("link_stats")["result"]
        assert stats["handshakes"] == 1, stats
        assert rig.request("param_get", param="MAX_SPEED_UM_S")["ok"]
    finally:
        proc.terminate()
        proc.wait(5.0)
