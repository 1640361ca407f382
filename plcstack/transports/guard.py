"""What every listening face does against clients that are slow, silent, many or hostile.

The gateway's S5-LAN and FETCH/WRITE faces, the Modbus TCP server, OPC UA, the web console,
``/metrics`` and the simulators listen on plant networks, where a scanner, a half-open socket,
a broken panel or a client that leaks sockets is a matter of time. One :class:`FaceGuard` per
face keeps such a client from holding what the others need:

* at most ``max_clients`` connections at once, and at most ``max_clients_per_host`` from one
  host, so one machine cannot take every slot; the next one is turned away at once;
* a connection must send one complete request within ``first_request_timeout`` seconds (a
  socket opened and left silent is closed long before the idle timeout);
* a connection that sends nothing for ``idle_timeout`` seconds is closed (a dead partner
  would otherwise hold its slot for ever);
* :class:`FrameDeadline`: a frame once begun must be complete within ``limit`` seconds of its
  *first* byte. A per-read timeout does not do it: a client that sends one header byte every
  half second restarts it with every byte and holds its connection for ever (slowloris).

Every refusal and every close is counted by face and reason (:data:`TOTALS`, which
``/metrics`` serves as ``plcstack_face_guard_closes_total``), and said at WARNING once per
host per burst (:class:`BurstLog`): the first at once, then one line with the count per
:data:`BURST_PERIOD` while it goes on; a flood of garbage or connections writes a few lines,
not one per frame. One INFO line per face at start says its limits (:meth:`FaceGuard.announce`).
:func:`close_writer` closes a stream after its answer, aborted if the peer does not read it.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

from plcstack.checks import Table
from plcstack.transports.peer import peer_address

__all__ = [
    "BURST_PERIOD",
    "CLOSE_LINGER",
    "FIRST_REQUEST_TIMEOUT",
    "FRAME_TIMEOUT",
    "LIMIT_KEYS",
    "TOTALS",
    "BurstLog",
    "FaceGuard",
    "FrameDeadline",
    "GuardedProtocol",
    "Limits",
    "Visit",
    "close_writer",
    "earliest",
    "parse_limits",
]

#: seconds a frame may take from its first byte to its last. Frames of these protocols
#: are at most a few KiB (a FETCH/WRITE write: 128 KiB), sent in one go by every real client;
#: only a client that trickles them, to hold a connection, takes longer.
FRAME_TIMEOUT = 5.0

#: seconds a closing connection may take to send what is still queued for a peer that reads
#: nothing, before it is aborted
CLOSE_LINGER = 1.0

#: seconds a new connection may take to send its first complete request: every client of
#: these protocols sends one as soon as it is connected; a socket that stays silent is a scan,
#: a leak or an attack, and must not hold a slot for the idle timeout (ten minutes)
FIRST_REQUEST_TIMEOUT = 10.0

#: seconds of a burst per log line: the first event is said at once, the ones after it in one
#: line per period with their count, and the burst is over after a period without one
BURST_PERIOD = 60.0

#: hosts (and kinds of event) a burst log follows at once; beyond, the oldest burst is said
#: and forgotten, so a flood from many addresses cannot grow it
MAX_BURSTS = 1024

#: the configuration keys of :func:`parse_limits`, in every listening face's table
LIMIT_KEYS = ("max_clients", "max_clients_per_host", "first_request_timeout", "idle_timeout")

#: what each reason a connection was refused or closed means, for the log
REASONS = {
    "max_clients": "the face serves {limit} clients at once",
    "max_clients_per_host": "one host may hold {limit} connections",
    "first_request_timeout": "no complete request within {limit:g} s of connecting",
    "idle_timeout": "nothing sent for {limit:g} s",
    "frame_timeout": "a request begun was not complete within {limit:g} s",
    "malformed": "it sent bytes that are no request of the protocol",
}


class Totals:
    """Refusals and closes of every face of the process, by face and reason: counters that
    only grow (a face restarted keeps counting on), read by ``/metrics``."""

    def __init__(self) -> None:
        self._counts: collections.Counter[tuple[str, str]] = collections.Counter()

    def add(self, face: str, reason: str, n: int = 1) -> None:
        self._counts[(face, reason)] += n

    def items(self) -> list[tuple[tuple[str, str], int]]:
        """``((face, reason), count)`` pairs, sorted."""
        return sorted(self._counts.items())

    def get(self, face: str, reason: str) -> int:
        return self._counts[(face, reason)]


#: the process's one set of totals
TOTALS = Totals()


@dataclass(frozen=True, slots=True)
class Limits:
    """How many clients one listening face serves and how long it waits for them (``None``:
    no bound). ``max_clients_per_host`` defaults to three quarters of ``max_clients`` (at
    least 1): a host with several legitimate clients (a SCADA server, a browser's six
    connections) is served, and a quarter of the slots stays for the others whatever one host
    opens."""

    max_clients: int | None = 64
    max_clients_per_host: int | None = None
    first_request_timeout: float | None = FIRST_REQUEST_TIMEOUT
    idle_timeout: float | None = 600.0

    def __post_init__(self) -> None:
        total, per_host = self.max_clients, self.max_clients_per_host
        for name, value in (("max_clients", total), ("max_clients_per_host", per_host)):
            if value is not None and (isinstance(value, bool) or value < 1):
                raise ValueError(f"{name} must be at least 1, not {value!r}")
        if per_host is None and total is not None:
            object.__setattr__(self, "max_clients_per_host", max(1, total - total // 4))
        elif per_host is not None and total is not None and per_host > total:
            raise ValueError(
                f"max_clients_per_host ({per_host}) cannot be more than max_clients ({total})"
            )
        for name in ("first_request_timeout", "idle_timeout"):
            seconds = getattr(self, name)
            if seconds is not None and not 0 < seconds < 1e9:
                raise ValueError(f"{name} must be seconds greater than 0, not {seconds!r}")

    def describe(self) -> str:
        """The limits in a sentence, as the face's start line says them."""
        parts = []
        if self.max_clients is not None:
            parts.append(
                f"at most {self.max_clients} clients, {self.max_clients_per_host} per host"
            )
        if self.first_request_timeout is not None:
            parts.append(f"a first request within {self.first_request_timeout:g} s")
        parts.append(
            "idle clients kept"
            if self.idle_timeout is None
            else f"idle clients closed after {self.idle_timeout:g} s"
        )
        return "; ".join(parts)


