"""Simulated E71 connection bound to fixed buffers (spec §8), with the PLC program's side as API.

One simulator = one E71 connection (its own local port, as on the module, §1.1) used for fixed
buffer communication, with procedure (60H telegrams / E0H answers, binary or ASCII) or without
(raw bytes, always binary), over TCP or UDP::

    sim = await start_fixed_buffer(code="ascii")          # with procedure, TCP
    words = await sim.receive()     # the PLC program takes a telegram -> the E71 answers E0 00
    end = await sim.send([1, 2, 3]) # the PLC program sends; returns the partner's end code

* Partner -> PLC: a telegram is stored in the receive buffer; the answer ``E0 00`` goes out only
  when the PLC program takes it with :meth:`FixedBufferSimulator.receive` ("received data taken",
  §8.1); until then further telegrams wait unread. Malformed telegrams are answered at once with
  50H/52H/54H and not stored.
* PLC -> partner: :meth:`FixedBufferSimulator.send` waits for ``E0`` + end code; an end code other
  than 00H is recorded as error 62H, no answer within ``ack_timeout`` as error 70H (§8.1, stored in
  :attr:`FixedBufferSimulator.errors`, the error log of the connection status area).
* TCP: one partner at a time (a second connection is closed). UDP: the partner is the source of
  the last datagram received (§13 A14) unless ``partner`` is given; without procedure
  ``broadcast=(ADDRESS, PORT)`` sends every PLC message there (partner IP FFFFFFFFH, §8.3).
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Sequence
from typing import Any, Literal, cast

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import Code
from plcstack.codecs.e71_buffers import (
    FixedBufferAck,
    FixedBufferConnection,
    FixedBufferData,
    FixedBufferError,
    RawBufferConnection,
)
from plcstack.errors import RemoteProtocolError
from plcstack.sim.base import Simulator, bound_address

__all__ = ["FixedBufferSimulator", "start_fixed_buffer"]

Message = tuple[int, ...] | bytes


#: bytes of received messages the simulated E71 holds for its PLC program before it stops
#: reading the partner (the real module has a fixed receive buffer area)
INBOX_BYTES = 64 * 1024


def _size(message: Message) -> int:
    return len(message) if isinstance(message, bytes) else 2 * len(message)


class FixedBufferSimulator(Simulator):
    """One E71 fixed-buffer connection; the methods are the PLC program's side."""

    def __init__(self, code: Code, procedure: bool, transport: str, ack_timeout: float) -> None:
        self.code = code
        self.procedure = procedure
        self.transport_kind = transport
        self.ack_timeout = ack_timeout
        self.host = "127.0.0.1"
        self.port = 0
        self.url = ""
        #: stored error codes (62H partner end code != 0, 70H no answer), newest last
        self.errors: list[int] = []
        #: end code of the last answer received from the partner (buffer 95, 105, ...)
        self.partner_end_code: int | None = None
        self._inbox: asyncio.Queue[Message] = asyncio.Queue()
        #: bytes of the messages in the inbox; above INBOX_BYTES the partner is not read (TCP)
        #: or its datagrams are dropped (UDP) until the PLC program takes messages
        self.inbox_bytes = 0
        #: partner datagrams dropped because the inbox was full (UDP, without procedure)
        self.dropped = 0
        self._paused: _TcpConn | None = None
        self._ack_waiter: asyncio.Future[int] | None = None
        self._send_lock = asyncio.Lock()
        self._server: asyncio.Server | None = None
        self._tcp: _TcpConn | None = None
        self._udp: asyncio.DatagramTransport | None = None
        self._udp_codec: FixedBufferConnection | RawBufferConnection | None = None
        self.partner: tuple[str, int] | None = None
        self.broadcast: tuple[str, int] | None = None
        self._owed: _TcpConn | Literal["udp"] | None = None

    # -- the PLC program's side ---------------------------------------------------------------
    @property
    def connected(self) -> bool:
        return self._tcp is not None or (self._udp is not None and self.partner is not None)

    async def receive(self, timeout: float | None = None) -> Message:
        """Take the next message from the receive buffer; with procedure this is "received data
        taken": the E71 answers the partner ``E0 00`` now."""
        async with asyncio.timeout(timeout):
            message = await self._inbox.get()
        self.inbox_bytes -= _size(message)
        paused = self._paused
        if paused is not None and self.inbox_bytes <= INBOX_BYTES:
            self._paused = None
            if paused.transport is not None and not paused.transport.is_closing():
                paused.transport.resume_reading()
        self._acknowledge(0)
        return message

    def pending(self) -> int:
        """Messages received and not yet taken by :meth:`receive`."""
        return self._inbox.qsize()

    async def send(self, message: Sequence[int] | bytes) -> int:
        """Send from the PLC; with procedure wait for the partner's answer and return its end
        code (00H = taken). Raises ``TimeoutError`` (error 70H) without an answer, or
        ``ConnectionError`` with no partner."""
        async with self._send_lock:
            if self.procedure:
                words = tuple(message) if not isinstance(message, bytes) else None
                if words is None:
                    raise TypeError("with procedure the PLC sends words")
                codec = self._codec()
                if isinstance(codec, FixedBufferConnection):
                    codec.awaiting_ack = False  # a timed-out send is forgotten
                data = self._encode(words)
                loop = asyncio.get_running_loop()
                self._ack_waiter = loop.create_future()
                self._write(data)
                try:
                    async with asyncio.timeout(self.ack_timeout):
                        end = await self._ack_waiter
                except TimeoutError:
                    self.errors.append(0x70)
                    raise
                finally:
                    self._ack_waiter = None
                self.partner_end_code = end
                if end != 0:
                    self.errors.append(0x62)
                return end
            if not isinstance(message, bytes):
                raise TypeError("without procedure the PLC sends bytes")
            self._write(RawBufferConnection().send(message))
            return 0

    # -- plumbing ---------------------------------------------------------------------------------
    def _codec(self) -> FixedBufferConnection | RawBufferConnection:
        if self._tcp is not None:
            return self._tcp.codec
        if self._udp_codec is None:
            raise ConnectionError("no partner connected")
        return self._udp_codec

    def _encode(self, words: tuple[int, ...]) -> bytes:
        codec = self._codec()
        assert isinstance(codec, FixedBufferConnection)
        return codec.send_data(words)

    def _write(self, data: bytes) -> None:
        if self._tcp is not None and self._tcp.transport is not None:
            self._tcp.transport.write(data)
        elif self._udp is not None and self.broadcast is not None and not self.procedure:
            self._udp.sendto(data, self.broadcast)
        elif self._udp is not None and self.partner is not None:
            self._udp.sendto(data, self.partner)
        else:
            raise ConnectionError("no partner connected")

    def _acknowledge(self, end_code: int) -> None:
        owed, self._owed = self._owed, None
        if owed is None or not self.procedure:
            return
        if owed == "udp":
            codec = self._udp_codec
            assert isinstance(codec, FixedBufferConnection)
            if self.partner is not None and self._udp is not None:
                self._udp.sendto(codec.send_ack(end_code), self.partner)
            self._pump(codec)
        elif owed.transport is not None:
            assert isinstance(owed.codec, FixedBufferConnection)
            owed.transport.write(owed.codec.send_ack(end_code))
            owed.pump()

    def _event(
        self,
        event: FixedBufferData | FixedBufferAck | FixedBufferError | bytes,
        reply: Any,
        owner: _TcpConn | Literal["udp"],
    ) -> None:
        if isinstance(event, FixedBufferData):
            self._owed = owner
            self._hold(event.values, owner)
        elif isinstance(event, bytes):
            self._hold(event, owner)
        elif isinstance(event, FixedBufferAck):
            if self._ack_waiter is not None and not self._ack_waiter.done():
                self._ack_waiter.set_result(event.end_code)
        else:
            reply(FixedBufferConnection(self.code, role="e71").refuse(event))

    def _hold(self, message: Message, owner: _TcpConn | Literal["udp"]) -> None:
        """Queue a partner's message for the PLC program, within INBOX_BYTES: without procedure
        the partner sends at will, and a program that does not receive must not cost memory."""
        if self.inbox_bytes > INBOX_BYTES and owner == "udp":
            self.dropped += 1
            return
        # a TCP partner is paused below, so beyond the bound only the rest of one chunk arrives
        self._inbox.put_nowait(message)
        self.inbox_bytes += _size(message)
        if (
            self.inbox_bytes > INBOX_BYTES
            and isinstance(owner, _TcpConn)
            and owner.transport is not None
            and self._paused is None
        ):
            self._paused = owner
            owner.transport.pause_reading()

    def _pump(self, codec: FixedBufferConnection | RawBufferConnection) -> None:
        while True:
            event = codec.next_event()
            if event is NEED_DATA:
                return
            self._event(event, self._udp_reply, "udp")

    def _udp_reply(self, data: bytes) -> None:
        if self._udp is not None and self.partner is not None:
            self._udp.sendto(data, self.partner)

    async def aclose(self) -> None:
        if self._tcp is not None and self._tcp.transport is not None:
            self._tcp.transport.abort()
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
        if self._udp is not None:
            self._udp.close()


