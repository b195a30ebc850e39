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


def _layout(spec: MessageSpec) -> _Layout:
    """Compile one spec's struct and range checks."""
    fixed = [f for f in spec.fields if f.wire is not TEXT]
    checks = tuple((f.name, *f.info.bounds()) for f in fixed)
    text_name = spec.fields[-1].name if spec.has_text else None
    return _Layout(
        spec, struct.Struct(spec.struct_format), tuple(f.name for f in fixed), checks, text_name
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
    for (name, lo, hi), value in zip(lay.checks, values, strict=True):
        if type(value) is not int and not isinstance(value, int):
            raise ValueError(f"{lay.spec.name}.{name} must be an integer, got {value!r}")
        if not lo <= value <= hi:
            raise ValueError(f"{lay.spec.name}.{name}={value} outside [{lo}, {hi}]")
    payload = lay.fixed.pack(*values)
    if lay.text_name is not None:
        payload += _encode_text(lay, getattr(msg, lay.text_name))
    return lay.spec.id, payload


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
    if size != fixed:
        raise PayloadError(f"{lay.spec.name}: {size} payload bytes, expected {fixed}")
    return lay.spec.cls(*lay.fixed.unpack_from(payload, offset))


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
