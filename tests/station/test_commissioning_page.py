"""Commissioning from the station: an intrinsics run started, followed and ended on the page.

The daemon runs in this process on the fake controller whose camera renders a board through a
seeded true rig (tests/commissioning/simrig.py), with the station enabled. The page starts the
run through the same op as `orbitar calibrate intrinsics`, shows the X / Y / size / skew bars
filling as views are kept, and a viewer's page follows it but cannot start one. The default test
cancels the run from the page; the slow one lets it finish: verdict, reasons, per-view errors and
the report, opened from the page's link. Screenshots go to tests/station/artifacts.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from host.config_ui import UiConfig
from host.geometry.head import Rig
from host.station.render import ViewInput
from tests.commissioning.simrig import BOARD, BOARD_CENTRE_W, STATIONS_MM, Harness, sim_daemon
from tests.hil_rig import free_port
from tests.station.conftest import ARTIFACTS, OPERATOR_TOKEN, VIEWER_TOKEN, dump

FAST_MM_S = 1500.0  # between stations, as tests/commissioning does


@contextlib.asynccontextmanager
async def station_daemon(tmp: Path) -> AsyncIterator[tuple[Harness, str]]:
    """The simulated daemon with its station; the camera's frames shown in the view.

    The harness's frame loop renders the board for the calibration but registers nothing, so
    here its frames go to the station as they are (no pose: the page says the overlay is
    withheld), for the screenshots to show what the run sees.
    """
    port = free_port()
    ui = UiConfig(enabled=True, port=port, operator_token=OPERATOR_TOKEN, viewer_token=VIEWER_TOKEN)
    async with sim_daemon(tmp, seed=5, ui=ui) as h:
        station = h.daemon.station
        assert station is not None

        async def show_camera() -> None:
            shown = None
            while True:
                frame = h.loop.frame_tap.latest()
                if frame is not None and frame is not shown:
                    station.hub.submit(ViewInput(frame.index, frame.exposure_ns, frame.image, None))
                    shown = frame
                await asyncio.sleep(0.25)  # a few frames a second: the run needs the CPU

        feed = asyncio.create_task(show_camera())
        try:
            await h.request("home")
            yield h, f"http://127.0.0.1:{port}"
        finally:
            feed.cancel()
            await asyncio.gather(feed, return_exceptions=True)


async def open_page(browser: Any, base: str, token: str) -> Any:
    """A page on the station, connected."""
    page = await browser.new_page(viewport={"width": 1600, "height": 1300}, bypass_csp=True)
    await page.goto(f"{base}/#token={token}")
    await page.wait_for_function("orbitar.connected && orbitar.status !== null")
    return page


async def start_intrinsics(page: Any) -> None:
    """Fill the intrinsics form as an installer would (a tape-measured centre) and start."""
    await page.select_option("#run-op", "calibrate_intrinsics")
    centre = " ".join(str(round(float(x) + 30.0, 1)) for x in BOARD_CENTRE_W)  # 3 cm off
    fields = {
        "board_centre_mm": centre,
        "stations_mm": ", ".join(str(s) for s in STATIONS_MM),
        "board.squares_x": str(BOARD.squares_x),
        "board.squares_y": str(BOARD.squares_y),
        "board.square_mm": str(BOARD.square_mm),
        "board.marker_mm": str(BOARD.marker_mm),
        "speed_mm_s": str(FAST_MM_S),
    }
    for key, value in fields.items():
        await page.fill(f'#run-form [data-key="{key}"]', value)
    await page.locator("#run-start").click()


def bars_js(least: int) -> str:
    """True once at least `least` coverage bars are partly filled on the page."""
    return (
        "[...document.querySelectorAll('#run-coverage .fill')]"
        f".filter((f) => parseFloat(f.style.width) > 0).length >= {least}"
    )


async def test_an_intrinsics_run_started_on_the_page_fills_the_bars_and_cancels(
    tmp_path: Path, browser: Any
) -> None:
    async with station_daemon(tmp_path) as (h, base):
        before = h.rig_path.read_text()
        page = await open_page(browser, base, OPERATOR_TOKEN)
        viewer = await open_page(browser, base, VIEWER_TOKEN)
        await start_intrinsics(page)
        await page.wait_for_function("orbitar.run && orbitar.run.state === 'running'")
        await page.wait_for_function(bars_js(2), timeout=20_000)  # views kept: bars fill
        await viewer.wait_for_function(bars_js(2), timeout=5_000)  # the viewer follows it
        running = await h.request("commissioning_status")
        assert running["state"] == "running"
        assert running["kind"] == "intrinsics"
        assert running["progress"]["accepted"] >= 1
        text = await page.locator("#run-state").text_content()
        assert "capturing" in text or "solving" in text, text
        # Each captured view's error is shown as it is captured, not only at the run's end.
        await page.wait_for_function("orbitar.run.progress.view_errors.length >= 2")
        errors = (await page.evaluate("orbitar.run.progress.view_errors"))[:2]
        await page.wait_for_function("document.querySelectorAll('#run-views tr').length >= 2")
        caption = await page.locator("#run-views caption").text_content()
        assert "as captured" in caption, caption
        for i, error in enumerate(errors):
            row = await page.locator("#run-views tr").nth(i).text_content()
            assert error["label"] in row, (row, error)
            if error["rms_px"] is None:
                assert error["status"] in row, (row, error)
            else:  # a kept view of the simulated board fits its PnP pose within a pixel
                assert 0.0 < error["rms_px"] < 1.0, error
                assert f"{error['rms_px']:.3f} px" in row, (row, error)
        await page.screenshot(path=str(ARTIFACTS / "commissioning_running.png"), full_page=True)
        # A viewer sees the run but may neither start nor cancel one.
        assert await viewer.evaluate("document.body.classList.contains('viewer')")
        for request in ("calibrate_intrinsics", "commissioning_cancel"):
            await viewer.evaluate(f"op('{request}', {{}})")
            await viewer.wait_for_function(
                f"orbitar.lastReply && orbitar.lastReply.op === '{request}'"
            )
            assert await viewer.evaluate("orbitar.lastReply.code") == "forbidden", request
        assert (await h.request("commissioning_status"))["state"] == "running"
        await viewer.screenshot(path=str(ARTIFACTS / "commissioning_viewer.png"), full_page=True)
        await page.locator("#run-cancel").click()
        await page.wait_for_function("orbitar.run && orbitar.run.state === 'cancelled'")
        assert "CANCELLED" in await page.locator("#run-verdict").text_content()
        await page.screenshot(path=str(ARTIFACTS / "commissioning_cancelled.png"), full_page=True)
        assert h.rig_path.read_text() == before
        # Looking at the workpiece, the error budget predicts the overlay's σ: the page shows it.
        await h.request("clear")
        s_now = (await h.request("status"))["controller"]["position_mm"] + h.loop.home_s_mm
        pan, tilt = Rig().aim(s_now, [-300.0, -300.0, 300.0])
        await h.request("head", pan_rad=pan, tilt_rad=tilt)
        sigma = (await h.budget_at(pan, tilt))["overlay_sigma_px"]
        assert sigma is not None
        # rounded as the page rounds (JavaScript's toFixed takes a tie up, Python's format
        # to even: a σ of 1.250 px reads 1.3 on the page and 1.2 from Python)
        shown = await page.evaluate(f"({sigma}).toFixed(1)")
        await page.wait_for_function(
            f"document.querySelector('#status').textContent.includes('{shown} px')",
            timeout=5_000,
        )
        row = await page.locator("#status tr", has_text="overlay σ").text_content()
        assert f"{shown} px" in row, row
        assert f"σ {shown} px" in await page.locator("#figures").text_content()
        await viewer.close()
        await page.close()


@pytest.mark.slow
async def test_an_intrinsics_run_from_the_page_ends_with_its_verdict_and_report(
    tmp_path: Path, browser: Any
) -> None:
    async with station_daemon(tmp_path) as (h, base):
        page = await open_page(browser, base, OPERATOR_TOKEN)
        await start_intrinsics(page)
        await page.wait_for_function(bars_js(4), timeout=60_000)
        await page.wait_for_function("orbitar.run && orbitar.run.state === 'done'", timeout=60_000)
        await page.wait_for_selector("#run-report:not([hidden])")
        result = (await h.request("commissioning_status"))["result"]
        assert result["passed"], result["reasons"]
        assert await page.locator("#run-verdict").text_content() == "PASS"
        reasons = await page.locator("#run-reasons").text_content()
        assert result["reasons"][0] in reasons
        rows = await page.locator("#run-views tr").count()
        assert rows == result["views"]["ok"]  # one row per kept view, outliers marked
        dropped = await page.locator("#run-views tr.outlier").count()
        assert dropped == len(result["rejected_views"])
        shown = await page.locator("#run-views tr:not(.outlier)").first.text_content()
        assert f"{result['per_view_rms_px'][0]:.3f} px" in shown
        await page.screenshot(path=str(ARTIFACTS / "commissioning_done.png"), full_page=True)
        async with page.expect_popup() as popup_info:
            await page.locator("#run-report").click()
        report = await popup_info.value
        await report.wait_for_load_state()
        assert "PASS" in await report.content()
        images = await report.evaluate(
            "[...document.images].map((i) => i.complete && i.naturalWidth > 0)"
        )
        assert images, "the report has figures"
        assert all(images), images  # and they load from the station too
        await report.screenshot(path=str(ARTIFACTS / "commissioning_report.png"), full_page=True)
        dump(ARTIFACTS / "commissioning_done.json", result)
        await page.close()


async def test_a_camera_workpiece_survey_starts_from_the_page_with_the_sidecars_points(
    tmp_path: Path, browser: Any
) -> None:
    """The survey form offers both methods and fills the model points from the parts sidecar
    the page shows; a malformed field is refused on the page with its label, nothing sent."""
    async with station_daemon(tmp_path) as (h, base):
        before = h.rig_path.read_text()
        page = await open_page(browser, base, OPERATOR_TOKEN)
        await page.select_option("#run-op", "survey_workpiece")
        methods = await page.locator('#run-form [data-key="method"] option').all_text_contents()
        assert methods == ["rangefinder", "camera"]
        sidecar = await page.evaluate("orbitar.info.parts.feature_points.map((p) => p.position_mm)")
        assert len(sidecar) >= 3  # the default model's P1..P5
        points = page.locator('#run-form [data-key="model_points_mm"]')
        assert await points.input_value() == await page.evaluate(f"JSON.stringify({sidecar})")
        await page.select_option('#run-form [data-key="method"]', "camera")
        await page.fill('#run-form [data-key="stations_mm"]', "300, x")
        await page.locator("#run-start").click()
        await page.wait_for_function("document.querySelector('#toast').textContent.length > 0")
        toast = await page.locator("#toast").text_content()
        assert "run not started" in toast, toast
        assert "camera: stations" in toast, toast
        assert (await h.request("commissioning_status"))["state"] == "none"
        here = (await h.request("status"))["controller"]["position_mm"] + h.loop.home_s_mm
        await page.fill('#run-form [data-key="stations_mm"]', f"{here:.0f}")
        await page.locator("#run-start").click()
        # The harness's hall has a board but no targets on the workpiece: the survey plans its
        # views from the points the page sent, films them, finds no target and fails, writing
        # nothing; the page shows the verdict and why.
        await page.wait_for_function("orbitar.run && orbitar.run.state === 'done'", timeout=30_000)
        status = await h.request("commissioning_status")
        assert status["kind"] == "workpiece", status
        assert status["progress"]["planned"] >= 1, status
        result = status["result"]
        assert not result["passed"], result
        assert "FAIL" in await page.locator("#run-verdict").text_content()
        reasons = await page.locator("#run-reasons").text_content()
        assert result["reasons"], result
        assert result["reasons"][0] in reasons, (reasons, result)
        await page.screenshot(path=str(ARTIFACTS / "survey_camera_failed.png"), full_page=True)
        assert h.rig_path.read_text() == before
        await page.close()