def parse_limits(t: Table, defaults: Limits, *, total_key: str = "max_clients") -> Limits:
    """The :data:`LIMIT_KEYS` of a face's table over ``defaults`` (durations as every table
    takes them, ``0`` turns a timeout off); :class:`ConfigError` naming ``[table] key``.
    ``total_key``: how the table names the clients at once (``[[gateway]]``:
    ``max_connections``, read by its own parser into ``defaults``)."""
    total = defaults.max_clients
    if "max_clients" in t:
        total = t.integer("max_clients", 1, 1, 10_000)
    per_host = defaults.max_clients_per_host if "max_clients" not in t else None
    if "max_clients_per_host" in t:
        per_host = t.integer("max_clients_per_host", 1, 1, 10_000)
    timeouts: dict[str, float | None] = {}
    for key, off in (("first_request_timeout", "no limit"), ("idle_timeout", "never")):
        default = getattr(defaults, key)
        if key in t:
            timeouts[key] = t.seconds(key, 0.0, hi=1e9, zero=off) or None
        else:
            timeouts[key] = default
    if total is not None and per_host is not None and per_host > total:
        raise t.error(
            "max_clients_per_host", f"({per_host}) cannot be more than {total_key} ({total})"
        )
    return Limits(total, per_host, timeouts["first_request_timeout"], timeouts["idle_timeout"])


class BurstLog:
    """Says repeated events once per burst: the first of a key at once, then one line per
    :data:`BURST_PERIOD` with how many more came, and nothing once the key was quiet for a
    period. ``key`` is who and what (a host and a reason)."""

    def __init__(self, log: logging.Logger, period: float = BURST_PERIOD) -> None:
        self.log = log
        self.period = period
        #: key -> [events not said yet, events of this period, the summary's text, first time]
        self._bursts: collections.OrderedDict[tuple[str, str], list[Any]] = (
            collections.OrderedDict()
        )
        self._timer: asyncio.TimerHandle | None = None

    def event(self, key: tuple[str, str], first: str, more: str) -> None:
        """One event of ``key``. ``first`` is logged when it starts a burst; ``more`` (with
        ``{n}``, the count, and ``{since}``, when the burst began) when later ones are
        summed up."""
        burst = self._bursts.get(key)
        if burst is not None:
            burst[0] += 1
            burst[1] += 1
            burst[2] = more
            return
        self.log.warning("%s", first)
        self._bursts[key] = [0, 1, more, time.strftime("%H:%M:%S")]
        if len(self._bursts) > MAX_BURSTS:
            old_key = next(iter(self._bursts))
            self._say(self._bursts.pop(old_key))
        if self._timer is None:
            self._timer = asyncio.get_running_loop().call_later(self.period, self._tick)

    def flush(self) -> None:
        """Say every burst's unsaid count now (a face that stops)."""
        for burst in self._bursts.values():
            self._say(burst)
        self._bursts.clear()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _say(self, burst: list[Any]) -> None:
        if burst[0]:
            self.log.warning("%s", burst[2].format(n=burst[0], since=burst[3]))
            burst[0] = 0

    def _tick(self) -> None:
        self._timer = None
        for key in list(self._bursts):
            burst = self._bursts[key]
            quiet = burst[1] == 0
            self._say(burst)
            burst[1] = 0
            if quiet:
                del self._bursts[key]
        if self._bursts:
            self._timer = asyncio.get_running_loop().call_later(self.period, self._tick)


