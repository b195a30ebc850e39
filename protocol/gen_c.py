"""Generate `c/orbitar_protocol.h`: the C99 single header the STM32 firmware includes.

Everything message-specific comes from the schema; the framing code (CRC, COBS, the incremental
decoder) is a fixed template that mirrors `protocol.framing` check for check, so a C receiver
counts exactly the drops the Python one counts.
"""

from __future__ import annotations

import enum

from protocol.crc import CRC_INIT, CRC_POLY, FRAME_RESIDUE, FRAME_XOROUT
from protocol.enums import Capability, Fault, Inputs, LogLevel, NakCode, State, Stream
from protocol.params import PARAMS
from protocol.schema import (
    CRC_SIZE,
    HEADER_SIZE,
    MAX_PAYLOAD,
    MAX_RAW_FRAME,
    MAX_WIRE_FRAME,
    PROTOCOL_VERSION,
    QUIET_HOLD_US,
    SCHEMA,
    TEXT,
    FieldSpec,
    Flag,
    MessageSpec,
    WireType,
)

# Every enum of protocol/enums.py, in declaration order (the spec lists them the same way).
ENUMS: tuple[type[enum.IntEnum] | type[enum.IntFlag], ...] = (
    State,
    Fault,
    NakCode,
    Stream,
    Inputs,
    LogLevel,
    Capability,
)


def snake(name: str) -> str:
    """CamelCase → snake_case for C identifiers."""
    return "".join("_" + c.lower() if c.isupper() and i else c.lower() for i, c in enumerate(name))


def c_int(value: int, wire: WireType) -> str:
    """A C literal of `value` in the field's type, safe at the type's extremes."""
    signed = wire.lo < 0
    bits = wire.size * 8
    if signed and value == -(1 << (bits - 1)):
        return f"INT{bits}_MIN"
    macro = "INT32_C" if signed else "UINT32_C"
    return f"{macro}({value})"


def crc_table() -> list[int]:
    """The 256-entry table of the unreflected CRC-16 with polynomial CRC_POLY."""
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ CRC_POLY) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return table


def generate_header(schema_hash: int) -> str:
    """The whole header text."""
    parts = [
        _PROLOGUE.format(
            version=PROTOCOL_VERSION,
            schema_hash=schema_hash,
            header=HEADER_SIZE,
            crc=CRC_SIZE,
            wire=MAX_WIRE_FRAME,
            raw=MAX_RAW_FRAME,
            payload=MAX_PAYLOAD,
            crc_init=CRC_INIT,
            crc_xorout=FRAME_XOROUT,
            crc_residue=FRAME_RESIDUE,
            quiet_hold=QUIET_HOLD_US,
        ),
        _flags(),
        _enum_block(),
        _param_block(),
        _CODEC_HELPERS,
    ]
    parts += [_message_block(spec) for spec in SCHEMA.specs()]
    parts += [_payload_check(), _crc_block(), _FRAMING, "#endif /* ORBITAR_PROTOCOL_H */\n"]
    return "\n".join(parts)


def _flags() -> str:
    """Header flag bits."""
    lines = ["/* ---- header flags ---- */"]
    lines += [f"#define ORB_FLAG_{f.name} 0x{int(f):02X}u" for f in Flag if f.value]
    return "\n".join(lines) + "\n"


def _enum_block() -> str:
    """One C enum per protocol enum (flags as bit values)."""
    out = ["/* ---- enumerations (protocol/enums.py) ---- */"]
    for en in ENUMS:
        prefix = "ORB_" + snake(en.__name__).upper()
        members = ",\n".join(f"    {prefix}_{m.name} = {int(m)}" for m in en.__members__.values())
        out.append(f"typedef enum {{\n{members}\n}} orb_{snake(en.__name__)}_t;\n")
    return "\n".join(out)


def _param_block() -> str:
    """Parameter ids, units, defaults and ranges as macros."""
    out = ["/* ---- parameters (protocol/params.py): id, default, min, max ---- */"]
    for p in PARAMS:
        name = f"ORB_PARAM_{p.name}"
        out.append(f"/* {p.doc} ({p.unit or 'no unit'}) */")
        out.append(f"#define {name} {int(p.id)}u")
        out.append(f"#define {name}_DEFAULT INT32_C({p.default})")
        out.append(f"#define {name}_MIN INT32_C({p.lo})")
        out.append(f"#define {name}_MAX INT32_C({p.hi})")
    out.append(f"#define ORB_PARAM_COUNT {len(PARAMS)}u\n")
    return "\n".join(out)


