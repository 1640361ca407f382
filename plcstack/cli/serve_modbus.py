"""``plcstack serve modbus CONFIG.toml``: poll the PLCs of a TOML file, serve them over Modbus TCP.

Tags with a ``modbus`` key (``"hr:100"``, ``"ir:0"``, ``"co:5"``, ``"di:0"``: table and 0-based
address) are served; ``[modbus]`` sets the endpoint (default ``127.0.0.1:5020``: loopback only),
``unit_id`` (default 1) and ``word_order`` (default ``"big"``: high word first). Reads are
answered from the latest poll (a PLC that does not answer: exception 0x0B), writes of tags with
``writable = true`` only after the PLC confirmed them. Two tags whose registers overlap are
refused when the file is loaded. See plcstack docs modbus.

With ``[metrics]`` in the file (or ``--metrics-port``) it also serves ``/metrics`` and
``/healthz`` as ``plcstack poll`` does, plus the Modbus requests, exception answers and clients.
It prints ``Modbus server listening on HOST:PORT`` on stderr once every PLC's first scan is in
(a PLC that does not answer: once that scan failed), so a client that connects then reads
values. Runs until Ctrl-C or SIGTERM (or ``--duration``), then prints the poller's statistics
on stderr.
"""

from __future__ import annotations

import argparse
from typing import Any

from plcstack.cli import plain_text
from plcstack.cli.run_options import add_run_options, overrides_of
from plcstack.cli.serve_run import metrics_settings, run_fed
from plcstack.config import load_config
from plcstack.config.overrides import apply_overrides
from plcstack.north.modbus.server import ModbusServer
from plcstack.poll.engine import Poller


def register(servers: Any) -> None:
    modbus = servers.add_parser(
        "modbus",
        help="a Modbus TCP server fed by the poller",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    modbus.add_argument("config", help="TOML file with [[plc]] tables, modbus keys and [modbus]")
    add_run_options(modbus, faces=("metrics",))
    modbus.set_defaults(func=run_modbus)


async def run_modbus(args: argparse.Namespace) -> int:
    whole = apply_overrides(load_config(args.config), overrides_of(args))  # read once
    config, north_config = whole.poll, whole.north
    metrics, ok = metrics_settings(north_config, "serve modbus")
    if not ok:
        return 2
    poller = Poller(config)  # every URL and address checked before anything is sent
    # overlaps refused here (the file read once)
    server = ModbusServer.from_config(poller, north_config.modbus)
    return await run_fed(
        poller,
        server,
        north_config,
        metrics,
        listening=lambda: f"Modbus server listening on {server.endpoint}",
        duration=args.duration,
        collectors=[server.collector()],
    )
