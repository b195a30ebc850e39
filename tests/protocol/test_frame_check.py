"""Version 2's frame check (appended or removed zeros fail) and HELLO/IDENTIFY across versions."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from firmware.controller import Firmware
from hil_sim.runner import Simulation
from protocol import PROTOCOL_VERSION, SCHEMA, FrameDecoder, cobs
from protocol.compat import encode_v1
from protocol.crc import FRAME_CHECK_VALUE, FRAME_RESIDUE, crc16, frame_crc
from protocol.messages import Hello, Identify

VECTORS: dict[str, Any] = json.loads(
    (Path(__file__).resolve().parents[2] / "protocol" / "vectors.json").read_text()
)


def test_frame_crc_is_crc16_genibus() -> None:
    assert frame_crc(b"123456789") == FRAME_CHECK_VALUE == 0xD64E
    data = b"\x02\x01\x05\x00\x13"
    assert crc16(data + frame_crc(data).to_bytes(2, "big")) == FRAME_RESIDUE


@pytest.mark.parametrize("case", VECTORS["rejects"], ids=lambda c: c["case"])
def test_every_reject_vector_is_dropped_in_its_counter(case: dict[str, Any]) -> None:
    dec = FrameDecoder()
    assert dec.feed(bytes.fromhex(case["frame_hex"])) == []
    assert {k: v for k, v in vars(dec.drops).items() if v} == {case["drop"]: 1}


def test_no_vector_passes_with_a_decoded_zero_added_or_its_last_byte_removed() -> None:
    # The fuzz finding: with a zero residue these passed and LOG grew or shrank by one.
    for vec in VECTORS["vectors"]:
        raw = bytes.fromhex(vec["raw_hex"])
        for damaged in (raw + b"\x00", raw + b"\x00\x00", raw + b"\x00" * 3, raw[:-1]):
            dec = FrameDecoder()
            assert dec.feed(cobs.encode(damaged) + b"\x00") == [], vec["message"]


@pytest.mark.parametrize("case", VECTORS["compat"], ids=lambda c: c["case"])
def test_handshake_messages_of_other_versions_are_read(case: dict[str, Any]) -> None:
    packets = FrameDecoder().feed(bytes.fromhex(case["frame_hex"]))
    assert len(packets) == 1
    msg = packets[0].message
    assert type(msg) is SCHEMA.by_name[case["message"]].cls
    assert {k: getattr(msg, k) for k in case["fields"]} == case["fields"]
    assert packets[0].version == case["version"]


def test_controller_answers_a_version_1_hello_so_that_a_version_1_host_can_read_it() -> None:
    sim = Simulation()
    fw: Firmware = sim.firmware
    sim.send(encode_v1(Hello(1, 0x1111_2222), 0, 1))
    sim.step(2)
    out = sim.receive()
    frame = out[: out.index(0) + 1]
    raw = cobs.decode(frame[:-1])
    assert raw[0] == 1
    assert raw[4] == SCHEMA.by_cls[Identify].id
    assert crc16(raw) == 0, "version 1's check: zero residue"
    assert len(raw) == 5 + 35 + 2
    packets = FrameDecoder().feed(frame)
    ident = packets[0].message
    assert isinstance(ident, Identify)
    assert ident.protocol_version == PROTOCOL_VERSION
    assert not fw.hello_seen, "a foreign HELLO opens no session"