def _message_block(spec: MessageSpec) -> str:
    """Id, size, struct, encode, decode and range check of one message."""
    base = f"orb_{spec.name.lower()}"
    upper = f"ORB_{spec.name}"
    lines = [
        f"/* ---- {spec.name} (0x{spec.id:02X}, {spec.direction.value}): {spec.doc} */",
        f"#define ORB_MSG_{spec.name} 0x{spec.id:02X}u",
        f"#define {upper}_SIZE {spec.fixed_size}u",
    ]
    if spec.has_text:
        lines.append(f"#define {upper}_TEXT_MAX {spec.max_text}u")
    if spec.records is not None:
        return "\n".join(lines) + "\n" + _batch_block(spec, base, upper)
    lines.append(_struct(spec, base, upper))
    lines.append(_encoder(spec, base, upper))
    lines.append(_decoder(spec, base, upper))
    lines.append(_range_check(base, spec))
    return "\n".join(lines)


def _struct(spec: MessageSpec, base: str, upper: str) -> str:
    """The payload struct, one member per field with its unit and meaning."""
    members = []
    for f in spec.fields:
        unit = f" [{f.info.unit}]" if f.info.unit else ""
        if f.wire is TEXT:
            members.append(f"    uint8_t {f.name}_len; /**< bytes used in {f.name} */")
            members.append(f"    uint8_t {f.name}[{upper}_TEXT_MAX]; /**< {f.info.doc} */")
        else:
            members.append(f"    {f.wire.c_type} {f.name}; /**<{unit} {f.info.doc} */")
    if not members:
        members.append("    uint8_t unused_; /**< C99 has no empty structs; not on the wire */")
    return "typedef struct {\n" + "\n".join(members) + f"\n}} {base}_t;\n"


def _encoder(spec: MessageSpec, base: str, upper: str) -> str:
    """Struct → payload bytes (little-endian); returns the length, 0 if the text is too long."""
    body, offset = [], 0
    for f in spec.fields:
        if f.wire is TEXT:
            body.append(f"    if (m->{f.name}_len > {upper}_TEXT_MAX) return 0u;")
            body.append(f"    memcpy(buf + {offset}, m->{f.name}, m->{f.name}_len);")
            body.append(f"    return {upper}_SIZE + (size_t)m->{f.name}_len;")
        else:
            body.append(f"    orb_put_{f.wire.name}(buf + {offset}, m->{f.name});")
            offset += f.wire.size
    if not spec.has_text:
        body.append(f"    return {upper}_SIZE;")
    if not spec.fields:
        body.insert(0, "    (void)m;\n    (void)buf;")
    return (
        f"static inline size_t {base}_encode(const {base}_t *m, uint8_t *buf)\n{{\n"
        + "\n".join(body)
        + "\n}\n"
    )


def _decoder(spec: MessageSpec, base: str, upper: str) -> str:
    """Payload bytes → struct; 0 on success, -1 on a bad length or invalid UTF-8 text."""
    body, offset = [], 0
    if spec.has_text:
        text = spec.fields[-1].name
        # With no fixed part, `len < 0u` would be always false and trip -Wtype-limits.
        low = f"len < {upper}_SIZE || " if spec.fixed_size else ""
        body.append(f"    if ({low}len > {upper}_SIZE + {upper}_TEXT_MAX) return -1;")
        body.append(f"    if (!orb_utf8_valid(buf + {upper}_SIZE, len - {upper}_SIZE)) return -1;")
    else:
        body.append(f"    if (len != {upper}_SIZE) return -1;")
    for f in spec.fields:
        if f.wire is TEXT:
            body.append(f"    m->{text}_len = (uint8_t)(len - {upper}_SIZE);")
            body.append(f"    memcpy(m->{text}, buf + {upper}_SIZE, m->{text}_len);")
        else:
            body.append(f"    m->{f.name} = orb_get_{f.wire.name}(buf + {offset});")
            offset += f.wire.size
    if not spec.fields:
        body.insert(0, "    (void)buf;\n    m->unused_ = 0u;")
    body.append("    return 0;")
    return (
        f"static inline int {base}_decode({base}_t *m, const uint8_t *buf, size_t len)\n{{\n"
        + "\n".join(body)
        + "\n}\n"
    )


