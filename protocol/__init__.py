"""The host↔controller link protocol: schema, codec and framing (stdlib only, no I/O)."""

from protocol.codec import PayloadError, decode_payload, encode_payload, spec_of
from protocol.enums import Fault, Inputs, LogLevel, NakCode, State, Stream
from protocol.framing import DropCounters, FrameDecoder, Packet, encode_frame
from protocol.params import PARAMS, PARAMS_BY_ID, ParamId, ParamSpec
from protocol.schema import (
    MAX_PAYLOAD,
    MAX_WIRE_FRAME,
    PROTOCOL_VERSION,
    SCHEMA,
    Direction,
    Flag,
    MessageSpec,
)

SCHEMA_HASH = SCHEMA.hash()

__all__ = [
    "MAX_PAYLOAD",
    "MAX_WIRE_FRAME",
    "PARAMS",
    "PARAMS_BY_ID",
    "PROTOCOL_VERSION",
    "SCHEMA",
    "SCHEMA_HASH",
    "Direction",
    "DropCounters",
    "Fault",
    "Flag",
    "FrameDecoder",
    "Inputs",
    "LogLevel",
    "MessageSpec",
    "NakCode",
    "Packet",
    "ParamId",
    "ParamSpec",
    "PayloadError",
    "State",
    "Stream",
    "decode_payload",
    "encode_frame",
    "encode_payload",
    "spec_of",
]
