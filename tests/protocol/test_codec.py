"""Payload codec: hypothesis round trips, every field's boundaries, clear range errors."""

from __future__ import annotations

import dataclasses
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import FrameDecoder, PayloadError, decode_payload, encode_frame, encode_payload
from protocol.codec import RAW_DECODERS, spec_of
from protocol.schema import SCHEMA, TEXT, MessageSpec
from tests.protocol.helpers import message_strategy, raw_frame

SPECS = SCHEMA.specs()
ANY_MESSAGE = st.one_of([message_strategy(s) for s in SPECS])


def _defaults(spec: MessageSpec) -> dict[str, Any]:
    """A valid instance's fields: the low end of every range."""
    return {f.name: "" if f.wire is TEXT else f.info.bounds()[0] for f in spec.fields}


@settings(max_examples=60, deadline=None)
@given(data=st.data())
@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_payload_round_trip(spec: MessageSpec, data: st.DataObject) -> None:
    msg = data.draw(message_strategy(spec))
    msg_id, payload = encode_payload(msg)
    assert msg_id == spec.id
    assert decode_payload(msg_id, payload) == msg


@settings(max_examples=300, deadline=None)
@given(msg=ANY_MESSAGE, seq=st.integers(0, 0xFFFF), flags=st.integers(0, 0xFF))
def test_frame_round_trip(msg: object, seq: int, flags: int) -> None:
    wire = encode_frame(msg, seq, flags)
    assert wire.endswith(b"\x00")
    assert b"\x00" not in wire[:-1]
    dec = FrameDecoder()
    [packet] = dec.feed(wire)
    assert (packet.seq, packet.flags, packet.message) == (seq, flags, msg)
    assert dec.drops.total() == 0


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_every_field_at_both_bounds(spec: MessageSpec) -> None:
    for f in spec.fields:
        if f.wire is TEXT:
            edges: list[Any] = ["", "é" * (spec.max_text // 2), "x" * spec.max_text]
        else:
            edges = list(f.info.bounds())
        for value in edges:
            msg = spec.cls(**{**_defaults(spec), f.name: value})
            assert decode_payload(*encode_payload(msg)) == msg, (f.name, value)


@pytest.mark.parametrize("spec", [s for s in SPECS if s.fields], ids=lambda s: s.name)
def test_out_of_range_names_field_and_range(spec: MessageSpec) -> None:
    for f in spec.fields:
        if f.wire is TEXT:
            too_long = "x" * (spec.max_text + 1)
            msg = spec.cls(**{**_defaults(spec), f.name: too_long})
            with pytest.raises(ValueError, match=rf"{spec.name}\.{f.name} is \d+ bytes"):
                encode_payload(msg)
            continue
        lo, hi = f.info.bounds()
        for bad in (lo - 1, hi + 1):
            msg = spec.cls(**{**_defaults(spec), f.name: bad})
            with pytest.raises(
                ValueError, match=rf"{spec.name}\.{f.name}={bad} outside \[{lo}, {hi}\]"
            ):
                encode_payload(msg)


def test_non_integer_field_is_a_clear_error() -> None:
    spec = SCHEMA.by_name["MOVE_TO"]
    msg = spec.cls(**{**_defaults(spec), "speed_um_s": 1.5})
    with pytest.raises(ValueError, match=r"MOVE_TO\.speed_um_s must be an integer"):
        encode_payload(msg)
    log = SCHEMA.by_name["LOG"].cls(level=0, text=b"bytes")
    with pytest.raises(ValueError, match=r"LOG\.text must be a str"):
        encode_payload(log)


def test_non_message_is_a_type_error() -> None:
    with pytest.raises(TypeError, match="not a protocol message"):
        encode_payload(object())
    with pytest.raises(TypeError, match="not a protocol message"):
        spec_of(3)


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_wrong_payload_length_is_a_payload_error(spec: MessageSpec) -> None:
    _, payload = encode_payload(spec.cls(**_defaults(spec)))
    with pytest.raises(PayloadError, match=spec.name):
        decode_payload(spec.id, payload + b"\x01" * (spec.max_text + 1))
    if spec.fixed_size:
        with pytest.raises(PayloadError, match=spec.name):
            decode_payload(spec.id, payload[: spec.fixed_size - 1])


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_raw_decoder_agrees_with_decode_payload(spec: MessageSpec) -> None:
    msg = spec.cls(**_defaults(spec))
    _, payload = encode_payload(msg)
    assert RAW_DECODERS[spec.id](raw_frame(spec.id, payload)) == msg
    with pytest.raises(PayloadError):
        RAW_DECODERS[spec.id](raw_frame(spec.id, payload + b"\x00" * (spec.max_text + 1)))


def test_text_must_be_utf8() -> None:
    with pytest.raises(PayloadError, match="UTF-8"):
        decode_payload(SCHEMA.by_name["LOG"].id, b"\x01\xc3\x28")


def test_unknown_id_is_a_key_error() -> None:
    with pytest.raises(KeyError):
        decode_payload(0xFF, b"")


def test_seq_out_of_range_is_rejected() -> None:
    msg = SCHEMA.by_name["STOP"].cls()
    for seq in (-1, 0x10000):
        with pytest.raises(ValueError, match=r"seq=.* outside \[0, 65535\]"):
            encode_frame(msg, seq)


def test_messages_are_plain_dataclasses() -> None:
    for s in SPECS:
        assert dataclasses.is_dataclass(s.cls)
        tail = [s.records.field_name] if s.records is not None else []
        assert [f.name for f in dataclasses.fields(s.cls)] == [f.name for f in s.fields] + tail
