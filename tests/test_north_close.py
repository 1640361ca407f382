"""MqttSink.aclose ends even when its task survives a cancellation (Python 3.11's wait_for
can swallow one that arrives with its result; aiomqtt awaits acknowledgements through it)."""

from __future__ import annotations

import asyncio

from plcstack.north.buffer import StoreAndForward
from plcstack.north.mqtt import MqttSettings, MqttSink
from plcstack.north.supervise import Supervisor


async def test_aclose_ends_a_task_that_swallowed_the_first_cancel() -> None:
    sink = MqttSink(MqttSettings(port=1), buffer=StoreAndForward(None))
    swallowed = 0

    async def stubborn() -> None:
        nonlocal swallowed
        while True:
            try:
                await asyncio.sleep(3600)
            except asyncio.CancelledError:
                swallowed += 1
                if swallowed >= 2:
                    raise
                # as 3.11's wait_for does when the result came with the cancel: carry on

    sink._task = Supervisor().start("mqtt", stubborn)
    await asyncio.sleep(0)
    async with asyncio.timeout(5) as bound:  # before the fix: only this bound ended it
        await sink.aclose(drain=0)
    assert not bound.expired()
    assert sink._task.task is not None and sink._task.task.done() and swallowed == 2