class FaceGuard:
    """The limits of one listening face (see the module): admits clients (:meth:`admit`),
    watches their first request and their silence (:class:`Visit`), counts and says what it
    refused and closed, and says a client's garbage once per burst (:meth:`malformed`).

    ``face`` is the face's label in ``/metrics`` (``modbus``, ``s5lan``...), ``title`` how the
    log names it ("Modbus server").
    """

    def __init__(self, face: str, title: str, limits: Limits, log: logging.Logger) -> None:
        self.face = face
        self.title = title
        self.limits = limits
        self.log = log
        self.bursts = BurstLog(log)
        #: connections served now, in all and by host
        self.current = 0
        self.hosts: collections.Counter[str] = collections.Counter()
        #: refusals and closes by reason, this face alone (:data:`TOTALS` has the process's)
        self.counts: collections.Counter[str] = collections.Counter()

    @property
    def refused(self) -> int:
        """Connections turned away at once (either cap)."""
        return self.counts["max_clients"] + self.counts["max_clients_per_host"]

    def announce(self, where: str) -> None:
        """The one INFO line of the face's start: where it listens and its limits."""
        self.log.info("%s on %s: %s", self.title, where, self.limits.describe())

    def admit(
        self, peername: Any, on_expire: Callable[[str], None] | None = None, *, idle: bool = True
    ) -> Visit | None:
        """A new connection from ``peername`` (a socket's ``getpeername()``): its
        :class:`Visit`, or None when a cap refuses it (counted and said; the caller closes
        it). ``on_expire(reason)`` is called when the visit's first-request or idle deadline
        passes (a protocol-callback server); a server that reads in a loop passes None and
        waits until :attr:`Visit.due`. ``idle=False``: the server keeps its own idle timeout
        (the visit watches the first request only)."""
        host = _host_of(peername)
        peer = peer_address(peername) or host
        limits = self.limits
        reason = None
        if limits.max_clients is not None and self.current >= limits.max_clients:
            reason = "max_clients"
        elif limits.max_clients_per_host is not None and (
            self.hosts[host] >= limits.max_clients_per_host
        ):
            reason = "max_clients_per_host"
        if reason is not None:
            self.ended(host, peer, reason, refused=True)
            return None
        self.current += 1
        self.hosts[host] += 1
        return Visit(self, host, peer, on_expire, idle)

    def ended(self, host: str, peer: str, reason: str, *, refused: bool = False) -> None:
        """Count a refusal or close for ``reason`` (a key of :data:`REASONS`) and say it once
        per host per burst."""
        self.counts[reason] += 1
        TOTALS.add(self.face, reason)
        limits = self.limits
        limit = {
            "max_clients": limits.max_clients,
            "max_clients_per_host": limits.max_clients_per_host,
            "first_request_timeout": limits.first_request_timeout,
            "idle_timeout": limits.idle_timeout,
            "frame_timeout": FRAME_TIMEOUT,
        }.get(reason)
        why = REASONS[reason].format(limit=limit if limit is not None else 0)
        verb = "refusing" if refused else "closed the connection of"
        self.bursts.event(
            (host, reason),
            f"{self.title}: {verb} {peer}: {why} (more from {host} are counted and said"
            f" once a minute)",
            f"{self.title}: {{n}} more connections of {host} {'refused' if refused else 'closed'}"
            f" since {{since}}: {why}",
        )

    def malformed(self, peer: str | None, host: str | None, what: str) -> None:
        """A client sent garbage (``what`` says how); said once per host per burst with the
        count of the rest. The caller decides whether the connection goes on."""
        host = host or peer or "?"
        self.counts["malformed"] += 1
        TOTALS.add(self.face, "malformed")
        self.bursts.event(
            (host, "malformed"),
            f"{self.title}: {peer or host} sent {what} (more from {host} are counted and said"
            " once a minute)",
            f"{self.title}: {{n}} more malformed requests from {host} since {{since}}",
        )

    def left(self, visit: Visit) -> None:
        """A visit ended (its connection closed)."""
        self.current -= 1
        left = self.hosts[visit.host] - 1
        if left > 0:
            self.hosts[visit.host] = left
        else:
            del self.hosts[visit.host]

    def close(self) -> None:
        """The face stops: say what bursts have not said yet."""
        self.bursts.flush()


