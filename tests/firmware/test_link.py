"""The firmware's bounded RX framer and TX queue."""

from __future__ import annotations

import random

from firmware.config import TX_QUEUE_FRAMES, TX_REPLY_RESERVE_FRAMES
from firmware.link import LinkCounters, RxFramer, TxQueue
from protocol import Flag, FrameDecoder, encode_frame
from protocol.messages import Ack, EncoderSample, Hello, MoveTo


def frames() -> bytes:
    """Three good frames back to back."""
    return (
        encode_frame(Hello(1, 2), 1, Flag.ACK_REQUESTED)
        + encode_frame(MoveTo(5, 6, 7), 2, Flag.ACK_REQUESTED)
        + encode_frame(Hello(1, 3), 3)
    )


def test_rx_framer_whole_bytewise_and_random_chunks_agree() -> None:
    data = frames()
    whole = RxFramer(LinkCounters()).feed(data)
    assert [f[0] for f in whole] == [1, 2, 3]
    bytewise = RxFramer(LinkCounters())
    got = [f for i in range(len(data)) for f in bytewise.feed(data[i : i + 1])]
    assert got == whole
    rng = random.Random(3)
    chunked = RxFramer(LinkCounters())
    pos, got = 0, []
    while pos < len(data):
        n = rng.randint(1, 9)
        got += chunked.feed(data[pos : pos + n])
        pos += n
    assert got == whole


def test_rx_framer_discards_oversize_and_corrupt_frames_and_resyncs() -> None:
    counters = LinkCounters()
    framer = RxFramer(counters)
    bad = bytearray(encode_frame(Hello(1, 2), 9))
    bad[3] ^= 0x10
    out = framer.feed(b"\x07" * 200 + b"\x00" + bytes(bad) + frames())
    assert [f[0] for f in out] == [1, 2, 3]
    assert counters.oversize == 1
    assert counters.bad_crc + counters.bad_cobs == 1


def test_tx_queue_drops_oldest_telemetry_never_replies_and_spends_seq_on_drops() -> None:
    # R-STREAM-1: a full queue sheds its oldest telemetry; replies always get a slot.
    counters = LinkCounters()
    tx = TxQueue(counters)
    for t in range(TX_QUEUE_FRAMES):
        tx.send(EncoderSample(t, 0, 0, 0, 0))
    assert len(tx) == TX_QUEUE_FRAMES - TX_REPLY_RESERVE_FRAMES
    for i in range(TX_REPLY_RESERVE_FRAMES + 2):
        tx.send(Ack(i, 1), reply=True)
    assert len(tx) == TX_QUEUE_FRAMES
    assert counters.tx_dropped == TX_REPLY_RESERVE_FRAMES + 2
    packets = FrameDecoder().feed(tx.drain(1 << 20))
    seqs = [p.seq for p in packets]
    assert seqs == sorted(seqs)
    acks = [p.message for p in packets if isinstance(p.message, Ack)]
    assert [a.req_seq for a in acks] == list(range(TX_REPLY_RESERVE_FRAMES + 2)), "no reply lost"
    samples = [p.message.mcu_time_us for p in packets if isinstance(p.message, EncoderSample)]
    assert samples == list(range(TX_QUEUE_FRAMES - len(samples), TX_QUEUE_FRAMES)), "oldest went"
    assert len(set(seqs)) == TX_QUEUE_FRAMES < tx.seq, "gaps let the host count losses"


def test_tx_queue_sends_no_more_than_the_link_takes() -> None:
    tx = TxQueue(LinkCounters())
    for t in range(5):
        tx.send(EncoderSample(t, 0, 0, 0, 0))
    frame = len(tx.drain(30))
    assert frame == 26, "one 26-byte frame fits in 30 bytes, two do not"
    assert len(tx) == 4


def test_tx_queue_sends_replies_before_queued_telemetry_with_seqs_in_order() -> None:
    # A reply (ACK/NAK) never waits behind telemetry: at most behind the frame being written.
    tx = TxQueue(LinkCounters())
    for t in range(4):
        tx.send(EncoderSample(t, 0, 0, 0, 0))
    first = FrameDecoder().feed(tx.drain(30))  # one 26-byte sample goes, the next is framed
    tx.send(Ack(7, 1), reply=True)
    rest = FrameDecoder().feed(tx.drain(1 << 20))
    kinds = [type(p.message).__name__ for p in first + rest]
    assert kinds == ["EncoderSample"] * 2 + ["Ack"] + ["EncoderSample"] * 2, kinds
    assert [p.seq for p in first + rest] == list(range(5)), "seqs in wire order, no gap"
    assert len(tx) == 0
