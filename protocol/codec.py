"""Payload codec built from the schema at import time: typed message ↔ payload bytes.

Each message gets its compiled layout once, at import: the struct of its fixed part, its range
checks, and a frame decoder that unpacks header-skip, payload and CRC-skip in one struct call.
The per-id table is the hot path of `FrameDecoder.feed`.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from protocol import messages as _messages  # noqa: F401  (registers every message)
from protocol.schema import CRC_SIZE, HEADER_SIZE, SCHEMA, TEXT, MessageSpec

RawDecoder = Callable[[bytes], object]


class PayloadError(ValueError):
    """A payload does not fit its message id (wrong length or undecodable text)."""


@dataclass(frozen=True)
class _Layout:
    """Precompiled per-message codec data."""

    spec: MessageSpec
    fixed: struct.Struct
    names: tuple[str, ...]
    checks: tuple[tuple[str, int, int], ...]
    text_name: str | None
    records: _Records | None = None


@dataclass(frozen=True)
class _Records:
    """Precompiled codec data of a batch's repeated tail."""

    name: str  # the message attribute holding the tuple
    cls: type[Any]
    struct: struct.Struct
    names: tuple[str, ...]
    checks: tuple[tuple[str, int, int], ...]
    max_count: int


def _layout(spec: MessageSpec) -> _Layout:
    """Compile one spec's struct and range checks."""
    fixed = [f for f in spec.fields if f.wire is not TEXT]
    checks = tuple((f.name, *f.info.bounds()) for f in fixed)
    text_name = spec.fields[-1].name if spec.has_text else None
    rec = spec.records
    tail = None
    if rec is not None:
        tail = _Records(
            rec.field_name,
            rec.cls,
            struct.Struct(rec.struct_format),
            tuple(f.name for f in rec.fields),
            tuple((f.name, *f.info.bounds()) for f in rec.fields),
            rec.max_count,
        )
    return _Layout(
        spec,
        struct.Struct(spec.struct_format),
        tuple(f.name for f in fixed),
        checks,
        text_name,
        tail,
    )


_BY_ID: dict[int, _Layout] = {s.id: _layout(s) for s in SCHEMA.specs()}
_BY_CLS: dict[type[Any], _Layout] = {lay.spec.cls: lay for lay in _BY_ID.values()}


def spec_of(msg: object) -> MessageSpec:
    """The spec of a message instance; TypeError for a non-message."""
    return _layout_of(msg).spec


def encode_payload(msg: object) -> tuple[int, bytes]:
    """Message → (id, payload); ValueError naming the field and range when out of range."""
    lay = _layout_of(msg)
    values = [getattr(msg, n) for n in lay.names]
    _check_values(lay.spec.name, lay.checks, values)
    payload = lay.fixed.pack(*values)
    if lay.text_name is not None:
        payload += _encode_text(lay, getattr(msg, lay.text_name))
    elif lay.records is not None:
        payload += _encode_records(lay.spec.name, lay.records, getattr(msg, lay.records.name))
    return lay.spec.id, payload


def _check_values(where: str, checks: tuple[tuple[str, int, int], ...], values: list[Any]) -> None:
    """ValueError naming the field when a value is not an int in its declared range."""
    for (name, lo, hi), value in zip(checks, values, strict=True):
        if type(value) is not int and not isinstance(value, int):
            raise ValueError(f"{where}.{name} must be an integer, got {value!r}")
        if not lo <= value <= hi:
            raise ValueError(f"{where}.{name}={value} outside [{lo}, {hi}]")


def _encode_records(where: str, rec: _Records, items: object) -> bytes:
    """A batch's records, packed in order; ValueError for a wrong type, count or value."""
    if not isinstance(items, tuple | list):
        raise ValueError(f"{where}.{rec.name} must be a tuple of {rec.cls.__name__}")
    if len(items) > rec.max_count:
        raise ValueError(f"{where}.{rec.name} has {len(items)} records, at most {rec.max_count}")
    out = []
    for i, item in enumerate(items):
        if type(item) is not rec.cls:
            raise ValueError(f"{where}.{rec.name}[{i}] must be a {rec.cls.__name__}, got {item!r}")
        values = [getattr(item, n) for n in rec.names]
        _check_values(f"{where}.{rec.name}[{i}]", rec.checks, values)
        out.append(rec.struct.pack(*values))
    return b"".join(out)


