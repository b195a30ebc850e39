"""Declarative message schema: wire types, field and message specs, and the registry.

Messages are declared once, as annotated dataclasses in `protocol.messages`; this module turns
each declaration into a `MessageSpec` (the table the codec, PROTOCOL.md, the test vectors and
the C header are generated from). Nothing else in the project restates a message's layout.
"""

from __future__ import annotations

import dataclasses
import enum
import struct
import typing
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

PROTOCOL_VERSION = 2
# Header: version u8, flags u8, seq u16 LE, message id u8.
HEADER_FORMAT = "<BBHB"
HEADER_SIZE = struct.calcsize(HEADER_FORMAT)
CRC_SIZE = 2
# Largest encoded frame on the wire, trailing delimiter included: one XBee unicast payload.
MAX_WIRE_FRAME = 84
# COBS adds one code byte per 254 data bytes; below 254 bytes it is exactly one.
MAX_RAW_FRAME = MAX_WIRE_FRAME - 2
MAX_PAYLOAD = MAX_RAW_FRAME - HEADER_SIZE - CRC_SIZE
# Capability.QUIET_CLOCK_PROBES: the longest a CLOCK_SYNC holds the controller's telemetry
# (PROTOCOL.md §8, R-QUIET-1): long enough for its reply and the host's second probe.
QUIET_HOLD_US = 40_000


class Direction(enum.Enum):
    """Which side sends a message."""

    TO_CONTROLLER = "host → controller"
    TO_HOST = "controller → host"
    BOTH = "both"


class Flag(enum.IntFlag):
    """Header flag bits; undefined bits are sent as 0 and ignored on receipt."""

    NONE = 0
    ACK_REQUESTED = 0x01  # reliable command: the receiver answers with the declared reply
    RETRANSMIT = 0x02  # informational: this frame repeats an earlier seq


@dataclass(frozen=True)
class WireType:
    """A fixed-size integer or a trailing UTF-8 text on the wire."""

    name: str
    code: str  # struct format character; "" for trailing text
    c_type: str
    lo: int
    hi: int

    @property
    def size(self) -> int:
        """Bytes on the wire (0 for the variable text)."""
        return struct.calcsize("<" + self.code) if self.code else 0


U8 = WireType("u8", "B", "uint8_t", 0, 0xFF)
I8 = WireType("i8", "b", "int8_t", -0x80, 0x7F)
U16 = WireType("u16", "H", "uint16_t", 0, 0xFFFF)
I16 = WireType("i16", "h", "int16_t", -0x8000, 0x7FFF)
U32 = WireType("u32", "I", "uint32_t", 0, 0xFFFF_FFFF)
I32 = WireType("i32", "i", "int32_t", -0x8000_0000, 0x7FFF_FFFF)
TEXT = WireType("text", "", "char", 0, 0)


@dataclass(frozen=True)
class FieldInfo:
    """Annotation metadata of one field: wire type, unit, documentation and valid range."""

    wire: WireType
    unit: str
    doc: str
    lo: int | None = None
    hi: int | None = None
    enum: type[enum.IntEnum] | type[enum.IntFlag] | None = None

    def bounds(self) -> tuple[int, int]:
        """Valid closed range: the declared one, else the wire type's."""
        lo = self.wire.lo if self.lo is None else self.lo
        hi = self.wire.hi if self.hi is None else self.hi
        return lo, hi


def field(
    wire: WireType,
    unit: str,
    doc: str,
    *,
    lo: int | None = None,
    hi: int | None = None,
    enum: type[enum.IntEnum] | type[enum.IntFlag] | None = None,
) -> FieldInfo:
    """Declare a field's wire metadata (used inside `Annotated[int, ...]`)."""
    return FieldInfo(wire, unit, doc, lo, hi, enum)


@dataclass(frozen=True)
class RecordsInfo:
    """Annotation of a message's trailing run of records: their class, how many, what they are."""

    cls: type[Any]
    max_count: int
    doc: str


def records(cls: type[Any], max_count: int, doc: str) -> RecordsInfo:
    """Declare a trailing run of 0..max_count records (used inside `Annotated[tuple[...], ...]`)."""
    return RecordsInfo(cls, max_count, doc)


