"""UDP transport: one message per datagram, datagrams from other addresses ignored."""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from plcstack.transports.base import (
    ProtocolTransport,
    QueueProtocolMixin,
    open_with_timeout,
    watch_socket,
)
from plcstack.transports.tap import Tap, combined, endpoints_of

__all__ = ["UdpTransport"]


class _UdpProtocol(QueueProtocolMixin, asyncio.DatagramProtocol):
    _drop_when_full = True  # a datagram socket cannot push back: count and drop

    def __init__(self, peer: str) -> None:
        self._init_queue(peer)
        self.remote: tuple[str, int] | None = None

    def datagram_received(self, data: bytes, addr: tuple[str | bytes, int]) -> None:
        # A connected UDP socket already filters by source in the kernel; this check keeps the
        # promise also where the OS delivers anyway (and documents it).
        if self.remote is not None and (addr[0], addr[1]) != self.remote:
            return
        self._push(data)

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable shows up here: a dead E71 port, reported now instead of a timeout.
        self._fail(exc)

    def connection_lost(self, exc: Exception | None) -> None:
        self._fail(exc or EOFError("socket closed"))


class _TappedUdpProtocol(_UdpProtocol):
    """A recorded endpoint (:mod:`.tap`): each datagram from the peer is told to the tap."""

    def __init__(self, peer: str, tap: Tap) -> None:
        super().__init__(peer)
        self._tap = tap

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        self.wire = self._tap.connection(endpoints_of(transport, "udp", "local"))

    def datagram_received(self, data: bytes, addr: tuple[str | bytes, int]) -> None:
        wire = self.wire
        if wire is not None and (self.remote is None or (addr[0], addr[1]) == self.remote):
            wire.received(data)
        super().datagram_received(data, addr)

    def connection_lost(self, exc: Exception | None) -> None:
        wire, self.wire = self.wire, None
        if wire is not None:
            wire.ended(by_peer=False)
        super().connection_lost(exc)


class UdpTransport(ProtocolTransport):
    """A connected UDP socket to ``host:port``. ``abort()`` + ``open()`` gets a new local port,
    so a reply that arrives after a timeout can never be read as the answer to the next request."""

    _join = False  # one datagram is one message: never glue two together

    def __init__(self, host: str, port: int) -> None:
        super().__init__(f"{host}:{port}")
        self.host = host
        self.port = port

    async def open(self, timeout: float | None) -> None:
        self.abort()
        loop = asyncio.get_running_loop()
        tap = combined(self._tap)
        peer = self.peer
        factory: Callable[[], _UdpProtocol] = (
            (lambda: _UdpProtocol(peer)) if tap is None else (lambda: _TappedUdpProtocol(peer, tap))
        )
        transport, protocol = await open_with_timeout(
            peer,
            loop.create_datagram_endpoint(factory, remote_addr=(self.host, self.port)),
            timeout,
        )
        remote = transport.get_extra_info("peername")
        protocol.remote = (remote[0], remote[1]) if remote else None
        self._opened(transport, protocol, transport.sendto)
        self._watch = watch_socket(transport)
