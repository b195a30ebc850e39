"""Payload codec built from the schema at import time: typed message ↔ payload bytes."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

from protocol import messages as _messages  # noqa: F401  (registers every message)
from protocol.schema import SCHEMA, TEXT, MessageSpec


class PayloadError(ValueError):
    """A payload does not fit its message id (wrong length or undecodable text)."""


@dataclass(frozen=True)
class _Layout:
    """Precompiled per-message codec data."""

    spec: MessageSpec
    fixed: struct.Struct
    names: tuple[str, ...]
    checks: tuple[tuple[str, int, int], ...]


def _layout(spec: MessageSpec) -> _Layout:
    """Compile one spec's struct and range checks."""
    fixed = [f for f in spec.fields if f.wire is not TEXT]
    checks = tuple((f.name, *f.info.bounds()) for f in fixed)
    return _Layout(spec, struct.Struct(spec.struct_format), tuple(f.name for f in fixed), checks)


_BY_ID: dict[int, _Layout] = {s.id: _layout(s) for s in SCHEMA.specs()}
_BY_CLS: dict[type[Any], _Layout] = {lay.spec.cls: lay for lay in _BY_ID.values()}


def spec_of(msg: object) -> MessageSpec:
    """The spec of a message instance; TypeError for a non-message."""
    lay = _BY_CLS.get(type(msg))
    if lay is None:
        raise TypeError(f"{type(msg).__name__} is not a protocol message")
    return lay.spec


def encode_payload(msg: object) -> tuple[int, bytes]:
    """Message → (id, payload); ValueError naming the field and range when out of range."""
    lay = _BY_CLS.get(type(msg))
    if lay is None:
        raise TypeError(f"{type(msg).__name__} is not a protocol message")
    values = [getattr(msg, n) for n in lay.names]
    for (name, lo, hi), value in zip(lay.checks, values, strict=True):
        if not isinstance(value, int):
            raise ValueError(f"{lay.spec.name}.{name} must be an integer, got {value!r}")
        if not lo <= value <= hi:
            raise ValueError(f"{lay.spec.name}.{name}={value} outside [{lo}, {hi}]")
    payload = lay.fixed.pack(*values)
    if lay.spec.has_text:
        text = getattr(msg, lay.spec.fields[-1].name)
        raw = text.encode("utf-8")
        if len(raw) > lay.spec.max_text:
            raise ValueError(
                f"{lay.spec.name}.{lay.spec.fields[-1].name} is {len(raw)} bytes, "
                f"at most {lay.spec.max_text}"
            )
        payload += raw
    return lay.spec.id, payload


def decode_payload(msg_id: int, payload: bytes, offset: int = 0) -> object:
    """(id, payload from offset) → message; KeyError for an unknown id, PayloadError if malformed.

    Range checks are not applied on decode: a receiver validates what it acts on (the
    firmware answers OUT_OF_RANGE), and telemetry is taken as sent.
    """
    lay = _BY_ID[msg_id]
    size = len(payload) - offset
    fixed = lay.fixed.size
    if lay.spec.has_text:
        if not fixed <= size <= fixed + lay.spec.max_text:
            raise PayloadError(f"{lay.spec.name}: {size} payload bytes")
        values = lay.fixed.unpack_from(payload, offset)
        try:
            text = payload[offset + fixed :].decode("utf-8")
        except UnicodeDecodeError as exc:
            raise PayloadError(f"{lay.spec.name}: text is not UTF-8") from exc
        return lay.spec.cls(*values, text)
    if size != fixed:
        raise PayloadError(f"{lay.spec.name}: {size} payload bytes, expected {fixed}")
    return lay.spec.cls(*lay.fixed.unpack_from(payload, offset))


def known_id(msg_id: int) -> bool:
    """Whether the schema declares this message id."""
    return msg_id in _BY_ID