@dataclass(frozen=True)
class FieldSpec:
    """One field as the codec and the generators see it."""

    name: str
    info: FieldInfo

    @property
    def wire(self) -> WireType:
        """The field's wire type."""
        return self.info.wire


@dataclass(frozen=True)
class RecordSpec:
    """The repeated tail of a message: `count` records of `fields`, filling the payload's end."""

    field_name: str  # the message attribute holding the tuple of records
    name: str
    cls: type[Any]
    fields: tuple[FieldSpec, ...]
    max_count: int
    doc: str

    @property
    def struct_format(self) -> str:
        """struct format of one record."""
        return "<" + "".join(f.wire.code for f in self.fields)

    @property
    def size(self) -> int:
        """Bytes of one record."""
        return struct.calcsize(self.struct_format)


@dataclass(frozen=True)
class MessageSpec:
    """One row of the message table."""

    id: int
    name: str
    direction: Direction
    acked: bool
    reply: str | None
    doc: str
    fields: tuple[FieldSpec, ...]
    cls: type[Any]
    max_text: int = 0
    records: RecordSpec | None = None  # a batch's repeated tail; never together with a text

    @property
    def max_size(self) -> int:
        """Largest payload: the fixed part plus the longest text or every record."""
        tail = self.records.max_count * self.records.size if self.records else self.max_text
        return self.fixed_size + tail

    @property
    def struct_format(self) -> str:
        """struct format of the fixed part of the payload."""
        return "<" + "".join(f.wire.code for f in self.fields if f.wire is not TEXT)

    @property
    def fixed_size(self) -> int:
        """Bytes of the fixed part of the payload."""
        return struct.calcsize(self.struct_format)

    @property
    def has_text(self) -> bool:
        """Whether the payload ends in a variable-length text."""
        return bool(self.fields) and self.fields[-1].wire is TEXT


class Schema:
    """The registry of message specs, by id, by name and by class."""

    def __init__(self) -> None:
        self.by_id: dict[int, MessageSpec] = {}
        self.by_name: dict[str, MessageSpec] = {}
        self.by_cls: dict[type[Any], MessageSpec] = {}

    def add(self, spec: MessageSpec) -> None:
        """Register a spec; ids and names must be unique."""
        if spec.id in self.by_id:
            raise ValueError(f"message id 0x{spec.id:02X} used by {self.by_id[spec.id].name}")
        if spec.name in self.by_name:
            raise ValueError(f"message name {spec.name} declared twice")
        self.by_id[spec.id] = spec
        self.by_name[spec.name] = spec
        self.by_cls[spec.cls] = spec

    def specs(self) -> list[MessageSpec]:
        """All specs ordered by id."""
        return [self.by_id[k] for k in sorted(self.by_id)]

    def canonical_text(self) -> str:
        """The text hashed for the handshake: everything that affects the wire (PROTOCOL §7).

        Line 1 `v<version>`; then one line per message in id order,
        `<id>:<NAME>:<acked 0|1>:<reply|None>:<field>,<field>...` with each field written
        `<name>:<wire type>:<lo>..<hi>[:<Enum>]`, a batch's records appended as
        `;<field>:<RECORD>*0..<max>:<field>,...`; then one line per enum a field names, in
        name order, `<Enum>=<MEMBER>:<value>,...` in value order; lines joined by "\n".
        """
        lines = [f"v{PROTOCOL_VERSION}"]
        enums: dict[str, type[enum.IntEnum] | type[enum.IntFlag]] = {}
        for spec in self.specs():
            cols = ",".join(_canonical_field(f) for f in spec.fields)
            rec = spec.records
            if rec is not None:
                inner = ",".join(_canonical_field(f) for f in rec.fields)
                cols += f";{rec.field_name}:{rec.name}*0..{rec.max_count}:{inner}"
            lines.append(f"{spec.id}:{spec.name}:{int(spec.acked)}:{spec.reply}:{cols}")
            every = spec.fields + (rec.fields if rec is not None else ())
            enums.update({f.info.enum.__name__: f.info.enum for f in every if f.info.enum})
        for name in sorted(enums):
            values = {k: int(v.value) for k, v in enums[name].__members__.items()}
            members = sorted(values.items(), key=lambda kv: (kv[1], kv[0]))
            lines.append(f"{name}=" + ",".join(f"{k}:{v}" for k, v in members))
        return "\n".join(lines)

    def hash(self) -> int:
        """CRC-32 of the canonical text: equal hashes mean equal wire layouts."""
        return zlib.crc32(self.canonical_text().encode()) & 0xFFFF_FFFF


