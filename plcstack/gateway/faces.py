"""The native faces of one PLC, on its one connection: what ``[[gateway]]`` and ``plcstack
gateway`` start.

Each face is one listening server in a protocol of the PLC's family (:class:`FaceSettings`):
``s5lan`` and ``fetchwrite`` (optionally in the Tani MK header) in front of an S5 PLC (an AS511
port, an S5-LAN module, a FETCH/WRITE CP), ``as511`` (the programming port on TCP, for an
engineer's PG software) in front of an AS511 port, ``e71`` (TCP or UDP, binary or ASCII) in
front of an E71. :class:`PlcFaces` runs all the faces of one PLC on one
:class:`~plcstack.clients.share.SharedConnection` of the PLC's client (the poller's, or the
gateway command's own): one bounded fair queue beside the scans, one write allow-list per face,
every write told to ``on_write``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final, Literal

from plcstack.clients.as511 import AS511Client
from plcstack.clients.base import Client
from plcstack.clients.e71 import E71Client
from plcstack.clients.share import (
    DEFAULT_MAX_WAIT,
    DEFAULT_QUEUE_SIZE,
    SharedConnection,
    ShareStats,
)
from plcstack.errors import AddressError
from plcstack.gateway import as511face, e71server
from plcstack.gateway.allow import DeviceAllowList, WriteAllowList
from plcstack.gateway.as511face import As511Executor
from plcstack.gateway.e71face import E71Executor
from plcstack.gateway.record import FaceWrite, WriteHook
from plcstack.gateway.s5backends import backend_for
from plcstack.gateway.store import ClientStore
from plcstack.resource import AsyncResource
from plcstack.sim import fetchwrite as fetchwrite_server
from plcstack.sim import s5lan as s5lan_server
from plcstack.sim.base import (
    DEFAULT_IDLE_TIMEOUT,
    DEFAULT_MAX_CONNECTIONS,
    Limits,
    Simulator,
    TcpSimulator,
)

__all__ = [
    "PROTOCOLS",
    "FaceSettings",
    "FacesApplied",
    "GatewayFaces",
    "PlcFaces",
    "check_fit",
]

log = logging.getLogger("plcstack.gateway")

Protocol = Literal["s5lan", "fetchwrite", "e71", "as511"]
#: the protocols a face speaks
PROTOCOLS: Final[tuple[Protocol, ...]] = ("s5lan", "fetchwrite", "e71", "as511")
#: clients at once of each face, unless its settings say otherwise
DEFAULT_CONNECTIONS: Final[dict[Protocol, int]] = {
    "s5lan": 8,
    "fetchwrite": DEFAULT_MAX_CONNECTIONS,
    "e71": e71server.DEFAULT_MAX_CONNECTIONS,
    "as511": as511face.DEFAULT_MAX_CONNECTIONS,
}
#: what answers a face's clients: an S5 store, the E71 or the AS511 executor
Answering = ClientStore | E71Executor | As511Executor


@dataclass(frozen=True)
class FaceSettings:
    """One native face: its protocol, where it listens, the PLC it stands in front of, what its
    clients may write (the allow-list grammar of the PLC's family; nothing by default), and the
    protocol's options (``mk`` for FETCH/WRITE, ``transport`` and ``code`` for E71)."""

    protocol: Protocol
    host: str
    port: int
    plc: str
    writable: str = ""
    mk: bool = False
    transport: Literal["tcp", "udp"] = "tcp"
    code: Literal["binary", "ascii"] = "binary"
    #: clients at once (None: the protocol's default)
    max_connections: int | None = None
    #: requests that may wait for the PLC's connection, from all its faces (None: the
    #: default, 32) and the seconds one may wait (None: 2); faces of one PLC share them
    queue: int | None = None
    max_wait: float | None = None
    #: the face guard's limits (:data:`~plcstack.transports.guard.LIMIT_KEYS`), replacing
    #: ``max_connections``; None: ``max_connections`` clients, three quarters of them from one
    #: host, a first request within 10 s, idle clients closed after 600 s
    limits: Limits | None = None

    def __post_init__(self) -> None:
        if self.queue is not None and self.queue < 1:
            raise AddressError(f"queue {self.queue} must be at least 1")
        if self.protocol not in PROTOCOLS:
            raise AddressError(f"a face speaks {', '.join(PROTOCOLS)}, not {self.protocol!r}")
        if self.mk and self.protocol != "fetchwrite":
            raise AddressError("mk (the Tani MK header) is a FETCH/WRITE option")
        if self.protocol != "e71" and (self.transport != "tcp" or self.code != "binary"):
            raise AddressError("transport and code are options of the e71 face")
        if self.max_connections is not None and self.max_connections < 1:
            raise AddressError(f"max_connections {self.max_connections} must be at least 1")
        self.allow_list()  # a bad writable is an error before anything listens

    @property
    def connections(self) -> int:
        return self.max_connections or DEFAULT_CONNECTIONS[self.protocol]

    @property
    def guard_limits(self) -> Limits:
        """What the face's guard allows its clients (see ``limits``)."""
        if self.limits is not None:
            return self.limits
        return Limits(self.connections, idle_timeout=DEFAULT_IDLE_TIMEOUT)

    def allow_list(self) -> WriteAllowList | DeviceAllowList:
        """``writable`` parsed in the grammar of the face's PLC family."""
        if self.protocol == "e71":
            return DeviceAllowList.parse(self.writable)
        return WriteAllowList.parse(self.writable)

    def describe(self) -> str:
        """``s5lan face of kiln1`` (``e71 face (udp, ascii) of press2``)."""
        extra = ""
        if self.protocol == "e71":
            extra = f" ({self.transport}, {self.code})"
        elif self.mk:
            extra = " (MK)"
        return f"{self.protocol} face{extra} of {self.plc}"


def check_fit(name: str, client: Client, faces: Sequence[FaceSettings]) -> None:
    """Each of ``faces`` can stand in front of ``client`` (the PLC ``name``): an S5 face of
    an S5 PLC, an AS511 face of an AS511 port, an E71 face of an E71; :class:`AddressError`
    naming the PLC otherwise."""
    if any(f.protocol != "e71" for f in faces):
        backend_for(client)  # an S5 face needs an S5 PLC: AddressError naming it
    if any(f.protocol == "as511" for f in faces) and not isinstance(client, AS511Client):
        raise AddressError(f"{name}: an AS511 face needs an AS511 PLC (as511:, as511+tcp:)")
    if any(f.protocol == "e71" for f in faces) and not isinstance(client, E71Client):
        raise AddressError(f"{name}: an E71 face needs an E71 PLC (e71+tcp: or e71+udp:)")


def _family_key(face: FaceSettings) -> tuple[str, str]:
    """Faces with the same key answer from one store or executor."""
    family = face.protocol if face.protocol in ("e71", "as511") else "s5"
    return family, str(face.allow_list())


@dataclass(frozen=True, slots=True)
class ClosedFace:
    """A face closed by a change: its settings and the clients it had then."""

    face: FaceSettings
    clients: int


@dataclass(frozen=True, slots=True)
class StartedFace:
    """A face started by a change, or (``error``: why) one that could not listen."""

    face: FaceSettings
    error: str | None


class PlcFaces(AsyncResource):
    """Every face of one PLC on one shared connection of ``client``; ``aopen`` starts them
    (a port taken is an ``OSError`` naming nothing started), ``aclose`` stops them. It never
    closes ``client``: that belongs to the poller (or to whoever made it)."""

    def __init__(
        self,
        name: str,
        client: Client,
        faces: Sequence[FaceSettings],
        *,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        max_wait: float = DEFAULT_MAX_WAIT,
        cache_max_age: float | None = None,
        read_previous: bool = False,
        on_write: WriteHook | None = None,
    ) -> None:
        if not faces:
            raise AddressError(f"{name}: no face to serve")
        check_fit(name, client, faces)
        self.name = name
        #: the faces, in the order given (after :meth:`start_missing`: those that listen)
        self.settings = tuple(faces)
        self.share = SharedConnection(client, name=name, queue_size=queue_size, max_wait=max_wait)
        self.cache_max_age = cache_max_age
        self.read_previous = read_previous
        self.on_write = on_write
        #: each face's store (S5) or executor (E71): its allow-list, its write record; faces
        #: of one family with the same allow-list share one (an S5 read cache serves both)
        self._shared: dict[tuple[str, str], Answering] = {}
        self.answering: list[Answering] = [self._answering_of(face) for face in faces]
        #: the running servers, in the order of ``settings``
        self.servers: list[Simulator] = []

    def _answering_of(self, face: FaceSettings) -> Answering:
        """The store or executor ``face`` answers from: the one of a face of its family with
        the same allow-list, or a new one."""
        key = _family_key(face)
        if key not in self._shared:
            self._shared[key] = self._answering(face)
        return self._shared[key]

    def _answering(self, face: FaceSettings) -> Answering:
        allow = face.allow_list()
        if face.protocol == "as511":
            assert isinstance(allow, WriteAllowList)
            return As511Executor(
                self.share,
                writable=allow,
                on_write=self.on_write,
                read_previous=self.read_previous,
            )
        if isinstance(allow, DeviceAllowList):
            return E71Executor(
                self.share,
                writable=allow,
                on_write=self.on_write,
                read_previous=self.read_previous,
            )
        return ClientStore(
            self.share,
            writable=allow,
            cache_max_age=self.cache_max_age,
            read_previous=self.read_previous,
            on_write=self.on_write,
        )

    async def aopen(self) -> None:
        """Start the queue and every face; the first face that cannot listen closes those
        started and raises its ``OSError``."""
        await self._begin(strict=True)

    async def open_each(self) -> list[StartedFace]:
        """Start the queue and every face, as :meth:`aopen` does, except that a face that
        cannot listen is returned with why (and not kept) while the others go on."""
        return await self._begin(strict=False)

    async def _begin(self, *, strict: bool) -> list[StartedFace]:
        await self.share.aopen()
        faces = list(zip(self.settings, self.answering, strict=True))
        self.settings, self.answering = (), []
        try:
            return await self._start_each(faces, strict=strict)
        except BaseException:
            await self.aclose()
            raise

    async def _start_each(
        self, faces: Sequence[tuple[FaceSettings, Answering]], *, strict: bool
    ) -> list[StartedFace]:
        started = []
        for face, answering in faces:
            try:
                server = await self._listen(face, answering)
            except OSError as exc:
                if strict:
                    raise
                started.append(StartedFace(face, f"{exc.strerror or exc}"))
                continue
            self.settings = (*self.settings, face)
            self.answering.append(answering)
            self.servers.append(server)
            started.append(StartedFace(face, None))
        return started

    async def aclose(self) -> None:
        servers, self.servers = self.servers, []
        for server in servers:
            await server.aclose()
        await self.share.aclose()

    async def _listen(self, face: FaceSettings, answering: Answering) -> Simulator:
        server = await _start(face, answering)
        # its limits: the line of its guard (plcstack.transports.guard)
        log.info(
            "%s listening on %s (%s); writable: %s",
            face.describe(),
            server.url,
            face.transport.upper(),
            face.allow_list(),
        )
        return server

    # -- changed while it runs (a reload) ---------------------------------------------------
    async def close_except(self, keep: Sequence[FaceSettings]) -> list[ClosedFace]:
        """Close every running face whose settings are not among ``keep`` (its clients see
        their connection closed); the others keep listening and keep their clients. Returns
        what was closed, with the clients each had."""
        wanted = list(keep)
        kept: list[tuple[FaceSettings, Answering, Simulator]] = []
        closing: list[tuple[FaceSettings, Simulator]] = []
        for face, answering, server in zip(
            self.settings, self.answering, self.servers, strict=True
        ):
            if face in wanted:
                wanted.remove(face)
                kept.append((face, answering, server))
            else:
                closing.append((face, server))
        self.settings = tuple(k[0] for k in kept)
        self.answering = [k[1] for k in kept]
        self.servers = [k[2] for k in kept]
        self._shared = {}
        for face, answering in zip(self.settings, self.answering, strict=True):
            self._shared.setdefault(_family_key(face), answering)
        closed = []
        for face, server in closing:
            clients = server.connection_count.current if isinstance(server, TcpSimulator) else 0
            await server.aclose()
            closed.append(ClosedFace(face, clients))
        return closed

    async def start_missing(self, faces: Sequence[FaceSettings]) -> list[StartedFace]:
        """Start every face of ``faces`` that is not running (after :meth:`close_except` of
        the same ``faces``: those that are new or changed). A face that cannot listen is
        returned with the reason and not kept; the others go on. ``AddressError`` before
        anything starts for a face that does not fit the PLC."""
        check_fit(self.name, self.share.client, faces)
        running = list(self.settings)
        missing = []
        for face in faces:
            if face in running:
                running.remove(face)
            else:
                missing.append((face, self._answering_of(face)))
        return await self._start_each(missing, strict=False)


async def _start(face: FaceSettings, answering: Answering) -> Simulator:
    """The server of one face, answering from its store or executor."""
    if isinstance(answering, As511Executor):
        return await as511face.start(
            answering, host=face.host, port=face.port, limits=face.guard_limits
        )
    if isinstance(answering, E71Executor):
        return await e71server.start(
            answering,
            host=face.host,
            port=face.port,
            transport=face.transport,
            code=face.code,
            limits=face.guard_limits,
        )
    if face.protocol == "s5lan":
        return await s5lan_server.start(
            host=face.host, port=face.port, store=answering, limits=face.guard_limits
        )
    return await fetchwrite_server.start(
        host=face.host,
        port=face.port,
        store=answering,
        mk=face.mk,
        limits=face.guard_limits,
    )


@dataclass(frozen=True, slots=True)
class FacesApplied:
    """What :meth:`GatewayFaces.apply` did: each face it touched as ``s5lan face of kiln1 on
    127.0.0.1:2000 (TCP)``; ``failed``: a face that could not listen, with why."""

    started: tuple[str, ...] = ()
    #: closed and started again on the same address (its entry changed, or its PLC's
    #: connection or queue did): its clients saw their connection closed
    restarted: tuple[str, ...] = ()
    closed: tuple[str, ...] = ()
    failed: tuple[str, ...] = ()
    #: faces that went on listening with their clients
    kept: int = 0

    def summary(self) -> str:
        """One line for the log of a reload: ``faces: 1 started, 0 restarted, ...``."""
        text = ", ".join(
            f"{len(lines)} {what}" + (f" ({'; '.join(lines)})" if lines else "")
            for what, lines in (
                ("started", self.started),
                ("restarted", self.restarted),
                ("closed", self.closed),
            )
        )
        text = f"faces: {text}, {self.kept} kept"
        if self.failed:
            text += f"; cannot listen: {'; '.join(self.failed)}"
        return text


class GatewayFaces(AsyncResource):
    """Every face of a run: a :class:`PlcFaces` per PLC with faces, on the PLC's client
    (``client_of(name)``: the poller's, looked up again by :meth:`apply`). ``on_write(plc,
    write)`` is told of each write; ``cache_max_age``: the S5 faces' read cache (see
    :class:`~plcstack.gateway.store.ClientStore`; off by default). No face at all is fine: a
    reload may add some."""

    def __init__(
        self,
        faces: Sequence[FaceSettings],
        client_of: Callable[[str], Client],
        *,
        cache_max_age: float | None = None,
        read_previous: bool = False,
        on_write: Callable[[str, FaceWrite], None] | None = None,
    ) -> None:
        self.client_of = client_of
        self.cache_max_age = cache_max_age
        self.read_previous = read_previous
        self.on_write = on_write
        self.settings = tuple(faces)
        self.plcs: list[PlcFaces] = [
            self._plc(name, settings) for name, settings in _by_plc(faces).items()
        ]
        self._changing = asyncio.Lock()
        #: the queue counts of each PLC's faces that a reload closed or started afresh
        self._before: list[tuple[str, ShareStats]] = []
        #: a PLC's face queue that ended by itself (never by a close): what :meth:`watch` says
        self._ended: asyncio.Future[tuple[str, asyncio.Task[None]]] | None = None

    def _plc(self, name: str, settings: Sequence[FaceSettings]) -> PlcFaces:
        """The faces of one PLC on its client now (AddressError: one does not fit it)."""
        queue = next((f.queue for f in settings if f.queue is not None), DEFAULT_QUEUE_SIZE)
        wait = next((f.max_wait for f in settings if f.max_wait is not None), DEFAULT_MAX_WAIT)
        hook = None if self.on_write is None else functools.partial(self.on_write, name)
        return PlcFaces(
            name,
            self.client_of(name),
            settings,
            queue_size=queue,
            max_wait=wait,
            cache_max_age=self.cache_max_age,
            read_previous=self.read_previous,
            on_write=hook,
        )

    @property
    def workers(self) -> list[asyncio.Task[None]]:
        """The task of each PLC's queue now (see :meth:`watch`, which follows reloads)."""
        return [p.share.worker for p in self.plcs if p.share.worker is not None]

    async def watch(self) -> None:
        """Until cancelled, across every :meth:`apply`: raises :class:`RuntimeError` naming
        the PLC when one of their face queues ends by itself (a defect; its faces would answer
        nothing more), so whoever runs the faces ends the run saying it."""
        if self._ended is None:
            self._ended = asyncio.get_running_loop().create_future()
            for plc in self.plcs:
                self._follow(plc)
        name, task = await asyncio.shield(self._ended)
        exc = task.exception()
        why = f"{type(exc).__name__}: {exc}" if exc is not None else "it ended"
        raise RuntimeError(f"the face queue of {name} stopped ({why})") from exc

    def _follow(self, plc: PlcFaces) -> None:
        worker = plc.share.worker
        if worker is not None and self._ended is not None:
            worker.add_done_callback(functools.partial(self._worker_ended, plc.name))

    def _worker_ended(self, name: str, task: asyncio.Task[None]) -> None:
        if task.cancelled() or self._ended is None or self._ended.done():
            return  # closed by its faces: not a failure
        self._ended.set_result((name, task))

    def listening(self) -> list[str]:
        """``s5lan face of kiln1 listening on 127.0.0.1:2000 (TCP)``, one line per face."""
        return [
            f"{face.describe()} listening on {server.host}:{server.port} ({face.transport.upper()})"
            for plc in self.plcs
            for face, server in zip(plc.settings, plc.servers, strict=True)
        ]

    def summary(self) -> list[str]:
        """One line per PLC with faces: its queue's counts (first those of faces a reload
        closed or started afresh, until then)."""
        lines = []
        every = [(f"{name} (until a reload)", s) for name, s in self._before]
        for name, s in [*every, *((plc.name, plc.share.stats) for plc in self.plcs)]:
            lines.append(
                f"faces of {name}: {s.executed} requests on its connection, busy {s.busy},"
                f" waited too long {s.expired}, client gone {s.skipped}, most waiting"
                f" {s.queue_peak}"
            )
        return lines

    async def aopen(self) -> None:
        try:
            for plc in self.plcs:
                await plc.aopen()
                self._follow(plc)
        except BaseException:
            await self.aclose()
            raise

    async def aclose(self) -> None:
        for plc in self.plcs:
            await plc.aclose()

    async def apply(self, faces: Sequence[FaceSettings]) -> FacesApplied:
        """Run ``faces`` (a reloaded file's ``[[gateway]]``, checked by :func:`check_faces`)
        instead of the faces running now; call it after the poller applied the same reload.

        A face whose settings did not change keeps listening and keeps its clients. A face
        whose entry changed is closed (its clients see their connection closed) and started
        again; so is every face of a PLC whose connection the poller made anew (its URL or a
        connection option changed) or whose ``queue`` or ``max_wait`` changed. A face whose
        entry (or PLC) is gone closes; a new entry starts. Each is said once in the log, at
        WARNING where clients were cut off. A face that cannot listen (its port taken) is
        said at ERROR and returned in ``failed``; the rest is applied, and the next apply of
        the same file tries it again. :class:`AddressError` if a face does not fit its PLC
        (nothing changed then); ``KeyError`` if ``client_of`` does not know a PLC.
        """
        async with self._changing:
            return await self._apply(tuple(faces))

    async def _apply(self, faces: tuple[FaceSettings, ...]) -> FacesApplied:
        wanted = _by_plc(faces)
        current = {plc.name: plc for plc in self.plcs}
        # everything that can fail, before anything changes
        fresh: dict[str, PlcFaces] = {}
        for name, settings in wanted.items():
            plc = current.get(name)
            if plc is None or not _same_queue(plc, settings, self.client_of(name)):
                fresh[name] = self._plc(name, settings)
            else:
                check_fit(name, plc.share.client, settings)
        # close: whole PLCs that go or start afresh, then the faces not kept
        closed: list[ClosedFace] = []
        for name, plc in current.items():
            if name not in wanted or name in fresh:
                closed.extend(ClosedFace(f, n) for f, n in _clients_of(plc))
                await plc.aclose()
                self._before.append((name, plc.share.stats))
        for name, plc in current.items():
            if name in wanted and name not in fresh:
                closed.extend(await plc.close_except(wanted[name]))
        # start: the new and changed faces of the PLCs kept, then the new PLCs' faces
        started: list[StartedFace] = []
        plcs: list[PlcFaces] = []
        kept = 0
        for name, settings in wanted.items():
            plc = fresh.get(name) or current[name]
            if name in fresh:
                started.extend(await plc.open_each())
                self._follow(plc)
            else:
                kept += len(plc.servers)
                started.extend(await plc.start_missing(settings))
            plcs.append(plc)
        self.plcs = plcs
        self.settings = faces
        return _said(closed, started, kept=kept)


def _by_plc(faces: Sequence[FaceSettings]) -> dict[str, list[FaceSettings]]:
    by_plc: dict[str, list[FaceSettings]] = {}
    for face in faces:
        by_plc.setdefault(face.plc, []).append(face)
    return by_plc


def _same_queue(plc: PlcFaces, settings: Sequence[FaceSettings], client: Client) -> bool:
    """Whether ``plc``'s running faces can take ``settings``: the same client (the poller did
    not connect it anew) and the same queue."""
    queue = next((f.queue for f in settings if f.queue is not None), DEFAULT_QUEUE_SIZE)
    wait = next((f.max_wait for f in settings if f.max_wait is not None), DEFAULT_MAX_WAIT)
    share = plc.share
    return share.client is client and share.queue_size == queue and share.max_wait == wait


def _clients_of(plc: PlcFaces) -> list[tuple[FaceSettings, int]]:
    return [
        (face, server.connection_count.current if isinstance(server, TcpSimulator) else 0)
        for face, server in zip(plc.settings, plc.servers, strict=True)
    ]


def _where(face: FaceSettings) -> str:
    return f"{face.describe()} on {face.host}:{face.port} ({face.transport.upper()})"


def _said(closed: list[ClosedFace], started: list[StartedFace], *, kept: int) -> FacesApplied:
    """Pair what closed with what started on the same address (a restart), log each once and
    make the result."""
    at = {(s.face.transport, s.face.host, s.face.port): s for s in started if s.face.port}
    restarted, gone, failed = [], [], []
    paired: set[int] = set()
    for c in closed:
        cut = f"; its {c.clients} clients' connections closed" if c.clients else ""
        again = at.get((c.face.transport, c.face.host, c.face.port))
        if again is not None and id(again) not in paired:
            paired.add(id(again))
            changed = _changed(c.face, again.face)
            if again.error is None:
                restarted.append(_where(again.face))
                level = logging.WARNING if c.clients else logging.INFO
                log.log(level, "%s restarted (%s)%s", _where(again.face), changed, cut)
                continue
        gone.append(_where(c.face))
        log.log(logging.WARNING if c.clients else logging.INFO, "%s closed%s", _where(c.face), cut)
    new = []
    for s in started:
        if s.error is not None:
            failed.append(f"{_where(s.face)}: {s.error}")
            log.error("%s cannot listen: %s; not serving", _where(s.face), s.error)
        elif id(s) not in paired:
            new.append(_where(s.face))
            log.info("%s started", _where(s.face))
    return FacesApplied(tuple(new), tuple(restarted), tuple(gone), tuple(failed), kept)


def _changed(old: FaceSettings, new: FaceSettings) -> str:
    """``its entry changed: writable, plc`` or why an unchanged entry restarted."""
    before, after = dataclasses.asdict(old), dataclasses.asdict(new)
    keys = [key for key in before if before[key] != after[key]]
    if keys:
        return f"its [[gateway]] entry changed: {', '.join(keys)}"
    return f"the connection or the queue of {new.plc} changed"
