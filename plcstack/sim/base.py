"""What every simulator offers to in-process users (tests, the demo, the benchmarks).

Each ``plcstack.sim.NAME`` module has ``async def start(...) -> Simulator`` that binds (port 0 picks
a free port) and returns once clients can connect. The object tells where it listens and the URL a
client should use, so callers never assemble URLs by hand.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
from abc import abstractmethod
from collections.abc import Iterator
from typing import Any

from plcstack.checks import parse_seconds
from plcstack.resource import AsyncResource
from plcstack.transports.guard import (
    CLOSE_LINGER,
    FIRST_REQUEST_TIMEOUT,
    FaceGuard,
    Limits,
    close_writer,
)
from plcstack.transports.peer import peer_address

log = logging.getLogger("plcstack.sim")

__all__ = [
    "CLOSE_LINGER",
    "DEFAULT_IDLE_TIMEOUT",
    "DEFAULT_MAX_CONNECTIONS",
    "ClientGone",
    "ConnectionCount",
    "FaceGuard",
    "Limits",
    "Simulator",
    "TcpSimulator",
    "UdpSimulator",
    "add_guard_arguments",
    "bound_address",
    "check_idle_timeout",
    "close_writer",
    "limits_of",
    "module_guard",
]

#: seconds a simulator keeps a connection on which the client sent nothing. Real modules drop
#: dead partners too (the E71 by its "existence check", a CP by its keep-alive); without it 8
#: idle sockets locked an E71 simulator out, 1 an S5-LAN one, for ever. Ten minutes is longer
#: than any sane poll interval, so a slow poller is never cut off; ``None`` turns it off.
DEFAULT_IDLE_TIMEOUT: float | None = 600.0
#: connections at once of the simulators whose modules have no documented limit (FETCH/WRITE,
#: AS511 over a serial device server); beyond it a connection is closed at once and counted
DEFAULT_MAX_CONNECTIONS = 16


def module_guard(
    face: str,
    title: str,
    max_connections: int = DEFAULT_MAX_CONNECTIONS,
    idle_timeout: float | None = DEFAULT_IDLE_TIMEOUT,
    limits: Limits | None = None,
    logger: logging.Logger = log,
) -> FaceGuard:
    """The guard of a simulated module's listener: ``limits`` (a gateway's face passes its
    own), or the module's: ``max_connections`` from any host (a module does not tell hosts
    apart), a first request within :data:`FIRST_REQUEST_TIMEOUT`, ``idle_timeout``. Its log
    lines go to ``logger`` (default ``plcstack.sim``)."""
    if limits is None:
        if max_connections < 1:
            raise ValueError("max_connections must be at least 1")
        limits = Limits(
            max_clients=max_connections,
            max_clients_per_host=max_connections,
            first_request_timeout=FIRST_REQUEST_TIMEOUT,
            idle_timeout=check_idle_timeout(idle_timeout),
        )
    return FaceGuard(face, title, limits, logger)


def check_idle_timeout(idle_timeout: float | None) -> float | None:
    """``None`` (off) or a finite number of seconds greater than 0."""
    if idle_timeout is None:
        return None
    from plcstack.durations import check_seconds

    return check_seconds("idle_timeout", idle_timeout)


def _cli_seconds(text: str) -> float:
    """A duration on the command line as a table takes it (``10``, ``2.5``, ``"500ms"``,
    ``"10m"``); 0 turns the limit off."""
    try:
        value: object = float(text)
    except ValueError:
        value = text
    try:
        return parse_seconds(value, zero=True)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _cli_count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if not 1 <= value <= 10_000:
        raise argparse.ArgumentTypeError(f"must be a whole number 1..10000, not {text!r}")
    return value


def add_guard_arguments(parser: argparse.ArgumentParser, max_connections: int) -> None:
    """The limits of every ``plcstack sim``, with the names of a listening face's keys
    (``max_clients``, ``max_clients_per_host``, ``first_request_timeout``, ``idle_timeout``);
    ``max_connections``: the module's own number of connections, the default."""
    parser.set_defaults(module_connections=max_connections)
    parser.add_argument(
        "--max-clients",
        type=_cli_count,
        default=None,
        metavar="N",
        help=f"connections at once; more are closed at once and counted (default"
        f" {max_connections}, as the module serves)",
    )
    parser.add_argument(
        "--max-clients-per-host",
        type=_cli_count,
        default=None,
        metavar="N",
        help="connections at once from one host (default: as many as --max-clients; a module"
        " does not tell hosts apart)",
    )
    parser.add_argument(
        "--first-request-timeout",
        type=_cli_seconds,
        default=FIRST_REQUEST_TIMEOUT,
        metavar="SECONDS",
        help=f"close a connection that sent no complete request this long after connecting"
        f" (default {FIRST_REQUEST_TIMEOUT:g}; 0 = no limit; 500ms, 1m as in a table)",
    )
    parser.add_argument(
        "--idle-timeout",
        type=_cli_seconds,
        default=DEFAULT_IDLE_TIMEOUT,
        metavar="SECONDS",
        help="close a connection that sent nothing for this long (default 600; 0 = never)",
    )


