"""Native faces of one PLC: a software S5-LAN module, or more E71 connections.

The hardware S5-LAN module is an AS511 gateway; so is this, and more: in front of one S5 PLC
(its programming port ``as511:///dev/ttyUSB0`` or ``as511+tcp://device-server:port``, an
S5-LAN module ``s5lan://``, a FETCH/WRITE CP ``fetchwrite://``), the same S5-LAN and
FETCH/WRITE servers the simulators use, executing their requests on the PLC through
:class:`~plcstack.gateway.store.ClientStore` instead of on a memory image; in front of an E71
(``e71+tcp://``, ``e71+udp://``), an E71 face in either code and on either transport::

    async with await plcstack.gateway.start(
        "as511:///dev/ttyUSB0", s5lan=("127.0.0.1", 5010), fetchwrite=("127.0.0.1", 5030),
        writable="DB10-20, M",
    ) as gw:
        await gw.serve_forever()

Binds 127.0.0.1 unless told otherwise; nothing is writable until ``writable`` names it. It is
a shortcut for one PLC and its faces: the options become ``[[gateway]]`` entries
(:func:`faces_of`) run by the same :class:`~plcstack.gateway.faces.GatewayFaces` that serves
them beside the poller in ``plcstack poll``, sharing the PLC's one connection with the scans.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, Literal

from plcstack.clients import connect
from plcstack.clients.base import Client
from plcstack.clients.share import SharedConnection
from plcstack.errors import AddressError
from plcstack.gateway.allow import DeviceAllowList, WriteAllowList
from plcstack.gateway.as511face import As511Executor
from plcstack.gateway.e71face import E71Executor
from plcstack.gateway.faces import DEFAULT_CONNECTIONS, FaceSettings, GatewayFaces, PlcFaces
from plcstack.gateway.record import FaceWrite
from plcstack.gateway.store import ClientStore, GatewayStats
from plcstack.resource import AsyncResource
from plcstack.sim.base import Simulator
from plcstack.sim.fetchwrite import FetchWriteSimulator
from plcstack.sim.s5lan import S5LanSimulator

__all__ = [
    "ClientStore",
    "DeviceAllowList",
    "E71Executor",
    "FaceSettings",
    "Gateway",
    "GatewayFaces",
    "GatewayStats",
    "PlcFaces",
    "WriteAllowList",
    "faces_of",
    "start",
]

#: network connections the S5-LAN side accepts at once (the hardware module: 1)
DEFAULT_S5LAN_CONNECTIONS = DEFAULT_CONNECTIONS["s5lan"]

Endpoint = tuple[str, int]


class Gateway(AsyncResource):
    """A running gateway: the faces of its PLC (``natives``: every face as ``[[gateway]]``
    runs them; ``faces``: those of its one PLC, with the queue of the PLC's connection, each
    face's store or executor, the servers). It owns its PLC client and closes it."""

    def __init__(self, natives: GatewayFaces) -> None:
        self.natives = natives
        (self.faces,) = natives.plcs
        self.share: SharedConnection = self.faces.share
        servers = self.faces.servers
        answering = self.faces.answering
        #: the S5-LAN and the FETCH/WRITE server, if it serves them
        self.s5lan = next((s for s in servers if isinstance(s, S5LanSimulator)), None)
        self.fetchwrite = next((s for s in servers if isinstance(s, FetchWriteSimulator)), None)
        #: the S5 faces' store (None in front of an E71)
        self.store = next((a for a in answering if isinstance(a, ClientStore)), None)
        #: the E71 faces' executor (None in front of an S5 PLC)
        self.executor = next((a for a in answering if isinstance(a, E71Executor)), None)
        #: the AS511 face's executor (None without one)
        self.pg = next((a for a in answering if isinstance(a, As511Executor)), None)

    @property
    def stats(self) -> GatewayStats:
        """The S5 faces' counters (zeros in front of an E71: see ``executor.counts``)."""
        return self.store.stats if self.store is not None else GatewayStats()

    @property
    def servers(self) -> list[Simulator]:
        return list(self.faces.servers)

    async def serve_forever(self) -> None:
        """Serve until cancelled, then close; raises if the queue of the PLC's connection
        stops by itself."""
        try:
            await self.natives.watch()
        finally:
            await self.aclose()

    async def aclose(self) -> None:
        await self.natives.aclose()
        await self.share.client.aclose()


def faces_of(
    plc: str,
    *,
    s5lan: Endpoint | None = None,
    fetchwrite: Endpoint | None = None,
    mk: bool = False,
    e71: Endpoint | None = None,
    e71_udp: Endpoint | None = None,
    e71_code: Literal["binary", "ascii"] = "binary",
    as511: Endpoint | None = None,
    writable: str = "",
    queue_size: int | None = None,
    max_wait: float | None = None,
    s5lan_connections: int | None = None,
) -> list[FaceSettings]:
    """The ``[[gateway]]`` entries that :func:`start`'s options (and ``plcstack gateway``'s)
    stand for, each face of the PLC named ``plc`` (None: the entry leaves the key out, so
    the face has the default); :class:`AddressError` without any."""
    faces: list[FaceSettings] = []
    face = functools.partial(FaceSettings, writable=writable, queue=queue_size, max_wait=max_wait)
    if s5lan is not None:
        faces.append(face("s5lan", *s5lan, plc, max_connections=s5lan_connections))
    if fetchwrite is not None:
        faces.append(face("fetchwrite", *fetchwrite, plc, mk=mk))
    if e71 is not None:
        faces.append(face("e71", *e71, plc, code=e71_code))
    if e71_udp is not None:
        faces.append(face("e71", *e71_udp, plc, transport="udp", code=e71_code))
    if as511 is not None:
        faces.append(face("as511", *as511, plc))
    if not faces:
        raise AddressError("a gateway needs --s5lan and/or --fetchwrite (or --e71) to serve on")
    return faces


async def start(
    plc: str | Client,
    *,
    s5lan: Endpoint | None = None,
    fetchwrite: Endpoint | None = None,
    mk: bool = False,
    e71: Endpoint | None = None,
    e71_udp: Endpoint | None = None,
    e71_code: Literal["binary", "ascii"] = "binary",
    as511: Endpoint | None = None,
    writable: str = "",
    queue_size: int | None = None,
    max_wait: float | None = None,
    cache_max_age: float | None = None,
    s5lan_connections: int | None = None,
    read_previous: bool = False,
    on_write: Callable[[str, FaceWrite], None] | None = None,
    **client_options: Any,
) -> Gateway:
    """Start a gateway in front of ``plc`` (a PLC's URL, or its client).

    ``s5lan``/``fetchwrite`` (an S5 PLC), ``as511`` (an AS511 port: the PG's face) and
    ``e71``/``e71_udp`` (an E71): (host, port) to serve on (port 0 = any free port; at least
    one); ``mk`` wraps FETCH/WRITE in the Tani
    header, ``e71_code`` is the E71 face's code; ``writable``: the allow-list of the PLC's family
    (:class:`WriteAllowList`, :class:`DeviceAllowList`; default: nothing); ``queue_size`` and
    ``max_wait``: see :class:`~plcstack.clients.share.SharedConnection` (None: 32 requests,
    2 s); ``s5lan_connections``: the S5-LAN face's clients at once (None: 8); ``cache_max_age`` and
    ``read_previous``: see :class:`ClientStore`; ``on_write(plc, write)`` is told of every
    write attempt (``plcstack gateway`` and ``plcstack poll`` hand it to their write path).
    """
    name = plc if isinstance(plc, str) else plc.name
    faces = faces_of(
        name,
        s5lan=s5lan,
        fetchwrite=fetchwrite,
        mk=mk,
        e71=e71,
        e71_udp=e71_udp,
        e71_code=e71_code,
        as511=as511,
        writable=writable,
        queue_size=queue_size,
        max_wait=max_wait,
        s5lan_connections=s5lan_connections,
    )
    client = plc if isinstance(plc, Client) else connect(plc, **client_options)
    try:
        natives = GatewayFaces(
            faces,
            {name: client}.__getitem__,
            cache_max_age=cache_max_age,
            read_previous=read_previous,
            on_write=on_write,
        )
        await natives.aopen()
    except BaseException:
        await client.aclose()
        raise
    return Gateway(natives)
