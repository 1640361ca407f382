"""Embedding the poller in your own program, with your own sink.

The poller reads every tag at its interval and hands out samples; what happens to them is up to
the consumer. This one keeps the latest value per tag and prints a line per batch.

    plcstack sim e71 &
    python examples/poller_sink.py              # polls e71+tcp://127.0.0.1:5000 for 3 s
    python examples/poller_sink.py URL 10       # another PLC, for 10 s
"""

from __future__ import annotations

import asyncio
import sys

from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller, Quality, Sample
from plcstack.values import FLOAT32, UINT16


class LatestValues:
    """A sink: the newest good value of every tag, and how many samples were bad."""

    def __init__(self) -> None:
        self.values: dict[str, object] = {}
        self.bad = 0

    def take(self, batch: list[Sample]) -> None:
        for sample in batch:
            if sample.quality is Quality.GOOD:
                self.values[f"{sample.plc}.{sample.tag}"] = sample.value
            else:
                self.bad += 1  # sample.error says why (timeout, refused address, ...)


async def main(url: str, seconds: float) -> None:
    config = PollConfig(
        plcs=(
            PlcConfig(
                name="press1",
                url=url,
                tags=(
                    TagConfig("strokes", "D100", UINT16),
                    TagConfig("force", "D102", FLOAT32),
                ),
            ),
        ),
        groups={"default": 0.5},  # seconds between scans
    )
    sink = LatestValues()
    loop = asyncio.get_running_loop()
    end = loop.time() + seconds
    async with Poller(config) as poller:  # connects, scans, and closes every PLC on the way out
        async for batch in poller.batches():
            sink.take(batch)
            print(f"{len(batch)} sample(s); latest: {sink.values}")
            if loop.time() >= end:
                break
    print(f"done: {sink.values}, {sink.bad} bad")


if __name__ == "__main__":
    url = sys.argv[1] if len(sys.argv) > 1 else "e71+tcp://127.0.0.1:5000"
    asyncio.run(main(url, float(sys.argv[2]) if len(sys.argv) > 2 else 3.0))