def limits_of(args: argparse.Namespace) -> Limits:
    """The :func:`add_guard_arguments` of parsed CLI arguments as a simulator's ``limits``;
    ValueError (the CLI's exit 2) for a per-host cap above the total."""
    total: int = args.max_clients or args.module_connections
    per_host: int = args.max_clients_per_host or total
    if per_host > total:
        raise ValueError(
            f"--max-clients-per-host {per_host} cannot be more than --max-clients ({total})"
        )
    return Limits(
        max_clients=total,
        max_clients_per_host=per_host,
        first_request_timeout=args.first_request_timeout or None,
        idle_timeout=args.idle_timeout or None,
    )


class ConnectionCount:
    """How many client connections a simulator holds now, and the most it ever held at once.

    The scale-out tests read ``peak`` to prove that no PLC ever had two pollers at once.
    """

    __slots__ = ("current", "peak", "total")

    def __init__(self) -> None:
        self.current = 0
        self.peak = 0
        self.total = 0

    def opened(self) -> None:
        self.current += 1
        self.total += 1
        self.peak = max(self.peak, self.current)

    def closed(self) -> None:
        self.current -= 1


class ClientGone:
    """Cancels a connection's handler when its client goes away while the handler waits on the
    client's behalf (:meth:`waiting`): a gateway's request of a client that closed its
    connection is then given up where it waits, and a queued write is never sent.

    Gone is: the connection lost (reset, aborted), or the client closed its side with nothing
    more to read. None of these protocols has a client that half-closes and waits for its
    answer; a client that closes after a timeout has given up, and it may be sending the same
    request again on a new connection. Looked at every ``PERIOD`` seconds, and only while a
    request waits. Start it in the handler's task; :meth:`close` it when the handler ends.
    """

    PERIOD = 0.05

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        handler = asyncio.current_task()
        if handler is None:
            raise RuntimeError("ClientGone is started by a connection's task")
        self._handler = handler
        self._reader = reader
        self._writer = writer
        self._busy = asyncio.Event()
        self.gone = False
        self._task = asyncio.ensure_future(self._watch())

    @contextlib.contextmanager
    def waiting(self) -> Iterator[None]:
        """While the handler waits for the answer of a request."""
        self._busy.set()
        try:
            yield
        finally:
            self._busy.clear()

    def close(self) -> None:
        self._task.cancel()

    async def _watch(self) -> None:
        while True:
            await self._busy.wait()
            if self._reader.at_eof() or self._writer.transport.is_closing():
                self.gone = True
                self._handler.cancel()
                return
            await asyncio.sleep(self.PERIOD)


