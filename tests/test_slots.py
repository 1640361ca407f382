"""Slots, the poller's concurrency cap: at most N holders, FIFO, cancellation, no leak.

The cap replaced ``asyncio.Semaphore`` so that callback scans can take a slot synchronously
(``try_acquire``); it must keep the semaphore's contract, and ``try_acquire`` must never let a
callback scan overtake the task-path scans queued for a slot.
"""

from __future__ import annotations

import asyncio

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.clients.flight import ConnectTurns, Slots
from tests.aio_helpers import eventually


def _free(slots: Slots) -> int:
    """How many slots can be taken now without waiting (taken and given back again)."""
    taken = 0
    while slots.try_acquire():
        taken += 1
    for _ in range(taken):
        slots.release()
    return taken


async def test_free_slots_are_taken_without_waiting() -> None:
    slots = Slots(3)
    assert not slots.locked()
    assert slots.try_acquire() and slots.try_acquire()
    assert await slots.acquire()  # free: returns without suspending
    assert slots.locked()
    assert not slots.try_acquire()
    slots.release()
    assert not slots.locked()
    assert _free(slots) == 1
    slots.release()
    slots.release()
    assert _free(slots) == 3


async def test_release_with_every_slot_free_is_an_error() -> None:
    with pytest.raises(RuntimeError):
        Slots(2).release()
    slots = Slots(2)
    assert slots.try_acquire()
    slots.release()
    with pytest.raises(RuntimeError):
        slots.release()
    assert _free(slots) == 2  # the refused release changed nothing


def test_at_least_one_slot() -> None:
    with pytest.raises(ValueError):
        Slots(0)


async def test_try_acquire_is_refused_while_anyone_waits() -> None:
    slots = Slots(2)
    order: list[int] = []
    assert slots.try_acquire() and slots.try_acquire()

    async def worker(i: int) -> None:
        await slots.acquire()
        order.append(i)
        await asyncio.sleep(0)
        slots.release()

    tasks = [asyncio.create_task(worker(i)) for i in range(4)]
    await asyncio.sleep(0)  # all four queue
    slots.release()  # handed to worker 0, which has not run yet
    assert not slots.try_acquire()  # a newcomer cannot overtake the queue
    slots.release()  # handed to worker 1
    assert not slots.try_acquire()
    await asyncio.gather(*tasks)
    assert order == [0, 1, 2, 3]
    assert _free(slots) == 2


async def test_a_waiter_cancelled_after_the_hand_over_passes_the_slot_on() -> None:
    slots = Slots(1)
    assert slots.try_acquire()
    got: list[str] = []

    async def worker(name: str) -> None:
        await slots.acquire()
        got.append(name)
        slots.release()

    first = asyncio.create_task(worker("first"))
    second = asyncio.create_task(worker("second"))
    await asyncio.sleep(0)
    slots.release()  # handed to "first", which has not run yet
    first.cancel()
    await asyncio.wait_for(asyncio.gather(first, second, return_exceptions=True), 5)
    assert first.cancelled()
    assert got == ["second"]
    assert _free(slots) == 1


async def test_a_waiter_cancelled_while_queued_leaves_the_queue() -> None:
    slots = Slots(1)
    assert slots.try_acquire()
    waiting = asyncio.create_task(slots.acquire())
    await asyncio.sleep(0)
    waiting.cancel()
    await asyncio.gather(waiting, return_exceptions=True)
    assert "0 waiting" in repr(slots)
    slots.release()
    assert not slots.locked()  # nobody left to hand it to
    assert _free(slots) == 1