class _TcpConn(asyncio.Protocol):
    def __init__(self, sim: FixedBufferSimulator) -> None:
        self.sim = sim
        self.codec: FixedBufferConnection | RawBufferConnection = (
            FixedBufferConnection(sim.code, role="e71") if sim.procedure else RawBufferConnection()
        )
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport_: asyncio.BaseTransport) -> None:
        # cast, not isinstance: uvloop's transports are not subclasses of asyncio.Transport
        transport = cast(asyncio.Transport, transport_)
        if self.sim._tcp is not None:
            transport.abort()  # the E71 connection has one partner
            return
        self.transport = transport
        self.sim._tcp = self

    def data_received(self, data: bytes) -> None:
        if self.transport is None:
            return
        try:
            self.codec.receive_data(data)
        except RemoteProtocolError:
            # a partner that floods while its telegram waits for our answer: close, as the
            # codec holds no more than the procedure allows
            self.transport.abort()
            return
        self.pump()

    def pump(self) -> None:
        while self.transport is not None:
            event = self.codec.next_event()
            if event is NEED_DATA:
                return
            self.sim._event(event, self.transport.write, self)

    def connection_lost(self, exc: Exception | None) -> None:
        if self.sim._paused is self:
            self.sim._paused = None
        if self.sim._tcp is self:
            self.sim._tcp = None
            if self.sim._owed is self:
                self.sim._owed = None
        self.transport = None