def _range_check(base: str, spec: MessageSpec) -> str:
    """1 when every field lies in its declared range (the firmware NAKs OUT_OF_RANGE otherwise)."""
    terms = []
    for f in spec.fields:
        if f.wire is TEXT:
            terms.append(f"m->{f.name}_len <= ORB_{spec.name}_TEXT_MAX")
            continue
        lo, hi = f.info.bounds()
        # Only bounds narrower than the type: a test against the type's own limit would be
        # always true and trip -Wtype-limits.
        if lo != f.wire.lo:
            terms.append(f"m->{f.name} >= {c_int(lo, f.wire)}")
        if hi != f.wire.hi:
            terms.append(f"m->{f.name} <= {c_int(hi, f.wire)}")
    expr = " &&\n           ".join(terms) if terms else "1"
    unused = "" if terms else "    (void)m;\n"
    return (
        f"static inline int {base}_in_range(const {base}_t *m)\n{{\n"
        f"{unused}    return {expr};\n}}\n"
    )


def _batch_block(spec: MessageSpec, base: str, upper: str) -> str:
    """A batch: its record struct, then struct, encode, decode and range check of the message."""
    rec = spec.records
    assert rec is not None
    rbase = f"orb_{rec.name.lower()}"
    count, items = f"{rec.field_name}_count", rec.field_name
    rmax, rsize = f"{upper}_{rec.field_name.upper()}_MAX", f"ORB_{rec.name}_SIZE"
    head = [
        f"#define {rmax} {rec.max_count}u",
        f"#define {rsize} {rec.size}u",
        f"/* {rec.name}: {rec.cls.__doc__ or ''} */",
        "typedef struct {",
        *_members(rec.fields),
        f"}} {rbase}_t;\n",
        "typedef struct {",
        *_members(spec.fields),
        f"    uint8_t {count}; /**< records used in {items} */",
        f"    {rbase}_t {items}[{rmax}]; /**< {rec.doc} */",
        f"}} {base}_t;\n",
    ]
    put, get, offset = [], [], 0
    for f in spec.fields:
        put.append(f"    orb_put_{f.wire.name}(buf + {offset}, m->{f.name});")
        get.append(f"    m->{f.name} = orb_get_{f.wire.name}(buf + {offset});")
        offset += f.wire.size
    rput, rget, offset = [], [], 0
    for f in rec.fields:
        rput.append(f"        orb_put_{f.wire.name}(p + {offset}, r->{f.name});")
        rget.append(f"        r->{f.name} = orb_get_{f.wire.name}(p + {offset});")
        offset += f.wire.size
    encode = [
        f"static inline size_t {base}_encode(const {base}_t *m, uint8_t *buf)\n{{",
        "    size_t i;",
        f"    if (m->{count} > {rmax}) return 0u;",
        *put,
        f"    for (i = 0; i < m->{count}; i++) {{",
        f"        uint8_t *p = buf + {upper}_SIZE + i * {rsize};",
        f"        const {rbase}_t *r = &m->{items}[i];",
        *rput,
        "    }",
        f"    return {upper}_SIZE + (size_t)m->{count} * {rsize};\n}}\n",
    ]
    decode = [
        f"static inline int {base}_decode({base}_t *m, const uint8_t *buf, size_t len)\n{{",
        "    size_t i, n;",
        f"    if (len < {upper}_SIZE || (len - {upper}_SIZE) % {rsize} != 0u) return -1;",
        f"    n = (len - {upper}_SIZE) / {rsize};",
        f"    if (n > {rmax}) return -1;",
        *get,
        f"    m->{count} = (uint8_t)n;",
        "    for (i = 0; i < n; i++) {",
        f"        const uint8_t *p = buf + {upper}_SIZE + i * {rsize};",
        f"        {rbase}_t *r = &m->{items}[i];",
        *rget,
        "    }",
        "    return 0;\n}\n",
    ]
    rterms = _bound_terms("r->", rec.fields)
    check = [
        f"static inline int {base}_in_range(const {base}_t *m)\n{{",
        "    size_t i;",
        f"    if (m->{count} > {rmax}) return 0;",
    ]
    terms = _bound_terms("m->", spec.fields)
    if terms:
        check.append(f"    if (!({' && '.join(terms)})) return 0;")
    check.append(f"    for (i = 0; i < m->{count}; i++) {{")
    if rterms:
        check.append(f"        const {rbase}_t *r = &m->{items}[i];")
        check.append(f"        if (!({' && '.join(rterms)})) return 0;")
    check += ["    }", "    return 1;\n}\n"]
    return "\n".join(head + encode + decode + check)


