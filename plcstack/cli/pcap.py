"""``--pcap FILE`` of ``read``, ``write``, ``poll`` and ``sim``: the PLC traffic as pcapng.

Every connection the command opens (and, for ``sim``, every connection its simulator
accepts) is written to FILE as it goes: TCP streams with their real addresses and ports, UDP
datagrams, AS511 serial lines. ``--pcap-limit`` bounds the file: at the limit it becomes
FILE.1 and a fresh FILE continues (so at most about twice the limit is on disk). A file that
cannot be created is a usage error (exit 2) before anything is sent; a capture that fails
later (a full disk) is said once when it happens, the command goes on, and it exits 1 with the
reason at its end. Open the file in Wireshark with the dissectors of ``plcstack wireshark``.
"""

from __future__ import annotations

import argparse
import functools
import logging
from collections.abc import Awaitable, Callable

from plcstack.cli import EXIT_PLC, UsageError, print_error
from plcstack.transports.tap import capturing
from plcstack.wire.capture import DEFAULT_LIMIT, PcapngCapture, parse_size

__all__ = ["add_pcap_options", "with_pcap"]

log = logging.getLogger("plcstack.cli.pcap")

Command = Callable[[argparse.Namespace], Awaitable[int]]


def _size(text: str) -> int:
    try:
        return parse_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_pcap_options(parser: argparse.ArgumentParser) -> None:
    """``--pcap FILE`` and ``--pcap-limit SIZE`` on ``parser``."""
    group = parser.add_argument_group("capture")
    group.add_argument(
        "--pcap",
        metavar="FILE",
        default=None,
        help="write the PLC traffic to FILE as pcapng (open it in Wireshark with the "
        "dissectors of: plcstack wireshark DIR)",
    )
    group.add_argument(
        "--pcap-limit",
        metavar="SIZE",
        type=_size,
        default=DEFAULT_LIMIT,
        help="at this size FILE becomes FILE.1 and a fresh FILE continues "
        "(default 100M; e.g. 512k, 2G)",
    )


def with_pcap(command: Command) -> Command:
    """``command`` run inside the capture its ``--pcap`` asks for (none: as it is)."""

    @functools.wraps(command)
    async def run(args: argparse.Namespace) -> int:
        path: str | None = getattr(args, "pcap", None)
        if path is None:
            return await command(args)
        capture = PcapngCapture(path, limit=getattr(args, "pcap_limit", DEFAULT_LIMIT))
        try:
            capture.open()
        except OSError as exc:
            raise UsageError(f"--pcap {path}: cannot write it: {exc.strerror or exc}") from None
        try:
            with capturing(capture):
                code = await command(args)
        finally:
            capture.close()
            log.info("capture %s: %d packets", path, capture.packets)
        if capture.failure is not None:
            print_error(f"{capture.failure} ({capture.lost} packets not recorded)")
            return code or EXIT_PLC
        return code

    return run
