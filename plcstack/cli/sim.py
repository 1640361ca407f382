"""``plcstack sim PROTOCOL``: run a PLC simulator until interrupted.

A simulator module ``plcstack.sim.NAME`` takes part by defining
``add_cli_arguments(parser)`` and ``async serve_cli(args, announce)``; ``serve_cli`` calls
``announce("listening on HOST:PORT")`` (or ``"serial port PATH"``) once it accepts clients, then
serves until cancelled. Scripts and tests wait for that one line on stdout.
"""

from __future__ import annotations

import argparse
import importlib
from typing import Any

#: simulator name -> module
SIMULATORS = {
    "e71": "plcstack.sim.e71",
    "s5lan": "plcstack.sim.s5lan",
    "as511": "plcstack.sim.as511",
    "fetchwrite": "plcstack.sim.fetchwrite",
}


def register(subparsers: Any) -> None:
    sim = subparsers.add_parser("sim", help="run a PLC simulator")
    kinds = sim.add_subparsers(dest="simulator", required=True, metavar="PROTOCOL")
    for name, module_name in SIMULATORS.items():
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise
            continue  # not built in this version: `plcstack sim NAME` then says invalid choice
        parser = kinds.add_parser(name, help=(module.__doc__ or "").strip().splitlines()[0])
        module.add_cli_arguments(parser)
        parser.set_defaults(func=_runner(module))


def _announce(line: str) -> None:
    print(line, flush=True)


def _runner(module: Any) -> Any:
    async def run(args: argparse.Namespace) -> int:
        await module.serve_cli(args, _announce)
        return 0

    return run
