"""Build PROTOCOL.md's generated sections: constants, message tables, enums, parameters, examples.

Each section is written between `<!-- BEGIN GENERATED: name -->` and `<!-- END GENERATED: name -->`
so the prose around it stays hand-written.
"""

from __future__ import annotations

import enum
import inspect
import re
from collections.abc import Callable
from typing import Any

from protocol import cobs
from protocol.gen_c import ENUMS
from protocol.params import PARAMS
from protocol.schema import (
    CRC_SIZE,
    HEADER_SIZE,
    MAX_PAYLOAD,
    MAX_RAW_FRAME,
    MAX_WIRE_FRAME,
    PROTOCOL_VERSION,
    SCHEMA,
    TEXT,
    Flag,
    MessageSpec,
)

EXAMPLE_MESSAGES = ("MOVE_TO", "ENCODER_SAMPLE", "ENCODER_BATCH")
_MEMBER_RE = re.compile(r"^\s+([A-Z_0-9]+)\s*=\s*[^#]+#\s*(.+)$")


def sections(schema_hash: int, vectors: list[dict[str, Any]]) -> dict[str, str]:
    """Section name → generated markdown."""
    builders: dict[str, Callable[[], str]] = {
        "constants": lambda: _constants(schema_hash),
        "message-summary": _summary,
        "messages": _messages,
        "enums": _enums,
        "params": _params,
        "examples": lambda: _examples(vectors),
    }
    return {name: build() for name, build in builders.items()}


def splice(text: str, name: str, body: str) -> str:
    """Replace the body between one section's markers; ValueError if the markers are missing."""
    begin, end = f"<!-- BEGIN GENERATED: {name} -->", f"<!-- END GENERATED: {name} -->"
    start, stop = text.find(begin), text.find(end)
    if start < 0 or stop < start:
        raise ValueError(f"PROTOCOL.md lacks the markers of section {name!r}")
    return text[: start + len(begin)] + "\n" + body.rstrip("\n") + "\n" + text[stop:]


def _table(head: list[str], rows: list[list[str]]) -> str:
    """A markdown table."""
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def _constants(schema_hash: int) -> str:
    """Protocol constants and flag bits."""
    rows = [
        ["PROTOCOL_VERSION", str(PROTOCOL_VERSION), "header byte 0 of every frame"],
        ["SCHEMA_HASH", f"0x{schema_hash:08X}", "CRC-32 of the schema's canonical text"],
        ["HEADER_SIZE", str(HEADER_SIZE), "version, flags, seq (2), msg_id"],
        ["CRC_SIZE", str(CRC_SIZE), "CRC-16/GENIBUS, big-endian"],
        ["MAX_WIRE_FRAME", str(MAX_WIRE_FRAME), "COBS bytes plus the 0x00 delimiter"],
        ["MAX_RAW_FRAME", str(MAX_RAW_FRAME), "header + payload + CRC before COBS"],
        ["MAX_PAYLOAD", str(MAX_PAYLOAD), "largest payload of any message"],
    ]
    rows += [[f"Flag.{f.name}", f"0x{int(f):02X}", _flag_doc(f)] for f in Flag if f.value]
    return _table(["name", "value", "meaning"], rows)


def _flag_doc(flag: Flag) -> str:
    """The comment beside a flag's declaration."""
    return _member_docs(Flag).get(flag.name or "", "")


def _summary() -> str:
    """One row per message."""
    rows = []
    for s in SCHEMA.specs():
        variable = s.has_text or s.records is not None
        size = f"{s.fixed_size}" + (f"..{s.max_size}" if variable else "")
        acked = "yes" if s.acked else "no"
        rows.append(
            [
                f"0x{s.id:02X}",
                f"[{s.name}](#{_anchor(s)})",
                s.direction.value,
                acked,
                s.reply or "–",
                size,
                s.doc,
            ]
        )
    return _table(
        ["id", "message", "direction", "acked", "reply", "payload bytes", "purpose"], rows
    )


def _anchor(spec: MessageSpec) -> str:
    """GitHub-style anchor of a message's heading."""
    return f"0x{spec.id:02x}-{spec.name.lower()}"


def _messages() -> str:
    """A heading and a field table per message."""
    out = []
    for s in SCHEMA.specs():
        reply = f", reply {s.reply}" if s.reply else ""
        acked = ", acked" if s.acked else ""
        out.append(f"#### 0x{s.id:02X} {s.name}\n")
        out.append(f"{s.direction.value}{acked}{reply}. {s.doc}\n")
        if not s.fields:
            out.append("No payload.\n")
            continue
        out.append(_field_table(s))
        if s.records is not None:
            out.append(_records_table(s))
    return "\n".join(out)


def _records_table(spec: MessageSpec) -> str:
    """The repeated tail of a batch: how many records, then one record's layout."""
    rec = spec.records
    assert rec is not None
    intro = (
        f"Then `{rec.field_name}`, {rec.doc}: 0..{rec.max_count} {rec.name} records of "
        f"{rec.size} bytes to the payload's end, their number (payload bytes − "
        f"{spec.fixed_size}) / {rec.size}; offsets within each record:\n"
    )
    rows, offset = [], 0
    for f in rec.fields:
        lo, hi = f.info.bounds()
        rng = f"{lo}..{hi}" + (f" ({f.info.enum.__name__})" if f.info.enum is not None else "")
        rows.append([str(offset), f.name, f.wire.name, f.info.unit, rng, f.info.doc])
        offset += f.wire.size
    return intro + "\n" + _table(["offset", "field", "type", "unit", "range", "meaning"], rows)


