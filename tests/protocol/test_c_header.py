"""The generated C header, compiled with -Werror, decodes and encodes every vector like Python.

The test writes a C program that includes protocol/c/orbitar_protocol.h, feeds every vector's
frame byte by byte through the C decoder and prints the fields, encodes every vector from its
fields and prints the wire bytes, and runs an injected-damage stream through the C decoder and
prints its drop counters. Each printed line is compared with what Python computes.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

from protocol import FrameDecoder
from protocol.generate import HEADER_PATH
from protocol.schema import SCHEMA, TEXT, MessageSpec
from tests.protocol.helpers import build_injected_stream, load_vectors

CC = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O1"]
VECTORS = load_vectors()
COUNTERS = [
    "bad_crc",
    "bad_cobs",
    "bad_length",
    "bad_version",
    "unknown_id",
    "bad_payload",
    "oversize",
]

pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler (cc, gcc or clang) on PATH")


def _c_bytes(data: bytes) -> str:
    """A C initializer list of bytes (never empty: C99 forbids empty initializers)."""
    return ", ".join(f"0x{b:02X}" for b in data) or "0"


def _printer(spec: MessageSpec) -> str:
    """A `case` decoding one message's payload and printing name=value for every field."""
    base = f"orb_{spec.name.lower()}"
    prints = []
    for f in spec.fields:
        if f.wire is TEXT:
            prints.append(f'printf(" {f.name}="); print_hex(m.{f.name}, m.{f.name}_len);')
        elif f.wire.lo < 0:
            prints.append(f'printf(" {f.name}=%ld", (long)m.{f.name});')
        else:
            prints.append(f'printf(" {f.name}=%lu", (unsigned long)m.{f.name});')
    rec = spec.records
    if rec is not None:
        inner = "".join(
            f'printf(" %s", "{f.name}"); printf("=%ld", (long)m.{rec.field_name}[i].{f.name}); '
            for f in rec.fields
        )
        prints.append(
            f"{{ size_t i; for (i = 0; i < m.{rec.field_name}_count; i++) {{ {inner}}} }}"
        )
    return (
        f"    case ORB_MSG_{spec.name}: {{\n        {base}_t m;\n"
        f"        if ({base}_decode(&m, p->payload, p->payload_len) != 0) {{"
        f' printf(" DECODE_FAILED"); break; }}\n'
        + "".join(f"        {line}\n" for line in prints)
        + "        break;\n    }\n"
    )


def _c_value(f: Any, value: Any) -> str:
    """A field value as a C expression of its type."""
    if f.wire.lo < 0:
        return f"(int32_t)({value}LL)"
    return f"(uint32_t){value}UL"


def _encoder(vec: dict[str, Any]) -> str:
    """Code that fills the struct from the vector's fields, encodes and prints the wire hex."""
    spec = SCHEMA.by_name[vec["message"]]
    base = f"orb_{spec.name.lower()}"
    lines = [f"    {{\n        {base}_t m;\n        memset(&m, 0, sizeof m);"]
    for f in spec.fields:
        value = vec["fields"][f.name]
        if f.wire is TEXT:
            raw = value.encode("utf-8")
            lines.append(f"        {{ static const uint8_t t[] = {{{_c_bytes(raw)}}};")
            lines.append(f"          m.{f.name}_len = {len(raw)}u;")
            lines.append(f"          memcpy(m.{f.name}, t, {len(raw)}u); }}")
        else:
            lines.append(f"        m.{f.name} = ({f.wire.c_type}){_c_value(f, value)};")
    rec = spec.records
    if rec is not None:
        items = vec["fields"][rec.field_name]
        lines.append(f"        m.{rec.field_name}_count = {len(items)}u;")
        for i, item in enumerate(items):
            for f in rec.fields:
                value, member = _c_value(f, item[f.name]), f"m.{rec.field_name}[{i}].{f.name}"
                lines.append(f"        {member} = ({f.wire.c_type}){value};")
    lines.append(
        f"        n = {base}_encode(&m, payload);\n"
        f"        w = orb_frame_encode(ORB_MSG_{spec.name}, {vec['seq']}u, {vec['flags']}u,"
        " payload, n, wire, sizeof wire);\n"
        f'        printf("E "); print_hex(wire, w); printf(" %d\\n", {base}_in_range(&m));\n    }}'
    )
    return "\n".join(lines)


