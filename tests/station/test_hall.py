"""The station shows the hall's other rigs from the bus: a second rig joins, changes state and
leaves, and the page's Hall panel follows (headless Chromium, Zenoh on 127.0.0.1 only)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Mapping
from typing import Any

import pytest

from host.bus.publisher import BusPublisher
from host.config_bus import BusConfig
from tests.hil_rig import Rigs, free_port
from tests.station.conftest import ARTIFACTS, StationRig, start_station

BUS = """
[bus]
enabled = true
rig_id = "rig-a"
listen = ["tcp/127.0.0.1:{port}"]
stats_interval_s = 0.2
"""


@pytest.fixture(scope="module")
def hall_rig(hil_rig_module: Rigs) -> tuple[StationRig, int]:
    """Emulator + daemon with the station and the bus."""
    bus_port = free_port()
    return start_station(hil_rig_module, BUS.format(port=bus_port)), bus_port


@pytest.fixture
async def rig_b(hall_rig: tuple[StationRig, int]) -> AsyncIterator[BusPublisher]:
    """A second rig on the bus, connected to the daemon's endpoint."""
    _, bus_port = hall_rig

    async def nothing() -> Mapping[str, Any]:
        return {}

    config = BusConfig(enabled=True, rig_id="rig-b", connect=(f"tcp/127.0.0.1:{bus_port}",))
    bus = BusPublisher(config, status=nothing, rig=nothing, stats=lambda: {"link_up": True})
    task = asyncio.create_task(bus.run())
    try:
        yield bus
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        await bus.close()


async def test_the_hall_panel_lists_the_rigs_on_the_bus(
    hall_rig: tuple[StationRig, int], rig_b: BusPublisher, browser: Any
) -> None:
    rig, _ = hall_rig
    page = await browser.new_page(viewport={"width": 1600, "height": 1000}, bypass_csp=True)
    await page.goto(rig.url())
    hall = page.locator("#hall")
    await page.wait_for_function("!document.getElementById('hall-panel').hidden", timeout=15000)
    await hall.locator("tr[data-rig='rig-a']").wait_for(timeout=15000)
    assert "(this rig)" in await hall.locator("tr[data-rig='rig-a']").inner_text()
    while not rig_b.up:
        await asyncio.sleep(0.05)
    rig_b.publish_state({"state": "HOMING", "position_mm": 812.5})
    row_b = hall.locator("tr[data-rig='rig-b']")
    await row_b.wait_for(timeout=15000)
    await page.wait_for_function(
        "document.querySelector(\"#hall tr[data-rig='rig-b']\").innerText.includes('HOMING')",
        timeout=15000,
    )
    text = await row_b.inner_text()
    assert "alive" in text
    assert "812.5 mm" in text
    ARTIFACTS.mkdir(exist_ok=True)
    await page.locator("#hall-panel").screenshot(path=str(ARTIFACTS / "hall.png"))
    await rig_b.close()  # the rig leaves: its liveliness token goes
    await page.wait_for_function(
        "document.querySelector(\"#hall tr[data-rig='rig-b']\").innerText.includes('gone')",
        timeout=15000,
    )
    await page.close()