def _field_table(spec: MessageSpec) -> str:
    """Offset, name, type, unit, range and meaning of every field."""
    rows, offset = [], 0
    for f in spec.fields:
        if f.wire is TEXT:
            rows.append([str(offset), f.name, "utf-8", "", f"0..{spec.max_text} bytes", f.info.doc])
            continue
        lo, hi = f.info.bounds()
        rng = f"{lo}..{hi}"
        if f.info.enum is not None:
            rng += f" ({f.info.enum.__name__})"
        rows.append([str(offset), f.name, f.wire.name, f.info.unit, rng, f.info.doc])
        offset += f.wire.size
    return _table(["offset", "field", "type", "unit", "range", "meaning"], rows)


def _enums() -> str:
    """A table per enum, meanings taken from the comments in protocol/enums.py."""
    out = []
    for en in ENUMS:
        kind = "bit flags" if issubclass(en, enum.IntFlag) else "values"
        docs = _member_docs(en)
        out.append(f"#### {en.__name__} ({kind})\n")
        out.append(f"{(en.__doc__ or '').strip()}\n")
        rows = [
            [_value(en, int(m)), name, docs.get(name, "")] for name, m in en.__members__.items()
        ]
        out.append(_table(["value", "name", "meaning"], rows))
    return "\n".join(out)


def _value(en: type[enum.Enum], value: int) -> str:
    """Flags in hex, values in decimal."""
    return f"0x{value:04X}" if issubclass(en, enum.IntFlag) else str(value)


def _member_docs(en: type[enum.Enum]) -> dict[str, str]:
    """Member name → the comment on its declaration line."""
    lines = inspect.getsource(en).splitlines()
    return {m.group(1): m.group(2).strip() for m in map(_MEMBER_RE.match, lines) if m}


def _params() -> str:
    """The parameter table."""
    rows = [
        [str(int(p.id)), p.name, p.unit, str(p.default), str(p.lo), str(p.hi), p.doc]
        for p in PARAMS
    ]
    return _table(["id", "name", "unit", "default", "min", "max", "meaning"], rows)


def _examples(vectors: list[dict[str, Any]]) -> str:
    """Byte-by-byte walk through the typical vector of each example message."""
    out = []
    for name in EXAMPLE_MESSAGES:
        vec = next(v for v in vectors if v["message"] == name and v["case"] == "typical")
        out.append(_example(SCHEMA.by_name[name], vec))
    return "\n".join(out)


def _example(spec: MessageSpec, vec: dict[str, Any]) -> str:
    """One worked example: fields, header, payload field by field, CRC, raw, COBS, wire."""
    raw = bytes.fromhex(vec["raw_hex"])
    fields = ", ".join(f"{k}={v}" for k, v in vec["fields"].items() if not isinstance(v, list))
    if spec.records is not None:
        fields += f", {len(vec['fields'][spec.records.field_name])} {spec.records.name} records"
    rows = [
        ["0", "version", _hex(raw[0:1]), f"{raw[0]}"],
        ["1", "flags", _hex(raw[1:2]), f"0x{vec['flags']:02X}"],
        ["2", "seq (u16 LE)", _hex(raw[2:4]), str(vec["seq"])],
        ["4", "msg_id", _hex(raw[4:5]), f"0x{spec.id:02X} {spec.name}"],
    ]
    offset = HEADER_SIZE
    for f in spec.fields:
        size = f.wire.size
        rows.append(
            [
                str(offset),
                f"{f.name} ({f.wire.name}{' LE' if size > 1 else ''})",
                _hex(raw[offset : offset + size]),
                str(vec["fields"][f.name]),
            ]
        )
        offset += size
    rec = spec.records
    for i, item in enumerate(vec["fields"][rec.field_name] if rec is not None else ()):
        assert rec is not None
        for f in rec.fields:
            size = f.wire.size
            part = f"{rec.field_name}[{i}].{f.name} ({f.wire.name}{' LE' if size > 1 else ''})"
            rows.append([str(offset), part, _hex(raw[offset : offset + size]), str(item[f.name])])
            offset += size
    rows.append([str(offset), "crc16 (BE)", _hex(raw[offset:]), vec["crc"]])
    enc = cobs.encode(raw)
    return (
        f"#### {spec.name}: {fields}; seq {vec['seq']}, flags 0x{vec['flags']:02X}\n\n"
        + _table(["offset", "part", "bytes", "value"], rows)
        + f"\n- raw frame ({len(raw)} bytes): `{_hex(raw)}`\n"
        + f"- CRC-16/GENIBUS over bytes 0..{offset - 1} = {vec['crc']}, appended big-endian\n"
        + f"- COBS ({len(enc)} bytes): `{_hex(enc)}`\n"
        + f"- wire ({len(enc) + 1} bytes, delimiter added): `{_hex(enc)} 00`\n"
    )


def _hex(data: bytes) -> str:
    """Bytes as space-separated hex pairs."""
    return data.hex(" ")