def _canonical_field(f: FieldSpec) -> str:
    """One field in the canonical text: name, wire type, bounds and enum."""
    if f.wire is TEXT:
        return f"{f.name}:{f.wire.name}"
    lo, hi = f.info.bounds()
    tail = f":{f.info.enum.__name__}" if f.info.enum is not None else ""
    return f"{f.name}:{f.wire.name}:{lo}..{hi}{tail}"


SCHEMA = Schema()

MessageT = typing.TypeVar("MessageT")


@typing.dataclass_transform()
def message(
    msg_id: int,
    direction: Direction,
    *,
    acked: bool = False,
    reply: str | None = None,
    max_text: int = 0,
) -> Callable[[type[MessageT]], type[MessageT]]:
    """Class decorator: make a slotted dataclass and register its spec in `SCHEMA`."""

    def wrap(cls: type[MessageT]) -> type[MessageT]:
        dc = dataclasses.dataclass(slots=True)(cls)
        hints = typing.get_type_hints(dc, include_extras=True)
        fields: list[FieldSpec] = []
        tail: RecordSpec | None = None
        for f in dataclasses.fields(dc):  # type: ignore[arg-type]
            meta = getattr(hints[f.name], "__metadata__", ())
            runs = [m for m in meta if isinstance(m, RecordsInfo)]
            if runs and tail is None:
                tail = _record_spec(f.name, runs[0])
                continue
            infos = [m for m in meta if isinstance(m, FieldInfo)]
            if len(infos) != 1 or tail is not None:
                raise TypeError(
                    f"{cls.__name__}.{f.name} needs exactly one field(...) annotation, "
                    "and records(...) only as the last field"
                )
            fields.append(FieldSpec(f.name, infos[0]))
        doc = (dc.__doc__ or "").strip()
        spec = MessageSpec(
            msg_id,
            _snake(dc.__name__),
            direction,
            acked,
            reply,
            doc,
            tuple(fields),
            dc,
            max_text,
            tail,
        )
        if spec.max_size > MAX_PAYLOAD or (tail is not None and spec.has_text):
            raise TypeError(f"{spec.name}: payload of {spec.max_size} bytes > {MAX_PAYLOAD}")
        SCHEMA.add(spec)
        return dc

    return wrap


@typing.dataclass_transform(frozen_default=True)
def record(cls: type[MessageT]) -> type[MessageT]:
    """Class decorator for a batch's record: a slotted, frozen dataclass of wire fields."""
    dc = dataclasses.dataclass(slots=True, frozen=True)(cls)
    hints = typing.get_type_hints(dc, include_extras=True)
    fields = []
    for f in dataclasses.fields(dc):  # type: ignore[arg-type]
        infos = [m for m in getattr(hints[f.name], "__metadata__", ()) if isinstance(m, FieldInfo)]
        if len(infos) != 1 or infos[0].wire is TEXT:
            raise TypeError(f"{cls.__name__}.{f.name} needs exactly one integer field(...)")
        fields.append(FieldSpec(f.name, infos[0]))
    _RECORD_FIELDS[dc] = tuple(fields)
    return dc


_RECORD_FIELDS: dict[type[Any], tuple[FieldSpec, ...]] = {}


def _record_spec(field_name: str, info: RecordsInfo) -> RecordSpec:
    """The spec of a message's records from their declared class."""
    fields = _RECORD_FIELDS.get(info.cls)
    if fields is None or info.max_count < 1:
        raise TypeError(f"{info.cls.__name__} is not declared with @record (or max_count < 1)")
    return RecordSpec(
        field_name, _snake(info.cls.__name__), info.cls, fields, info.max_count, info.doc
    )


def _snake(camel: str) -> str:
    """MoveTo → MOVE_TO: the name used in the spec and the C header."""
    out = "".join("_" + c if c.isupper() and i else c for i, c in enumerate(camel))
    return out.upper()