def decode_payload(msg_id: int, payload: bytes, offset: int = 0) -> object:
    """(id, payload from offset) → message; KeyError for an unknown id, PayloadError if malformed.

    Range checks are not applied on decode: a receiver validates what it acts on (the
    firmware answers OUT_OF_RANGE), and telemetry is taken as sent.
    """
    lay = _BY_ID[msg_id]
    size = len(payload) - offset
    fixed = lay.fixed.size
    if lay.text_name is not None:
        if not fixed <= size <= fixed + lay.spec.max_text:
            raise PayloadError(f"{lay.spec.name}: {size} payload bytes")
        values = lay.fixed.unpack_from(payload, offset)
        return lay.spec.cls(*values, _decode_text(lay, payload[offset + fixed :]))
    if lay.records is not None:
        return _decode_batch(lay, lay.records, payload, offset, len(payload))
    if size != fixed:
        raise PayloadError(f"{lay.spec.name}: {size} payload bytes, expected {fixed}")
    return lay.spec.cls(*lay.fixed.unpack_from(payload, offset))


def _decode_batch(lay: _Layout, rec: _Records, buf: bytes, start: int, end: int) -> object:
    """The fixed part, then as many whole records as fill buf[start:end] (at most max_count)."""
    size = end - start - lay.fixed.size
    count, rest = divmod(size, rec.struct.size)
    if size < 0 or rest or count > rec.max_count:
        raise PayloadError(
            f"{lay.spec.name}: {end - start} payload bytes, expected {lay.fixed.size} + "
            f"0..{rec.max_count} × {rec.struct.size}"
        )
    head = lay.fixed.unpack_from(buf, start)
    tail = buf[start + lay.fixed.size : end]
    cls = rec.cls
    return lay.spec.cls(*head, tuple(cls(*v) for v in rec.struct.iter_unpack(tail)))


def known_id(msg_id: int) -> bool:
    """Whether the schema declares this message id."""
    return msg_id in _BY_ID


def _layout_of(msg: object) -> _Layout:
    """The compiled layout of a message instance; TypeError for a non-message."""
    lay = _BY_CLS.get(type(msg))
    if lay is None:
        raise TypeError(f"{type(msg).__name__} is not a protocol message")
    return lay


def _encode_text(lay: _Layout, text: object) -> bytes:
    """The trailing text as UTF-8; ValueError when it is not a str or too long."""
    if not isinstance(text, str):
        raise ValueError(f"{lay.spec.name}.{lay.text_name} must be a str, got {text!r}")
    raw = text.encode("utf-8")
    if len(raw) > lay.spec.max_text:
        raise ValueError(
            f"{lay.spec.name}.{lay.text_name} is {len(raw)} bytes, at most {lay.spec.max_text}"
        )
    return raw


def _decode_text(lay: _Layout, raw: bytes) -> str:
    """UTF-8 text → str; PayloadError when it is not valid UTF-8."""
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise PayloadError(f"{lay.spec.name}: text is not UTF-8") from exc


def _raw_decoder(lay: _Layout) -> RawDecoder:
    """A decoder of a whole raw frame (header, payload, CRC) whose header names this id."""
    if lay.records is not None:
        rec = lay.records

        def decode_batch_frame(raw: bytes) -> object:
            return _decode_batch(lay, rec, raw, HEADER_SIZE, len(raw) - CRC_SIZE)

        return decode_batch_frame
    if lay.text_name is not None:
        # Variable length: fall back to the general path over the payload slice.
        msg_id = lay.spec.id

        def decode_text_frame(raw: bytes) -> object:
            return decode_payload(msg_id, raw[: len(raw) - CRC_SIZE], HEADER_SIZE)

        return decode_text_frame
    # Fixed length: one struct skips the header, unpacks the fields and skips the CRC.
    whole = struct.Struct(f"<{HEADER_SIZE}x{lay.fixed.format[1:]}{CRC_SIZE}x")
    size, unpack, cls, name = whole.size, whole.unpack, lay.spec.cls, lay.spec.name

    def decode_fixed_frame(raw: bytes) -> object:
        if len(raw) != size:
            raise PayloadError(f"{name}: {len(raw) - HEADER_SIZE - CRC_SIZE} payload bytes")
        return cls(*unpack(raw))

    return decode_fixed_frame


# id → decoder of a whole raw frame; the framing layer looks ids up here (one dict lookup).
RAW_DECODERS: dict[int, RawDecoder] = {i: _raw_decoder(lay) for i, lay in _BY_ID.items()}
