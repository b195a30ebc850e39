"""XBee API frames: Digi's documented examples byte for byte, escaping, checksums, bad input."""

from __future__ import annotations

import random

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.xbee_frames import (
    ApiFrameDecoder,
    ReceivePacket,
    TransmitRequest,
    TransmitStatus,
    checksum,
    encode_api_frame,
    escape,
    status_name,
)

# Digi's XBee/XBee-PRO documentation, "Transmit Request frame" example: send "TxData0A" to
# 0013A200400A0127, frame id 1, 16-bit address FFFE, radius 0, options 0.
DIGI_TX = bytes.fromhex(
    "7E 00 16 10 01 00 13 A2 00 40 0A 01 27 FF FE 00 00 54 78 44 61 74 61 30 41 13"
)
# The same in API mode 2: the 0x13 of the address and the checksum 0x13 are escaped.
DIGI_TX_ESCAPED = bytes.fromhex(
    "7E 00 16 10 01 00 7D 33 A2 00 40 0A 01 27 FF FE 00 00 54 78 44 61 74 61 30 41 7D 33"
)
# Digi's "Receive Packet frame" example: "RxData" from 0013A20040522BAA, 16-bit 7D84, acked.
DIGI_RX = bytes.fromhex("7E 00 12 90 00 13 A2 00 40 52 2B AA 7D 84 01 52 78 44 61 74 61 0D")
# Digi's escaping example: frame data 23 11 is sent as 7E 00 02 23 7D 31 CB.
DIGI_ESCAPE_EXAMPLE = bytes.fromhex("7E 00 02 23 7D 31 CB")
TX_ADDR = 0x0013A200400A0127
RX_ADDR = 0x0013A20040522BAA


def test_transmit_request_matches_digi_example_in_both_modes() -> None:
    request = TransmitRequest(1, TX_ADDR, b"TxData0A")
    assert encode_api_frame(request.frame_data(), escaped=False) == DIGI_TX
    assert encode_api_frame(request.frame_data(), escaped=True) == DIGI_TX_ESCAPED


def test_receive_packet_matches_digi_example() -> None:
    frame_data = ApiFrameDecoder(escaped=False).feed(DIGI_RX)[0]
    assert ReceivePacket.parse(frame_data) == ReceivePacket(RX_ADDR, b"RxData", 0x7D84, 0x01)
    assert encode_api_frame(frame_data, escaped=False) == DIGI_RX
    # In mode 2 the 0x7D of the 16-bit address must itself be escaped.
    assert bytes.fromhex("7D 5D 84") in encode_api_frame(frame_data, escaped=True)


def test_escaping_matches_digi_example() -> None:
    assert encode_api_frame(bytes((0x23, 0x11)), escaped=True) == DIGI_ESCAPE_EXAMPLE
    assert ApiFrameDecoder(escaped=True).feed(DIGI_ESCAPE_EXAMPLE) == [bytes((0x23, 0x11))]


def test_escape_covers_exactly_the_four_special_bytes() -> None:
    for byte in range(256):
        expected = (
            bytes((0x7D, byte ^ 0x20)) if byte in (0x7E, 0x7D, 0x11, 0x13) else bytes((byte,))
        )
        assert escape(bytes((byte,))) == expected


def test_checksum_rule() -> None:
    assert checksum(bytes.fromhex("23 11")) == 0xCB
    data = bytes(range(1, 40))
    assert (sum(data) + checksum(data)) & 0xFF == 0xFF


def test_parse_round_trips() -> None:
    rx = ReceivePacket(RX_ADDR, b"RxData", 0x7D84, 0x01)
    assert ReceivePacket.parse(rx.frame_data()) == rx
    status = TransmitStatus(0x47, 2, 0x01, 0x02, 0x1234)
    assert TransmitStatus.parse(status.frame_data()) == status
    with pytest.raises(ValueError, match="header needs"):
        ReceivePacket.parse(bytes((0x90, 1, 2)))


def test_status_names() -> None:
    assert status_name(0x00) == "success"
    assert status_name(0x01) == "mac_ack_failure"
    assert status_name(0x74) == "payload_too_large"
    assert status_name(0xEE) == "status_0xee"


@pytest.mark.parametrize("escaped", [False, True])
def test_decoder_counts_bad_checksum_and_keeps_going(escaped: bool) -> None:
    good = encode_api_frame(TransmitRequest(5, TX_ADDR, b"abc").frame_data(), escaped)
    bad = bytearray(good)
    bad[-1] ^= 0x01  # checksum byte; never one that needs escaping here
    decoder = ApiFrameDecoder(escaped=escaped)
    assert decoder.feed(bytes(bad) + good) == [TransmitRequest(5, TX_ADDR, b"abc").frame_data()]
    assert decoder.stats.bad_checksum == 1
    assert decoder.stats.frames_ok == 1


def test_mode2_resyncs_on_a_bare_start_delimiter() -> None:
    good = encode_api_frame(ReceivePacket(RX_ADDR, b"hello").frame_data(), escaped=True)
    decoder = ApiFrameDecoder(escaped=True)
    out = decoder.feed(good[:9] + good)
    assert out == [ReceivePacket(RX_ADDR, b"hello").frame_data()]
    assert decoder.stats.truncated == 1


