"""The control socket: ops, errors, roles, subscriptions and slow subscribers."""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import stat
import struct
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import msgpack
import pytest

from host.config import ControlConfig, load_config
from host.config_fields import ConfigError
from host.control.api import PoseSample
from host.control.client import ControlClient, ControlRequestError
from host.control.limits import TokenBucket
from host.control.ops import OpContext, Role, dispatch
from host.control.server import ControlServer, ControlServerError
from host.control.wire import MAX_MESSAGE_BYTES, pack, read_message
from protocol import ParamId
from tests.fakes import MemoryController as FakeController

OP_TOKEN = "operator-secret-0123456789"
VIEW_TOKEN = "viewer-secret-0123456789"
IDENTITY = ((1.0, 0, 0, 0), (0, 1.0, 0, 0), (0, 0, 1.0, 0), (0, 0, 0, 1.0))


@pytest.fixture
async def fake() -> FakeController:
    controller = FakeController()
    await controller.connect()
    return controller


@pytest.fixture
async def server(tmp_path: Path, fake: FakeController) -> AsyncIterator[ControlServer]:
    config = ControlConfig(
        socket_path=str(tmp_path / "ctl.sock"),
        tcp_enabled=True,
        tcp_port=0,
        operator_token=OP_TOKEN,
        viewer_token=VIEW_TOKEN,
        queue_max=8,
    )
    pose = PoseSample(123, IDENTITY, "READY", 5.0)
    srv = ControlServer(OpContext(fake, latest_pose=lambda: pose), config)
    await srv.start()
    yield srv
    await srv.close()


@pytest.fixture
async def client(server: ControlServer) -> AsyncIterator[ControlClient]:
    c = await ControlClient.connect_unix(server.config.socket_path)
    yield c
    await c.close()


async def test_socket_file_has_configured_mode(server: ControlServer) -> None:
    mode = os.stat(server.config.socket_path).st_mode
    assert stat.S_ISSOCK(mode)
    assert stat.S_IMODE(mode) == 0o660


async def test_status_reports_controller_and_pose(client: ControlClient) -> None:
    status = await client.request("status")
    assert status["link_up"] is True
    assert status["controller"]["state"] == "IDLE"
    assert status["pose"]["t_ns"] == 123
    assert status["pose"]["T_w_c"][3] == [0.0, 0.0, 0.0, 1.0]


async def test_motion_ops_reach_the_controller(client: ControlClient, fake: FakeController) -> None:
    await client.request("home")
    await client.request("move", position_mm=300.0, speed_mm_s=50.0)
    await client.request("head", pan_rad=0.5, tilt_rad=-0.2)
    await client.request("stop")
    names = [name for name, _ in fake.calls]
    assert names[-4:] == ["home", "move_to", "set_head", "stop"]
    assert fake.calls[-3] == ("move_to", (300.0, 50.0))
    assert fake.head_rad == (0.5, -0.2)


async def test_controller_refusal_is_a_failed_reply(client: ControlClient) -> None:
    with pytest.raises(ControlRequestError) as exc:
        await client.request("move", position_mm=10.0)  # not homed: the fake NAKs
    assert exc.value.code == "failed"
    assert "BAD_STATE" in exc.value.message


@pytest.mark.parametrize(
    ("op", "args", "code"),
    [
        ("move", {}, "bad_args"),
        ("move", {"position_mm": "far"}, "bad_args"),
        ("move", {"position_mm": math.nan}, "bad_args"),
        ("jog", {"velocity_mm_s": 1e9}, "out_of_range"),
        ("head", {"pan_rad": 0.0, "tilt_rad": 3.0}, "out_of_range"),
        ("param_set", {"param": "MAX_SPEED_UM_S", "value": 10**9}, "out_of_range"),
        ("param_set", {"param": "NO_SUCH", "value": 1}, "bad_args"),
        ("fly", {}, "unknown_op"),
        ("subscribe", {"topics": ["weather"]}, "bad_args"),
    ],
)
async def test_bad_requests_never_reach_the_controller(
    client: ControlClient, fake: FakeController, op: str, args: dict[str, Any], code: str
) -> None:
    before = len(fake.calls)
    with pytest.raises(ControlRequestError) as exc:
        await client.request(op, **args)
    assert exc.value.code == code
    assert len(fake.calls) == before


async def test_params_by_name_and_id(client: ControlClient, fake: FakeController) -> None:
    await client.request("param_set", param="WATCHDOG_MS", value=800)
    got = await client.request("param_get", param=int(ParamId.WATCHDOG_MS))
    assert got == {"param": "WATCHDOG_MS", "value": 800, "unit": "ms"}
    await client.request("param_persist")
    assert fake.calls[-1][0] == "persist_params"