class Visit:
    """One admitted connection's stay: its first-request and idle deadlines.

    The face calls :meth:`touch` when bytes arrive, :meth:`served` when a complete request
    was taken, and :meth:`leave` when the connection is gone. A loop-reading server waits
    for bytes until :attr:`due` and then asks :meth:`expired`; a protocol-callback server
    gets ``on_expire(reason)`` from one timer, re-armed only when it fires.
    """

    __slots__ = (
        "_gone",
        "_handle",
        "_idle",
        "_last",
        "_loop",
        "_started",
        "guard",
        "host",
        "on_expire",
        "peer",
        "served_once",
    )

    def __init__(
        self,
        guard: FaceGuard,
        host: str,
        peer: str,
        on_expire: Callable[[str], None] | None,
        idle: bool = True,
    ) -> None:
        self.guard = guard
        self._idle = idle
        self.host = host
        self.peer = peer
        self.on_expire = on_expire
        self.served_once = False
        self._gone = False
        self._loop = asyncio.get_running_loop()
        self._started = self._last = self._loop.time()
        self._handle: asyncio.TimerHandle | None = None
        self._arm()

    @property
    def due(self) -> float | None:
        """Loop time at which the visit ends unless a request (or, once served, any byte)
        comes first; None: never."""
        limits = self.guard.limits
        timeout = limits.idle_timeout if self._idle else None
        idle = None if timeout is None else self._last + timeout
        if self.served_once or limits.first_request_timeout is None:
            return idle
        first = self._started + limits.first_request_timeout
        return first if idle is None else min(first, idle)

    def touch(self) -> None:
        """Bytes arrived."""
        self._last = self._loop.time()

    def served(self) -> None:
        """A complete request was taken: the first-request deadline is met (its bytes were
        touched as they came)."""
        self.served_once = True

    def expired(self) -> str | None:
        """The reason the visit ends now (counted and said), or None if it is not due yet."""
        due = self.due
        if due is None or self._loop.time() < due:
            return None
        limits = self.guard.limits
        first = (
            not self.served_once
            and limits.first_request_timeout is not None
            and due == self._started + limits.first_request_timeout
        )
        reason = "first_request_timeout" if first else "idle_timeout"
        self.guard.ended(self.host, self.peer, reason)
        return reason

    def frame_late(self) -> None:
        """The face closes the connection: a frame begun was not complete in time."""
        self.guard.ended(self.host, self.peer, "frame_timeout")

    def malformed(self, what: str) -> None:
        """The client sent garbage: said once per host per burst (:meth:`FaceGuard.malformed`)."""
        self.guard.malformed(self.peer, self.host, what)

    def leave(self) -> None:
        """The connection is gone (idempotent)."""
        if self._gone:
            return
        self._gone = True
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None
        self.guard.left(self)

    def _arm(self) -> None:
        if self.on_expire is None:
            return
        due = self.due
        if due is not None:
            self._handle = self._loop.call_at(due, self._fire)

    def _fire(self) -> None:
        self._handle = None
        if self._gone:
            return
        reason = self.expired()
        if reason is None:
            self._arm()  # touched or served since: the deadline moved on
        elif self.on_expire is not None:
            self.on_expire(reason)


