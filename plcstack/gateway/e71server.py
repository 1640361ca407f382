"""The E71 face on the network: 1E frames over TCP (a connection per client) or UDP (a datagram
per request), binary or ASCII, each request answered by an :class:`E71Executor`.

TCP: requests of one connection are answered strictly one after another (the E71's rule), a
connection that sends nothing for ``idle_timeout`` seconds or trickles a frame for longer than
a few seconds is closed, at most ``max_connections`` clients are served at once (the next is
turned away, counted and said once per burst), and a client that stops reading its answers is
not read either. A client that goes away while its request waits gets the request given up
unsent. UDP: each datagram is one request, answered to its source address; each source has its
own line in the PLC's queue, and too many requests at once are answered "busy" without a task.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
from typing import Any, Literal

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import Code, E71ServerConnection, ErrorResponse
from plcstack.codecs.e71_commands import DECODERS
from plcstack.gateway.e71face import E71Executor, Event, Session, command_of
from plcstack.sim.base import (
    DEFAULT_IDLE_TIMEOUT,
    ClientGone,
    TcpSimulator,
    UdpSimulator,
    check_idle_timeout,
    close_writer,
)
from plcstack.transports.guard import FRAME_TIMEOUT, ClientLimit, FrameDeadline
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
    """A running E71 face on TCP; ``executor`` answers, ``limit`` counts the refused clients."""

    def __init__(
        self,
        server: asyncio.Server,
        executor: E71Executor,
        code: Code,
        *,
        max_connections: int,
        idle_timeout: float | None,
    ) -> None:
        super().__init__(server, *_scheme(code, "tcp"))
        self.executor = executor
        self.code = code
        self.idle_timeout = idle_timeout
        self.limit = ClientLimit(max_connections, f"E71 face {self.url}", log)
        #: connections closed because a request was begun and not completed in time
        self.late_frames = 0
        #: requests received (answered or not)
        self.requests = 0

    @property
    def refused_connections(self) -> int:  # type: ignore[override]
        return self.limit.refused

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = peer_address(writer.get_extra_info("peername"))
        if not self.limit.admit(peer):
            writer.transport.abort()
            return
        task = asyncio.current_task()
        if task is not None:
            self.track(task)
        gone = ClientGone(reader, writer)
        codec = E71ServerConnection(self.code, extensions=DECODERS)
        session = Session()
        frame = FrameDeadline(FRAME_TIMEOUT)
        try:
            while True:
                frame.note(codec.buffered > 0)
                due = frame.due
                try:
                    async with (
                        asyncio.timeout(self.idle_timeout)
                        if due is None
                        else asyncio.timeout_at(due)
                    ):
                        data = await reader.read(65536)
                except TimeoutError:
                    if due is not None:
                        self.late_frames += 1
                    else:
                        self.idle_closed += 1
                    return
                if not data:
                    return
                codec.receive_data(data)
                while (event := codec.next_event()) is not NEED_DATA:
                    self.requests += 1
                    with gone.waiting():
                        answer = await self.executor.answer(event, session, peer)
                    writer.write(codec.send(answer))
                    await writer.drain()  # a client that does not read is not read either
        except (ConnectionError, OSError, asyncio.CancelledError):
            return  # the client went away (or the face stops): nothing to answer
        finally:
            gone.close()
            self.limit.release()
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
) -> E71TcpFace | E71UdpFace:
    """Serve the E71 face of ``executor``'s PLC on ``host:port`` (0: any free port)."""
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
    idle = check_idle_timeout(idle_timeout)
    faces: list[E71TcpFace] = []

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(asyncio.CancelledError):
            await faces[0].handle(reader, writer)

    server = await asyncio.start_server(handle, host, port)
    face = E71TcpFace(server, executor, code_, max_connections=max_connections, idle_timeout=idle)
    faces.append(face)
    return face
