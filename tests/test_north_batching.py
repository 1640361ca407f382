"""The north side takes the poller's scans in batches that gather for ``[poll] batch_wait``.

With a thousand PLCs a consumer woken once per event-loop pass cost more CPU per sample than the
requests did (issue 16); the pipeline therefore asks the poller for gathered batches.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterable
from typing import Any

from plcstack.north.config import NorthConfig
from plcstack.north.pipeline import North
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.samples import Quality, Sample, Scan, flatten


class _Poller:
    """What North reads of a Poller, recording how it asks for batches."""

    def __init__(self, config: PollConfig) -> None:
        self.config = config
        self.waits: list[float] = []
        self.stats: dict[str, Any] = {}
        self.dropped = 0

    async def scans(self, wait: float = 0.0) -> AsyncIterator[list[Scan]]:
        self.waits.append(wait)
        yield [Scan("p", "default", 1.0, 2.0, (Sample("p", "a", 1, Quality.GOOD, 1.0, 2.0),))]


def _config(**kw: Any) -> PollConfig:
    plc = PlcConfig(name="p", url="e71+tcp://127.0.0.1:5000", tags=(TagConfig("a", "D0"),))
    return PollConfig((plc,), **kw)


async def test_pipeline_gathers_batches_for_batch_wait() -> None:
    for config, expected in ((_config(), 0.01), (_config(batch_wait=0), 0.0)):
        poller = _Poller(config)
        seen: list[list[Scan]] = []
        north = North(poller, NorthConfig())
        await north.run(emit=seen.append)
        assert poller.waits == [expected]
        assert [s.value for batch in seen for s in flatten(batch)] == [1]


async def test_opcua_server_gathers_batches_for_batch_wait() -> None:
    from plcstack.north.opcua import OpcUaServer
    from plcstack.poll.engine import Poller

    poller = Poller(_config(batch_wait=0.25))  # never started: only its batches are asked for
    recorder = _Poller(poller.config)
    poller.scans = recorder.scans  # type: ignore[method-assign]
    server = OpcUaServer(poller)
    sent: list[list[Sample]] = []
    observed: list[list[Scan]] = []

    async def send(batch: Iterable[Sample]) -> None:
        sent.append(list(batch))

    server.send = send  # type: ignore[method-assign,assignment]
    try:
        async with asyncio.timeout(5):  # a consumer iterating the unstarted poller would wait
            await server.run(observe=observed.append)
    finally:
        await poller.aclose()
    assert recorder.waits == [0.25]
    assert [s.value for batch in sent for s in batch] == [1]
    assert [flatten(batch) for batch in observed] == sent
