"""cancel_until_done: a task that drops a cancel (as Python 3.11's wait_for can) still ends."""

from __future__ import annotations

import asyncio

from plcstack.resource import cancel_until_done


async def test_a_task_that_drops_the_first_cancel_is_cancelled_until_it_ends() -> None:
    cancels = 0

    async def stubborn() -> None:
        nonlocal cancels
        try:
            await asyncio.sleep(10)
        except asyncio.CancelledError:
            cancels += 1  # dropped, as a wait_for whose answer came with the cancel drops it
        await asyncio.sleep(10)

    task = asyncio.create_task(stubborn())
    await asyncio.sleep(0)
    async with asyncio.timeout(5):
        await cancel_until_done([task])
    assert task.cancelled() and cancels == 1


async def test_ended_tasks_are_left_as_they_are() -> None:
    async def done() -> int:
        return 7

    task = asyncio.create_task(done())
    await task
    await cancel_until_done([task])
    assert task.result() == 7
