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
import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final, Literal

from plcstack.checks import Listen, Table
from plcstack.clients.as511 import AS511Client
from plcstack.clients.base import Client
from plcstack.clients.e71 import E71Client
from plcstack.clients.share import DEFAULT_MAX_WAIT, DEFAULT_QUEUE_SIZE, SharedConnection
from plcstack.errors import AddressError, ConfigError
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
from plcstack.sim.base import DEFAULT_IDLE_TIMEOUT, DEFAULT_MAX_CONNECTIONS, Limits, Simulator
from plcstack.transports.guard import parse_limits

__all__ = ["PROTOCOLS", "FaceSettings", "GatewayFaces", "PlcFaces", "check_faces", "parse_gateway"]

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
        self.name = name
        self.settings = tuple(faces)
        self.share = SharedConnection(client, name=name, queue_size=queue_size, max_wait=max_wait)
        if any(f.protocol != "e71" for f in faces):
            backend_for(client)  # an S5 face needs an S5 PLC: AddressError naming it
        if any(f.protocol == "as511" for f in faces) and not isinstance(client, AS511Client):
            raise AddressError(f"{name}: an AS511 face needs an AS511 PLC (as511:, as511+tcp:)")
        if any(f.protocol == "e71" for f in faces) and not isinstance(client, E71Client):
            raise AddressError(f"{name}: an E71 face needs an E71 PLC (e71+tcp: or e71+udp:)")
        self.cache_max_age = cache_max_age
        self.read_previous = read_previous
        self.on_write = on_write
        #: each face's store (S5) or executor (E71): its allow-list, its write record; faces
        #: of one family with the same allow-list share one (an S5 read cache serves both)
        shared: dict[tuple[str, str], Answering] = {}
        self.answering: list[Answering] = []
        for face in faces:
            family = face.protocol if face.protocol in ("e71", "as511") else "s5"
            key = (family, str(face.allow_list()))
            if key not in shared:
                shared[key] = self._answering(face)
            self.answering.append(shared[key])
        #: the running servers, in the order of ``faces``
        self.servers: list[Simulator] = []

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
        await self.share.aopen()
        try:
            for face, answering in zip(self.settings, self.answering, strict=True):
                server = await _start(face, answering)
                self.servers.append(server)
                # its limits: the line of its guard (plcstack.transports.guard)
                log.info(
                    "%s listening on %s (%s); writable: %s",
                    face.describe(),
                    server.url,
                    face.transport.upper(),
                    face.allow_list(),
                )
        except BaseException:
            await self.aclose()
            raise

    async def aclose(self) -> None:
        servers, self.servers = self.servers, []
        for server in servers:
            await server.aclose()
        await self.share.aclose()


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


# -- [[gateway]]: the faces of the configuration file ----------------------------------------------
#: the URL schemes of the PLCs each face can stand in front of
_SCHEMES: Final[dict[Protocol, tuple[str, ...]]] = {
    "s5lan": ("as511", "as511+tcp", "s5lan", "fetchwrite"),
    "fetchwrite": ("as511", "as511+tcp", "s5lan", "fetchwrite"),
    "as511": ("as511", "as511+tcp"),
    "e71": ("e71+tcp", "e71+udp"),
}
_TRANSPORTS: Final[tuple[Literal["tcp", "udp"], ...]] = ("tcp", "udp")
_TCP: Final[Literal["tcp", "udp"]] = "tcp"
_CODES: Final[tuple[Literal["binary", "ascii"], ...]] = ("binary", "ascii")
_BINARY: Final[Literal["binary", "ascii"]] = "binary"
_KEYS: Final = (
    "protocol",
    "listen",
    "plc",
    "writable",
    "mk",
    "transport",
    "code",
    "max_connections",
    "max_clients_per_host",
    "first_request_timeout",
    "idle_timeout",
    "queue",
    "max_wait",
)


def parse_gateway(table: Table) -> FaceSettings:
    """One ``[[gateway]]`` table: a native face of a PLC of the same file (which PLC exists,
    and that the face fits it, :func:`check_faces` says once the PLCs are read)::

        [[gateway]]
        protocol = "s5lan"           # "s5lan" | "fetchwrite" | "e71" | "as511"
        listen = "0.0.0.0:2000"
        plc = "kiln1"                # a [[plc]] of this file
        writable = "DB10-20, M"      # nothing writable by default
        # max_connections, max_clients_per_host, first_request_timeout, idle_timeout: the
        # face guard's limits (plcstack.transports.guard)
    """
    table.keys(_KEYS)
    if "protocol" not in table:
        raise table.error(None, f"needs protocol = one of {', '.join(PROTOCOLS)}")
    protocol = table.choice("protocol", PROTOCOLS[0], PROTOCOLS)
    if "listen" not in table:
        raise table.error(None, 'needs listen = "HOST:PORT" (where the face listens)')
    listen = table.listen(Listen("127.0.0.1", 0))
    writable = table.raw("writable", "")
    if not isinstance(writable, str):
        raise table.error("writable", f'must be a string such as "DB10-20, M", not {writable!r}')
    mk = table.boolean("mk", False)
    transport = table.choice("transport", _TCP, _TRANSPORTS)
    code = table.choice("code", _BINARY, _CODES)
    connections = (
        table.integer("max_connections", 1, 1, 4096) if "max_connections" in table else None
    )
    limits = None
    if any(k in table for k in ("max_clients_per_host", "first_request_timeout", "idle_timeout")):
        # the guard's keys; the face's clients at once are its max_connections
        total = connections or DEFAULT_CONNECTIONS[protocol]
        defaults = Limits(total, idle_timeout=DEFAULT_IDLE_TIMEOUT)
        limits = parse_limits(table, defaults, total_key="max_connections")
    queue = table.integer("queue", 1, 1, 65536) if "queue" in table else None
    max_wait = table.seconds("max_wait", 2.0, hi=3600.0) if "max_wait" in table else None
    plc = table.text("plc", "")
    try:  # what FaceSettings itself checks: writable's grammar, options of the wrong face
        return FaceSettings(
            protocol,
            listen.host,
            listen.port,
            plc,
            writable,
            mk=mk,
            transport=transport,
            code=code,
            max_connections=connections,
            limits=limits,
            queue=queue,
            max_wait=max_wait,
        )
    except AddressError as exc:
        key = next((k for k in ("writable", "mk", "transport", "code") if k in exc.message), None)
        message = exc.message
        if key is not None:  # said after the key: "[[gateway]] #2 mk ... is a FETCH/WRITE ..."
            message = message.removeprefix(f"{key}: ").removeprefix(f"{key} ")
        raise table.error(key, message) from None


