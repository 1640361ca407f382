"""TCP transport on a plain ``asyncio.Protocol``."""

from __future__ import annotations

import asyncio
import socket

from plcstack.errors import ConnectionLost
from plcstack.transports.base import QueueProtocolMixin, Transport, open_with_timeout

__all__ = ["TcpTransport"]


class _TcpProtocol(QueueProtocolMixin, asyncio.Protocol):
    def __init__(self, peer: str) -> None:
        self._init_queue(peer)

    def data_received(self, data: bytes) -> None:
        self._push(data)

    def eof_received(self) -> bool | None:
        self._fail(EOFError("peer closed the connection"))
        return None

    def connection_lost(self, exc: Exception | None) -> None:
        self._fail(exc or EOFError("connection closed"))


class TcpTransport(Transport):
    """One TCP connection to ``host:port``; ``open()`` again after a close reconnects."""

    def __init__(self, host: str, port: int) -> None:
        self.host = host
        self.port = port
        self.peer = f"{host}:{port}"
        self._transport: asyncio.Transport | None = None
        self._protocol: _TcpProtocol | None = None

    @property
    def is_open(self) -> bool:
        return (
            self._transport is not None
            and self._protocol is not None
            and self._protocol._closed_exc is None
            and not self._transport.is_closing()
        )

    async def open(self, timeout: float | None) -> None:
        self.abort()
        loop = asyncio.get_running_loop()
        result = await open_with_timeout(
            self.peer,
            loop.create_connection(lambda: _TcpProtocol(self.peer), self.host, self.port),
            timeout,
        )
        transport, protocol = result
        sock = transport.get_extra_info("socket")
        if sock is not None:
            # Requests are small and latency-bound: never let Nagle hold one back.
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._transport, self._protocol = transport, protocol

    def write(self, data: bytes) -> None:
        if not self.is_open:
            raise ConnectionLost(f"not connected to {self.peer}")
        assert self._transport is not None
        self._transport.write(data)

    async def read(self) -> bytes:
        if self._protocol is None:
            raise ConnectionLost(f"not connected to {self.peer}")
        return await self._protocol._next_chunk(join=True)

    def discard_received(self) -> None:
        if self._protocol is not None:
            self._protocol._chunks.clear()

    def abort(self) -> None:
        if self._transport is not None:
            self._transport.abort()
        self._transport = None
        self._protocol = None

    async def aclose(self) -> None:
        transport, protocol = self._transport, self._protocol
        self._transport = None
        self._protocol = None
        if transport is None or protocol is None:
            return
        transport.close()
        # Give the close a moment to flush; a peer that never answers FIN must not hang us.
        try:
            async with asyncio.timeout(1.0):
                while protocol._closed_exc is None:
                    try:
                        await protocol._next_chunk(join=True)
                    except ConnectionLost:
                        break
        except TimeoutError:
            transport.abort()
