"""A software S5-LAN module: S5-LAN-LINK and FETCH/WRITE served from an S5 on its programming port.

The hardware S5-LAN module is an AS511 gateway; so is this. One AS511 link to the CPU
(``as511:///dev/ttyUSB0`` or ``as511+tcp://device-server:port``), and on the network the same
S5-LAN and FETCH/WRITE servers the simulators use, executing their requests on the real CPU
through :class:`~plcstack.gateway.store.As511Store` instead of on a memory image::

    async with await plcstack.gateway.start(
        "as511:///dev/ttyUSB0", s5lan=("127.0.0.1", 5010), fetchwrite=("127.0.0.1", 5030),
        writable="DB10-20, M",
    ) as gw:
        await gw.serve_forever()

Binds 127.0.0.1 unless told otherwise; nothing is writable until ``writable`` names it.
"""

from __future__ import annotations

import asyncio
from typing import Any

from plcstack.clients import connect
from plcstack.clients.as511 import AS511Client
from plcstack.errors import AddressError
from plcstack.gateway.allow import WriteAllowList
from plcstack.gateway.store import As511Store, GatewayStats
from plcstack.resource import AsyncResource
from plcstack.sim import fetchwrite as fetchwrite_server
from plcstack.sim import s5lan as s5lan_server
from plcstack.sim.base import TcpSimulator

__all__ = ["As511Store", "Gateway", "GatewayStats", "WriteAllowList", "start"]

#: network connections the S5-LAN side accepts at once (the hardware module: 1)
DEFAULT_S5LAN_CONNECTIONS = 8


class Gateway(AsyncResource):
    """A running gateway: ``store`` (queue, cache, statistics) and the servers in front of it."""

    def __init__(
        self,
        store: As511Store,
        s5lan: s5lan_server.S5LanSimulator | None,
        fetchwrite: fetchwrite_server.FetchWriteSimulator | None,
    ) -> None:
        self.store = store
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
        await self.store.aclose()


async def start(
    plc: str | AS511Client,
    *,
    s5lan: tuple[str, int] | None = None,
    fetchwrite: tuple[str, int] | None = None,
    mk: bool = False,
    writable: str | WriteAllowList = "",
    queue_size: int = 32,
    max_wait: float = 2.0,
    cache_max_age: float | None = None,
    s5lan_connections: int = DEFAULT_S5LAN_CONNECTIONS,
    **client_options: Any,
) -> Gateway:
    """Start a gateway in front of ``plc`` (an ``as511:``/``as511+tcp:`` URL or a client).

    ``s5lan``/``fetchwrite``: (host, port) to serve on (port 0 = any free port; at least one);
    ``mk`` wraps FETCH/WRITE in the Tani header; ``writable``: see
    :class:`~plcstack.gateway.allow.WriteAllowList` (default: nothing); ``queue_size``,
    ``max_wait`` and ``cache_max_age``: see :class:`As511Store`.
    """
    if s5lan is None and fetchwrite is None:
        raise AddressError("a gateway needs --s5lan and/or --fetchwrite to serve on")
    allow = writable if isinstance(writable, WriteAllowList) else WriteAllowList.parse(writable)
    if isinstance(plc, AS511Client):
        client = plc
    else:
        made = connect(plc, **client_options)
        if not isinstance(made, AS511Client):
            raise AddressError(f"{plc}: the gateway needs an as511: or as511+tcp: URL")
        client = made
    store = As511Store(
        client,
        writable=allow,
        queue_size=queue_size,
        max_wait=max_wait,
        cache_max_age=cache_max_age,
    )
    await store.aopen()
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
        await store.aclose()
        raise
    return Gateway(store, lan, fw)
