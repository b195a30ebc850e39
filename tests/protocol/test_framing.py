"""The incremental decoder: whole, byte by byte, random chunks; damage counted exactly."""

from __future__ import annotations

import random

import pytest

from protocol import DropCounters, Flag, FrameDecoder, Packet, encode_frame
from protocol.gen_vectors import build
from protocol.schema import MAX_WIRE_FRAME, SCHEMA, MessageSpec
from tests.protocol.helpers import (
    InjectedStream,
    build_injected_stream,
    load_vectors,
    raw_frame,
    wire,
)

VECTORS = load_vectors()
COUNTERS = list(vars(DropCounters()))


def _feed(data: bytes, chunks: list[int] | None = None) -> tuple[list[Packet], FrameDecoder]:
    """Feed `data` whole, or cut at the given sizes (cycled); return the packets and decoder."""
    dec = FrameDecoder()
    if chunks is None:
        return dec.feed(data), dec
    out: list[Packet] = []
    pos, i = 0, 0
    while pos < len(data):
        size = chunks[i % len(chunks)]
        out += dec.feed(data[pos : pos + size])
        pos, i = pos + size, i + 1
    return out, dec


def _random_chunks(seed: int) -> list[int]:
    rng = random.Random(seed)
    return [rng.randint(1, 97) for _ in range(500)]


@pytest.mark.parametrize("vec", VECTORS, ids=lambda v: f"{v['message']}-{v['case']}")
def test_every_vector_decodes_to_its_fields(vec: dict[str, object]) -> None:
    spec = SCHEMA.by_name[str(vec["message"])]
    packets, dec = _feed(bytes.fromhex(str(vec["frame_hex"])))
    assert [(p.seq, p.flags, p.message) for p in packets] == [
        (vec["seq"], vec["flags"], build(spec, vec["fields"]))  # type: ignore[arg-type]
    ]
    assert dec.frames_ok == 1
    assert dec.drops.total() == 0


@pytest.mark.parametrize("vec", VECTORS, ids=lambda v: f"{v['message']}-{v['case']}")
def test_every_vector_encodes_to_its_frame(vec: dict[str, object]) -> None:
    msg = build(SCHEMA.by_name[str(vec["message"])], vec["fields"])  # type: ignore[arg-type]
    assert encode_frame(msg, vec["seq"], vec["flags"]).hex() == vec["frame_hex"]  # type: ignore[arg-type]


ALL_VECTORS = b"".join(bytes.fromhex(str(v["frame_hex"])) for v in VECTORS)


@pytest.mark.parametrize("chunking", ["whole", "bytes", "random1", "random2"])
def test_all_vectors_in_any_chunking(chunking: str) -> None:
    chunks = {
        "whole": None,
        "bytes": [1],
        "random1": _random_chunks(1),
        "random2": _random_chunks(2),
    }[chunking]
    packets, dec = _feed(ALL_VECTORS, chunks)
    assert len(packets) == len(VECTORS) == dec.frames_ok
    assert [p.seq for p in packets] == [v["seq"] for v in VECTORS]
    assert dec.bytes_in == len(ALL_VECTORS)


def _check_injected(stream: InjectedStream, chunks: list[int] | None) -> None:
    """Every good frame out in order; the drops exactly those injected."""
    packets, dec = _feed(bytes(stream.data), chunks)
    assert [(p.seq, p.flags, p.message) for p in packets] == stream.good
    assert dec.frames_ok == len(stream.good)
    assert dec.drops.total() == stream.expected_total
    # Injections of unknown kind (flips, truncations, short garbage) may land in any counter.
    unknown = stream.expected_total - sum(stream.expected.values())
    for name in COUNTERS:
        want = stream.expected.get(name, 0)
        assert want <= getattr(dec.drops, name) <= want + unknown, name


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("chunking", ["whole", "bytes", "random"])
def test_injected_damage_is_counted_and_good_frames_survive(seed: int, chunking: str) -> None:
    stream = build_injected_stream(seed, rounds=300)
    chunks = {"whole": None, "bytes": [1], "random": _random_chunks(seed)}[chunking]
    _check_injected(stream, chunks)


@pytest.mark.parametrize("chunking", ["whole", "bytes", "random"])
def test_damage_of_known_kind_gives_exact_counters(chunking: str) -> None:
    stream = build_injected_stream(7, rounds=400, exact_only=True)
    chunks = {"whole": None, "bytes": [1], "random": _random_chunks(7)}[chunking]
    packets, dec = _feed(bytes(stream.data), chunks)
    assert len(packets) == len(stream.good)
    got = {n: getattr(dec.drops, n) for n in COUNTERS if getattr(dec.drops, n)}
    assert got == stream.expected
    assert len(stream.expected) == 7  # every counter exercised