class _UdpEndpoint(asyncio.DatagramProtocol):
    def __init__(self, sim: FixedBufferSimulator, fixed_partner: bool) -> None:
        self.sim = sim
        self.fixed_partner = fixed_partner

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        sim = self.sim
        if self.fixed_partner and sim.partner is not None and addr[:2] != sim.partner:
            return  # data from stations not registered for the connection are ignored (§8.1)
        sim.partner = (addr[0], addr[1])
        codec = sim._udp_codec
        assert codec is not None
        try:
            codec.receive_data(data)
        except RemoteProtocolError:
            return  # more datagrams than the procedure allows while an answer is owed: dropped
        sim._pump(codec)


async def start_fixed_buffer(
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    code: Code | Literal["binary", "ascii"] = "binary",
    transport: Literal["tcp", "udp"] = "tcp",
    procedure: bool = True,
    partner: tuple[str, int] | None = None,
    broadcast: tuple[str, int] | None = None,
    ack_timeout: float = 5.0,
) -> FixedBufferSimulator:
    """Start one fixed-buffer E71 connection; returns once partners can connect."""
    code_ = code if isinstance(code, Code) else Code(code)
    if not procedure:
        code_ = Code.BINARY  # §8.2: always binary
    sim = FixedBufferSimulator(code_, procedure, transport, ack_timeout)
    loop = asyncio.get_running_loop()
    if transport == "udp":
        sim._udp_codec = (
            FixedBufferConnection(code_, role="e71", transport="udp")
            if procedure
            else RawBufferConnection()
        )
        sim.partner = partner
        sim.broadcast = broadcast
        dtransport, _ = await loop.create_datagram_endpoint(
            lambda: _UdpEndpoint(sim, partner is not None), local_addr=(host, port)
        )
        if broadcast is not None:
            sock = dtransport.get_extra_info("socket")
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        sim._udp = dtransport
        sockname = dtransport.get_extra_info("sockname")
    else:
        server = await loop.create_server(lambda: _TcpConn(sim), host, port)
        sim._server = server
        sockname = server.sockets[0].getsockname()
    query = [f"code={code_.value}"] if code_ is Code.ASCII else []
    if not procedure:
        query.append("procedure=0")
    sim.host, sim.port, sim.url = bound_address(sockname, f"e71+{transport}", "&".join(query))
    return sim
