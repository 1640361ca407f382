"""What ``serve opcua`` and ``serve modbus`` share: their run options and one run of a fed server.

Both poll the PLCs of a file and feed a server from the scans; both also serve ``/metrics`` and
``/healthz`` as ``plcstack poll`` does, send client writes through the run's one write path (so
each is an ``[audit]`` line with the tag's value before the write), run until Ctrl-C, SIGTERM or
``--duration``, and end with the poller's statistics. Written once, so the two servers cannot
drift apart in what their options mean or in what a write's audit line holds.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable
from contextlib import AbstractAsyncContextManager
from typing import Any, Protocol

from plcstack.cli import print_error
from plcstack.cli.poll import StopEvent, install_stop_signals, remove_stop_signals
from plcstack.north.config import NorthConfig
from plcstack.north.metrics import MetricsSettings
from plcstack.north.pipeline import North, missing
from plcstack.north.supervise import run_until
from plcstack.north.writes import WritePath
from plcstack.poll.engine import Poller, format_stats
from plcstack.poll.samples import Scan
from plcstack.systemd.notify import Notifier
from plcstack.systemd.service import ScanWatch, ServiceNotifier, notifying, stall_limit

__all__ = ["FedServer", "metrics_settings", "run_fed"]


class FedServer(AbstractAsyncContextManager[Any], Protocol):
    """A north-side server fed by a poller (the OPC UA and the Modbus server)."""

    writes: WritePath

    async def run(
        self,
        observe: Callable[[list[Any]], object] | None = None,
        stored: Callable[[list[Any]], object] | None = None,
    ) -> None: ...


def metrics_settings(
    north_config: NorthConfig, command: str
) -> tuple[MetricsSettings | None, bool]:
    """The metrics endpoint of the run (``[metrics]``, with ``--metrics-port`` applied), and
    whether it can be served (prometheus_client installed; else one error line)."""
    metrics = north_config.metrics
    if metrics is not None:
        problem = missing([("[metrics]", "prometheus_client", "metrics")])
        if problem is not None:
            print_error(f"{command}: {problem}")
            return None, False
    return metrics, True


async def run_fed(
    poller: Poller,
    server: FedServer,
    north_config: NorthConfig,
    metrics: MetricsSettings | None,
    *,
    listening: Callable[[], str],
    duration: float | None,
    collectors: Iterable[Any] = (),
) -> int:
    """Run ``server`` fed by ``poller`` until stopped; the exit code.

    ``listening`` says where the server listens, printed on stderr once the first scan of every
    PLC is stored (a PLC that does not answer: once its first scan failed): the line a script
    or an operator waits for, after which a client reads the PLCs' values, not "waiting for
    initial data". ``collectors`` are the server's own Prometheus collectors.
    """
    # the north side of `plcstack poll`, metrics and the audit: the same collector, HTTP server
    # and write path (every client write is an [audit] line naming the server as its source)
    north = North(poller, NorthConfig(metrics=metrics, audit=north_config.audit))
    server.writes = north.writes

    def observe(batch: list[Scan]) -> None:
        north.collector.observe(batch)
        north.writes.observe(batch)  # the audit's "previous" value of a written tag

    # the PLCs that scan (a PLC without tags never does)
    waiting = {plc for plc in poller.plcs if poller.tags(plc)}

    def stored(batch: list[Scan]) -> None:
        if waiting:
            waiting.difference_update(scan.plc for scan in batch)
            if not waiting:
                print(listening(), file=sys.stderr, flush=True)

    if north.metrics is not None:
        for collector in collectors:
            north.metrics.registry.register(collector)
    stop = StopEvent()
    installed = install_stop_signals(stop)
    try:
        async with poller, north, server:  # a metrics port that is taken fails first
            if north.metrics is not None:
                host, port = north.metrics.settings.host, north.metrics.port
                print(f"metrics on http://{host}:{port}/metrics", file=sys.stderr, flush=True)
            if not waiting:  # nothing to wait for
                print(listening(), file=sys.stderr, flush=True)
            # under systemd: ready with the line above, pings while requests keep ending
            limit = stall_limit(poller.config)
            service = ServiceNotifier(
                Notifier.from_environment(),
                ready=lambda: not waiting,
                status=listening,
                alive=ScanWatch(lambda: poller.stats, limit),
                ready_within=limit,
            )
            async with notifying(service):
                await run_until(server, stop, duration, observe=observe, stored=stored)
    finally:
        remove_stop_signals(installed)
    print(format_stats(poller.stats, dropped_total=poller.dropped), file=sys.stderr)
    return stop.exit_code()
