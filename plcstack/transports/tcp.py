"""TCP transport on an ``asyncio.BufferedProtocol``."""

from __future__ import annotations

import asyncio
import socket

from plcstack.errors import ConnectionLost
from plcstack.transports.base import (
    ProtocolTransport,
    QueueProtocolMixin,
    open_with_timeout,
    watch_socket,
)

__all__ = ["TcpTransport"]


#: bytes one receive takes at most; larger replies simply arrive in several chunks. Every reply
#: of our protocols but the largest FETCH/WRITE and S5-LAN ones fits in one.
RECEIVE_BUFFER = 4096


class _TcpProtocol(QueueProtocolMixin, asyncio.BufferedProtocol):
    """Receives into one small buffer per connection.

    With a plain ``Protocol`` the selector loop calls ``sock.recv(256 KiB)`` for every chunk: a
    256 KiB allocation per reply which, depending on the process's allocation history, costs
    ``mmap``/``munmap`` system calls each time (measured: 20-60 µs per request at 1000 PLCs, and
    the main source of noise between benchmark runs). ``recv_into`` a reused buffer avoids it.
    """

    def __init__(self, peer: str) -> None:
        self._init_queue(peer)
        self._buffer = memoryview(bytearray(RECEIVE_BUFFER))

    def get_buffer(self, sizehint: int) -> memoryview:
        return self._buffer

    def buffer_updated(self, nbytes: int) -> None:
        receiver = self._receiver
        if receiver is not None:  # a callback exchange's answer: straight to it (``_push``)
            receiver.chunk_received(bytes(self._buffer[:nbytes]))
        else:
            self._push(bytes(self._buffer[:nbytes]))

    def eof_received(self) -> bool | None:
        self._fail(EOFError("peer closed the connection"))
        return None

    def connection_lost(self, exc: Exception | None) -> None:
        self._fail(exc or EOFError("connection closed"))


class TcpTransport(ProtocolTransport):
    """One TCP connection to ``host:port``; ``open()`` again after a close reconnects."""

    def __init__(self, host: str, port: int) -> None:
        super().__init__(f"{host}:{port}")
        self.host = host
        self.port = port

    async def open(self, timeout: float | None) -> None:
        self.abort()
        loop = asyncio.get_running_loop()
        transport, protocol = await open_with_timeout(
            self.peer,
            loop.create_connection(lambda: _TcpProtocol(self.peer), self.host, self.port),
            timeout,
        )
        sock = transport.get_extra_info("socket")
        if sock is not None:
            # Requests are small and latency-bound: never let Nagle hold one back.
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._transport, self._protocol = transport, protocol
        self._watch = watch_socket(transport)

    def _send(self, data: bytes) -> None:
        self._transport.write(data)  # type: ignore[union-attr]

    async def aclose(self) -> None:
        self._watch = None
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
            transport.abort()  # type: ignore[attr-defined]