async def test_link_down_is_unavailable(client: ControlClient, fake: FakeController) -> None:
    await fake.close()
    with pytest.raises(ControlRequestError) as exc:
        await client.request("home")
    assert exc.value.code == "unavailable"
    assert (await client.request("status"))["link_up"] is False


async def test_garbage_gets_error_reply_and_connection_survives(client: ControlClient) -> None:
    body = b"\xc1\xc1\xc1"  # 0xc1 is never valid msgpack
    await client.send_raw(struct.pack(">I", len(body)) + body)
    array = msgpack.packb([1, 2, 3])
    await client.send_raw(struct.pack(">I", len(array)) + array)
    no_id = msgpack.packb({"op": "status"})
    await client.send_raw(struct.pack(">I", len(no_id)) + no_id)
    await client.send_raw(pack({"id": None, "op": ["estop"]}))  # unhashable op
    await client.send_raw(pack({"id": {"a": 1}, "op": "fly"}))  # echoed back: unhashable id
    assert (await client.request("status"))["link_up"] is True
    codes = [m["error"]["code"] for m in client.unmatched]
    assert codes == ["bad_request"] * 4 + ["unknown_op"]


async def test_oversized_request_gets_error_then_close(client: ControlClient) -> None:
    await client.send_raw(struct.pack(">I", MAX_MESSAGE_BYTES + 1))
    with pytest.raises(ConnectionError):
        await client.next_event(timeout_s=5)
    assert client.unmatched[0]["error"]["code"] == "too_large"


async def test_daemon_survives_oversized_client(server: ControlServer) -> None:
    c1 = await ControlClient.connect_unix(server.config.socket_path)
    await c1.send_raw(struct.pack(">I", 10**9))
    await c1.close()
    async with await ControlClient.connect_unix(server.config.socket_path) as c2:
        assert "link_up" in await c2.request("status")


async def test_subscription_delivers_events(server: ControlServer, client: ControlClient) -> None:
    result = await client.request("subscribe", topics=["state", "pose"])
    assert result["topics"] == ["pose", "state"]
    server.publish("link", {"ignored": True})
    server.publish("state", {"state": "READY"})
    event = await client.next_event(timeout_s=5)
    assert event == {"topic": "state", "data": {"state": "READY"}}
    await client.request("unsubscribe", topics=["state"])
    server.publish("state", {"state": "MOVING"})
    server.publish("pose", {"n": 1})
    assert (await client.next_event(timeout_s=5))["topic"] == "pose"


async def test_slow_subscriber_drops_oldest_and_is_told(
    server: ControlServer, client: ControlClient
) -> None:
    await client.request("subscribe", topics=["pose"])
    for i in range(5000):
        # No await in between: the writer cannot run, exactly like a client that never reads.
        server.publish("pose", {"n": i})
    assert server.stats["events_dropped"] > 0
    seen: list[int] = []
    overflow = None
    while len(seen) < 8 or overflow is None:
        event = await client.next_event(timeout_s=5)
        if event["topic"] == "overflow":
            overflow = event["data"]
        else:
            seen.append(event["data"]["n"])
            if seen[-1] == 4999:
                break
    assert overflow is not None
    assert overflow["dropped"] > 0
    assert seen[-1] == 4999  # the newest survives, the oldest went
    assert seen == list(range(5000 - server.queue_max, 5000))


async def test_tcp_requires_hello_and_viewer_cannot_move(
    server: ControlServer, fake: FakeController
) -> None:
    assert server.tcp_port
    async with await ControlClient.connect_tcp("127.0.0.1", server.tcp_port) as c:
        with pytest.raises(ControlRequestError) as exc:
            await c.request("status")
        assert exc.value.code == "unauthorized"
        with pytest.raises(ControlRequestError):
            await c.request("hello", token="wrong")
        assert (await c.request("hello", token=VIEW_TOKEN))["role"] == "viewer"
        assert "controller" in await c.request("status")
        before = len(fake.calls)
        for op in ("home", "clear", "param_persist"):
            with pytest.raises(ControlRequestError) as exc:
                await c.request(op)
            assert exc.value.code == "forbidden"
        assert len(fake.calls) == before


async def test_viewer_may_stop_and_estop(server: ControlServer, fake: FakeController) -> None:
    assert server.tcp_port
    async with await ControlClient.connect_tcp("127.0.0.1", server.tcp_port) as c:
        await c.request("hello", token=VIEW_TOKEN)
        assert await c.request("stop") == {"sent": True, "acked": True}
        assert await c.request("estop") == {"sent": True, "acked": True}
    assert [name for name, _ in fake.calls[-2:]] == ["stop", "estop"]
    assert fake.state.name == "ESTOP"


