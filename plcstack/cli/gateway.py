"""plcstack gateway PLC-URL --s5lan HOST:PORT --fetchwrite HOST:PORT: native faces of one PLC.

Serves S5-LAN-LINK and/or FETCH/WRITE clients on the network from an S5 CPU reached through its
programming port (as511:///dev/ttyUSB0, or as511+tcp://HOST:PORT for a serial device server),
an S5-LAN module (s5lan://HOST:PORT) or a FETCH/WRITE CP (fetchwrite://HOST:PORT); the
programming port itself on TCP for PG software (--as511, writes with --writable AS); or E71
clients (--e71 TCP, --e71-udp UDP, --e71-code binary or ascii) from an E71 (e71+tcp://...),
more of them than its eight connections. One request at a time on the PLC's connection; network
requests wait in one bounded, fair queue, and a request that waits longer than --max-wait is
answered with the protocol's timeout error, not executed.

Safe by default: a bare port binds 127.0.0.1 only (give 0.0.0.0:PORT to serve the network), and
nothing is writable until --writable names it, e.g. --writable "DB10-20, M" or "D100-199"
(plcstack docs gateway).
Prints one "... listening on HOST:PORT (TCP)" line per server once it accepts clients.
Ctrl-C exits 130, SIGTERM 0 (and --duration 0 once it ran out); a start-up failure is one line
on stderr with exit 2; a run that ends because the gateway failed exits 1 with one line saying
what. A refused write is one WARNING on stderr; --audit FILE appends one JSON line per write
attempt (plcstack docs gateway).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from typing import Any

from plcstack import gateway
from plcstack.cli import UsageError, plain_text, print_error
from plcstack.cli.faces import gateway_faces
from plcstack.cli.signals import Signals, StopEvent, ended_early
from plcstack.clients import connect
from plcstack.clients.as511 import AS511Client
from plcstack.errors import AddressError
from plcstack.gateway.as511face import As511Executor
from plcstack.gateway.e71face import E71Executor
from plcstack.gateway.faces import FaceSettings, PlcFaces
from plcstack.gateway.store import ClientStore, GatewayStats
from plcstack.north.audit import Audit, AuditSettings
from plcstack.north.writes import WritePath
from plcstack.systemd.notify import Notifier
from plcstack.systemd.service import ServiceNotifier, notifying


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "gateway",
        help="serve S5-LAN and FETCH/WRITE from an S5 PLC, or E71 faces of an E71",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "plc",
        help="as511:///dev/ttyUSB0, as511+tcp://HOST:PORT, s5lan://..., fetchwrite://... or "
        "e71+tcp://...",
    )
    parser.add_argument(
        "--s5lan", metavar="[HOST:]PORT", help="serve S5-LAN-LINK here (host default 127.0.0.1)"
    )
    parser.add_argument(
        "--fetchwrite", metavar="[HOST:]PORT", help="serve FETCH/WRITE here (default 127.0.0.1)"
    )
    parser.add_argument("--mk", action="store_true", help="FETCH/WRITE inside the Tani MK header")
    parser.add_argument(
        "--as511",
        metavar="[HOST:]PORT",
        help="serve the programming port (AS511) on TCP here, for PG software (an AS511 PLC)",
    )
    parser.add_argument(
        "--e71", metavar="[HOST:]PORT", help="serve E71 1E frames on TCP here (an E71 PLC)"
    )
    parser.add_argument(
        "--e71-udp", metavar="[HOST:]PORT", help="serve E71 1E frames on UDP here (an E71 PLC)"
    )
    parser.add_argument(
        "--e71-code",
        choices=("binary", "ascii"),
        default="binary",
        help="the E71 faces' code, whatever the PLC's (default binary)",
    )
    parser.add_argument(
        "--writable",
        default="",
        metavar="LIST",
        help='what network clients may write, e.g. "DB10-20, DX3, M, Q" or "D100-199, Y"'
        " (default: nothing)",
    )
    parser.add_argument(
        "--cache-max-age",
        type=float,
        default=None,
        metavar="SECONDS",
        help="serve repeated reads from a cache at most this old (default: off)",
    )
    parser.add_argument(
        "--queue-size",
        type=int,
        default=None,
        help="requests that may wait for the PLC (32); [[gateway]]'s queue",
    )
    parser.add_argument(
        "--max-wait",
        type=float,
        default=None,
        metavar="SECONDS",
        help="answer a request that waited longer with a timeout error, unexecuted (2);"
        " [[gateway]]'s max_wait",
    )
    parser.add_argument(
        "--s5lan-connections",
        type=int,
        default=None,
        help=f"S5-LAN clients at once (default {gateway.DEFAULT_S5LAN_CONNECTIONS});"
        " [[gateway]]'s max_connections",
    )
    parser.add_argument(
        "--duration", type=float, default=None, help="stop after SECONDS (default: until Ctrl-C)"
    )
    parser.add_argument(
        "--audit",
        metavar="FILE",
        default=None,
        help="append one JSON line per write attempt to FILE (rotated at 10 MiB, 5 kept)",
    )
    parser.set_defaults(func=run)


def parse_endpoint(text: str | None, option: str) -> tuple[str, int] | None:
    """``PORT`` or ``HOST:PORT`` (``[v6]:PORT``) -> (host, port); a bare port binds loopback."""
    if text is None:
        return None
    host, sep, port_text = text.rpartition(":")
    host = host.strip("[]") if sep else "127.0.0.1"
    try:
        port = int(port_text)
    except ValueError:
        raise UsageError(f"{option} {text!r}: expected PORT or HOST:PORT") from None
    if not 0 <= port <= 65535:
        raise UsageError(f"{option} {text!r}: a port is 0..65535")
    return host or "127.0.0.1", port


def face_settings(args: argparse.Namespace) -> list[FaceSettings]:
    """The ``[[gateway]]`` entries the command's options stand for, in front of the PLC at
    the URL (named by its URL); :class:`UsageError` for options that say none or a bad one."""
    endpoints = {
        key: parse_endpoint(vars(args)[key], f"--{key.replace('_', '-')}")
        for key in ("s5lan", "fetchwrite", "e71", "e71_udp", "as511")
    }
    if all(x is None for x in endpoints.values()):
        raise UsageError("gateway: give --s5lan and/or --fetchwrite (an E71: --e71, --e71-udp)")
    try:
        return gateway.faces_of(
            args.plc,
            **endpoints,
            mk=args.mk,
            e71_code=args.e71_code,
            writable=args.writable,
            queue_size=args.queue_size,
            max_wait=args.max_wait,
            s5lan_connections=args.s5lan_connections,
        )
    except AddressError as exc:
        raise UsageError(f"gateway: {exc}") from None


async def run(args: argparse.Namespace) -> int:
    faces = face_settings(args)
    if args.duration is not None and not args.duration > 0:
        raise UsageError("--duration must be greater than 0")
    try:
        client = connect(args.plc)
    except AddressError as exc:
        raise UsageError(f"gateway: {exc}") from None
    audit = Audit(AuditSettings(args.audit)) if args.audit else None
    try:
        if audit is not None:
            audit.open()
        # the faces as plcstack poll runs them: each write through the run's one write path
        writes = WritePath(None, audit=audit)
        clients = {args.plc: client}
        natives = gateway_faces(
            faces, clients.__getitem__, writes, cache_max_age=args.cache_max_age
        )
        await natives.aopen()
    except (AddressError, OSError) as exc:
        await client.aclose()
        if audit is not None:
            audit.close()
        if isinstance(exc, AddressError):
            raise UsageError(f"gateway: {exc}") from None
        raise UsageError(f"gateway cannot start: {exc.strerror or exc}") from None
    (faces_of_plc,) = natives.plcs
    stop = StopEvent()
    signals = Signals(stop)
    signals.__enter__()
    failure: str | None = None
    try:
        listening = [
            f"{face.protocol} listening on {server.host}:{server.port} ({face.transport.upper()})"
            for face, server in zip(faces_of_plc.settings, faces_of_plc.servers, strict=True)
        ]
        for line in listening:
            print(line, flush=True)
        print(f"writable: {faces[0].allow_list()}", flush=True)
        # under systemd: ready now that it listens
        status = f"gateway to {args.plc}: {'; '.join(listening)}"
        async with notifying(ServiceNotifier(Notifier.from_environment(), status=lambda: status)):
            stopper = asyncio.create_task(stop.wait())
            # the PLC side: the queue of its connection stopping ends the run, said
            watcher = asyncio.create_task(natives.watch(), name="the gateway")
            done, _ = await asyncio.wait(
                {stopper, watcher}, timeout=args.duration, return_when=asyncio.FIRST_COMPLETED
            )
            failure = ended_early(done - {stopper}, stop)
            for task in (stopper, watcher):
                task.cancel()
            await asyncio.gather(stopper, watcher, return_exceptions=True)
    finally:
        signals.__exit__()
        await natives.aclose()
        await client.aclose()
        if audit is not None:
            audit.close()
        print(_summary(faces_of_plc), file=sys.stderr)
    if failure is not None:
        print_error(f"gateway: {failure}")
        return 1
    return stop.exit_code()


def _summary(faces: PlcFaces) -> str:
    """The counts said on stderr at the end of a run."""
    executor = next((a for a in faces.answering if isinstance(a, E71Executor)), None)
    store = next((a for a in faces.answering if isinstance(a, ClientStore)), None)
    pg = next((a for a in faces.answering if isinstance(a, As511Executor)), None)
    if executor is not None:
        c = executor.counts
        return (
            f"gateway: {sum(c.values())} requests; answered by the PLC {c['ok']}; busy "
            f"{c['busy']}, expired {c['expired']}, denied {c['denied']}, failed {c['failed']}"
        )
    if store is None and pg is not None:
        return f"gateway: {pg.transactions} PG transactions, {pg.refused} refused"
    s = store.stats if store is not None else GatewayStats()
    line = "AS511" if isinstance(faces.share.client, AS511Client) else "PLC"
    return (
        f"gateway: {s.reads} reads, {s.writes} writes; {line} {s.line_reads} reads, "
        f"{s.line_writes} writes; cache hits {s.cache_hits}; busy {s.busy}, "
        f"expired {s.expired}, denied {s.denied}, failed {s.failed}"
    )