def check_faces(faces: Sequence[FaceSettings], plcs: Sequence[tuple[str, str]]) -> None:
    """Every face names a PLC of the file (``(name, url)`` pairs) that it can stand in front
    of, no two faces listen on one address, and the faces of one PLC agree on its queue.
    :class:`ConfigError` naming the ``[[gateway]]`` (its key, for the line) otherwise."""
    urls = dict(plcs)
    listening: dict[tuple[str, str, int], int] = {}
    #: (PLC, key) -> (the value, the index of the face that gave it first)
    shared: dict[tuple[str, str], tuple[float, int]] = {}
    for index, face in enumerate(faces):
        where, path = f"[[gateway]] #{index + 1}", f"gateway[{index}]"
        url = urls.get(face.plc)
        if url is None:
            known = ", ".join(urls) or "none"
            raise ConfigError(
                f"{where} plc {face.plc!r} is no [[plc]] of this file (PLCs: {known})",
                key=f"{path}.plc",
            )
        scheme = url.partition("://")[0].lower()
        if scheme not in _SCHEMES[face.protocol]:
            raise ConfigError(
                f"{where}: a {face.protocol} face stands in front of "
                f"{' or '.join(_SCHEMES[face.protocol])} PLCs, and {face.plc} is {scheme}:",
                key=f"{path}.protocol",
            )
        at = (face.transport, face.host, face.port)
        if face.port and at in listening:
            raise ConfigError(
                f"{where} listens on {face.host}:{face.port} ({face.transport}) as "
                f"[[gateway]] #{listening[at] + 1} does",
                key=f"{path}.listen",
            )
        listening[at] = index
        for key, mine in (("queue", face.queue), ("max_wait", face.max_wait)):
            if mine is None:
                continue
            theirs, first = shared.setdefault((face.plc, key), (mine, index))
            if mine != theirs:
                raise ConfigError(
                    f"{where} {key} {mine:g} differs from [[gateway]] #{first + 1}'s "
                    f"({theirs:g}): the faces of {face.plc} share one queue",
                    key=f"{path}.{key}",
                )


class GatewayFaces(AsyncResource):
    """Every face of a run: a :class:`PlcFaces` per PLC with faces, on the PLC's client
    (``client_of(name)``: the poller's). ``on_write(plc, write)`` is told of each write."""

    def __init__(
        self,
        faces: Sequence[FaceSettings],
        client_of: Callable[[str], Client],
        *,
        read_previous: bool = False,
        on_write: Callable[[str, FaceWrite], None] | None = None,
    ) -> None:
        by_plc: dict[str, list[FaceSettings]] = {}
        for face in faces:
            by_plc.setdefault(face.plc, []).append(face)
        self.plcs: list[PlcFaces] = []
        for name, settings in by_plc.items():
            queue = next((f.queue for f in settings if f.queue is not None), DEFAULT_QUEUE_SIZE)
            wait = next((f.max_wait for f in settings if f.max_wait is not None), DEFAULT_MAX_WAIT)
            hook = None if on_write is None else functools.partial(on_write, name)
            self.plcs.append(
                PlcFaces(
                    name,
                    client_of(name),
                    settings,
                    queue_size=queue,
                    max_wait=wait,
                    read_previous=read_previous,
                    on_write=hook,
                )
            )

    @property
    def workers(self) -> list[asyncio.Task[None]]:
        """The task of each PLC's queue (watched: one that ends ends the run)."""
        return [p.share.worker for p in self.plcs if p.share.worker is not None]

    def listening(self) -> list[str]:
        """``s5lan face of kiln1 listening on 127.0.0.1:2000 (TCP)``, one line per face."""
        return [
            f"{face.describe()} listening on {server.host}:{server.port} ({face.transport.upper()})"
            for plc in self.plcs
            for face, server in zip(plc.settings, plc.servers, strict=True)
        ]

    def summary(self) -> list[str]:
        """One line per PLC with faces: its queue's counts."""
        lines = []
        for plc in self.plcs:
            s = plc.share.stats
            lines.append(
                f"faces of {plc.name}: {s.executed} requests on its connection, busy {s.busy},"
                f" waited too long {s.expired}, client gone {s.skipped}, most waiting"
                f" {s.queue_peak}"
            )
        return lines

    async def aopen(self) -> None:
        try:
            for plc in self.plcs:
                await plc.aopen()
        except BaseException:
            await self.aclose()
            raise

    async def aclose(self) -> None:
        for plc in self.plcs:
            await plc.aclose()
