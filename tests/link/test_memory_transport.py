"""The in-memory transport: seeded impairments, ordering, and clean shutdown."""

from __future__ import annotations

import asyncio

import pytest

from host.transport.base import TransportError
from host.transport.memory import Impairment, memory_pair


async def test_pair_delivers_in_order() -> None:
    a, b = memory_pair()
    got: list[bytes] = []
    b.set_receiver(got.append)
    await a.open()
    await b.open()
    for i in range(50):
        a.send(bytes([i + 1, 0]))
    await asyncio.sleep(0)
    await a.close()
    await b.close()
    assert got == [bytes([i + 1, 0]) for i in range(50)]
    assert a.stats.frames_out == 50 and b.stats.chunks_in == 50  # noqa: PT018


async def test_loss_and_duplicates_are_seeded_and_counted() -> None:
    runs = []
    for _ in range(2):
        a, b = memory_pair(Impairment(loss=0.2, duplicate=0.1), seed=42)
        got: list[bytes] = []
        b.set_receiver(got.append)
        await a.open()
        await b.open()
        for i in range(500):
            a.send(i.to_bytes(2, "big"))
        await asyncio.sleep(0.01)
        st = a.tx.stats
        assert len(got) == st.delivered == 500 - st.lost + st.duplicated
        runs.append(got)
        await a.close()
        await b.close()
    assert runs[0] == runs[1]  # same seed, same fate for every frame
    assert 60 < 500 - len(set(runs[0])) < 140


async def test_jitter_reorders_unless_order_is_kept() -> None:
    for keep, expect_sorted in ((True, True), (False, False)):
        imp = Impairment(delay_s=0.001, jitter_s=0.01, keep_order=keep)
        a, b = memory_pair(imp, seed=3)
        got: list[int] = []

        def receive(data: bytes, got: list[int] = got) -> None:
            got.append(int.from_bytes(data, "big"))

        b.set_receiver(receive)
        await a.open()
        await b.open()
        for i in range(100):
            a.send(i.to_bytes(2, "big"))
        await asyncio.sleep(0.03)
        await a.close()
        await b.close()
        assert len(got) == 100
        assert (got == sorted(got)) is expect_sorted


async def test_close_cancels_frames_in_flight_and_unavailable_fails_open() -> None:
    a, b = memory_pair(Impairment(delay_s=10.0))
    await a.open()
    await b.open()
    a.send(b"x\x00")
    await a.close()  # the conftest fixture fails the test if a timer is left
    await b.close()
    assert a.tx.stats.dropped_closed == 1
    a.available = False
    with pytest.raises(TransportError, match="not available"):
        await a.open()


async def test_disconnect_reports_loss() -> None:
    a, _ = memory_pair()
    lost: list[Exception | None] = []
    a.set_receiver(lambda _d: None, lost.append)
    await a.open()
    a.disconnect()
    assert len(lost) == 1
    with pytest.raises(TransportError):
        a.send(b"\x01\x00")
    await a.close()
