"""``plcstack serve opcua CONFIG.toml``: poll the PLCs of a TOML file and serve them over OPC UA.

The ``[opcua]`` table of the same file sets the endpoint (default ``opc.tcp://127.0.0.1:4840/
plcstack``: loopback only), security policies and logins; see docs/opcua.md. Runs until Ctrl-C or
SIGTERM (or ``--duration``), then prints the poller's statistics on stderr.

With ``[metrics]`` in the file (or ``--metrics-port``) it also serves ``/metrics`` and ``/healthz``
as ``plcstack poll`` does (the same collector; docs/north.md). ``--metrics-port`` overrides the
port, so ``plcstack poll`` and this command can run from one file side by side. ``[mqtt]`` and
``[report]`` are for ``plcstack poll`` and are not used here.

``plcstack serve opcua --hash-password`` reads a password from stdin and prints the
``password_hash`` to put under ``[opcua.users.NAME]``.

Needs the optional extra: ``pip install 'plcstack[opcua]'`` (asyncua).
"""

from __future__ import annotations

import argparse
import getpass
import importlib.util
import sys
from pathlib import Path
from typing import Any

from plcstack.cli import plain_text, print_error, serve_modbus
from plcstack.cli.poll import StopEvent, install_stop_signals, remove_stop_signals
from plcstack.north.config import NorthConfig, load_config
from plcstack.north.metrics import MetricsSettings
from plcstack.north.opcua_config import hash_password, parse_opcua_config
from plcstack.north.pipeline import North, missing
from plcstack.poll.engine import Poller, format_stats


def register(subparsers: Any) -> None:
    serve = subparsers.add_parser(
        "serve",
        help="serve the polled PLCs to other systems (opcua, modbus)",
        description="Serve the PLCs of a poll config to other systems.",
    )
    servers = serve.add_subparsers(dest="server", required=True, metavar="SERVER")
    opcua = servers.add_parser(
        "opcua",
        help="an OPC UA server fed by the poller (needs plcstack[opcua])",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    opcua.add_argument("config", nargs="?", help="TOML file with [[plc]] tables and [opcua]")
    opcua.add_argument(
        "--duration", type=float, default=None, help="stop after SECONDS (default: until Ctrl-C)"
    )
    opcua.add_argument(
        "--metrics-port",
        type=int,
        default=None,
        metavar="PORT",
        help="serve /metrics and /healthz on this port (overrides [metrics] port; 0 = any free"
        " port; host from [metrics], default 127.0.0.1)",
    )
    opcua.add_argument(
        "--hash-password",
        action="store_true",
        help="read a password from stdin, print its password_hash for [opcua.users.NAME]",
    )
    opcua.set_defaults(func=run_opcua)
    serve_modbus.register(servers)


async def run_opcua(args: argparse.Namespace) -> int:
    if args.hash_password:
        password = (
            getpass.getpass("password: ") if sys.stdin.isatty() else sys.stdin.readline()
        ).rstrip("\n")
        if not password:
            print_error("serve opcua: empty password")
            return 2
        print(hash_password(password))
        return 0
    if args.config is None:
        print_error("serve opcua: CONFIG is required")
        return 2
    if args.duration is not None and not args.duration > 0:
        print_error("serve opcua: --duration must be greater than 0")
        return 2
    metrics_port = getattr(args, "metrics_port", None)
    if metrics_port is not None and not 0 <= metrics_port <= 65535:
        print_error("serve opcua: --metrics-port must be 0..65535")
        return 2
    if importlib.util.find_spec("asyncua") is None:
        print_error("serve opcua: asyncua is not installed; pip install 'plcstack[opcua]'")
        return 2
    # -v (INFO) logs every write; the log options are the ones every subcommand has
    config, north_config = load_config(args.config)  # read once
    opcua_config = north_config.opcua or parse_opcua_config({}, base=Path(args.config).parent)
    from plcstack.north.opcua import OpcUaServer, run_until  # asyncua: only when serving

    metrics = north_config.metrics
    if metrics is not None or metrics_port is not None:
        problem = missing([("[metrics]", "prometheus_client", "metrics")])
        if problem is not None:
            print_error(f"serve opcua: {problem}")
            return 2
    if metrics_port is not None:
        metrics = MetricsSettings(metrics.host if metrics else "127.0.0.1", metrics_port)
    poller = Poller(config)  # every URL and address checked before anything is sent
    server = OpcUaServer(poller, opcua_config)
    # the north side of `plcstack poll`, metrics only: the same collector and HTTP server
    north = North(poller, NorthConfig(metrics=metrics, audit=north_config.audit))
    server.writes = north.writes  # OPC UA writes share the run's write path and its audit
    stop = StopEvent()
    installed = install_stop_signals(stop)
    try:
        async with poller, north, server:  # a metrics port that is taken fails first
            print(f"OPC UA server listening on {server.url}", file=sys.stderr, flush=True)
            if north.metrics is not None:
                host, port = north.metrics.settings.host, north.metrics.port
                print(f"metrics on http://{host}:{port}/metrics", file=sys.stderr, flush=True)
            await run_until(server, stop, args.duration, observe=north.collector.observe)
    finally:
        remove_stop_signals(installed)
    print(format_stats(poller.stats, dropped_total=poller.dropped), file=sys.stderr)
    return stop.exit_code()
