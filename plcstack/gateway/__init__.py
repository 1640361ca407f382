"""A software S5-LAN module: S5-LAN-LINK and FETCH/WRITE served from any S5 PLC.

The hardware S5-LAN module is an AS511 gateway; so is this, and more: in front of one S5 PLC
(its programming port ``as511:///dev/ttyUSB0`` or ``as511+tcp://device-server:port``, an
S5-LAN module ``s5lan://``, a FETCH/WRITE CP ``fetchwrite://``), the same S5-LAN and
FETCH/WRITE servers the simulators use, executing their requests on the PLC through
:class:`~plcstack.gateway.store.ClientStore` instead of on a memory image::

    async with await plcstack.gateway.start(
        "as511:///dev/ttyUSB0", s5lan=("127.0.0.1", 5010), fetchwrite=("127.0.0.1", 5030),
        writable="DB10-20, M",
    ) as gw:
        await gw.serve_forever()

Binds 127.0.0.1 unless told otherwise; nothing is writable until ``writable`` names it. The
same faces run beside the poller in ``plcstack poll`` (``[[gateway]]``), sharing the PLC's one
connection with the scans.
"""

from __future__ import annotations

import asyncio
from typing import Any

from plcstack.clients import connect
from plcstack.clients.base import Client
from plcstack.clients.share import SharedConnection
from plcstack.errors import AddressError
from plcstack.gateway.allow import WriteAllowList
from plcstack.gateway.record import WriteHook
from plcstack.gateway.store import ClientStore, GatewayStats
from plcstack.resource import AsyncResource
from plcstack.sim import fetchwrite as fetchwrite_server
from plcstack.sim import s5lan as s5lan_server
from plcstack.sim.base import TcpSimulator

__all__ = ["ClientStore", "Gateway", "GatewayStats", "WriteAllowList", "start"]

#: network connections the S5-LAN side accepts at once (the hardware module: 1)
DEFAULT_S5LAN_CONNECTIONS = 8


class Gateway(AsyncResource):
    """A running gateway: ``store`` (cache, statistics), the queue of the PLC's connection
    (``share``) and the servers in front of them. It owns its PLC client and closes it."""

    def __init__(
        self,
        store: ClientStore,
        s5lan: s5lan_server.S5LanSimulator | None,
        fetchwrite: fetchwrite_server.FetchWriteSimulator | None,
    ) -> None:
        self.store = store
        self.share = store.share
        self.s5lan = s5lan
        self.fetchwrite = fetchwrite

    @property
    def stats(self) -> GatewayStats:
        return self.store.stats

    @property
    def servers(self) -> list[TcpSimulator]:
        return [s for s in (self.s5lan, self.fetchwrite) if s is not None]

    async def serve_forever(self) -> None:
        """Serve until cancelled, then close."""
        try:
            await asyncio.Event().wait()
        finally:
            await self.aclose()

    async def aclose(self) -> None:
        for server in self.servers:
            await server.aclose()
        await self.share.aclose()
        await self.share.client.aclose()


async def start(
    plc: str | Client,
    *,
    s5lan: tuple[str, int] | None = None,
    fetchwrite: tuple[str, int] | None = None,
    mk: bool = False,
    writable: str | WriteAllowList = "",
    queue_size: int = 32,
    max_wait: float = 2.0,
    cache_max_age: float | None = None,
    s5lan_connections: int = DEFAULT_S5LAN_CONNECTIONS,
    read_previous: bool = False,
    on_write: WriteHook | None = None,
    **client_options: Any,
) -> Gateway:
    """Start a gateway in front of ``plc`` (an S5 PLC's URL, or its client).

    ``s5lan``/``fetchwrite``: (host, port) to serve on (port 0 = any free port; at least one);
    ``mk`` wraps FETCH/WRITE in the Tani header; ``writable``: see
    :class:`~plcstack.gateway.allow.WriteAllowList` (default: nothing); ``queue_size`` and
    ``max_wait``: see :class:`~plcstack.clients.share.SharedConnection`; ``cache_max_age``,
    ``read_previous`` and ``on_write`` (told of every write attempt): see :class:`ClientStore`.
    """
    if s5lan is None and fetchwrite is None:
        raise AddressError("a gateway needs --s5lan and/or --fetchwrite to serve on")
    allow = writable if isinstance(writable, WriteAllowList) else WriteAllowList.parse(writable)
    client = plc if isinstance(plc, Client) else connect(plc, **client_options)
    try:
        share = SharedConnection(client, queue_size=queue_size, max_wait=max_wait)
        store = ClientStore(
            share,
            writable=allow,
            cache_max_age=cache_max_age,
            read_previous=read_previous,
            on_write=on_write,
        )
    except AddressError:
        await client.aclose()
        raise
    await share.aopen()
    lan = fw = None
    try:
        if s5lan is not None:
            lan = await s5lan_server.start(
                host=s5lan[0], port=s5lan[1], store=store, max_connections=s5lan_connections
            )
        if fetchwrite is not None:
            fw = await fetchwrite_server.start(
                host=fetchwrite[0], port=fetchwrite[1], store=store, mk=mk
            )
    except BaseException:
        if lan is not None:
            await lan.aclose()
        await share.aclose()
        await client.aclose()
        raise
    return Gateway(store, lan, fw)
