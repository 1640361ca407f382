"""From the poller to every sink: one consumer, report-by-exception once, then fan-out.

```python
async with Poller(config.poll) as poller, North(poller, config.north) as north:
    await north.run(emit=lambda batch: ...)   # optional extra sink, e.g. lines on stdout
```

The consumer takes the poller's scans (:class:`~plcstack.poll.samples.Scan`: PLC, group,
times, samples), in batches that gather for ``[poll] batch_wait`` seconds after their first
scan (10 ms by default: with a thousand PLCs, one wake-up per event-loop pass cost more CPU
than the requests themselves), lets the metrics see them (``up`` needs the unfiltered truth),
filters each scan once through :class:`ReportByException` and hands the same list of scans to
each sink's ``submit`` (:class:`~plcstack.poll.samples.ScanSink`, the one protocol of every
sink). Sinks never block the consumer: the MQTT sink queues (memory,
then disk), stdout is written by the caller's ``emit``.
Writes come back the other way only through the poller's ``write_tag``.

Every sink is supervised (:mod:`plcstack.north.supervise`): a sample a sink cannot take costs
that sample only (ERROR log with PLC and tag, ``plcstack_sink_errors_total{sink}``), a sink
task that dies is restarted with backoff, and ``/healthz`` answers 503 naming it meanwhile.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Any, Self, cast

from plcstack.north.audit import Audit
from plcstack.north.config import NorthConfig
from plcstack.north.history import History
from plcstack.north.influx_sink import InfluxSink
from plcstack.north.layout import JsonLayout, Reachability, scan_groups
from plcstack.north.metrics import MetricsServer, PlcstackCollector
from plcstack.north.mqtt import MqttSink
from plcstack.north.rbe import ReportByException
from plcstack.north.supervise import Supervisor
from plcstack.north.trace import TraceSink
from plcstack.north.writes import WritePath
from plcstack.output import float32_tags
from plcstack.poll.samples import Scan, ScanSink

__all__ = ["North", "missing", "needs_of", "sink_name"]

log = logging.getLogger("plcstack.north")


def sink_name(sink: Any) -> str:
    """How logs, metrics and ``/healthz`` name a sink: its ``name``, else its class."""
    return str(getattr(sink, "name", None) or type(sink).__name__)


def missing(needs: Sequence[tuple[str, str, str]]) -> str | None:
    """The first of ``(what, module, extra)`` whose module cannot be imported, as one line
    naming the pip install that fixes it; None if all are there. Checked at start: a sink
    whose library is missing would otherwise fail only inside its task, after the run began."""
    for what, module, extra in needs:
        try:
            importlib.import_module(module)
        except ImportError:
            return (
                f"{what} needs the Python package {module.split('.')[0]}, which is not installed:"
                f" pip install 'plcstack[{extra}]'"
            )
    return None


def needs_of(config: NorthConfig) -> list[tuple[str, str, str]]:
    """``(what, module, extra)`` for each optional library the configured tables use."""
    needs = []
    if config.mqtt is not None:
        if config.mqtt.mode == "sparkplug":
            needs += [
                ("[mqtt] mode = sparkplug", "aiomqtt", "sparkplug"),
                ("[mqtt] mode = sparkplug", "google.protobuf", "sparkplug"),
            ]
        else:
            needs.append(("[mqtt]", "aiomqtt", "mqtt"))
    if config.metrics is not None:
        needs.append(("[metrics]", "prometheus_client", "metrics"))
    if config.web is not None:
        needs.append(("[web] or --web-port", "aiohttp", "web"))
    if config.influx.url is not None:
        needs.append(("[influx] url", "aiohttp", "influx"))
    return needs


class North:
    """The north side of one poller: RBE, the MQTT sink and the metrics server as configured."""

    def __init__(self, poller: Any, config: NorthConfig, *, sinks: Sequence[ScanSink] = ()) -> None:
        self.poller = poller
        self.config = config
        self.rbe = ReportByException(config.report)
        self.supervisor = Supervisor()
        self.audit: Audit | None = None
        if config.audit is not None:
            self.audit = Audit(config.audit, on_error=lambda: self.supervisor.count("audit"))
        # the one write path of every north side of this run (a scale-out Worker has no
        # write_tag yet: every write is refused with the reason)
        self.writes = WritePath(poller if hasattr(poller, "write_tag") else None, audit=self.audit)
        #: every sink of the run, each taking scans through its one ``submit`` (the others'
        #: methods - start, aclose, summary, probe, supervisor - are optional)
        self.sinks: list[ScanSink] = list(sinks)
        self.mqtt: MqttSink | None = None
        #: whether each PLC is reachable, by the rule the MQTT status uses: changes are logged
        self.reachability = Reachability(scan_groups(poller.config.plcs))
        self._offline: set[str] = set()
        if config.mqtt is not None:
            layout: Any = None
            if config.mqtt.mode == "sparkplug":
                from plcstack.north.sparkplug import SparkplugLayout

                layout = SparkplugLayout.for_config(config.mqtt, poller.config, poller)
            else:
                mqtt = config.mqtt
                layout = JsonLayout(
                    mqtt.prefix,
                    mqtt.client_id,
                    mqtt.qos,
                    float32_tags(poller.config.plcs),
                    scan_groups(poller.config.plcs),
                )
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
                layout=layout,
                writable=writable,
                plcs=[plc.name for plc in poller.config.plcs],
                writes=self.writes,
            )
            self.sinks.append(self.mqtt)
        #: the embedded history: a sink, and what the web console's trends read
        self.history: History | None = None
        if config.history is not None:
            self.history = History(config.history, supervisor=self.supervisor)
            self.sinks.append(self.history)
        #: the flight recorder: rings on the PLCs' connections, a sink that sees them go
        #: offline, and what the web console's capture download reads
        self.trace: TraceSink | None = None
        if config.trace is not None:
            self.trace = TraceSink(config.trace)
            self.trace.attach(poller)
            self.sinks.append(self.trace)
        self.influx: InfluxSink | None = None
        if config.influx.url is not None:  # the Influx writer: a sink with its own queue
            self.influx = InfluxSink(config.influx, poller.config.plcs, supervisor=self.supervisor)
            self.sinks.append(self.influx)
        self.web: Any = None
        if config.web is not None:  # the web console: a sink, and a server (the web extra)
            from plcstack.north.web.server import WebConsole

            self.web = WebConsole(
                poller,
                config.web,
                writes=self.writes,
                history=self.history,
                reachable=self.reachability.get,
                trace=self.trace,
            )
            self.sinks.append(self.web)
        for sink in self.sinks:
            if hasattr(sink, "supervisor"):
                cast(Any, sink).supervisor = self.supervisor  # its tasks run under the run's
        self.collector = PlcstackCollector(
            poller,
            [s for s in self.sinks if isinstance(s, MqttSink)],
            self.rbe,
            supervisor=self.supervisor,
        )
        self.metrics: MetricsServer | None = None
        if config.metrics is not None:
            self.metrics = MetricsServer(self.collector, config.metrics, self._health)
            if self.influx is not None:
                self.metrics.registry.register(self.influx)
        self._running = False

    def _health(self) -> str | None:
        if not self._running:
            return "the poller is not running"
        problems = [self.supervisor.health()]
        if self.influx is not None:
            problems.append(self.influx.health_problem())
        return "; ".join(p for p in problems if p is not None) or None

    async def __aenter__(self) -> Self:
        try:
            if self.audit is not None:
                self.audit.open()  # a file that cannot be written stops the start (exit 2)
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
                try:
                    await close()
                except Exception as exc:  # the others still close; this one is said
                    name = sink_name(sink)
                    log.error(
                        "%s: closing failed: %s: %s",
                        name,
                        type(exc).__name__,
                        exc,
                        extra={"face": name},
                    )
        await self.supervisor.aclose()
        if self.metrics is not None:
            await self.metrics.aclose()
        if self.audit is not None:
            self.audit.close()

    def summary(self) -> list[str]:
        """One line per sink for stderr at the end of a run: sent, not delivered (and where
        it is kept), dropped, failures."""
        lines = []
        for sink in self.sinks:
            describe = getattr(sink, "summary", None)
            text = describe() if describe is not None else sink_name(sink)
            errors = self.supervisor.errors.get(sink_name(sink), 0)
            lines.append(f"{text}, {errors} sink errors")
        errors = self.supervisor.errors.get("stdout", 0)
        if errors:
            lines.append(f"stdout: {errors} sink errors (samples it could not take)")
        return lines

    def deliver(
        self, batch: Sequence[Scan], emit: Callable[[list[Scan]], None] | None = None
    ) -> list[Scan]:
        """One batch of scans through metrics, RBE and every sink; returns what was reported."""
        self.collector.observe(batch)
        self.writes.observe(batch)  # the audit's "previous" (nothing without an audit)
        self._log_reachability(batch)
        reported = self.rbe.filter(batch) if self.config.reports_by_exception else list(batch)
        if reported:
            submit = self.supervisor.submit
            for sink in self.sinks:
                submit(sink_name(sink), sink.submit, reported, getattr(sink, "probe", None))
            if emit is not None:
                submit("stdout", emit, reported)
        return reported

    def _log_reachability(self, batch: Sequence[Scan]) -> None:
        """A PLC going offline (with the reason) and coming back: one WARNING per change, so
        an operator sees it at the default log level, not once per scan."""
        update = self.reachability.update
        for scan in batch:
            state = update(scan)
            if state is None:
                continue
            plc = scan.plc
            if not state:
                reason = next((s.error for s in scan.samples if s.error), None) or "no good value"
                log.warning("PLC %s is offline: %s", plc, reason, extra={"plc": plc})
                self._offline.add(plc)
            elif plc in self._offline:
                self._offline.discard(plc)
                log.warning("PLC %s is back online", plc, extra={"plc": plc})
            else:
                log.info("PLC %s is online", plc, extra={"plc": plc})

    async def run(self, emit: Callable[[list[Scan]], None] | None = None) -> None:
        """Consume the poller's (or a scale-out Worker's) scans until cancelled: one list per
        wake-up, gathered for ``batch_wait``."""
        poller = self.poller
        async for batch in poller.scans(wait=poller.config.batch_wait):
            self.deliver(batch, emit)
