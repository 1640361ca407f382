"""The ``plcstack`` command line.

Each subcommand lives in its own module with a ``register(subparsers)`` function that sets
``func`` on its parser: an ``async def`` taking the parsed arguments and returning the exit code.

One exit-code rule for every subcommand (``EXIT_CODES``, also in ``plcstack --help``):

====  ==========================================================================================
0     success (also ``--help``, ``--version``, a SIGTERM that ends ``poll``/``demo``/``sim``,
      and a reader of stdout that went away: ``| head``)
1     the PLC side failed: error code, timeout, unreachable or lost connection, malformed answer
2     bad usage: options, URL, address, value, config file, a simulator that cannot start
130   interrupted with Ctrl-C (SIGINT); ``poll`` and ``demo`` still print their statistics first
====  ==========================================================================================

Every failure is exactly one line on stderr, ``plcstack: error: ...``. A bug (an exception that is
no ``PlcError``) is one line too, ``plcstack: internal error: ...`` with exit 1; the traceback
follows only with ``--log-level debug`` (``-vv``).
"""

from __future__ import annotations

import argparse
import asyncio
import importlib
import logging
import os
import select
import sys
from collections.abc import Iterator, Sequence
from io import TextIOWrapper  # not ``import io``: the submodule plcstack.cli.io takes ``io``
from typing import NoReturn

from plcstack import __version__
from plcstack.errors import AddressError, PlcError
from plcstack.logs import FORMATS, LEVELS, configure, on_journal

#: subcommand modules, in the order ``--help`` lists them
COMMAND_MODULES = [
    "plcstack.cli.demo",
    "plcstack.cli.poll",
    "plcstack.cli.serve",
    "plcstack.cli.io",
    "plcstack.cli.e71",
    "plcstack.cli.sim",
    "plcstack.cli.gateway",
    "plcstack.cli.systemd",
    "plcstack.cli.bench",
    "plcstack.cli.tags",
    "plcstack.cli.wireshark",
    "plcstack.cli.docs",
]

EXIT_OK = 0
EXIT_PLC = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

EXIT_CODES = (
    "exit codes: 0 success; 1 the PLC side failed (error code, timeout, unreachable); "
    "2 bad usage (options, URL, address, value, config, a simulator that cannot start); "
    "130 Ctrl-C"
)

_log = logging.getLogger("plcstack.cli")


class UsageError(Exception):
    """Bad usage found after parsing (a simulator that cannot bind, a missing option, a file
    that cannot be read): exit 2 with this one-line message."""


def plain_text(doc: str | None) -> str:
    """A module docstring as a help text: reStructuredText's double backticks dropped."""
    return (doc or "").replace("``", "")


def add_logging_options(parser: argparse.ArgumentParser) -> None:
    """``-v``/``--log-level`` on ``parser``. SUPPRESS defaults, so the value given on the top
    level (``plcstack -v read ...``) survives a subcommand that did not repeat it."""
    group = parser.add_argument_group("logging")
    group.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=argparse.SUPPRESS,
        help="more log output on stderr: -v info, -vv debug (with the frame trace)",
    )
    group.add_argument(
        "--log-level",
        choices=LEVELS,
        type=str.lower,
        default=argparse.SUPPRESS,
        help="log level (default warning); debug shows every frame as hex",
    )
    group.add_argument(
        "--log-format",
        choices=FORMATS,
        type=str.lower,
        default=argparse.SUPPRESS,
        help="text (default: one line per record; under systemd with its syslog priority first"
        " and no time) or json (one JSON object per line: time, level, logger, message, plc,"
        " tag, face)",
    )


