"""Choosing and configuring a backend by name or URL; bad options name the key."""

from __future__ import annotations

import asyncio

import pytest

from host.transport import (
    BACKENDS,
    TransportConfigError,
    TransportError,
    create_transport,
    open_transport,
    parse_url,
    transport_from_config,
)
from host.transport.can import CanTransport
from host.transport.serial import SerialTransport
from host.transport.xbee import XBeeTransport


def test_backends_table() -> None:
    expected = {"serial": SerialTransport, "xbee": XBeeTransport, "can": CanTransport}
    assert expected == BACKENDS
    for name, cls in BACKENDS.items():
        assert cls.scheme == name


def test_url_forms() -> None:
    assert parse_url("/dev/ttyUSB0") == ("serial", {"url": "/dev/ttyUSB0"})
    assert parse_url("socket://127.0.0.1:5000") == ("serial", {"url": "socket://127.0.0.1:5000"})
    kind, opts = parse_url("xbee:///dev/ttyUSB1?dest_addr64=0013A20040A1B2C3&api_mode=2")
    assert (kind, opts) == (
        "xbee",
        {"url": "/dev/ttyUSB1", "dest_addr64": "0013A20040A1B2C3", "api_mode": 2},
    )
    kind, opts = parse_url("can://slcan/dev/ttyACM0?node_id=0x05&bitrate=250000")
    assert (kind, opts) == (
        "can",
        {"interface": "slcan", "channel": "dev/ttyACM0", "node_id": 5, "bitrate": 250000},
    )


def test_config_with_url_and_overrides() -> None:
    transport = transport_from_config({"url": "loop://", "baudrate": 9600})
    assert isinstance(transport, SerialTransport)
    assert transport.describe() == "serial loop:// @9600"
    xbee = transport_from_config(
        {"kind": "xbee", "url": "/dev/x", "dest_addr64": "0013A200 40A1B2C3"}
    )
    assert isinstance(xbee, XBeeTransport)
    assert xbee.dest_addr64 == 0x0013A20040A1B2C3


@pytest.mark.parametrize(
    ("config", "names"),
    [
        ({"kind": "zigbee"}, "transport.kind"),
        ({"kind": "serial"}, "transport.url: required"),
        ({"kind": "serial", "url": "/dev/x", "baud": 9600}, "transport.baud: unknown option"),
        ({"kind": "serial", "url": "/dev/x", "baudrate": -1}, "baudrate must be a positive"),
        ({"kind": "serial", "url": "COM3x"}, "url 'COM3x'"),
        ({"kind": "xbee", "url": "/dev/x"}, "transport.dest_addr64: required"),
        ({"kind": "xbee", "url": "/dev/x", "dest_addr64": "zz"}, "dest_addr64 'zz'"),
        ({"kind": "xbee", "url": "/dev/x", "dest_addr64": 1, "api_mode": 3}, "api_mode"),
        ({"kind": "can", "interface": "virtual", "channel": "c", "node_id": 0}, "node_id=0"),
        ({"kind": "can", "interface": "nonesuch", "channel": "c"}, "interface 'nonesuch'"),
        ({"url": "can:///dev/x"}, "names no CAN interface"),
        ({"url": "can://virtual/x?node_id=abc"}, "transport.node_id"),
        ({}, "needs 'kind' or 'url'"),
    ],
)
def test_bad_options_name_the_key(config: dict[str, object], names: str) -> None:
    with pytest.raises(TransportConfigError, match=names):
        transport_from_config(config)


async def test_open_of_a_missing_device_is_a_clear_error(tmp_path: object) -> None:
    with pytest.raises(TransportError, match="serial /nonexistent/tty @115200"):
        await open_transport({"url": "/nonexistent/tty"})
    transport = create_transport("serial", url="/nonexistent/tty")
    with pytest.raises(TransportError):
        await transport.open()
    assert transport.state.value == "closed"


async def test_loop_url_echoes() -> None:
    transport = await open_transport({"url": "loop://"})
    got: list[bytes] = []
    transport.set_receiver(got.append)
    try:
        transport.send(b"\x03abc\x00")
        for _ in range(100):
            if b"".join(got) == b"\x03abc\x00":
                break
            await asyncio.sleep(0.005)
        assert b"".join(got) == b"\x03abc\x00"
    finally:
        await transport.close()