def bound_address(sockname: Any, scheme: str, query: str = "") -> tuple[str, int, str]:
    """Host, port and client URL of a simulator bound at ``sockname`` (a socket's
    ``getsockname()``), e.g. ``e71+tcp://127.0.0.1:40001``: every network simulator's URL. The
    URL names the address as the logs and the audit do (:func:`peer_address`: an IPv6 host in
    brackets, as a URL needs it)."""
    host: str = sockname[0]
    port: int = sockname[1]
    return host, port, f"{scheme}://{peer_address(sockname)}" + (f"?{query}" if query else "")


class Simulator(AsyncResource):
    """A running simulator. Close it with ``await sim.aclose()`` or ``async with``."""

    #: the URL a plcstack client uses to reach this simulator, e.g. ``e71+tcp://127.0.0.1:40001``
    url: str
    #: the address it is bound to
    host: str
    port: int

    @abstractmethod
    async def aclose(self) -> None: ...

    async def serve_forever(self) -> None:
        """Serve until cancelled (the CLI's ``plcstack sim``)."""
        try:
            await asyncio.Event().wait()
        finally:
            await self.aclose()


class TcpSimulator(Simulator):
    """A simulator behind one ``asyncio.Server``; ``host``/``port`` are the bound address.

    ``guard`` holds its limits (connections at once and per host, the first-request and idle
    deadlines; :func:`module_guard`) and counts what they refused and closed."""

    def __init__(
        self, server: asyncio.Server, scheme: str, query: str = "", guard: FaceGuard | None = None
    ) -> None:
        self.server = server
        self.host, self.port, self.url = bound_address(
            server.sockets[0].getsockname(), scheme, query
        )
        self._conn_tasks: set[asyncio.Task[None]] = set()
        #: client connections now / at most at once (simulators without per-connection tasks
        #: call ``opened``/``closed`` themselves)
        self.connection_count = ConnectionCount()
        self.guard = guard if guard is not None else module_guard(scheme, f"{scheme} simulator")
        self.guard.announce(self.url)

    @property
    def idle_timeout(self) -> float | None:
        """Seconds without a byte from the client before its connection is closed."""
        return self.guard.limits.idle_timeout

    @property
    def idle_closed(self) -> int:
        """Connections closed because the client sent nothing for ``idle_timeout`` seconds."""
        return self.guard.counts["idle_timeout"]

    @property
    def refused_connections(self) -> int:
        """Connections closed at once because the simulator was at a connection cap."""
        return self.guard.refused

    @property
    def first_request_closed(self) -> int:
        """Connections closed because no complete request came in time after connecting."""
        return self.guard.counts["first_request_timeout"]

    @property
    def late_frames(self) -> int:
        """Connections closed because a request begun was not complete in time (a header
        trickled byte by byte)."""
        return self.guard.counts["frame_timeout"]

    def track(self, task: asyncio.Task[None]) -> None:
        """Remember a per-connection task so ``aclose`` can end it (no task outlives the sim);
        the connection counts as open until the task ends."""
        self._conn_tasks.add(task)
        self.connection_count.opened()
        task.add_done_callback(self._untrack)

    def _untrack(self, task: asyncio.Task[None]) -> None:
        self._conn_tasks.discard(task)
        self.connection_count.closed()

    async def aclose(self) -> None:
        self.server.close()
        for task in list(self._conn_tasks):
            task.cancel()
        if self._conn_tasks:
            await asyncio.gather(*self._conn_tasks, return_exceptions=True)
        await self.server.wait_closed()
        self.guard.close()


class UdpSimulator(Simulator):
    """A simulator on one bound UDP socket (``asyncio.DatagramTransport``); replies go to the
    datagram's source address. ``host``/``port`` are the bound address."""

    def __init__(self, transport: asyncio.DatagramTransport, scheme: str, query: str = "") -> None:
        self.transport = transport
        self.host, self.port, self.url = bound_address(
            transport.get_extra_info("sockname"), scheme, query
        )

    async def aclose(self) -> None:
        self.transport.close()
