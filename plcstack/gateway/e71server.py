"""The E71 face on the network: 1E frames over TCP (a connection per client) or UDP (a datagram
per request), binary or ASCII, each request answered by an :class:`E71Executor`.

TCP: requests of one connection are answered strictly one after another (the E71's rule); the
face's guard (:mod:`plcstack.transports.guard`) serves at most ``max_clients`` clients (three
quarters of them from one host), closes a connection that sends no request within
``first_request_timeout``, nothing for ``idle_timeout`` seconds or trickles a frame for longer
than a few seconds, counts what it refused and closed and says it once per host per burst, as
it says a client's garbage (bytes that are no E71 request); a client that stops reading its
answers is not read either. A client that goes away while its request waits gets the request
given up unsent. UDP: each datagram is one request, answered to its source address; each source
has its own line in the PLC's queue, and too many requests at once are answered "busy" without
a task.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
from typing import Any, Literal

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import BadRequest, Code, E71ServerConnection, ErrorResponse
from plcstack.codecs.e71_commands import DECODERS
from plcstack.codecs.e71_end_codes import GARBAGE_END_CODES
from plcstack.gateway.e71face import E71Executor, Event, Session, command_of
from plcstack.sim.base import (
    DEFAULT_IDLE_TIMEOUT,
    ClientGone,
    TcpSimulator,
    UdpSimulator,
    check_idle_timeout,
    close_writer,
)
from plcstack.transports.guard import FRAME_TIMEOUT, FaceGuard, FrameDeadline, Limits, earliest
from plcstack.transports.peer import peer_address

__all__ = ["DEFAULT_MAX_CONNECTIONS", "E71TcpFace", "E71UdpFace", "start"]

log = logging.getLogger("plcstack.gateway.e71")

#: face clients of one TCP face at once (the E71 itself: 8)
DEFAULT_MAX_CONNECTIONS = 32
#: UDP sources whose monitor registrations are kept (the longest unheard is forgotten)
UDP_SESSIONS = 1024


def _scheme(code: Code, transport: str) -> tuple[str, str]:
    return f"e71+{transport}", "code=ascii" if code is Code.ASCII else ""


class E71TcpFace(TcpSimulator):
    """A running E71 face on TCP; ``executor`` answers, ``guard`` counts what it refused and
    closed."""

    def __init__(
        self, server: asyncio.Server, executor: E71Executor, code: Code, guard: FaceGuard
    ) -> None:
        super().__init__(server, *_scheme(code, "tcp"), guard)
        self.executor = executor
        self.code = code
        #: requests received (answered or not)
        self.requests = 0

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        visit = self.guard.admit(writer.get_extra_info("peername"))
        if visit is None:
            writer.transport.abort()
            return
        task = asyncio.current_task()
        if task is not None:
            self.track(task)
        gone = ClientGone(reader, writer)
        codec = E71ServerConnection(self.code, extensions=DECODERS)
        session = Session()
        frame = FrameDeadline(FRAME_TIMEOUT)
        loop = asyncio.get_running_loop()
        try:
            while True:
                frame.note(codec.buffered > 0)
                due = frame.due
                try:
                    async with asyncio.timeout_at(earliest(due, visit.due)):
                        data = await reader.read(65536)
                except TimeoutError:
                    if due is not None and loop.time() >= due:
                        visit.frame_late()
                        return
                    if visit.expired() is not None:
                        return
                    continue
                if not data:
                    return
                visit.touch()
                codec.receive_data(data)
                while (event := codec.next_event()) is not NEED_DATA:
                    self.requests += 1
                    visit.served()
                    if isinstance(event, BadRequest) and event.end_code in GARBAGE_END_CODES:
                        visit.malformed(
                            f"a malformed request ({event.reason}; answered {event.end_code:02X}H)"
                        )
                    with gone.waiting():
                        answer = await self.executor.answer(event, session, visit.peer)
                    writer.write(codec.send(answer))
                    await writer.drain()  # a client that does not read is not read either
        except (ConnectionError, OSError, asyncio.CancelledError):
            return  # the client went away (or the face stops): nothing to answer
        finally:
            gone.close()
            visit.leave()
            await close_writer(writer)


class _Datagrams(asyncio.DatagramProtocol):
    def __init__(self, face: list[E71UdpFace]) -> None:
        self.face = face

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        if self.face:
            self.face[0].received(data, addr)


class E71UdpFace(UdpSimulator):
    """A running E71 face on UDP: one request per datagram, answered to its source."""

    def __init__(
        self, transport: asyncio.DatagramTransport, executor: E71Executor, code: Code
    ) -> None:
        super().__init__(transport, *_scheme(code, "udp"))
        self.executor = executor
        self.code = code
        self.codec = E71ServerConnection(code, transport="udp", extensions=DECODERS)
        self.sessions: collections.OrderedDict[str, Session] = collections.OrderedDict()
        self.tasks: set[asyncio.Task[None]] = set()
        #: requests at once beyond which a datagram is answered busy without a task
        self.max_pending = 2 * executor.share.queue_size
        self.busy = 0

    def received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self.codec.receive_data(data)
        event = self.codec.next_event()
        if event is NEED_DATA:  # pragma: no cover - a datagram is always one event
            return
        peer = peer_address(addr) or "?"
        if len(self.tasks) >= self.max_pending:
            self.busy += 1
            busy = ErrorResponse(command_of(event), 0x5B, 0x11)
            self.transport.sendto(self.codec.send(busy), addr)
            return
        session = self.sessions.pop(peer, None) or Session()
        self.sessions[peer] = session  # most recently heard last
        while len(self.sessions) > UDP_SESSIONS:
            self.sessions.popitem(last=False)
        task = asyncio.ensure_future(self._answer(event, session, peer, addr))
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    async def _answer(
        self, event: Event, session: Session, peer: str, addr: tuple[str | Any, int]
    ) -> None:
        try:
            answer = await self.executor.answer(event, session, peer)
        except asyncio.CancelledError:
            return
        if not self.transport.is_closing():
            self.transport.sendto(self.codec.send(answer), addr)

    async def aclose(self) -> None:
        await super().aclose()
        for task in list(self.tasks):
            task.cancel()
        if self.tasks:
            await asyncio.gather(*self.tasks, return_exceptions=True)


async def start(
    executor: E71Executor,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    transport: Literal["tcp", "udp"] = "tcp",
    code: Code | Literal["binary", "ascii"] = "binary",
    max_connections: int = DEFAULT_MAX_CONNECTIONS,
    idle_timeout: float | None = DEFAULT_IDLE_TIMEOUT,
    limits: Limits | None = None,
) -> E71TcpFace | E71UdpFace:
    """Serve the E71 face of ``executor``'s PLC on ``host:port`` (0: any free port).

    TCP: ``limits`` (the ``[[gateway]]`` table's keys) or ``max_connections`` clients, three
    quarters of them per host, and ``idle_timeout`` (see :mod:`plcstack.transports.guard`)."""
    code_ = code if isinstance(code, Code) else Code(code)
    if transport == "udp":
        holder: list[E71UdpFace] = []
        loop = asyncio.get_running_loop()
        dtransport, _ = await loop.create_datagram_endpoint(
            lambda: _Datagrams(holder), local_addr=(host, port)
        )
        udp = E71UdpFace(dtransport, executor, code_)
        holder.append(udp)
        return udp
    if transport != "tcp":
        raise ValueError(f"transport must be 'tcp' or 'udp', not {transport!r}")
    if limits is None:
        limits = Limits(max_clients=max_connections, idle_timeout=check_idle_timeout(idle_timeout))
    guard = FaceGuard("e71", f"E71 face {host}:{port}", limits, log)
    faces: list[E71TcpFace] = []

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(asyncio.CancelledError):
            await faces[0].handle(reader, writer)

    server = await asyncio.start_server(handle, host, port)
    face = E71TcpFace(server, executor, code_, guard)
    faces.append(face)
    return face
