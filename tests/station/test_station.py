"""The station without a browser: WebSocket protocol, dead-man, frame hub, sidecar, config."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import struct
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import cv2
import numpy as np
import pytest

from host.commissioning.env import CommissioningEnv
from host.config import Config, config_from_dict
from host.config_fields import ConfigError
from host.control.ops import OpContext
from host.frames.loop import FrameLoop
from host.frames.registrar import Registration
from host.frames.sources import Frame, SourceState, VideoCaptureSource
from host.geometry.camera import CameraModel
from host.geometry.model import box
from host.registration.pose_buffer import LookupStatus
from host.station.hub import FrameHub
from host.station.parts import BUILTIN_SIDECAR, PartsError, load_parts, parse_parts
from host.station.render import ViewInput, ViewRenderer
from host.station.server import Station
from tests.fakes import MemoryController
from tests.rig.helpers import rig_file

OPERATOR = "operator-token-0123"
VIEWER = "viewer-token-01234"
DEADMAN_MS = 250.0


def station_config(**ui: Any) -> Config:
    """A small camera and the station on a free port."""
    table = {"enabled": True, "port": 0, "operator_token": OPERATOR, "viewer_token": VIEWER}
    table.update(ui)
    rig = rig_file(
        "[camera]\nwidth = 320\nheight = 256\n[camera.intrinsics]\n"
        "u0 = 160.0\nv0 = 128.0\nfx = 300.0\nfy = 300.0\nk1 = 0.0\nk2 = 0.0\n"
    )
    return config_from_dict({"camera": {"source": "none"}, "rig": {"path": str(rig)}, "ui": table})


@pytest.fixture
async def station() -> AsyncIterator[tuple[Station, MemoryController]]:
    fake = MemoryController()
    await fake.connect()
    st = Station(station_config(deadman_ms=DEADMAN_MS), OpContext(fake))
    await st.start()
    try:
        yield st, fake
    finally:
        await st.close()


async def hello(ws: aiohttp.ClientWebSocketResponse, token: str) -> dict[str, Any]:
    """Authenticate; the first JSON message back."""
    await ws.send_json({"type": "hello", "token": token})
    return await next_json(ws, "hello")


async def next_json(ws: aiohttp.ClientWebSocketResponse, kind: str) -> dict[str, Any]:
    """The next JSON message of a type (frames and status in between are skipped)."""
    while True:
        msg = await asyncio.wait_for(ws.receive(), 5.0)
        if msg.type is aiohttp.WSMsgType.TEXT:
            data: dict[str, Any] = json.loads(msg.data)
            if data.get("type") in (kind, "error"):
                return data
        elif msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED):
            return {"type": "closed", "code": ws.close_code}


def calls(fake: MemoryController, name: str) -> int:
    """How often the controller was asked to do `name`."""
    return sum(1 for call, _ in fake.calls if call == name)


async def test_a_jog_stops_when_hold_messages_pause(
    station: tuple[Station, MemoryController],
) -> None:
    st, fake = station
    async with aiohttp.ClientSession() as http, http.ws_connect(f"{st.url}ws") as ws:
        assert (await hello(ws, OPERATOR))["role"] == "operator"
        await ws.send_json({"type": "op", "id": 1, "op": "jog", "args": {"velocity_mm_s": 50}})
        assert (await next_json(ws, "reply"))["ok"] is True
        for _ in range(5):  # held for 0.5 s: no stop
            await ws.send_json({"type": "hold"})
            await asyncio.sleep(0.1)
        assert calls(fake, "stop") == 0
        t0 = time.monotonic()
        message = await next_json(ws, "deadman")  # the page froze: holds stop, socket open
        took_ms = (time.monotonic() - t0) * 1e3
        assert message["why"] == "hold messages stopped"
        assert calls(fake, "stop") == 1
        assert DEADMAN_MS - 100 < took_ms < DEADMAN_MS + 150


async def test_a_dropped_socket_stops_its_jog(station: tuple[Station, MemoryController]) -> None:
    st, fake = station
    async with aiohttp.ClientSession() as http:
        ws = await http.ws_connect(f"{st.url}ws")
        await hello(ws, OPERATOR)
        await ws.send_json({"type": "op", "id": 1, "op": "jog", "args": {"velocity_mm_s": -80}})
        await next_json(ws, "reply")
        await ws.close()
    for _ in range(50):
        if calls(fake, "stop"):
            break
        await asyncio.sleep(0.01)
    assert calls(fake, "stop") == 1
    assert st.stats["deadman_stops"] == 1


async def test_roles_and_tokens(station: tuple[Station, MemoryController]) -> None:
    st, fake = station
    async with aiohttp.ClientSession() as http:
        async with http.ws_connect(f"{st.url}ws") as ws:
            refused = await hello(ws, "wrong")
            assert refused == {"type": "error", "code": "unauthorized"}
            assert (await next_json(ws, "never"))["code"] == 4401
        async with http.ws_connect(f"{st.url}ws") as ws:
            welcome = await hello(ws, VIEWER)
            assert welcome["role"] == "viewer"
            assert welcome["parts"]["feature_points"][0]["name"] == "P1"
            for op, args in (("jog", {"velocity_mm_s": 10}), ("move_track", {"track_s_mm": 5})):
                await ws.send_json({"type": "op", "id": 2, "op": op, "args": args})
                reply = await next_json(ws, "reply")
                assert reply["code"] == "forbidden", reply
            await ws.send_json({"type": "op", "id": 3, "op": "jog", "args": {}})
            assert (await next_json(ws, "reply"))["code"] in ("forbidden", "bad_args")
        async with http.ws_connect(f"{st.url}ws") as ws:
            await hello(ws, OPERATOR)
            await ws.send_json({"type": "op", "id": 4, "op": "jog", "args": {"velocity_mm_s": 1e9}})
            reply = await next_json(ws, "reply")
            assert reply["code"] == "out_of_range"  # the control socket's own validation
            assert "velocity_mm_s" in reply["message"]
        async with http.get(f"{st.url}mjpeg?token=wrong") as response:
            assert response.status == 401
    assert calls(fake, "jog") == 0


async def test_frames_carry_exposure_time_and_points(
    station: tuple[Station, MemoryController],
) -> None:
    st, _ = station
    async with aiohttp.ClientSession() as http, http.ws_connect(f"{st.url}ws") as ws:
        await hello(ws, VIEWER)
        T_w_c = np.eye(4)
        T_w_c[:3, 3] = [0.0, 0.0, 3000.0]
        T_w_c[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking down at the workpiece
        exposure_ns = time.monotonic_ns()
        st.hub.submit(ViewInput(7, exposure_ns, None, T_w_c))
        msg = await asyncio.wait_for(ws.receive(), 5.0)
        while msg.type is not aiohttp.WSMsgType.BINARY:
            msg = await asyncio.wait_for(ws.receive(), 5.0)
        (length,) = struct.unpack(">I", msg.data[:4])
        header = json.loads(msg.data[4 : 4 + length])
        image = cv2.imdecode(np.frombuffer(msg.data[4 + length :], np.uint8), cv2.IMREAD_COLOR)
        assert header["index"] == 7
        assert header["exposure_ms"] == pytest.approx(exposure_ns / 1e6)
        assert image is not None
        assert image.shape == (256, 320, 3)
        assert header["points"], "feature points in view are listed"


async def test_a_stalled_viewer_holds_one_frame_and_slows_nothing() -> None:
    camera = CameraModel(width=64, height=48, u0=32, v0=24, fx=60, fy=60, k1=0, k2=0)
    hub = FrameHub(ViewRenderer(camera, box(10, 10, 10), np.eye(4), load_parts(None)))
    hub.start()
    try:
        stalled = hub.attach()
        for i in range(200):
            hub.submit(ViewInput(i, time.monotonic_ns(), None, None))  # returns at once
            await asyncio.sleep(0.001)
        await asyncio.sleep(0.05)
        assert hub.stats.encoded > 0
        assert stalled.frame is not None
        assert stalled.frame.index == hub.latest.index if hub.latest else False
        assert stalled.dropped == stalled.offered - 1  # everything but the newest was let go
        assert hub.stats.dropped + hub.stats.encoded == hub.stats.submitted
    finally:
        await hub.close()


async def test_each_viewer_gets_the_ghost_it_chose_and_one_choice_costs_one_encode() -> None:
    camera = CameraModel(width=320, height=256, u0=160, v0=128, fx=300, fy=300, k1=0, k2=0)
    hub = FrameHub(ViewRenderer(camera, box(400, 400, 400), np.eye(4), load_parts(None)))
    hub.start()
    T_w_c = np.eye(4)
    T_w_c[:3, 3] = [0.0, 0.0, 3000.0]
    T_w_c[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking down at the box
    ghost = T_w_c.copy()
    ghost[0, 3] += 150.0  # the encoder-only pose, 150 mm off
    try:
        with_ghost, without = hub.attach(True), hub.attach(False)
        hub.submit(ViewInput(1, time.monotonic_ns(), None, T_w_c, ghost))
        a, b = await asyncio.wait_for(with_ghost.take(), 5.0), await without.take()
        assert (a.ghost, b.ghost) == (True, False)
        pixels = [
            np.asarray(cv2.imdecode(np.frombuffer(f.jpeg, np.uint8), cv2.IMREAD_COLOR))
            for f in (a, b)
        ]
        violet = [
            int(((p[..., 2] > 150) & (p[..., 0] > 110) & (p[..., 1] < 170)).sum()) for p in pixels
        ]
        assert violet[0] > 50, violet  # the ghost's edges where asked
        assert violet[1] < 5, violet  # and only there
        without.ghost = True  # the page's toggle: now both want it, one encode serves both
        hub.submit(ViewInput(2, time.monotonic_ns(), None, T_w_c, ghost))
        a, b = await asyncio.wait_for(with_ghost.take(), 5.0), await without.take()
        assert a is b  # one encode served both
        assert a.ghost
        hub.submit(ViewInput(3, time.monotonic_ns(), None, T_w_c, None))  # no drift filter yet
        assert not (await asyncio.wait_for(with_ghost.take(), 5.0)).ghost
    finally:
        await hub.close()


async def test_the_page_sets_its_ghost_and_reads_run_progress_and_reports(
    tmp_path: Path, station: tuple[Station, MemoryController]
) -> None:
    st, _ = station
    st.context.commissioning = CommissioningEnv(report_root=tmp_path)
    run = tmp_path / "20260101-000000-intrinsics"
    run.mkdir()
    (run / "index.html").write_text("<h1>PASS</h1><img src='figure1.png'>")
    (run / "figure1.png").write_bytes(b"\x89PNG")
    (tmp_path / "secret.txt").write_text("not a report")

    async def finished(progress: dict[str, Any]) -> dict[str, Any]:
        progress["coverage"] = {"x": 1.0, "y": 0.5, "size": 0.2, "skew": 0.7}
        return {"passed": True, "reasons": ["ok"], "report": str(run / "index.html")}

    job = st.context.commissioning.jobs.start("intrinsics", finished)
    await job.task
    async with aiohttp.ClientSession() as http, http.ws_connect(f"{st.url}ws") as ws:
        hello_msg = await hello(ws, VIEWER)
        assert "calibrate_intrinsics" in hello_msg["runs"]
        assert hello_msg["camera"]["fx"] == pytest.approx(300.0)
        await ws.send_json({"type": "view", "ghost": False})
        assert (await next_json(ws, "view"))["ghost"] is False
        status = await next_json(ws, "status")
        comm = status["commissioning"]
        assert comm["state"] == "done"
        assert comm["progress"]["coverage"]["x"] == 1.0
        url = comm["report_url"]
        assert url.endswith("/20260101-000000-intrinsics/index.html")
        async with http.get(st.url.rstrip("/") + url) as reply:
            assert reply.status == 200
            assert "PASS" in await reply.text()
            assert "style-src 'unsafe-inline'" in reply.headers["Content-Security-Policy"]
        async with http.get(st.url.rstrip("/") + url.replace("index.html", "figure1.png")) as r:
            assert r.status == 200
        wrong_key = url.replace(st.reports_key, "x" * len(st.reports_key))
        bad = [wrong_key, url.replace("index.html", "secret.txt"), url.replace(run.name, "..")]
        for path in bad:
            async with http.get(st.url.rstrip("/") + path) as reply:
                assert reply.status == 404, path


async def test_a_new_rig_file_reaches_the_drawing_and_the_pages(
    station: tuple[Station, MemoryController],
) -> None:
    st, _ = station
    async with aiohttp.ClientSession() as http, http.ws_connect(f"{st.url}ws") as ws:
        assert (await hello(ws, VIEWER))["camera"]["fx"] == pytest.approx(300.0)
        rig = rig_file(
            "[camera]\nwidth = 320\nheight = 256\n[camera.intrinsics]\n"
            "u0 = 161.0\nv0 = 128.0\nfx = 612.5\nfy = 611.0\nk1 = 0.0\nk2 = 0.0\n"
        )
        new = config_from_dict({"camera": {"source": "none"}, "rig": {"path": str(rig)},
                                "ui": dataclasses.asdict(st.config)})  # fmt: skip
        st.apply_rig(new)  # as the daemon does once a calibration is written
        info = await next_json(ws, "info")
        assert info["camera"]["fx"] == pytest.approx(612.5)
        assert info["camera"]["u0"] == pytest.approx(161.0)
        assert st.hub.renderer.camera.fy == pytest.approx(611.0)


async def test_nothing_is_drawn_without_viewers() -> None:
    camera = CameraModel(width=64, height=48)
    hub = FrameHub(ViewRenderer(camera, box(10, 10, 10), np.eye(4), load_parts(None)))
    hub.start()
    try:
        hub.submit(ViewInput(1, 0, None, None))
        await asyncio.sleep(0.05)
        assert hub.stats.submitted == hub.stats.encoded == 0
    finally:
        await hub.close()


async def test_a_new_viewer_gets_a_recent_frame_at_once_and_never_an_old_one() -> None:
    camera = CameraModel(width=64, height=48)
    hub = FrameHub(ViewRenderer(camera, box(10, 10, 10), np.eye(4), load_parts(None)))
    hub.start()
    try:
        first = hub.attach()
        hub.submit(ViewInput(1, time.monotonic_ns(), None, None))
        await asyncio.wait_for(first.take(), 5.0)
        assert hub.attach().frame is not None  # just drawn: the newcomer's first image at once
        assert hub.latest is not None
        hub.latest = dataclasses.replace(hub.latest, encoded_ns=time.monotonic_ns() - 10**10)
        hub._latest_by_ghost.clear()
        assert hub.attach().frame is None  # drawn 10 s ago: the next view is drawn for it
    finally:
        await hub.close()


async def test_a_pong_says_when_the_ping_came_and_when_the_pong_left(
    station: tuple[Station, MemoryController],
) -> None:
    st, _ = station
    async with aiohttp.ClientSession() as http, http.ws_connect(f"{st.url}ws") as ws:
        await hello(ws, VIEWER)
        before_ms = time.monotonic_ns() / 1e6
        await ws.send_json({"type": "ping", "t": 12.5})
        pong = await next_json(ws, "pong")
        after_ms = time.monotonic_ns() / 1e6
    assert pong["t"] == 12.5
    # The daemon's clock at receipt and at sending: the page takes their difference, the time
    # the pong waited behind other messages, out of the round trip (as NTP does).
    assert before_ms <= pong["host_ms"] <= pong["sent_ms"] <= after_ms


def test_the_builtin_sidecar_names_p1_to_p5() -> None:
    parts = load_parts(BUILTIN_SIDECAR)
    assert [p.name for p in parts.points] == ["P1", "P2", "P3", "P4", "P5"]
    assert all(set(part.points) <= {"P1", "P2", "P3", "P4", "P5"} for part in parts.parts)


@pytest.mark.parametrize(
    ("table", "needle"),
    [
        ({"feature_points": [{"name": "P1", "position_mm": [0, 0]}]}, "feature_points[0]"),
        ({"feature_points": [{"position_mm": [0, 0, 0]}]}, "feature_points[0].name"),
        ({"parts": [{"name": "a", "centre_mm": [0, 0, 0], "points": ["P9"]}]}, "'P9'"),
        ({"colour": "red"}, "colour: unknown key"),
        (
            {"feature_points": [{"name": "P", "position_mm": [0, 0, 0]}] * 2},
            "used twice",
        ),
    ],
)
def test_a_bad_sidecar_names_the_key(table: dict[str, Any], needle: str) -> None:
    with pytest.raises(PartsError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        parse_parts(table)


def test_a_missing_sidecar_is_no_error(tmp_path: Path) -> None:
    assert load_parts(tmp_path / "robot.parts.json").points == ()


@pytest.mark.parametrize(
    ("ui", "needle"),
    [
        ({"enabled": True}, "ui.operator_token"),
        ({"tls_cert": "a.pem"}, "ui.tls_key"),
        ({"operator_token": "x" * 16, "viewer_token": "x" * 16}, "ui.viewer_token"),
        ({"operator_token": "short"}, "ui.operator_token: 5 characters"),
        ({"port": 70000}, "ui.port"),
    ],
)
def test_ui_config_problems_name_the_key(ui: dict[str, Any], needle: str) -> None:
    with pytest.raises(ConfigError, match=needle):
        config_from_dict({"ui": ui})


def test_a_video_file_plays_at_its_frame_rate_and_its_end_is_reported(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    fps, count = 40.0, 12
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (64, 48))
    for i in range(count):
        writer.write(np.full((48, 64, 3), i * 10, np.uint8))
    writer.release()
    source = VideoCaptureSource(str(path))
    t0 = time.monotonic()
    frames = []
    while (frame := source.read()) is not None:
        frames.append(frame)
    elapsed = time.monotonic() - t0
    source.close()
    assert len(frames) == count
    assert elapsed >= 0.9 * (count - 1) / fps  # paced, not read at decoding speed
    stamps = np.diff([f.exposure_ns for f in frames]) / 1e9
    assert np.median(stamps) == pytest.approx(1 / fps, rel=0.3)
    assert source.state is SourceState.ENDED
    assert source.describe()["state"] == "ended"
    assert source.describe()["kind"] == "file"


async def test_a_tap_on_the_plan_moves_through_the_move_op(
    station: tuple[Station, MemoryController],
) -> None:
    st, fake = station
    await fake.home()
    async with aiohttp.ClientSession() as http, http.ws_connect(f"{st.url}ws") as ws:
        await hello(ws, OPERATOR)
        args = {"track_s_mm": 1234.5, "speed_mm_s": 80}
        await ws.send_json({"type": "op", "id": 1, "op": "move_track", "args": args})
        assert (await next_json(ws, "reply"))["ok"] is True
        length = st.track.length_mm
        await ws.send_json(
            {"type": "op", "id": 2, "op": "move_track", "args": {"track_s_mm": length + 1}}
        )
        assert (await next_json(ws, "reply"))["code"] == "out_of_range"
    moves = [args for call, args in fake.calls if call == "move_to"]
    assert moves == [(1234.5, 80.0)]  # home_s_mm = 0 and no position yet: s itself


async def test_mjpeg_serves_the_newest_frame_with_its_exposure(
    station: tuple[Station, MemoryController],
) -> None:
    st, _ = station
    async with aiohttp.ClientSession() as http:
        async with http.get(f"{st.url}mjpeg?token={VIEWER}") as reply:
            assert reply.headers["Content-Type"].startswith("multipart/x-mixed-replace")
            while st.hub.viewer_count == 0:
                await asyncio.sleep(0.01)
            st.hub.submit(ViewInput(3, 123_000_000, None, None))
            reader = aiohttp.MultipartReader.from_response(reply)
            part = await asyncio.wait_for(reader.next(), 5.0)
            assert isinstance(part, aiohttp.BodyPartReader)
            assert part.headers["X-Exposure-Ms"] == "123.000"
            jpeg = await part.read()
            assert cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR) is not None
        bearer = {"Authorization": f"Bearer {VIEWER}"}
        async with http.get(f"{st.url}frame.jpg", headers=bearer) as r:
            assert r.status == 200
            assert r.headers["Content-Type"] == "image/jpeg"


async def test_video_file_frames_reach_the_page_paced(
    station: tuple[Station, MemoryController], tmp_path: Path
) -> None:
    st, _ = station
    path = tmp_path / "scene.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 25.0, (320, 256))
    for i in range(15):
        writer.write(np.full((256, 320, 3), 40 + 10 * i, np.uint8))
    writer.release()
    source = VideoCaptureSource(str(path))

    def register(frame: Frame) -> Registration:
        return Registration(
            frame.index, frame.exposure_ns, LookupStatus.STALE, None, 0.0, 0.0, 0.0,
            None, 0, None, None, frame.image,
        )  # fmt: skip

    loop: FrameLoop[Registration] = FrameLoop(source, register, [st.on_registration])
    async with aiohttp.ClientSession() as http, http.ws_connect(f"{st.url}ws") as ws:
        await hello(ws, VIEWER)
        run = asyncio.create_task(loop.run())
        seen: list[tuple[int, float, float]] = []
        while len(seen) < 5:
            msg = await asyncio.wait_for(ws.receive(), 5.0)
            if msg.type is not aiohttp.WSMsgType.BINARY:
                continue
            (length,) = struct.unpack(">I", msg.data[:4])
            header = json.loads(msg.data[4 : 4 + length])
            image = cv2.imdecode(np.frombuffer(msg.data[4 + length :], np.uint8), 0)
            assert image is not None
            seen.append((header["index"], header["exposure_ms"], float(image.mean())))
            assert header["registered"] is False  # no pose: the frame, but no overlay
            await ws.send_json({"type": "ack", "index": header["index"]})
        await run
    indices = [s[0] for s in seen]
    assert indices == sorted(indices)
    span_ms = seen[-1][1] - seen[0][1]
    assert span_ms >= 0.8 * (indices[-1] - indices[0]) * 40.0  # 25 fps, not decoding speed
    assert seen[-1][2] > seen[0][2]  # later frames of the file are brighter
    assert loop.status()["source"]["state"] == "ended"


async def test_the_station_serves_tls(tmp_path: Path) -> None:
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    made = await asyncio.create_subprocess_exec(
        "openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
        "-subj", "/CN=127.0.0.1", "-keyout", str(key), "-out", str(cert),
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL,
    )  # fmt: skip
    if await made.wait() != 0:
        pytest.skip("openssl could not make a test certificate")
    st = Station(station_config(tls_cert=str(cert), tls_key=str(key)), OpContext(None))
    await st.start()
    try:
        assert st.url.startswith("https://")
        async with aiohttp.ClientSession() as http, http.get(st.url, ssl=False) as reply:
            assert reply.status == 200
            assert "E-STOP" in await reply.text()
    finally:
        await st.close()


async def test_a_flooding_page_is_refused_but_its_stop_is_not(
    station: tuple[Station, MemoryController],
) -> None:
    st, fake = station

    async def slow_param(param_id: int) -> int:  # a slow link: requests stay in flight
        await asyncio.sleep(0.3)
        return 0

    fake.get_param = slow_param  # type: ignore[method-assign]
    async with aiohttp.ClientSession() as http, http.ws_connect(f"{st.url}ws") as ws:
        await hello(ws, OPERATOR)
        ops = [{"type": "op", "id": i, "op": "param_get", "args": {"param": "WATCHDOG_MS"}}
               for i in range(40)]  # fmt: skip
        for message in ops:
            await ws.send_json(message)
        await ws.send_json({"type": "op", "id": "s", "op": "stop", "args": {}})
        replies: list[dict[str, Any]] = []
        while len(replies) < 41:
            replies.append(await next_json(ws, "reply"))
        assert any(r.get("code") == "busy" for r in replies)
        assert next(r for r in replies if r["id"] == "s")["ok"] is True
    assert calls(fake, "stop") == 1


async def test_a_page_that_never_acknowledges_holds_one_frame_and_slows_nobody(
    station: tuple[Station, MemoryController],
) -> None:
    st, _ = station
    async with aiohttp.ClientSession() as http:
        stalled = await http.ws_connect(f"{st.url}ws")
        await hello(stalled, VIEWER)  # and from now on it reads nothing, acknowledges nothing
        live = await http.ws_connect(f"{st.url}ws")
        await hello(live, VIEWER)
        received = 0
        for i in range(60):
            st.hub.submit(ViewInput(i, time.monotonic_ns(), None, None))
            await asyncio.sleep(0.01)
            while True:  # the live page takes and acknowledges what it gets
                try:
                    msg = await asyncio.wait_for(live.receive(), 0.001)
                except TimeoutError:
                    break
                if msg.type is aiohttp.WSMsgType.BINARY:
                    received += 1
                    await live.send_json({"type": "ack"})
        sessions = {s.frames_sent: s for s in st.sessions}
        slow = sessions[min(sessions)]
        assert slow.frames_sent <= 2  # one, then one a second without acknowledgements
        assert slow._slot is not None
        assert slow._slot.dropped >= 50  # the rest replaced in its one-frame slot
        assert received >= 20  # the other page kept getting frames meanwhile
        assert st.hub.stats.encoded >= 20
        await stalled.close()
        await live.close()


async def test_only_a_request_that_ends_the_jog_disarms_the_deadman(
    station: tuple[Station, MemoryController],
) -> None:
    st, fake = station
    async with aiohttp.ClientSession() as http, http.ws_connect(f"{st.url}ws") as ws:
        await hello(ws, OPERATOR)
        requests = [
            ("jog", {"velocity_mm_s": 40}),
            ("head", {"pan_rad": 0.1, "tilt_rad": 0.0}),  # turning the head leaves the jog on
            ("move", {"position_mm": 1e9}),  # refused (out of range): the jog goes on
        ]
        for i, (op, args) in enumerate(requests):
            await ws.send_json({"type": "op", "id": i, "op": op, "args": args})
            await ws.send_json({"type": "hold"})
        replies = {r["op"]: r for r in [await next_json(ws, "reply") for _ in requests]}
        assert replies["head"]["ok"] is True
        assert replies["move"]["ok"] is False
        assert (await next_json(ws, "deadman"))["why"] == "hold messages stopped"
        assert calls(fake, "stop") == 1
        await ws.send_json({"type": "op", "id": 9, "op": "jog", "args": {"velocity_mm_s": 40}})
        await ws.send_json({"type": "op", "id": 10, "op": "jog", "args": {"velocity_mm_s": 0}})
        await next_json(ws, "reply")
        await next_json(ws, "reply")
        await asyncio.sleep(DEADMAN_MS / 1000 * 2)
        assert calls(fake, "stop") == 1  # released properly: nothing more to stop
