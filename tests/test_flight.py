"""SingleFlight, the clients' single-flight lock: mutual exclusion, FIFO, cancellation.

The lock replaced ``asyncio.Lock`` on every request's path (issue 16), so it must keep that
contract: never two holders, waiters served in arrival order, a waiter cancelled before or
after it was handed the lock never holds it and never strands the ones behind it.
"""

from __future__ import annotations

import asyncio

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.clients.flight import SingleFlight


async def test_free_lock_is_taken_without_waiting() -> None:
    lock = SingleFlight()
    assert lock.try_acquire()
    assert lock.locked()
    assert not lock.try_acquire()
    lock.release()
    assert not lock.locked()
    async with lock:
        assert lock.locked()
    assert not lock.locked()


async def test_release_of_a_free_lock_is_an_error() -> None:
    with pytest.raises(RuntimeError):
        SingleFlight().release()


async def test_waiters_are_served_in_arrival_order_and_newcomers_queue() -> None:
    lock = SingleFlight()
    order: list[int] = []
    assert lock.try_acquire()

    async def worker(i: int) -> None:
        async with lock:
            order.append(i)
            await asyncio.sleep(0)

    tasks = [asyncio.create_task(worker(i)) for i in range(5)]
    await asyncio.sleep(0)  # all five queue
    lock.release()
    # the lock went to worker 0 at release: a newcomer cannot overtake it
    assert not lock.try_acquire()
    await asyncio.gather(*tasks)
    assert order == [0, 1, 2, 3, 4]
    assert not lock.locked()


async def test_a_waiter_cancelled_after_the_hand_over_passes_the_lock_on() -> None:
    lock = SingleFlight()
    assert lock.try_acquire()
    got: list[str] = []

    async def worker(name: str) -> None:
        async with lock:
            got.append(name)

    first = asyncio.create_task(worker("first"))
    second = asyncio.create_task(worker("second"))
    await asyncio.sleep(0)
    lock.release()  # handed to "first", which has not run yet
    first.cancel()
    await asyncio.wait_for(asyncio.gather(first, second, return_exceptions=True), 5)
    assert first.cancelled()
    assert got == ["second"]
    assert not lock.locked()


async def test_a_waiter_cancelled_while_queued_leaves_the_queue() -> None:
    lock = SingleFlight()
    assert lock.try_acquire()
    waiting = asyncio.create_task(lock.acquire())
    await asyncio.sleep(0)
    waiting.cancel()
    await asyncio.gather(waiting, return_exceptions=True)
    lock.release()
    assert not lock.locked()  # nobody left to hand it to
    assert lock.try_acquire()


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 3), st.booleans(), st.integers(0, 3)), min_size=1, max_size=12
    )
)
def test_random_schedules_keep_exclusion_order_and_progress(
    script: list[tuple[int, bool, int]],
) -> None:
    """Workers start after ``delay`` loop passes, hold the lock ``hold`` passes; some are
    cancelled at a random moment. Never two holders; the ones not cancelled all get the lock,
    in the order they started waiting; the lock ends free."""

    async def run() -> None:
        lock = SingleFlight()
        holders = 0
        queued: list[int] = []
        acquired: list[int] = []

        async def worker(i: int, delay: int, hold: int) -> None:
            nonlocal holders
            for _ in range(delay):
                await asyncio.sleep(0)
            queued.append(i)
            if not lock.try_acquire():
                await lock.acquire()
            try:
                holders += 1
                assert holders == 1
                acquired.append(i)
                for _ in range(hold):
                    await asyncio.sleep(0)
            finally:
                holders -= 1
                lock.release()

        tasks = [asyncio.create_task(worker(i, d, h)) for i, (d, _, h) in enumerate(script)]
        for i, (delay, cancel, hold) in enumerate(script):
            if cancel:
                for _ in range((delay + hold) % 4):
                    await asyncio.sleep(0)
                tasks[i].cancel()
        # bounded: a waiter stranded by a lost hand-over would otherwise hang the test
        gathered = asyncio.gather(*tasks, return_exceptions=True)
        for result in await asyncio.wait_for(gathered, 5):
            if isinstance(result, Exception):  # a failed assertion inside a worker
                raise result
        finished = [i for i, t in enumerate(tasks) if not t.cancelled()]
        assert set(finished) <= set(acquired)
        # served in the order they queued (a cancelled one may be missing, never reordered)
        assert acquired == [i for i in queued if i in acquired]
        assert not lock.locked()

    asyncio.run(run())


# -- turns: one task's several requests with nothing in between --------------------------------


async def test_a_turn_lets_its_own_requests_through_and_holds_off_the_others() -> None:
    lock = SingleFlight()
    order: list[str] = []
    turn_started = asyncio.Event()
    go_on = asyncio.Event()

    async def request(name: str) -> None:
        if not lock.try_acquire():
            await lock.acquire()
        order.append(name)
        lock.release()

    async def turn() -> None:
        await lock.hold()
        turn_started.set()
        await request("turn 1")  # its own: at once, and the lock stays held
        await go_on.wait()
        await request("turn 2")
        lock.unhold()

    holder = asyncio.create_task(turn())
    await turn_started.wait()
    other = asyncio.create_task(request("other"))
    await asyncio.sleep(0)
    assert lock.locked() and not lock.try_acquire()  # held between the turn's requests
    go_on.set()
    await asyncio.wait_for(asyncio.gather(holder, other), 5)
    assert order == ["turn 1", "turn 2", "other"]
    assert not lock.locked()


async def test_a_turn_waits_in_arrival_order_and_gives_up_at_its_deadline() -> None:
    lock = SingleFlight()
    assert lock.try_acquire()  # a request in flight
    loop = asyncio.get_running_loop()
    late = asyncio.create_task(lock.hold(loop.time() + 0.05))
    queued = asyncio.create_task(lock.acquire())
    with pytest.raises(TimeoutError):
        await asyncio.wait_for(late, 5)
    # the expired turn left the queue: the next release goes to the request behind it
    lock.release()
    assert await asyncio.wait_for(queued, 5)
    assert lock.locked()
    lock.release()
    assert not lock.locked()


async def test_a_turn_handed_the_lock_before_its_deadline_holds_it() -> None:
    lock = SingleFlight()
    assert lock.try_acquire()
    loop = asyncio.get_running_loop()
    turn = asyncio.create_task(lock.hold(loop.time() + 5.0))
    await asyncio.sleep(0)
    lock.release()
    await asyncio.wait_for(turn, 5)
    assert lock.locked()
    waiting = asyncio.create_task(lock.acquire())
    await asyncio.sleep(0)
    assert not waiting.done()
    lock.unhold()
    assert await asyncio.wait_for(waiting, 5)
    lock.release()
    with pytest.raises(RuntimeError):
        lock.unhold()


async def test_a_cancelled_turn_leaves_the_queue() -> None:
    lock = SingleFlight()
    assert lock.try_acquire()
    turn = asyncio.create_task(lock.hold())
    await asyncio.sleep(0)
    turn.cancel()
    await asyncio.gather(turn, return_exceptions=True)
    lock.release()
    assert not lock.locked()
