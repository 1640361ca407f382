"""The loop's shared deadline heap (transports/deadlines.py): order, never early, stale entries
ignored, nothing kept alive: a connection or a loop that is gone is collected."""

from __future__ import annotations

import asyncio
import gc
import weakref

from plcstack.transports.deadlines import Deadlines, deadlines_of, future_factory
from tests.aio_helpers import eventually


class _Conn:
    def __init__(self, log: list[tuple[str, float, float]], name: str) -> None:
        self.log, self.name = log, name

    def on_timer(self, when: float) -> None:
        self.log.append((self.name, when, asyncio.get_running_loop().time()))


async def test_callbacks_run_in_time_order_never_early() -> None:
    loop = asyncio.get_running_loop()
    deadlines = Deadlines(loop)
    log: list[tuple[str, float, float]] = []
    conns = [_Conn(log, f"c{i}") for i in range(5)]
    now = loop.time()
    for i, delay in enumerate([0.04, 0.01, 0.03, 0.0, 0.02]):
        deadlines.call_at(now + delay, conns[i].on_timer)
    await eventually(lambda: len(log) == 5, "all five deadlines came due")
    assert [name for name, _, _ in log] == ["c3", "c1", "c4", "c2", "c0"]
    resolution = deadlines._resolution
    assert all(fired >= when - resolution for _, when, fired in log)
    assert len(deadlines) == 0


async def test_a_later_entry_armed_first_does_not_delay_an_earlier_one() -> None:
    loop = asyncio.get_running_loop()
    deadlines = deadlines_of(loop)
    assert deadlines_of(loop) is deadlines
    log: list[tuple[str, float, float]] = []
    late, early = _Conn(log, "late"), _Conn(log, "early")
    deadlines.call_at(loop.time() + 5.0, late.on_timer)
    deadlines.call_at(loop.time() + 0.01, early.on_timer)
    await eventually(lambda: log, "the early deadline came due")
    assert [name for name, _, _ in log] == ["early"]


async def test_a_connection_that_is_gone_is_not_kept_or_called() -> None:
    loop = asyncio.get_running_loop()
    deadlines = Deadlines(loop)
    log: list[tuple[str, float, float]] = []
    conn = _Conn(log, "gone")
    alive = weakref.ref(conn)
    deadlines.call_at(loop.time() + 0.01, conn.on_timer)
    del conn
    gc.collect()
    assert alive() is None
    assert len(deadlines) == 1
    await eventually(lambda: len(deadlines) == 0, "the dead entry's time came and it was dropped")
    assert log == []


def test_a_closed_loop_is_collected_with_entries_pending() -> None:
    loop = asyncio.new_event_loop()
    log: list[tuple[str, float, float]] = []
    conn = _Conn(log, "pending")
    conn.loop = loop  # type: ignore[attr-defined]  # as a protocol holds its loop
    deadlines_of(loop).call_at(loop.time() + 60.0, conn.on_timer)
    gone = weakref.ref(loop)
    loop.close()
    del loop, conn  # only the pending entry could still reach them now
    gc.collect()
    assert gone() is None


async def test_future_factory_makes_the_loops_futures() -> None:
    loop = asyncio.get_running_loop()
    future = future_factory(loop)()
    assert isinstance(future, asyncio.Future) and future.get_loop() is loop
    assert type(future) is type(loop.create_future())


def test_future_factory_keeps_a_loops_own_create_future() -> None:
    class OwnFutures(asyncio.SelectorEventLoop):
        def create_future(self) -> asyncio.Future[object]:
            return super().create_future()

    loop = OwnFutures()
    try:
        assert future_factory(loop) == loop.create_future  # the loop's own method, kept
    finally:
        loop.close()