class GuardedProtocol(asyncio.Protocol):
    """The protocol of a server plcstack does not write (aiohttp's), behind a
    :class:`FaceGuard`: the guard admits the connection (``refuse`` answers one it turns away,
    else it is aborted), the first request counts as complete when ``request_end`` has come
    (an HTTP header's blank line), and everything else is the inner protocol's."""

    def __init__(
        self,
        guard: FaceGuard,
        inner: Callable[[], asyncio.Protocol],
        request_end: bytes,
        refuse: Callable[[asyncio.Transport], None] | None = None,
    ) -> None:
        self._guard = guard
        self._make = inner
        self._end = request_end
        self._refuse = refuse
        self._inner: asyncio.Protocol | None = None
        self._visit: Visit | None = None
        self._transport: asyncio.Transport | None = None
        self._tail = b""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        stream = cast(asyncio.Transport, transport)  # uvloop's are no subclasses of asyncio's
        self._visit = self._guard.admit(
            transport.get_extra_info("peername"), self._expired, idle=False
        )
        if self._visit is None:
            if self._refuse is not None:
                self._refuse(stream)
            else:
                stream.abort()
            return
        self._transport = stream
        self._inner = self._make()
        self._inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        inner, visit = self._inner, self._visit
        if inner is None or visit is None:
            return
        if not visit.served_once:
            seen = self._tail + data
            if self._end in seen:
                visit.served()
                self._tail = b""
            else:
                self._tail = seen[-(len(self._end) - 1) :] if len(self._end) > 1 else b""
        visit.touch()
        inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self._inner.eof_received() if self._inner is not None else None

    def connection_lost(self, exc: Exception | None) -> None:
        if self._visit is not None:
            self._visit.leave()
        if self._inner is not None:
            self._inner.connection_lost(exc)

    def pause_writing(self) -> None:
        if self._inner is not None:
            self._inner.pause_writing()

    def resume_writing(self) -> None:
        if self._inner is not None:
            self._inner.resume_writing()

    def _expired(self, reason: str) -> None:
        if self._transport is not None:
            self._transport.abort()


def earliest(*times: float | None) -> float | None:
    """The earliest of some deadlines (loop times; None: that one does not run), or None."""
    running = [t for t in times if t is not None]
    return min(running) if running else None


def _host_of(peername: Any) -> str:
    """The host part of a socket's peer name (the key of the per-host cap)."""
    if isinstance(peername, tuple | list) and peername:
        return str(peername[0])
    if isinstance(peername, str) and peername:
        return peername
    return "?"


async def close_writer(writer: asyncio.StreamWriter) -> None:
    """Close a client's stream and take how it ended.

    asyncio keeps the end of a connection (a reset by the peer, say) in a future that only
    ``wait_closed()`` reads. Left unread, the garbage collector may report it as "Future
    exception was never retrieved" (whether it does depends on the order it frees things in):
    noise that reads like a fault of the server. A peer that reads nothing would hold the
    close for ever (the answer still queued), so after :data:`CLOSE_LINGER` seconds the
    connection is aborted. A cancel while closing (the server stops) aborts too and ends
    normally, as the handlers that call this end on a cancel.
    """
    writer.close()
    try:
        async with asyncio.timeout(CLOSE_LINGER):
            await writer.wait_closed()
    except (ConnectionError, OSError):
        pass  # the peer reset or left: the outcome is read, nothing more to do
    except (TimeoutError, asyncio.CancelledError):
        writer.transport.abort()
        with contextlib.suppress(ConnectionError, OSError, asyncio.CancelledError):
            await writer.wait_closed()


class FrameDeadline:
    """When the frame being received must be complete: ``limit`` seconds after its first byte.

    Call :meth:`note` after each chunk with whether part of a frame is still buffered. A server
    that reads in a loop waits until :attr:`due`; a protocol-callback server passes
    ``on_expire``, called once when a frame is still incomplete at its deadline.
    """

    __slots__ = ("_handle", "_loop", "limit", "on_expire", "started")

    def __init__(self, limit: float | None, on_expire: Callable[[], None] | None = None) -> None:
        self.limit = limit
        self.on_expire = on_expire
        self.started: float | None = None
        self._loop = asyncio.get_running_loop()
        self._handle: asyncio.TimerHandle | None = None

    @property
    def due(self) -> float | None:
        """Loop time at which the frame begun must be complete (None: no frame begun)."""
        if self.started is None or self.limit is None:
            return None
        return self.started + self.limit

    def note(self, buffered: bool) -> None:
        """Part of a frame is buffered (its clock starts now if it did not run), or none is."""
        if not buffered:
            self.started = None
            self.cancel()
        elif self.started is None:
            self.started = self._loop.time()
            if self.on_expire is not None and self.limit is not None:
                self._handle = self._loop.call_later(self.limit, self._fire)

    def cancel(self) -> None:
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None

    def _fire(self) -> None:
        self._handle = None
        if self.on_expire is not None:
            self.on_expire()