@pytest.mark.parametrize(
    "kind",
    ["bad_crc", "bad_cobs", "bad_length", "bad_version", "unknown_id", "bad_payload", "oversize"],
)
def test_each_damage_kind_hits_exactly_its_counter(kind: str) -> None:
    good = encode_frame(SCHEMA.by_name["STOP"].cls(), 5)
    raw = bytearray(raw_frame(SCHEMA.by_name["HOME"].id, b"\x10\x27\x00\x00"))
    bad = {
        "bad_crc": wire(bytes(raw[:-1]) + bytes([raw[-1] ^ 1])),
        "bad_cobs": b"\x09\x01\x02\x00",
        "bad_length": wire(b"\x01\x00\x05"),
        "bad_version": wire(raw_frame(raw[4], bytes(raw[5:-2]), version=9)),
        "unknown_id": wire(raw_frame(0x7F, b"")),
        "bad_payload": wire(raw_frame(raw[4], bytes(raw[5:-3]))),
        "oversize": b"\x55" * MAX_WIRE_FRAME + b"\x00",
    }[kind]
    for chunks in (None, [1], [3, 50]):
        packets, dec = _feed(good + bad + good, chunks)
        assert [p.seq for p in packets] == [5, 5]
        assert {n: getattr(dec.drops, n) for n in COUNTERS if getattr(dec.drops, n)} == {kind: 1}


def test_frame_of_exactly_max_size_passes_and_one_more_byte_is_oversize() -> None:
    longest = b"\x55" * (MAX_WIRE_FRAME - 1)
    _, dec = _feed(longest + b"\x00", [7])
    assert dec.drops.oversize == 0
    assert dec.drops.total() == 1
    _, dec = _feed(b"\x55" + longest + b"\x00", [7])
    assert dec.drops.oversize == 1
    assert dec.drops.total() == 1


def test_an_oversize_run_spanning_many_feeds_counts_once() -> None:
    good = encode_frame(SCHEMA.by_name["STOP"].cls(), 9)
    packets, dec = _feed(b"\x33" * 1000 + b"\x00" + good, [10])
    assert [p.seq for p in packets] == [9]
    assert dec.drops.oversize == 1
    assert dec.drops.total() == 1


def test_reset_forgets_a_partial_frame() -> None:
    good = encode_frame(SCHEMA.by_name["STOP"].cls(), 3)
    dec = FrameDecoder()
    assert dec.feed(good[:4]) == []
    dec.reset()
    assert [p.seq for p in dec.feed(good)] == [3]
    assert dec.drops.total() == 0


def test_idle_delimiters_are_not_errors() -> None:
    good = encode_frame(SCHEMA.by_name["STOP"].cls(), 1)
    packets, dec = _feed(b"\x00" * 50 + good + b"\x00" * 50, [1])
    assert len(packets) == 1
    assert dec.drops.total() == 0


def _wire_lengths(spec: MessageSpec) -> set[int]:
    """Wire lengths of a message with every field at its wire type's extremes or random, at the
    extreme seqs and with every flag off and on: the content must not change the length."""
    rng = random.Random(spec.id)
    fills = [
        {f.name: f.wire.lo for f in spec.fields},
        {f.name: f.wire.hi for f in spec.fields},
        *({f.name: rng.randint(f.wire.lo, f.wire.hi) for f in spec.fields} for _ in range(20)),
    ]
    all_flags = Flag.ACK_REQUESTED | Flag.RETRANSMIT
    return {
        len(encode_frame(spec.cls(**values), seq, flags))
        for values in fills
        for seq in (0, 0xFFFF)
        for flags in (Flag.NONE, all_flags)
    }


def test_clock_sync_probe_is_exactly_as_long_on_the_wire_as_its_reply() -> None:
    # The host takes the midpoint of a probe's round trip as the instant the controller read its
    # clock. On a byte-serial line a frame occupies the line for its length, so any difference
    # between probe and reply shifts every mapped timestamp by half of it (43 µs per byte at
    # 115200 baud). PROTOCOL.md §8 requires the two to stay equally long.
    probe = SCHEMA.by_name["CLOCK_SYNC"]
    reply = SCHEMA.by_name[probe.reply or ""]
    assert reply.name == "CLOCK_SYNC_REPLY"
    probe_lengths, reply_lengths = _wire_lengths(probe), _wire_lengths(reply)
    assert len(probe_lengths) == 1, f"CLOCK_SYNC wire length varies: {sorted(probe_lengths)}"
    assert probe_lengths == reply_lengths, (
        f"CLOCK_SYNC is {probe_lengths.pop()} bytes on the wire, "
        f"CLOCK_SYNC_REPLY {reply_lengths.pop()}"
    )


def test_clock_sync_padding_defaults_to_zero_and_is_not_range_limited() -> None:
    # Senders send zeros; receivers ignore the value, so no value may count as out of range.
    probe = SCHEMA.by_name["CLOCK_SYNC"]
    padding = [f for f in probe.fields if f.name != "token"]
    assert [f.name for f in padding] == ["padding0", "padding1", "padding2"]
    msg = probe.cls(token=7)
    assert all(getattr(msg, f.name) == 0 for f in padding)
    assert all(f.info.bounds() == (f.wire.lo, f.wire.hi) for f in padding)