class CommandParser(argparse.ArgumentParser):
    """The parser of ``plcstack`` and, by argparse's inheritance, of every subcommand.

    Two differences from argparse's own: a usage error is the same one line as every other
    error (``plcstack: error: read: ...`` and where to get help, exit 2) instead of a usage
    block under a prefix of its own; and a subcommand's options may stand anywhere among its
    positionals (``read URL D100 --timeout 1 2``), which plain argparse refuses for an optional
    positional like ``count`` (it reports ``unrecognized arguments: 2``).
    """

    _intermixing = False

    def error(self, message: str) -> NoReturn:
        command = self.prog.removeprefix("plcstack").strip()
        where = f"{command}: " if command else ""
        _fail("error", f"{where}{message} (see: {self.prog} --help)")
        sys.exit(EXIT_USAGE)

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        if self._intermixing or self._subparsers is not None:
            return super().parse_known_args(args, namespace)
        # argparse's intermixed parsing calls back into this method for its two passes
        self._intermixing = True
        try:
            return super().parse_known_intermixed_args(args, namespace)
        finally:
            self._intermixing = False


def _all_parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):  # aliases share a parser
                yield from _all_parsers(sub)


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(
        prog="plcstack",
        description="Read, write, poll and simulate legacy PLCs (MELSEC E71, Siemens S5).",
        epilog=EXIT_CODES + ". Documentation: plcstack docs (lists the pages, also in the wheel); "
        "examples: plcstack demo --write-config FILE.",
    )
    parser.add_argument("--version", action="version", version=f"plcstack {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    for each in _all_parsers(parser):
        add_logging_options(each)
    return parser


def _level(args: argparse.Namespace) -> str:
    explicit: str | None = getattr(args, "log_level", None)
    if explicit is not None:
        return explicit
    verbose: int = getattr(args, "verbose", 0)
    return "warning" if verbose == 0 else "info" if verbose == 1 else "debug"


def _fail(kind: str, message: object) -> None:
    # one line, whatever the message holds; filed as an error by journald under systemd
    text = " ".join(str(message).split()) or "(no message)"
    priority = "<3>" if on_journal() else ""
    print(f"{priority}plcstack: {kind}: {text}", file=sys.stderr, flush=True)


def print_error(message: object) -> None:
    """``plcstack: error: MESSAGE`` as one line on stderr: for a command that reports a failure
    and returns its exit code itself (the one prefix every error line of the CLI has)."""
    _fail("error", message)


def _tolerant_output() -> None:
    """A terminal that is not UTF-8 (``LANG=de_DE.ISO-8859-1``, a Windows code page, a serial
    console) cannot show every character a page, a tag name or a PLC string holds (a unit ``°C``,
    Japanese device comments): such a character is written escaped, as ``\\xb0``, instead of
    ending the command with a UnicodeEncodeError after half its output."""
    for stream in (sys.stdout, sys.stderr):
        if isinstance(stream, TextIOWrapper) and stream.errors == "strict":
            stream.reconfigure(errors="backslashreplace")


def _stdout_gone() -> bool:
    """Whether stdout is a pipe whose reader has closed it (``plcstack docs | head -3``). Then
    the reader has what it wanted, as for ``poll``, whose samples stop the same way: exit 0,
    and stdout is pointed at /dev/null so the interpreter's last flush does not complain."""
    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        if not any(events & select.POLLERR for _, events in poller.poll(0)):
            return False
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, fd)
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no file behind stdout, no select.poll
        return False
    return True


def main(argv: Sequence[str] | None = None) -> int:
    _tolerant_output()
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or the one-line usage error already printed
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    unconfigure = configure(_level(args), getattr(args, "log_format", "text"))
    try:
        code: int = asyncio.run(args.func(args))
        sys.stdout.flush()  # a reader that went away shows here, not as noise at exit
    except BrokenPipeError:
        if not _stdout_gone():
            raise  # a socket's EPIPE that no layer wrapped: the bug it is, below
        return EXIT_OK
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except (AddressError, UsageError) as exc:
        _fail("error", exc)
        return EXIT_USAGE
    except PlcError as exc:
        _fail("error", exc)
        return EXIT_PLC
    except Exception as exc:
        _log.debug("traceback of the internal error", exc_info=True)
        _fail("internal error", f"{type(exc).__name__}: {exc} (a bug; -vv shows the traceback)")
        return EXIT_PLC
    finally:
        unconfigure()
    return code