def _members(fields: tuple[FieldSpec, ...]) -> list[str]:
    """Struct members of integer fields, each with its unit and meaning."""
    out = []
    for f in fields:
        unit = f" [{f.info.unit}]" if f.info.unit else ""
        out.append(f"    {f.wire.c_type} {f.name}; /**<{unit} {f.info.doc} */")
    return out


def _bound_terms(prefix: str, fields: tuple[FieldSpec, ...]) -> list[str]:
    """Range tests of the bounds narrower than each field's type (others are always true)."""
    terms = []
    for f in fields:
        lo, hi = f.info.bounds()
        if lo != f.wire.lo:
            terms.append(f"{prefix}{f.name} >= {c_int(lo, f.wire)}")
        if hi != f.wire.hi:
            terms.append(f"{prefix}{f.name} <= {c_int(hi, f.wire)}")
    return terms


def _payload_check() -> str:
    """Generic length/text check by id, used by the frame decoder to count bad payloads."""
    cases = []
    for spec in SCHEMA.specs():
        upper = f"ORB_{spec.name}"
        if spec.records is not None:
            rsize = f"ORB_{spec.records.name}_SIZE"
            rmax = f"{upper}_{spec.records.field_name.upper()}_MAX"
            cond = (
                f"len >= {upper}_SIZE && (len - {upper}_SIZE) % {rsize} == 0u &&\n"
                f"                (len - {upper}_SIZE) / {rsize} <= {rmax}"
            )
        elif spec.has_text:
            cond = (
                f"({f'len >= {upper}_SIZE && ' if spec.fixed_size else ''}"
                f"len <= {upper}_SIZE + {upper}_TEXT_MAX &&\n"
                f"                orb_utf8_valid(payload + {upper}_SIZE, len - {upper}_SIZE))"
            )
        else:
            cond = f"len == {upper}_SIZE"
        cases.append(
            f"    case ORB_MSG_{spec.name}:\n"
            f"        return ({cond}) ? ORB_PAYLOAD_OK : ORB_PAYLOAD_BAD;"
        )
    return (
        "/* ---- payload check by id: the frame decoder's unknown_id / bad_payload */\n"
        "#define ORB_PAYLOAD_OK 0\n#define ORB_PAYLOAD_UNKNOWN_ID (-1)\n"
        "#define ORB_PAYLOAD_BAD (-2)\n"
        "static inline int orb_payload_check(uint8_t msg_id, const uint8_t *payload, size_t len)\n"
        "{\n    switch (msg_id) {\n"
        + "\n".join(cases)
        + "\n    default:\n        return ORB_PAYLOAD_UNKNOWN_ID;\n    }\n}\n"
    )


def _crc_block() -> str:
    """Table-driven CRC-16/IBM-3740 and its bitwise reference."""
    table = crc_table()
    rows = [
        "    " + ", ".join(f"0x{v:04X}u" for v in table[i : i + 8]) + "," for i in range(0, 256, 8)
    ]
    return _CRC.format(table="\n".join(rows), poly=CRC_POLY)