def _program(header: Path, stream: bytes) -> str:
    """The whole C test program."""
    frames = [bytes.fromhex(v["frame_hex"]) for v in VECTORS]
    arrays = "\n".join(
        f"static const uint8_t F{i}[] = {{{_c_bytes(f)}}};" for i, f in enumerate(frames)
    )
    table = ", ".join(f"{{F{i}, sizeof F{i}}}" for i in range(len(frames)))
    counters = " ".join(f"{c}=%lu" for c in COUNTERS)
    counter_args = ", ".join(f"(unsigned long)d.drops.{c}" for c in COUNTERS)
    return f"""#include "{header}"
#include <stdio.h>

static void print_hex(const uint8_t *p, size_t n)
{{
    size_t i;
    for (i = 0; i < n; i++) printf("%02x", p[i]);
}}

static void print_packet(const orb_packet_t *p)
{{
    printf("D %u %u %u", (unsigned)p->msg_id, (unsigned)p->seq, (unsigned)p->flags);
    switch (p->msg_id) {{
{"".join(_printer(s) for s in SCHEMA.specs())}    default: printf(" UNKNOWN"); break;
    }}
    printf("\\n");
}}

{arrays}
static const struct {{ const uint8_t *data; size_t len; }} FRAMES[] = {{{table}}};
static const uint8_t STREAM[] = {{{_c_bytes(stream)}}};

int main(void)
{{
    orb_decoder_t d;
    orb_packet_t pkt;
    uint8_t payload[ORB_MAX_PAYLOAD], wire[ORB_MAX_WIRE_FRAME];
    size_t i, j, n, w, good = 0;
    const uint8_t check[] = "123456789";
    printf("CRC %04x %04x\\n", (unsigned)orb_crc16(check, 9, ORB_CRC_INIT),
           (unsigned)orb_crc16_bitwise(check, 9, ORB_CRC_INIT));
    for (i = 0; i < sizeof FRAMES / sizeof FRAMES[0]; i++) {{
        orb_decoder_init(&d);
        for (j = 0; j < FRAMES[i].len; j++) {{
            if (orb_decoder_feed(&d, FRAMES[i].data[j], &pkt)) print_packet(&pkt);
        }}
    }}
{chr(10).join(_encoder(v) for v in VECTORS)}
    orb_decoder_init(&d);
    for (j = 0; j < sizeof STREAM; j++) good += (size_t)orb_decoder_feed(&d, STREAM[j], &pkt);
    printf("S good=%lu ok=%lu {counters}\\n", (unsigned long)good, (unsigned long)d.frames_ok,
           {counter_args});
    return 0;
}}
"""


def _expected_decode(vec: dict[str, Any]) -> str:
    """The line the C decoder must print for a vector."""
    spec = SCHEMA.by_name[vec["message"]]
    parts = [f"D {spec.id} {vec['seq']} {vec['flags']}"]
    for f in spec.fields:
        value = vec["fields"][f.name]
        shown = value.encode("utf-8").hex() if f.wire is TEXT else str(value)
        parts.append(f"{f.name}={shown}")
    if spec.records is not None:
        for item in vec["fields"][spec.records.field_name]:
            parts += [f"{f.name}={item[f.name]}" for f in spec.records.fields]
    return " ".join(parts)


@pytest.fixture(scope="module")
def c_output(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[str], bytes]:
    """Compile and run the program once; its output lines and the damage stream it was fed."""
    work = tmp_path_factory.mktemp("c_header")
    stream = bytes(build_injected_stream(11, rounds=200).data)
    src = work / "vectors.c"
    src.write_text(_program(HEADER_PATH, stream), encoding="utf-8")
    exe = work / "vectors"
    build = subprocess.run(
        [str(CC), *CFLAGS, str(src), "-o", str(exe)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert build.returncode == 0, build.stderr
    run = subprocess.run([str(exe)], capture_output=True, text=True, timeout=30, check=True)
    return run.stdout.splitlines(), stream


def test_c_crc_check_value(c_output: tuple[list[str], bytes]) -> None:
    assert c_output[0][0] == "CRC 29b1 29b1"


def test_c_decodes_every_vector_like_python(c_output: tuple[list[str], bytes]) -> None:
    decoded = [line for line in c_output[0] if line.startswith("D ")]
    assert decoded == [_expected_decode(v) for v in VECTORS]


def test_c_encodes_every_vector_to_the_same_bytes(c_output: tuple[list[str], bytes]) -> None:
    encoded = [line for line in c_output[0] if line.startswith("E ")]
    # Every vector's fields are in range, so the C range check must agree (last column 1).
    assert encoded == [f"E {v['frame_hex']} 1" for v in VECTORS]


def test_c_decoder_counts_damage_like_python(c_output: tuple[list[str], bytes]) -> None:
    lines, stream = c_output
    dec = FrameDecoder()
    good = len(dec.feed(stream))
    counters = " ".join(f"{c}={getattr(dec.drops, c)}" for c in COUNTERS)
    assert dec.drops.total() > 100
    assert [line for line in lines if line.startswith("S ")] == [
        f"S good={good} ok={dec.frames_ok} {counters}"
    ]
