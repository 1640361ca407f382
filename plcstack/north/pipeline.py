"""From the poller to every sink: one consumer, report-by-exception once, then fan-out.

```python
async with Poller(config) as poller, North(poller, parse_north(config.north)) as north:
    await north.run(emit=lambda batch: ...)   # optional extra sink, e.g. lines on stdout
```

The consumer takes what the poller has, in batches that gather for ``[poll] batch_wait``
seconds after their first sample (10 ms by default: with a thousand PLCs, one wake-up per
event-loop pass cost more CPU than the requests themselves), lets the metrics see it (``up``
needs the unfiltered truth), filters it once through :class:`ReportByException` and hands
the same list to each sink. Sinks never block the consumer: the MQTT sink queues (memory,
then disk), stdout is written by the caller's ``emit``.
Writes come back the other way only through the poller's ``write_tag``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Any, Self

from plcstack.north.config import NorthConfig
from plcstack.north.metrics import MetricsServer, PlcstackCollector
from plcstack.north.mqtt import MqttSink
from plcstack.north.rbe import ReportByException
from plcstack.poll.samples import Sample

__all__ = ["North"]


class North:
    """The north side of one poller: RBE, the MQTT sink and the metrics server as configured."""

    def __init__(self, poller: Any, config: NorthConfig, *, sinks: Sequence[Any] = ()) -> None:
        self.poller = poller
        self.config = config
        self.rbe = ReportByException(config.report)
        self.sinks: list[Any] = list(sinks)
        self.mqtt: MqttSink | None = None
        if config.mqtt is not None:
            group_of = {
                (plc.name, tag.name): tag.group for plc in poller.config.plcs for tag in plc.tags
            }
            layout: Any = None
            if config.mqtt.mode == "sparkplug":
                from plcstack.north.sparkplug import SparkplugLayout

                layout = SparkplugLayout.for_config(config.mqtt, poller.config)
            writable = {
                (plc.name, tag.name): bool(getattr(tag, "writable", True))
                for plc in poller.config.plcs
                for tag in plc.tags
            }
            # a scale-out Worker has no write_tag (yet): its sink refuses writes with the reason
            writer = poller if hasattr(poller, "write_tag") else None
            self.mqtt = MqttSink(
                config.mqtt,
                writer=writer,
                group_of=group_of,
                layout=layout,
                writable=writable,
                plcs=[plc.name for plc in poller.config.plcs],
            )
            self.sinks.append(self.mqtt)
        self.collector = PlcstackCollector(
            poller, [s for s in self.sinks if hasattr(s, "buffer")], self.rbe
        )
        self.metrics: MetricsServer | None = None
        if config.metrics is not None:
            self.metrics = MetricsServer(self.collector, config.metrics, self._health)
        self._running = False

    def _health(self) -> str | None:
        return None if self._running else "the poller is not running"

    async def __aenter__(self) -> Self:
        try:
            for sink in self.sinks:
                start = getattr(sink, "start", None)
                if start is not None:
                    await start()
            if self.metrics is not None:
                await self.metrics.start()
        except BaseException:
            # a sink that cannot start (credentials missing, TLS files unusable, port taken):
            # close what was opened (the queue's file), then report it
            await self.aclose()
            raise
        self._running = True
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        self._running = False
        for sink in self.sinks:
            close = getattr(sink, "aclose", None)
            if close is not None:
                with contextlib.suppress(Exception):
                    await close()
        if self.metrics is not None:
            await self.metrics.aclose()

    def deliver(
        self, batch: Sequence[Sample], emit: Callable[[list[Sample]], None] | None = None
    ) -> list[Sample]:
        """One batch through metrics, RBE and every sink; returns what was reported."""
        self.collector.observe(batch)
        reported = self.rbe.filter(batch) if self.config.reports_by_exception else list(batch)
        if reported:
            for sink in self.sinks:
                sink.submit(reported)
            if emit is not None:
                emit(reported)
        return reported

    async def run(self, emit: Callable[[list[Sample]], None] | None = None) -> None:
        """Consume the poller until cancelled."""
        poller = self.poller
        batches = getattr(poller, "batches", None)
        if batches is not None:  # the Poller: one list per wake-up, gathered for batch_wait
            async for batch in batches(wait=poller.config.batch_wait):
                self.deliver(batch, emit)
            return
        async for first in poller:  # anything else that iterates samples (a scale-out Worker)
            batch = [first]
            batch.extend(poller.drain())
            self.deliver(batch, emit)
