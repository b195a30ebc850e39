"""The message table's shape: ids, types, docs, units, replies and sizes (zigpy-xbee style)."""

from __future__ import annotations

import pytest

from protocol import PARAMS, SCHEMA_HASH
from protocol.enums import Capability, Fault, Inputs
from protocol.schema import (
    MAX_PAYLOAD,
    MAX_RAW_FRAME,
    MAX_WIRE_FRAME,
    SCHEMA,
    TEXT,
    Direction,
    MessageSpec,
)

SPECS = SCHEMA.specs()
REPLY_NAMES = {s.reply for s in SPECS if s.reply}
UNITS_ALLOWED = {
    "",
    "µs",
    "ms",
    "µm",
    "µm/s",
    "µm/s²",
    "µrad",
    "counts",
    "counts/s",
    "steps",
    "Hz",
    "bytes",
    "param",
}


def test_ids_and_names_are_unique_and_fit_a_byte() -> None:
    ids = [s.id for s in SPECS]
    assert len(set(ids)) == len(ids)
    assert all(0 < i <= 0xFF for i in ids)
    assert len({s.name for s in SPECS}) == len(SPECS)


def test_directions_partition_the_id_space() -> None:
    # Commands below 0x80, controller messages from 0x80: a glance at an id tells its direction.
    for s in SPECS:
        if s.direction is Direction.TO_HOST:
            assert s.id >= 0x80, s.name
        else:
            assert s.id < 0x80, s.name


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_every_field_is_typed_documented_and_has_a_unit_column(spec: MessageSpec) -> None:
    assert spec.doc
    assert "\n" not in spec.doc
    for f in spec.fields:
        assert f.wire.name in {"u8", "i8", "u16", "i16", "u32", "i32", "text"}
        assert f.info.doc.strip(), f"{spec.name}.{f.name} has no doc"
        assert f.info.unit in UNITS_ALLOWED, f"{spec.name}.{f.name} unit {f.info.unit!r}"
        lo, hi = f.info.bounds()
        if f.wire is not TEXT:
            assert f.wire.lo <= lo <= hi <= f.wire.hi, f"{spec.name}.{f.name}"
    text_fields = [f for f in spec.fields if f.wire is TEXT]
    assert len(text_fields) <= 1
    assert not text_fields or spec.fields[-1] is text_fields[0]
    assert (spec.max_text > 0) == spec.has_text


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_enum_fields_cover_their_enum(spec: MessageSpec) -> None:
    for f in spec.fields:
        if f.info.enum is None:
            continue
        lo, hi = f.info.bounds()
        values = [int(m) for m in f.info.enum.__members__.values()]
        if f.info.enum is Capability:
            assert (lo, hi) == (0, 0xFFFF_FFFF), "every bit readable: unknown bits are ignored"
        elif issubclass(f.info.enum, Fault | Inputs):
            assert hi == sum(values), f"{spec.name}.{f.name}: all flags together"
        else:
            assert min(values) >= lo, f"{spec.name}.{f.name}"
            assert max(values) == hi, f"{spec.name}.{f.name}"


@pytest.mark.parametrize("spec", [s for s in SPECS if s.reply], ids=lambda s: s.name)
def test_every_commands_reply_exists_goes_to_host_and_starts_with_req_seq(
    spec: MessageSpec,
) -> None:
    assert spec.direction is Direction.TO_CONTROLLER
    reply = SCHEMA.by_name[spec.reply or ""]
    assert reply.direction is Direction.TO_HOST
    assert reply.fields[0].name == "req_seq"
    assert reply.fields[0].wire.name == "u16"


def test_acked_commands_have_replies_and_replies_are_not_commands() -> None:
    for s in SPECS:
        if s.acked:
            assert s.reply is not None, s.name
        if s.name in REPLY_NAMES:
            assert not s.acked
            assert s.reply is None
    # CLOCK_SYNC is answered but never retransmitted.
    assert SCHEMA.by_name["CLOCK_SYNC"].reply
    assert not SCHEMA.by_name["CLOCK_SYNC"].acked


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_every_message_fits_max_payload_with_its_longest_text(spec: MessageSpec) -> None:
    assert spec.fixed_size + spec.max_text <= MAX_PAYLOAD


def test_size_constants_are_consistent() -> None:
    # One COBS overhead byte below 254 bytes, plus the delimiter.
    assert MAX_RAW_FRAME + 2 == MAX_WIRE_FRAME == 84
    assert MAX_PAYLOAD == MAX_RAW_FRAME - 5 - 2


def test_schema_hash_is_stable_and_covers_the_layout() -> None:
    text = SCHEMA.canonical_text()
    assert SCHEMA.hash() == SCHEMA_HASH
    for s in SPECS:
        assert f"{s.id}:{s.name}:" in text
        for f in s.fields:
            assert f"{f.name}:{f.wire.name}" in text


def test_params_are_unique_with_defaults_in_range() -> None:
    assert len({int(p.id) for p in PARAMS}) == len(PARAMS)
    for p in PARAMS:
        assert p.lo <= p.default <= p.hi, p.name
        assert -(2**31) <= p.lo <= p.hi < 2**31, p.name  # they travel as i32
        assert p.doc
        assert p.unit in UNITS_ALLOWED | {""}