_PROLOGUE = """\
/*
 * orbitar_protocol.h: the Orbitar host <-> controller link, C99, single header.
 *
 * GENERATED by `python -m protocol.generate` from protocol/messages.py, enums.py and
 * params.py. Do not edit: change the schema and regenerate. The spec is protocol/PROTOCOL.md.
 *
 * wire  = COBS(raw) 0x00
 * raw   = version u8 | flags u8 | seq u16 LE | msg_id u8 | payload | crc16 BE
 * Payload fields are little-endian and packed; encode/decode use byte shifts only, so the
 * code is independent of the target's endianness and alignment.
 *
 * Transmit side (PROTOCOL.md section 14, R-STREAM-1): keep two TX queues, replies (ACK, NAK,
 * IDENTIFY, PARAM_VALUE, CLOCK_SYNC_REPLY, the STATUS sent on a state change) and telemetry
 * (samples, batches, REF_MARK, HEARTBEAT). Frame the next one only when the UART/DMA or radio
 * module has room, replies first, and give the seq when framing, so a reply waits at most
 * behind the frame being written and the seqs leave in order. A full queue drops its oldest
 * telemetry and still spends that frame's seq, so the host counts the loss.
 */
#ifndef ORBITAR_PROTOCOL_H
#define ORBITAR_PROTOCOL_H

#include <stddef.h>
#include <stdint.h>
#include <string.h>

#define ORB_PROTOCOL_VERSION {version}u
#define ORB_SCHEMA_HASH UINT32_C(0x{schema_hash:08X})
#define ORB_HEADER_SIZE {header}u
#define ORB_CRC_SIZE {crc}u
#define ORB_MAX_WIRE_FRAME {wire}u /* encoded bytes plus the 0x00 delimiter */
#define ORB_MAX_RAW_FRAME {raw}u
#define ORB_MAX_PAYLOAD {payload}u
#define ORB_CRC_INIT 0x{crc_init:04X}u
/* Frame check CRC-16/GENIBUS: the register below, final XOR ORB_CRC_XOROUT; the register run
 * over a good frame, CRC included, ends at ORB_CRC_RESIDUE (appended zeros change it). */
#define ORB_CRC_XOROUT 0x{crc_xorout:04X}u
#define ORB_CRC_RESIDUE 0x{crc_residue:04X}u
/* QUIET_CLOCK_PROBES (section 8): a CLOCK_SYNC that finds no hold starts one; the controller
 * then writes replies only, no telemetry, until the next CLOCK_SYNC's reply has been written
 * (released on the tick after it) or ORB_QUIET_HOLD_US after the first probe arrived. */
#define ORB_QUIET_HOLD_US {quiet_hold}u
"""

_CODEC_HELPERS = """\
/* ---- little-endian field access by shifts ---- */
static inline void orb_put_u8(uint8_t *p, uint8_t v) { p[0] = v; }
static inline void orb_put_i8(uint8_t *p, int8_t v) { p[0] = (uint8_t)v; }
static inline void orb_put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}
static inline void orb_put_i16(uint8_t *p, int16_t v) { orb_put_u16(p, (uint16_t)v); }
static inline void orb_put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
    p[2] = (uint8_t)((v >> 16) & 0xFFu);
    p[3] = (uint8_t)(v >> 24);
}
static inline void orb_put_i32(uint8_t *p, int32_t v) { orb_put_u32(p, (uint32_t)v); }
static inline uint8_t orb_get_u8(const uint8_t *p) { return p[0]; }
static inline uint16_t orb_get_u16(const uint8_t *p)
{
    return (uint16_t)((uint16_t)p[0] | (uint16_t)((uint16_t)p[1] << 8));
}
static inline uint32_t orb_get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
           ((uint32_t)p[3] << 24);
}
/* Two's complement without implementation-defined unsigned -> signed conversion. */
static inline int8_t orb_get_i8(const uint8_t *p)
{
    return (p[0] & 0x80u) ? (int8_t)((int)p[0] - 256) : (int8_t)p[0];
}
static inline int16_t orb_get_i16(const uint8_t *p)
{
    uint16_t u = orb_get_u16(p);
    return (u & 0x8000u) ? (int16_t)((int32_t)u - 65536) : (int16_t)u;
}
static inline int32_t orb_get_i32(const uint8_t *p)
{
    uint32_t u = orb_get_u32(p);
    return (u & 0x80000000u) ? (int32_t)(u - 0x80000000u) + INT32_MIN : (int32_t)u;
}

/* Strict UTF-8 (no overlongs, surrogates or code points above U+10FFFF), as Python decodes. */
static inline int orb_utf8_valid(const uint8_t *s, size_t n)
{
    size_t i = 0;
    while (i < n) {
        uint8_t c = s[i];
        size_t k, j;
        uint32_t cp, min;
        if (c < 0x80u) {
            i++;
            continue;
        } else if ((c & 0xE0u) == 0xC0u) {
            k = 1u; cp = c & 0x1Fu; min = 0x80u;
        } else if ((c & 0xF0u) == 0xE0u) {
            k = 2u; cp = c & 0x0Fu; min = 0x800u;
        } else if ((c & 0xF8u) == 0xF0u) {
            k = 3u; cp = c & 0x07u; min = 0x10000u;
        } else {
            return 0;
        }
        if (n - i <= k) return 0;
        for (j = 1u; j <= k; j++) {
            if ((s[i + j] & 0xC0u) != 0x80u) return 0;
            cp = (cp << 6) | (uint32_t)(s[i + j] & 0x3Fu);
        }
        if (cp < min || cp > 0x10FFFFu || (cp >= 0xD800u && cp <= 0xDFFFu)) return 0;
        i += k + 1u;
    }
    return 1;
}
"""