def test_decoder_counts_junk_and_bad_length() -> None:
    decoder = ApiFrameDecoder(escaped=False)
    assert decoder.feed(b"\x01\x02" + bytes.fromhex("7E 00 00")) == []
    assert decoder.stats.junk_bytes == 2
    assert decoder.stats.bad_length == 1


@given(
    payload=st.binary(min_size=0, max_size=84),
    frame_id=st.integers(1, 255),
    escaped=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_any_frame_survives_any_chunking(
    payload: bytes, frame_id: int, escaped: bool, seed: int
) -> None:
    frames = [
        TransmitRequest(frame_id, TX_ADDR, payload).frame_data(),
        ReceivePacket(RX_ADDR, payload).frame_data(),
    ]
    stream = b"".join(encode_api_frame(f, escaped) for f in frames)
    rng = random.Random(seed)
    decoder = ApiFrameDecoder(escaped=escaped)
    out: list[bytes] = []
    pos = 0
    while pos < len(stream):
        step = rng.randint(1, 16)
        out += decoder.feed(stream[pos : pos + step])
        pos += step
    assert out == frames
    if escaped:
        assert all(b not in (0x11, 0x13) for b in stream)
        assert stream.count(0x7E) == 2


class TestAgainstDigiLibrary:
    """Our frames equal digi-xbee's `output()` bytes (a reference only; skipped if missing)."""

    @pytest.fixture(autouse=True)
    def _digi(self) -> None:
        pytest.importorskip("digi.xbee")

    @pytest.mark.parametrize("escaped", [False, True])
    def test_transmit_request(self, escaped: bool) -> None:
        from digi.xbee.models.address import XBee16BitAddress, XBee64BitAddress  # type: ignore[import-untyped,import-not-found,unused-ignore]
        from digi.xbee.packets.common import TransmitPacket  # type: ignore[import-untyped,import-not-found,unused-ignore]

        theirs = TransmitPacket(
            0x33,
            XBee64BitAddress.from_hex_string("0013A20040A1B2C3"),
            XBee16BitAddress.from_hex_string("FFFE"),
            0,
            0,
            rf_data=bytes(range(0x05, 0x19)),
        ).output(escaped=escaped)
        ours = TransmitRequest(0x33, 0x0013A20040A1B2C3, bytes(range(0x05, 0x19))).frame_data()
        assert encode_api_frame(ours, escaped) == bytes(theirs)

    @pytest.mark.parametrize("escaped", [False, True])
    def test_receive_packet(self, escaped: bool) -> None:
        from digi.xbee.models.address import XBee16BitAddress, XBee64BitAddress  # type: ignore[import-untyped,import-not-found,unused-ignore]
        from digi.xbee.packets.common import ReceivePacket as DigiReceive  # type: ignore[import-untyped,import-not-found,unused-ignore]

        theirs = DigiReceive(
            XBee64BitAddress.from_hex_string("0013A20040522BAA"),
            XBee16BitAddress.from_hex_string("7D84"),
            0x01,
            rf_data=b"RxData\x7e\x11",
        ).output(escaped=escaped)
        ours = ReceivePacket(RX_ADDR, b"RxData\x7e\x11", 0x7D84, 0x01).frame_data()
        assert encode_api_frame(ours, escaped) == bytes(theirs)

    def test_transmit_status(self) -> None:
        from digi.xbee.models.address import XBee16BitAddress  # type: ignore[import-untyped,import-not-found,unused-ignore]
        from digi.xbee.models.status import TransmitStatus as DigiStatus  # type: ignore[import-untyped,import-not-found,unused-ignore]
        from digi.xbee.packets.common import TransmitStatusPacket  # type: ignore[import-untyped,import-not-found,unused-ignore]

        theirs = TransmitStatusPacket(
            0x47, XBee16BitAddress.from_hex_string("1234"), 3, DigiStatus.get(0x01)
        ).output()
        ours = TransmitStatus(0x47, 3, 0x01, 0, 0x1234).frame_data()
        assert encode_api_frame(ours, escaped=False) == bytes(theirs)


def test_transport_counts_bad_unknown_short_and_foreign_frames() -> None:
    from host.transport.xbee import XBeeTransport

    got: list[bytes] = []
    transport = XBeeTransport("/dev/null", dest_addr64=RX_ADDR, api_mode=1)
    transport.set_receiver(got.append)
    good = ReceivePacket(RX_ADDR, b"\x02A\x00").frame_data()
    bad = bytearray(encode_api_frame(good, False))
    bad[-1] ^= 0xFF
    stream = (
        bytes(bad)
        + encode_api_frame(bytes((0x88, 0x01, 0x41, 0x50, 0x00)), False)  # AT response: not ours
        + encode_api_frame(bytes((0x8B, 0x01)), False)  # status too short
        + encode_api_frame(ReceivePacket(TX_ADDR, b"\x02B\x00").frame_data(), False)  # stranger
        + encode_api_frame(TransmitStatus(1, 2, 0x21).frame_data(), False)
        + encode_api_frame(good, False)
    )
    transport._on_uart_bytes(stream)
    extra = transport.stats.extra
    assert got == [b"\x02A\x00"]
    assert extra["xbee_bad_checksum"] == 1
    assert extra["xbee_unknown_type"] == 1
    assert extra["xbee_short_frames"] == 1
    assert extra["xbee_foreign_source"] == 1
    assert extra["xbee_network_ack_failure"] == 1
    assert extra["xbee_retries"] == 2
    assert extra["xbee_failed"] == 1
