"""The floor: the thinnest asyncio client that still does the same wire work as the stack.

A floor client writes pre-built request bytes and waits for exactly the known number of reply
bytes, on a bare ``asyncio.Protocol`` with one future per wait. No parsing, no validation in the
timed path (the warm-up compares one reply with the expected bytes), no deadlines, no locks. What
the stack adds on top of this (codec, typed API, single-flight lock, timeouts, error mapping) is
exactly what the stack/floor ratio prices.
"""

from __future__ import annotations

import asyncio
import socket
import struct
from typing import cast

from plcstack.bench.frames import FloorJob, ScriptJob

__all__ = ["FloorError", "FloorTcp", "FloorUdp", "open_floor"]


class FloorError(Exception):
    """The simulator did not answer as the spec says: the floor's numbers would be meaningless."""


class _StreamProtocol(asyncio.Protocol):
    def __init__(self) -> None:
        self.buf = bytearray()
        self.need = 0
        self.waiter: asyncio.Future[None] | None = None
        self.transport: asyncio.Transport | None = None
        self.lost: BaseException | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # a cast, not an isinstance check: uvloop's transports do not subclass asyncio.Transport
        self.transport = cast(asyncio.Transport, transport)

    def data_received(self, data: bytes) -> None:
        self.buf += data
        waiter = self.waiter
        if waiter is not None and len(self.buf) >= self.need and not waiter.done():
            waiter.set_result(None)

    def connection_lost(self, exc: Exception | None) -> None:
        self.lost = exc or ConnectionResetError("connection closed by the simulator")
        waiter = self.waiter
        if waiter is not None and not waiter.done():
            waiter.set_exception(FloorError(str(self.lost)))


class FloorTcp:
    """One TCP connection; :meth:`exchange` replays a job, :meth:`script` a dialogue."""

    def __init__(self, transport: asyncio.Transport, protocol: _StreamProtocol) -> None:
        self._transport = transport
        self._protocol = protocol
        self._seq = 0

    async def _receive(self, count: int) -> bytes:
        proto = self._protocol
        if len(proto.buf) < count:
            if proto.lost is not None:
                raise FloorError(str(proto.lost))
            proto.need = count
            proto.waiter = asyncio.get_running_loop().create_future()
            try:
                await proto.waiter
            finally:
                proto.waiter = None
        out = bytes(proto.buf[:count])
        del proto.buf[:count]
        return out

    async def exchange(self, job: FloorJob) -> bytes:
        request = job.request
        if job.mk_seq_offsets:
            patched = bytearray(request)
            for offset in job.mk_seq_offsets:
                struct.pack_into("<H", patched, offset, self._seq)
                self._seq = (self._seq + 1) & 0xFFFF
            request = bytes(patched)
        self._transport.write(request)
        return await self._receive(job.reply_len)

    async def script(self, job: ScriptJob) -> bytes:
        received = bytearray()
        for send, expect in job.steps:
            self._transport.write(send)
            if expect:
                received += await self._receive(expect)
        return bytes(received)

    async def run(self, job: FloorJob | ScriptJob) -> bytes:
        if isinstance(job, ScriptJob):
            return await self.script(job)
        return await self.exchange(job)

    async def aclose(self) -> None:
        self._transport.close()
        await asyncio.sleep(0)


class _DatagramProtocol(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.waiter: asyncio.Future[bytes] | None = None
        self.pending: list[bytes] = []

    def datagram_received(self, data: bytes, addr: tuple[str | bytes, int]) -> None:
        waiter = self.waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(data)
        else:
            self.pending.append(data)

    def error_received(self, exc: Exception) -> None:
        waiter = self.waiter
        if waiter is not None and not waiter.done():
            waiter.set_exception(FloorError(str(exc)))


class FloorUdp:
    """A connected UDP socket: one request datagram, one reply datagram."""

    def __init__(self, transport: asyncio.DatagramTransport, protocol: _DatagramProtocol) -> None:
        self._transport = transport
        self._protocol = protocol

    async def exchange(self, job: FloorJob) -> bytes:
        proto = self._protocol
        self._transport.sendto(job.request)
        if proto.pending:
            return proto.pending.pop(0)
        proto.waiter = asyncio.get_running_loop().create_future()
        try:
            return await proto.waiter
        finally:
            proto.waiter = None

    async def run(self, job: FloorJob | ScriptJob) -> bytes:
        if isinstance(job, ScriptJob):
            raise FloorError("a scripted dialogue needs a stream transport")
        return await self.exchange(job)

    async def aclose(self) -> None:
        self._transport.close()
        await asyncio.sleep(0)


async def open_floor(host: str, port: int, *, udp: bool = False) -> FloorTcp | FloorUdp:
    """Connect a floor client (TCP with TCP_NODELAY, as the stack's transport sets it)."""
    loop = asyncio.get_running_loop()
    if udp:
        dtransport, dprotocol = await loop.create_datagram_endpoint(
            _DatagramProtocol, remote_addr=(host, port)
        )
        return FloorUdp(dtransport, dprotocol)
    transport, protocol = await loop.create_connection(_StreamProtocol, host, port)
    sock = transport.get_extra_info("socket")
    if sock is not None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return FloorTcp(transport, protocol)