@settings(max_examples=80, deadline=None)
@given(
    st.integers(1, 3),
    st.lists(
        st.tuples(
            st.integers(0, 3),  # loop passes before asking for a slot
            st.none() | st.integers(0, 6),  # cancelled after this many passes, or never
            st.integers(0, 3),  # loop passes the slot is held
        ),
        min_size=1,
        max_size=12,
    ),
)
def test_random_schedules_keep_the_cap_order_and_progress(
    size: int, script: list[tuple[int, int | None, int]]
) -> None:
    """Workers ask for a slot after ``delay`` loop passes (``try_acquire``, else ``acquire``),
    hold it ``hold`` passes; some are cancelled at a random moment (before asking, while
    queued, just after a hand-over, while holding). Never more than ``size`` holders; a
    ``try_acquire`` never succeeds while a worker is queued; the queued ones are served in the
    order they queued; everyone not cancelled gets a slot; every slot is free at the end."""

    async def run() -> None:
        slots = Slots(size)
        holders = 0
        queued: list[int] = []  # workers that had to wait, in the order they queued
        served: list[int] = []  # those of them that got a slot, in the order they resumed
        acquired: set[int] = set()
        waiting: set[int] = set()  # queued, not yet resumed (handed a slot or not)

        async def worker(i: int, delay: int, hold: int) -> None:
            nonlocal holders
            for _ in range(delay):
                await asyncio.sleep(0)
            if slots.try_acquire():
                # nobody may be queued still (one handed a slot and not yet resumed is no
                # longer queued: its future is done)
                assert all(f.done() for f in slots._waiters), "overtook the queue"
            else:
                queued.append(i)
                waiting.add(i)
                try:
                    await slots.acquire()
                finally:
                    waiting.discard(i)
                served.append(i)
            try:
                holders += 1
                assert holders <= size
                acquired.add(i)
                for _ in range(hold):
                    await asyncio.sleep(0)
            finally:
                holders -= 1
                slots.release()

        tasks = [asyncio.create_task(worker(i, d, h)) for i, (d, _, h) in enumerate(script)]
        cancels = sorted((at, i) for i, (_, at, _) in enumerate(script) if at is not None)
        passes = 0
        for at, i in cancels:
            while passes < at:
                await asyncio.sleep(0)
                passes += 1
            tasks[i].cancel()
        # bounded: a waiter stranded by a lost hand-over would otherwise hang the test
        gathered = asyncio.gather(*tasks, return_exceptions=True)
        for result in await asyncio.wait_for(gathered, 5):
            if isinstance(result, Exception):  # a failed assertion inside a worker
                raise result
        finished = {i for i, t in enumerate(tasks) if not t.cancelled()}
        assert finished <= acquired  # progress
        # FIFO: served in the order they queued (a cancelled one may be missing, never reordered)
        assert served == [i for i in queued if i in served]
        assert holders == 0 and not waiting
        assert _free(slots) == size  # nothing leaked
        assert not slots._waiters

    asyncio.run(run())


# -- ConnectTurns: the connects of one poller's clients --------------------------------------------
async def test_connect_turns_let_at_once_connects_run_and_queue_the_rest() -> None:
    turns = ConnectTurns(2, hold=60.0)
    running: list[int] = []
    most = 0
    go = asyncio.Event()

    async def connect(i: int) -> None:
        nonlocal most
        async with turns.turn():
            running.append(i)
            most = max(most, len(running))
            await go.wait()
            running.remove(i)

    tasks = [asyncio.create_task(connect(i)) for i in range(5)]
    await eventually(lambda: len(running) == 2, "two connects got their turn")
    await asyncio.sleep(0.01)  # a third (there must be none) would get in now
    assert sorted(running) == [0, 1]  # the first two, in arrival order
    go.set()
    await asyncio.gather(*tasks)
    assert most == 2 and not running


async def test_a_connect_past_its_hold_gives_its_turn_back() -> None:
    """A connect that waits on a dead peer must not keep the others from connecting."""
    turns = ConnectTurns(1, hold=0.05)
    dead = asyncio.Event()
    entered = asyncio.Event()

    async def dead_connect() -> None:
        async with turns.turn():
            entered.set()
            await dead.wait()

    stuck = asyncio.create_task(dead_connect())
    await entered.wait()
    async with asyncio.timeout(5):  # the hold, not the dead connect, ends the first turn
        async with turns.turn():
            assert not stuck.done()
    dead.set()
    await stuck  # ends its turn late: the turn was given back once, not twice
    assert repr(turns) == "<ConnectTurns <Slots 1/1 free, 0 waiting>, hold 0.05 s>"


async def test_a_connect_that_fails_or_is_cancelled_gives_its_turn_back() -> None:
    turns = ConnectTurns(1, hold=60.0)
    with pytest.raises(OSError):
        async with turns.turn():
            raise OSError("refused")
    waiting = asyncio.Event()

    async def blocked() -> None:
        async with turns.turn():
            waiting.set()
            await asyncio.sleep(60)

    task = asyncio.create_task(blocked())
    await waiting.wait()
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    async with asyncio.timeout(1):
        async with turns.turn():
            pass


def test_connect_turns_need_a_positive_hold() -> None:
    with pytest.raises(ValueError, match="hold"):
        ConnectTurns(1, hold=0)
