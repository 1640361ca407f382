"""``plcstack serve modbus CONFIG.toml``: poll the PLCs of a TOML file, serve them over Modbus TCP.

Tags with a ``modbus`` key (``"hr:100"``, ``"ir:0"``, ``"co:5"``, ``"di:0"``: table and 0-based
address) are served; ``[modbus]`` sets the endpoint (default ``127.0.0.1:5020``: loopback only),
``unit_id`` (default 1) and ``word_order`` (default ``"big"``: high word first). Reads are
answered from the latest poll (a PLC that does not answer: exception 0x0B), writes of tags with
``writable = true`` only after the PLC confirmed them. Two tags whose registers overlap are
refused when the file is loaded. See plcstack docs modbus.

The same runtime as ``plcstack poll CONFIG --format none``, with the Modbus server running even
when the file has no ``[modbus]`` table: every other face the file configures runs too, on the
same poller and one connection per PLC. With ``[metrics]`` in the file (or ``--metrics-port``) it
also serves ``/metrics``, ``/healthz`` and ``/livez``, with the Modbus requests, exception
answers and clients. It prints ``Modbus server listening on HOST:PORT`` on stderr once every
PLC's first scan is in (a PLC that does not answer: once that scan failed), so a client that
connects then reads values. Runs until Ctrl-C or SIGTERM (or ``--duration``), then prints the
poller's statistics on stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

from plcstack.cli import plain_text
from plcstack.cli.run_options import add_run_options
from plcstack.cli.serve_run import run_served
from plcstack.north.config import NorthConfig
from plcstack.north.modbus.config import ModbusSettings


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
    return await run_served(args, "serve modbus", _with_modbus)


def _with_modbus(north: NorthConfig) -> NorthConfig:
    """The Modbus server runs: with the file's ``[modbus]``, else its defaults."""
    return dataclasses.replace(north, modbus=north.modbus or ModbusSettings())