async def test_estop_behind_a_full_pipeline_runs_at_once(
    client: ControlClient, fake: FakeController
) -> None:
    gate = asyncio.Event()

    async def slow_param(param_id: int) -> int:
        await gate.wait()
        return 0

    fake.get_param = slow_param  # type: ignore[method-assign]
    pipeline = [{"id": 100 + i, "op": "param_get", "args": {"param": 1}} for i in range(17)]
    await client.send_raw(b"".join(pack(m) for m in pipeline))
    result = await asyncio.wait_for(client.request("estop"), 5)
    assert result == {"sent": True, "acked": True}
    assert fake.state.name == "ESTOP"
    busy = [m for m in client.unmatched if m["id"] == 116]  # the 17th ordinary request
    assert busy
    assert busy[0]["error"]["code"] == "busy"
    assert not [m for m in client.unmatched if m["id"] < 116]  # the 16 still wait
    gate.set()


async def test_estop_with_the_link_down_names_the_watchdog(
    client: ControlClient, fake: FakeController
) -> None:
    await client.request("param_set", param="WATCHDOG_MS", value=800)
    await fake.close()
    for op in ("estop", "stop"):
        with pytest.raises(ControlRequestError) as exc:
            await client.request(op)
        assert exc.value.code == "unavailable"
        assert f"{op} not sent: the controller link is down" in exc.value.message
        assert "watchdog stops the trolley" in exc.value.message
        assert "800 ms" in exc.value.message


async def test_dispatch_serves_a_caller_without_a_socket(fake: FakeController) -> None:
    ctx = OpContext(fake)
    assert await dispatch(ctx, Role.VIEWER, "stop", {}) == {
        "ok": True,
        "result": {"sent": True, "acked": True},
    }
    refused = await dispatch(ctx, Role.VIEWER, "move", {"position_mm": 1.0})
    assert refused["error"]["code"] == "forbidden"
    assert (await dispatch(ctx, Role.NONE, "status", {}))["error"]["code"] == "unauthorized"
    assert (await dispatch(ctx, Role.OPERATOR, "move", {}))["error"]["code"] == "bad_args"
    down = await dispatch(OpContext(None), Role.OPERATOR, "estop", {})
    assert down["error"]["code"] == "unavailable"
    assert down["error"]["detail"] == {
        "sent": False,
        "acked": False,
        "watchdog_ms": 500,
        "watchdog_known": False,
    }
    assert "500 ms, the default, unless changed" in down["error"]["message"]


async def test_short_tokens_are_refused(tmp_path: Path) -> None:
    config = ControlConfig(socket_path=str(tmp_path / "s.sock"), viewer_token="short")
    with pytest.raises(ControlServerError, match=r"control\.viewer_token: 5 characters"):
        await ControlServer(OpContext(None), config).start()


async def test_tcp_operator_may_move(server: ControlServer, fake: FakeController) -> None:
    assert server.tcp_port
    async with await ControlClient.connect_tcp("127.0.0.1", server.tcp_port) as c:
        assert (await c.request("hello", token=OP_TOKEN))["role"] == "operator"
        await c.request("estop")
    assert fake.state.name == "ESTOP"


async def test_stop_is_not_queued_behind_a_slow_request(
    server: ControlServer, client: ControlClient, fake: FakeController
) -> None:
    gate = asyncio.Event()

    async def slow_home() -> None:
        await gate.wait()

    fake.home = slow_home  # type: ignore[method-assign]
    home = asyncio.create_task(client.request("home"))
    await client.request("stop")  # answered while home still waits
    assert not home.done()
    gate.set()
    await home


async def test_second_daemon_on_same_path_is_refused(server: ControlServer) -> None:
    other = ControlServer(OpContext(None), server.config)
    with pytest.raises(ControlServerError, match="another daemon"):
        await other.start()
    await asyncio.sleep(0.1)  # the probe's connection comes and goes on the first server
    assert (await other_status(server))["link_up"] is True


async def other_status(server: ControlServer) -> dict[str, object]:
    """A status request over a fresh connection."""
    async with await ControlClient.connect_unix(server.config.socket_path) as c:
        result: dict[str, object] = await c.request("status")
        return result


async def test_stale_socket_file_is_replaced(tmp_path: Path) -> None:
    import socket

    path = tmp_path / "stale.sock"
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(path))
    s.close()  # the file stays, nobody listens: what a crashed daemon leaves
    srv = ControlServer(OpContext(None), ControlConfig(socket_path=str(path)))
    await srv.start()
    try:
        async with await ControlClient.connect_unix(str(path)) as c:
            assert (await c.request("status"))["link_up"] is False
    finally:
        await srv.close()
    assert not path.exists()


