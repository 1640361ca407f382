"""``plcstack sim PROTOCOL``: run a PLC simulator until interrupted.

A simulator module ``plcstack.sim.NAME`` takes part by defining
``add_cli_arguments(parser)`` and ``async serve_cli(args, announce)``; ``serve_cli`` calls
``announce("listening on HOST:PORT (TCP)")`` (or ``"serial port PATH"``) once it accepts clients,
then serves until cancelled. Scripts and tests wait for that one line on stdout.

Anything that goes wrong before that line (a port in use or out of range, a host name that does
not resolve, an option the simulator refuses) is a start-up error: one line on stderr, exit 2.
Ctrl-C ends the simulator with exit 130, SIGTERM with exit 0; SIGHUP is logged and ignored.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib
import signal
from typing import Any

from plcstack.cli import EXIT_INTERRUPTED, UsageError
from plcstack.cli.pcap import add_pcap_options, with_pcap
from plcstack.cli.signals import Signals, StopEvent
from plcstack.systemd.notify import Notifier
from plcstack.systemd.service import ServiceNotifier, notifying

#: simulator name -> module
SIMULATORS = {
    "e71": "plcstack.sim.e71",
    "s5lan": "plcstack.sim.s5lan",
    "as511": "plcstack.sim.as511",
    "fetchwrite": "plcstack.sim.fetchwrite",
    "replay": "plcstack.wire.replay",
}

#: port options every simulator may have, checked before anything is bound
_PORT_OPTIONS = ("port", "write_port")


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
        add_pcap_options(parser)
        parser.set_defaults(func=with_pcap(_runner(name, module)))


def check_options(args: argparse.Namespace) -> None:
    """Option values no simulator can use, refused before anything is bound."""
    for option in _PORT_OPTIONS:
        value = getattr(args, option, None)
        if value is not None and not 0 <= value <= 65535:
            flag = "--" + option.replace("_", "-")
            raise UsageError(f"{flag} {value}: a port is 0..65535 (0 = any free port)")
    baud = getattr(args, "baud", None)
    if baud is not None and baud <= 0:
        raise UsageError(f"--baud {baud}: a baud rate is a positive number, e.g. 9600")


def _runner(name: str, module: Any) -> Any:
    async def run(args: argparse.Namespace) -> int:
        check_options(args)
        started: list[str] = []

        def announce(line: str) -> None:
            started.append(line)
            print(line, flush=True)

        task = asyncio.current_task()
        assert task is not None
        # Our own handlers for both signals, as `poll` and `demo` have: asyncio.run's SIGINT
        # handling only exists when SIGINT has its default handler at start-up (a parent that
        # ignores it, as some test runners and shells do for their children, left Ctrl-C
        # without effect: seen once in CI as a simulator that never ended); and SIGHUP, which
        # never ends a plcstack process
        stop = StopEvent()
        signals = Signals(stop, on_stop=task.cancel)
        signals.__enter__()
        # under systemd: ready once listening, the listening lines as its status
        service = ServiceNotifier(
            Notifier.from_environment(),
            ready=lambda: bool(started),
            status=lambda: f"sim {name}: " + "; ".join(started),
        )
        try:
            async with notifying(service):
                await module.serve_cli(args, announce)
        except (OSError, ValueError, OverflowError) as exc:
            if started:
                raise
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            where = _where(args)
            raise UsageError(f"sim {name} cannot start{where}: {reason}") from None
        except asyncio.CancelledError:
            if stop.by is None:
                raise
        finally:
            signals.__exit__()
        return EXIT_INTERRUPTED if stop.by is signal.SIGINT else 0

    return run


def _where(args: argparse.Namespace) -> str:
    host, port = getattr(args, "host", None), getattr(args, "port", None)
    if getattr(args, "pty", False) or host is None or port is None:
        return ""
    return f" on {host}:{port}"
