"""The north side takes the poller's scans in batches that gather for ``[poll] batch_wait``.

With a thousand PLCs a consumer woken once per event-loop pass cost more CPU per sample than the
requests did (issue 16); the pipeline therefore asks the poller for gathered batches.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Sequence
from typing import Any

from plcstack.north.config import NorthConfig
from plcstack.north.face import FaceBase
from plcstack.north.pipeline import North
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.poll.samples import Quality, Sample, Scan, flatten


class _Poller(Poller):
    """A Poller (never started) that records how the runtime asks for batches."""

    def __init__(self, config: PollConfig) -> None:
        super().__init__(config)
        self.waits: list[float] = []

    async def scans(self, wait: float = 0.0) -> AsyncIterator[list[Scan]]:
        self.waits.append(wait)
        yield [Scan("p", "default", 1.0, 2.0, (Sample("p", "a", 1, Quality.GOOD, 1.0, 2.0),))]


class _Recorder(FaceBase):
    name = "recorder"

    def __init__(self) -> None:
        self.seen: list[list[Scan]] = []

    def submit(self, scans: Sequence[Scan]) -> None:
        self.seen.append(list(scans))


def _config(**kw: Any) -> PollConfig:
    plc = PlcConfig(name="p", url="e71+tcp://127.0.0.1:5000", tags=(TagConfig("a", "D0"),))
    return PollConfig((plc,), **kw)


async def test_the_runtime_gathers_batches_for_batch_wait() -> None:
    """Every face (stdout, MQTT, OPC UA, Modbus, web) is fed by this one consumer."""
    for config, expected in ((_config(), 0.01), (_config(batch_wait=0), 0.0)):
        poller = _Poller(config)
        recorder = _Recorder()
        north = North(poller, NorthConfig(), faces=[recorder])
        try:
            await north.run()
        finally:
            await poller.aclose()
        assert poller.waits == [expected]
        assert [s.value for batch in recorder.seen for s in flatten(batch)] == [1]
