"""``plcstack serve modbus CONFIG.toml``: poll the PLCs of a TOML file, serve them over Modbus TCP.

Tags with a ``modbus`` key (``"hr:100"``, ``"ir:0"``, ``"co:5"``, ``"di:0"``: table and 0-based
address) are served; ``[modbus]`` sets the endpoint (default ``127.0.0.1:5020``: loopback only),
``unit_id`` (default 1) and ``word_order`` (default ``"big"``: high word first). Reads are
answered from the latest poll (a PLC that does not answer: exception 0x0B), writes of tags with
``writable = true`` only after the PLC confirmed them. Two tags whose registers overlap are
refused when the file is loaded. See docs/modbus.md.

With ``[metrics]`` in the file (or ``--metrics-port``) it also serves ``/metrics`` and
``/healthz`` as ``plcstack poll`` does, plus the Modbus requests, exception answers and clients.
Runs until Ctrl-C or SIGTERM (or ``--duration``), then prints the poller's statistics on stderr.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from plcstack.cli import plain_text, print_error
from plcstack.cli.poll import StopEvent, install_stop_signals, remove_stop_signals
from plcstack.north.config import NorthConfig, load_config
from plcstack.north.metrics import MetricsSettings
from plcstack.north.modbus.server import ModbusServer
from plcstack.north.pipeline import North
from plcstack.north.supervise import run_until
from plcstack.poll.engine import Poller, format_stats
from plcstack.poll.samples import Scan


def register(servers: Any) -> None:
    modbus = servers.add_parser(
        "modbus",
        help="a Modbus TCP server fed by the poller",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    modbus.add_argument("config", help="TOML file with [[plc]] tables, modbus keys and [modbus]")
    modbus.add_argument(
        "--duration", type=float, default=None, help="stop after SECONDS (default: until Ctrl-C)"
    )
    modbus.add_argument(
        "--metrics-port",
        type=int,
        default=None,
        metavar="PORT",
        help="serve /metrics and /healthz on this port (overrides [metrics] port; 0 = any free"
        " port; host from [metrics], default 127.0.0.1)",
    )
    modbus.set_defaults(func=run_modbus)


async def run_modbus(args: argparse.Namespace) -> int:
    if args.duration is not None and not args.duration > 0:
        print_error("serve modbus: --duration must be greater than 0")
        return 2
    metrics_port = args.metrics_port
    if metrics_port is not None and not 0 <= metrics_port <= 65535:
        print_error("serve modbus: --metrics-port must be 0..65535")
        return 2
    config, north_config = load_config(args.config)  # read once
    metrics = north_config.metrics
    if metrics_port is not None:
        metrics = MetricsSettings(metrics.host if metrics else "127.0.0.1", metrics_port)
    poller = Poller(config)  # every URL and address checked before anything is sent
    server = ModbusServer.from_config(poller)  # overlaps refused here (the file read once)
    # the north side of `plcstack poll`, metrics and the audit: the same collector, HTTP server
    # and write path (every Modbus write is an [audit] line with source "modbus")
    north = North(poller, NorthConfig(metrics=metrics, audit=north_config.audit))
    server.writes = north.writes

    def observe(batch: list[Scan]) -> None:
        north.collector.observe(batch)
        north.writes.observe(batch)  # the audit's "previous" value of a written tag

    if north.metrics is not None:
        north.metrics.registry.register(server.collector())
    stop = StopEvent()
    installed = install_stop_signals(stop)
    try:
        async with poller, north, server:  # a metrics port that is taken fails first
            print(f"Modbus server listening on {server.endpoint}", file=sys.stderr, flush=True)
            if north.metrics is not None:
                host, port = north.metrics.settings.host, north.metrics.port
                print(f"metrics on http://{host}:{port}/metrics", file=sys.stderr, flush=True)
            await run_until(server, stop, args.duration, observe=observe)
    finally:
        remove_stop_signals(installed)
    print(format_stats(poller.stats, dropped_total=poller.dropped), file=sys.stderr)
    return stop.exit_code()