_CRC = """\
/* ---- CRC-16 register (CRC-16/IBM-3740): poly 0x{poly:04X}, init 0xFFFF, no reflection;
 *      check value crc("123456789") = 0x29B1. Frames add the final XOR (CRC-16/GENIBUS). ---- */
static const uint16_t orb_crc16_table[256] = {{
{table}
}};
static inline uint16_t orb_crc16(const uint8_t *data, size_t len, uint16_t crc)
{{
    size_t i;
    for (i = 0; i < len; i++) {{
        crc = (uint16_t)((crc << 8) ^ orb_crc16_table[((crc >> 8) ^ data[i]) & 0xFFu]);
    }}
    return crc;
}}
/* Bit at a time: 30 bytes of flash instead of 512, for the smallest parts. */
static inline uint16_t orb_crc16_bitwise(const uint8_t *data, size_t len, uint16_t crc)
{{
    size_t i;
    int b;
    for (i = 0; i < len; i++) {{
        crc ^= (uint16_t)((uint16_t)data[i] << 8);
        for (b = 0; b < 8; b++) {{
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x{poly:04X}u) : (uint16_t)(crc << 1);
        }}
    }}
    return crc;
}}
"""

_FRAMING = """\
/* ---- COBS ---- */
/* Encode n bytes; returns the encoded length (no delimiter), 0 if cap is too small. */
static inline size_t orb_cobs_encode(const uint8_t *src, size_t n, uint8_t *dst, size_t cap)
{
    size_t i, code_pos = 0u, o = 1u;
    uint8_t code = 1u;
    if (cap == 0u) return 0u;
    for (i = 0; i < n; i++) {
        if (src[i] != 0u) {
            if (o >= cap) return 0u;
            dst[o++] = src[i];
            code++;
        }
        /* A zero ends the block; so do 254 data bytes (code 0xFF, no implied zero). */
        if (src[i] == 0u || code == 0xFFu) {
            if (o >= cap) return 0u;
            dst[code_pos] = code;
            code_pos = o++;
            code = 1u;
        }
    }
    dst[code_pos] = code;
    return o;
}

/* Decode one frame (no delimiter); returns the decoded length or -1 if malformed. */
static inline int orb_cobs_decode(const uint8_t *src, size_t n, uint8_t *dst, size_t cap)
{
    size_t i = 0u, j, o = 0u;
    if (n == 0u) return -1;
    while (i < n) {
        uint8_t code = src[i];
        size_t end = i + code;
        if (code == 0u || end > n) return -1;
        for (j = i + 1u; j < end; j++) {
            if (src[j] == 0u || o >= cap) return -1;
            dst[o++] = src[j];
        }
        if (code != 0xFFu && end < n) {
            if (o >= cap) return -1;
            dst[o++] = 0u;
        }
        i = end;
    }
    return (int)o;
}

/* ---- frames ---- */
/* Header, payload and CRC, COBS-encoded, 0x00 appended; returns the wire length, 0 on error. */
static inline size_t orb_frame_encode(uint8_t msg_id, uint16_t seq, uint8_t flags,
                                      const uint8_t *payload, size_t len, uint8_t *wire,
                                      size_t cap)
{
    uint8_t raw[ORB_MAX_RAW_FRAME];
    uint16_t crc;
    size_t n;
    if (len > ORB_MAX_PAYLOAD || cap < 2u) return 0u;
    raw[0] = ORB_PROTOCOL_VERSION;
    raw[1] = flags;
    orb_put_u16(raw + 2, seq);
    raw[4] = msg_id;
    if (len > 0u) memcpy(raw + ORB_HEADER_SIZE, payload, len);
    crc = (uint16_t)(orb_crc16(raw, ORB_HEADER_SIZE + len, ORB_CRC_INIT) ^ ORB_CRC_XOROUT);
    raw[ORB_HEADER_SIZE + len] = (uint8_t)(crc >> 8); /* big-endian: register ends at residue */
    raw[ORB_HEADER_SIZE + len + 1u] = (uint8_t)(crc & 0xFFu);
    n = orb_cobs_encode(raw, ORB_HEADER_SIZE + len + ORB_CRC_SIZE, wire, cap - 1u);
    if (n == 0u || n + 1u > ORB_MAX_WIRE_FRAME) return 0u;
    wire[n] = 0u;
    return n + 1u;
}

typedef struct {
    uint32_t bad_crc;
    uint32_t bad_cobs;
    uint32_t bad_length;
    uint32_t bad_version;
    uint32_t unknown_id;
    uint32_t bad_payload;
    uint32_t oversize;
} orb_drop_counters_t;

typedef struct {
    uint16_t seq;
    uint8_t flags;
    uint8_t msg_id;
    const uint8_t *payload; /* points into the decoder; valid until the next feed */
    size_t payload_len;
} orb_packet_t;

typedef struct {
    uint8_t enc[ORB_MAX_WIRE_FRAME - 1u]; /* encoded bytes of the frame in progress */
    uint8_t raw[ORB_MAX_RAW_FRAME];
    size_t len;
    int discarding; /* an oversize frame is being skipped up to its delimiter */
    uint32_t frames_ok;
    orb_drop_counters_t drops;
} orb_decoder_t;

static inline void orb_decoder_init(orb_decoder_t *d) { memset(d, 0, sizeof *d); }

/* One delimited frame: 1 and *pkt filled when good, else 0 with the reason counted. */
static inline int orb_decoder_frame(orb_decoder_t *d, orb_packet_t *pkt)
{
    int n = orb_cobs_decode(d->enc, d->len, d->raw, sizeof d->raw);
    size_t raw_len, plen;
    int check;
    if (n < 0) { d->drops.bad_cobs++; return 0; }
    raw_len = (size_t)n;
    if (raw_len < ORB_HEADER_SIZE + ORB_CRC_SIZE) { d->drops.bad_length++; return 0; }
    if (orb_crc16(d->raw, raw_len, ORB_CRC_INIT) != ORB_CRC_RESIDUE) {
        d->drops.bad_crc++;
        return 0;
    }
    /* A C controller answers HELLO of other versions as PROTOCOL.md section 7 says; this
     * decoder keeps to its own version. */
    if (d->raw[0] != ORB_PROTOCOL_VERSION) { d->drops.bad_version++; return 0; }
    plen = raw_len - ORB_HEADER_SIZE - ORB_CRC_SIZE;
    check = orb_payload_check(d->raw[4], d->raw + ORB_HEADER_SIZE, plen);
    if (check == ORB_PAYLOAD_UNKNOWN_ID) { d->drops.unknown_id++; return 0; }
    if (check != ORB_PAYLOAD_OK) { d->drops.bad_payload++; return 0; }
    pkt->flags = d->raw[1];
    pkt->seq = orb_get_u16(d->raw + 2);
    pkt->msg_id = d->raw[4];
    pkt->payload = d->raw + ORB_HEADER_SIZE;
    pkt->payload_len = plen;
    d->frames_ok++;
    return 1;
}

/* Feed one received byte (e.g. from the UART ISR's ring buffer); 1 when *pkt is a good frame. */
static inline int orb_decoder_feed(orb_decoder_t *d, uint8_t byte, orb_packet_t *pkt)
{
    if (byte != 0u) {
        if (d->discarding) return 0;
        if (d->len >= sizeof d->enc) {
            /* Longer than any legal frame: count once, skip to the next delimiter. */
            d->drops.oversize++;
            d->discarding = 1;
            d->len = 0u;
            return 0;
        }
        d->enc[d->len++] = byte;
        return 0;
    }
    if (d->discarding) {
        d->discarding = 0;
        return 0;
    }
    if (d->len == 0u) return 0; /* idle fill between frames */
    {
        int ok = orb_decoder_frame(d, pkt);
        d->len = 0u;
        return ok;
    }
}

static inline uint32_t orb_drops_total(const orb_drop_counters_t *c)
{
    return c->bad_crc + c->bad_cobs + c->bad_length + c->bad_version + c->unknown_id +
           c->bad_payload + c->oversize;
}
"""
