"""``plcstack serve opcua CONFIG.toml``: poll the PLCs of a TOML file and serve them over OPC UA.

The same runtime as ``plcstack poll CONFIG --format none``, with the OPC UA server running even
when the file has no ``[opcua]`` table: every other face the file configures (``[mqtt]``,
``[modbus]``, ``[web]``, ``[metrics]``, ``[audit]``) runs too, on the same poller and one
connection per PLC. The ``[opcua]`` table sets the endpoint (default ``opc.tcp://127.0.0.1:4840/
plcstack``: loopback only), security policies and logins (plcstack docs opcua). It prints ``OPC
UA server listening on URL`` on stderr once every PLC's first scan is in (a PLC that does not
answer: once that scan failed), so a client that connects then reads values. Runs until Ctrl-C
or SIGTERM (or ``--duration``), then prints the poller's statistics on stderr.

With ``[metrics]`` in the file (or ``--metrics-port``, which overrides its port) it also serves
``/metrics``, ``/healthz`` and ``/livez`` (plcstack docs north).

``plcstack serve opcua --hash-password`` reads a password from stdin and prints the
``password_hash`` to put under ``[opcua.users.NAME]``.

Needs the optional extra: ``pip install 'plcstack[opcua]'`` (asyncua).
"""

from __future__ import annotations

import argparse
import dataclasses
import getpass
import importlib.util
import sys
from typing import Any

from plcstack.cli import plain_text, print_error, serve_modbus
from plcstack.cli.run_options import add_run_options
from plcstack.cli.serve_run import run_served
from plcstack.north.config import NorthConfig
from plcstack.north.opcua_config import OpcUaConfig, hash_password


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
    add_run_options(opcua, faces=("metrics",))
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
    if importlib.util.find_spec("asyncua") is None:
        print_error("serve opcua: asyncua is not installed; pip install 'plcstack[opcua]'")
        return 2
    # -v (INFO) logs every write; the log options are the ones every subcommand has
    return await run_served(args, "serve opcua", _with_opcua)


def _with_opcua(north: NorthConfig) -> NorthConfig:
    """The OPC UA server runs: with the file's ``[opcua]``, else its defaults."""
    return dataclasses.replace(north, opcua=north.opcua or OpcUaConfig())