async def test_config_check_names_a_short_token(tmp_path: Path) -> None:
    path = tmp_path / "orbitar.toml"
    path.write_text('[control]\ntcp_enabled = true\noperator_token = "abc"\n')
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert "control.operator_token: 3 characters, need 16 or more" in str(exc.value)


async def test_config_check_names_bad_limits(tmp_path: Path) -> None:
    path = tmp_path / "orbitar.toml"
    path.write_text("[control]\nmax_tcp_connections = 0\nclient_buffer_kb = 10\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert "control.max_tcp_connections" in str(exc.value)
    assert "control.client_buffer_kb" in str(exc.value)


async def test_idle_clients_are_cut_off_but_subscribers_stay(
    tmp_path: Path, fake: FakeController
) -> None:
    config = ControlConfig(socket_path=str(tmp_path / "idle.sock"), idle_timeout_s=1.0)
    srv = ControlServer(OpContext(fake), config)
    await srv.start()
    try:
        idle = await ControlClient.connect_unix(config.socket_path)
        watcher = await ControlClient.connect_unix(config.socket_path)
        await watcher.request("subscribe", topics=["state"])
        with pytest.raises(ConnectionError):
            await idle.next_event(timeout_s=5)
        assert idle.unmatched[0]["error"]["code"] == "timeout"
        assert "control.idle_timeout_s" in idle.unmatched[0]["error"]["message"]
        assert not watcher.closed
        assert (await watcher.request("status"))["link_up"] is True
        await idle.close()
        await watcher.close()
    finally:
        await srv.close()


async def test_a_slow_reader_is_paused_not_cut_off(tmp_path: Path) -> None:
    config = ControlConfig(socket_path=str(tmp_path / "slow.sock"), client_buffer_kb=256)
    srv = ControlServer(OpContext(None), config)
    await srv.start()
    try:
        reader, writer = await asyncio.open_unix_connection(config.socket_path)
        n = 12_000  # ~700 kB of replies: far past the kernel buffers and the 32 kB pause mark
        writer.write(b"".join(pack({"id": i, "op": "status"}) for i in range(n)))
        sending = asyncio.create_task(writer.drain())
        for _ in range(200):  # not reading: the server stops reading us
            if srv.stats["read_pauses"]:
                break
            await asyncio.sleep(0.05)
        assert srv.stats["read_pauses"] >= 1

        async def read_all() -> list[Any]:
            return [(await read_message(reader) or {}).get("id") for _ in range(n)]

        ids = await asyncio.wait_for(read_all(), 15)  # resumes at once, not after stall_timeout_s
        await sending
        assert ids == list(range(n))
        assert srv.stats["cut_off"] == 0
        writer.close()
    finally:
        await srv.close()


async def test_replies_past_the_buffer_limit_cut_the_client_off(tmp_path: Path) -> None:
    config = ControlConfig(socket_path=str(tmp_path / "big.sock"), client_buffer_kb=256)
    srv = ControlServer(OpContext(None), config)
    await srv.start()
    try:
        reader, writer = await asyncio.open_unix_connection(config.socket_path)
        writer.write(pack({"id": 0, "op": "status"}))
        await asyncio.sleep(0.2)
        (conn,) = srv._clients
        for i in range(20):  # replies of requests already in flight, 1.2 MB, never read
            conn.reply({"id": i, "ok": True, "result": "x" * 60_000})
        assert conn.backlog_bytes() == 0  # dropped at once: the memory is back
        assert srv.stats["cut_off"] == 1
        with contextlib.suppress(ConnectionError):
            await asyncio.wait_for(reader.read(), 5)  # the connection ends
        writer.close()
    finally:
        await srv.close()


async def test_failed_hellos_over_all_connections_are_throttled(server: ControlServer) -> None:
    assert server.tcp_port
    server.hello_failures = TokenBucket(burst=2, rate_per_s=0.01)
    for expect_closed in (False, False, True):  # the third guess in a row, on a new connection
        async with await ControlClient.connect_tcp("127.0.0.1", server.tcp_port) as c:
            with pytest.raises(ControlRequestError):
                await c.request("hello", token="guess-" * 4)
            if expect_closed:
                with pytest.raises(ConnectionError):
                    await c.next_event(timeout_s=5)
                assert "too many failed hellos" in c.unmatched[0]["error"]["message"]
            else:
                assert (await c.request("hello", token=OP_TOKEN))["role"] == "operator"
    assert server.stats["hello_failures"] == 3
