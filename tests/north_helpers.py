"""Shared bits of the north-side tests: samples and an MQTT subscriber that survives restarts."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from typing import Any

import aiomqtt

from plcstack.poll.samples import Quality, Sample


def sample(
    plc: str, tag: str, value: Any, t: float = 1_800_000_000.0, error: str | None = None
) -> Sample:
    quality = Quality.GOOD if error is None else Quality.BAD
    return Sample(plc, tag, None if error else value, quality, t, t + 0.001, error)


class Subscriber:
    """A persistent-session subscriber (clean_session off, QoS 1) that reconnects by itself, so
    messages published while it is away (broker restart) are queued for it by the broker."""

    def __init__(self, host: str, port: int, topic: str, client_id: str = "test-sub") -> None:
        self.host, self.port, self.topic, self.client_id = host, port, topic, client_id
        self.messages: list[tuple[str, bytes]] = []
        #: the QoS each message arrived with (the lower of the publisher's and ours, 1)
        self.qos: list[int] = []
        self.subscribed = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    async def _run(self) -> None:
        while True:
            try:
                async with aiomqtt.Client(
                    self.host, self.port, identifier=self.client_id, clean_session=False
                ) as client:
                    await client.subscribe(self.topic, qos=1)
                    self.subscribed.set()
                    async for m in client.messages:
                        assert isinstance(m.payload, bytes)
                        self.qos.append(m.qos)
                        self.messages.append((str(m.topic), m.payload))
            except aiomqtt.MqttError:
                await asyncio.sleep(0.05)

    def json(self) -> list[Any]:
        return [json.loads(p) for _, p in self.messages]

    async def wait_for(self, predicate: Any, timeout: float = 10.0) -> None:
        async with asyncio.timeout(timeout):
            while not predicate(self):  # noqa: ASYNC110 - polls a test condition
                await asyncio.sleep(0.02)


@contextlib.asynccontextmanager
async def subscriber(
    host: str, port: int, topic: str, client_id: str = "test-sub"
) -> AsyncIterator[Subscriber]:
    sub = Subscriber(host, port, topic, client_id)
    task = asyncio.create_task(sub._run())
    try:
        async with asyncio.timeout(5):
            await sub.subscribed.wait()
        yield sub
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
