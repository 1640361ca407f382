"""The ``plcstack`` command line.

Each subcommand lives in its own module with a ``register(subparsers)`` function that sets
``func`` on its parser: an ``async def`` taking the parsed arguments and returning the exit code.
Exit codes: 0 success, 1 a PLC-side failure (error code, timeout, dead peer), 2 bad usage.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib
import sys
from collections.abc import Sequence

from plcstack.errors import AddressError, PlcError

#: subcommand modules, in the order ``--help`` lists them
COMMAND_MODULES = [
    "plcstack.cli.demo",
    "plcstack.cli.poll",
    "plcstack.cli.serve",
    "plcstack.cli.io",
    "plcstack.cli.e71",
    "plcstack.cli.sim",
    "plcstack.cli.bench",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="plcstack",
        description="Read, write, poll and simulate legacy PLCs (MELSEC E71, Siemens S5).",
    )
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code: int = asyncio.run(args.func(args))
    except KeyboardInterrupt:
        return 130
    except AddressError as exc:
        print(f"plcstack: error: {exc}", file=sys.stderr)
        return 2
    except PlcError as exc:
        print(f"plcstack: error: {exc}", file=sys.stderr)
        return 1
    return code
