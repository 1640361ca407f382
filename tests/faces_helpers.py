"""Helpers of the native-face tests: a poller on one simulated PLC, and raw exchanges that keep
every byte of an answer (to compare a face's answer with the PLC's own, byte for byte)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager, suppress
from typing import Any, Literal, Protocol

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import Code
from plcstack.gateway import e71server
from plcstack.gateway.e71face import E71Executor
from plcstack.gateway.faces import FaceSettings, PlcFaces
from plcstack.gateway.record import FaceWrite
from plcstack.gateway.store import ClientStore
from plcstack.poll.config import parse_poll_config
from plcstack.poll.engine import Poller
from plcstack.sim.base import TcpSimulator

__all__ = ["KINDS", "RawDatagrams", "RawStream", "Transport", "e71_faces", "polled", "s5_faces"]

Transport = Literal["tcp", "udp"]
KINDS: tuple[tuple[Transport, Code], ...] = (
    ("tcp", Code.BINARY),
    ("tcp", Code.ASCII),
    ("udp", Code.BINARY),
    ("udp", Code.ASCII),
)


E71Face = e71server.E71TcpFace | e71server.E71UdpFace


class _Codec(Protocol):
    def send(self, request: Any) -> bytes: ...

    def receive_data(self, data: bytes) -> None: ...

    def next_event(self) -> Any: ...


@asynccontextmanager
async def polled(
    url: str, tags: str, *, interval: float = 0.02, timeout: float = 5.0
) -> AsyncIterator[Poller]:
    """A poller of one PLC ``kiln1`` at ``url``; ``tags``: the body of its ``[plc.tags]``."""
    text = f"""
[poll]
interval = {interval}
timeout = {timeout}
backoff_max = 0.2

[[plc]]
name = "kiln1"
url = "{url}"

[plc.tags]
{tags}
"""
    async with Poller(parse_poll_config(text)) as poller:
        yield poller


class RawStream:
    """One TCP connection and a client codec: each :meth:`ask` returns the decoded answer and
    every byte it came in."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, codec: _Codec):
        self.reader = reader
        self.writer = writer
        self.codec = codec

    @classmethod
    async def open(cls, host: str, port: int, codec: _Codec) -> RawStream:
        reader, writer = await asyncio.open_connection(host, port)
        return cls(reader, writer, codec)

    async def ask(self, request: Any, timeout: float = 10.0) -> tuple[Any, bytes]:
        self.writer.write(self.codec.send(request))
        raw = b""
        async with asyncio.timeout(timeout):
            while True:
                chunk = await self.reader.read(65536)
                if not chunk:
                    raise ConnectionError(f"closed after {raw.hex(' ')}")
                raw += chunk
                self.codec.receive_data(chunk)
                event = self.codec.next_event()
                if event is not NEED_DATA:
                    return event, raw

    async def aclose(self) -> None:
        self.writer.close()
        with suppress(ConnectionError, OSError):
            await self.writer.wait_closed()


class RawDatagrams:
    """A UDP socket and a client codec: each :meth:`ask` sends one request datagram and returns
    the decoded answer and its bytes."""

    def __init__(
        self, transport: asyncio.DatagramTransport, queue: asyncio.Queue[bytes], codec: _Codec
    ):
        self.transport = transport
        self.queue = queue
        self.codec = codec

    @classmethod
    async def open(cls, host: str, port: int, codec: _Codec) -> RawDatagrams:
        queue: asyncio.Queue[bytes] = asyncio.Queue()

        class _Receiver(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: Any) -> None:
                queue.put_nowait(data)

        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(_Receiver, remote_addr=(host, port))
        return cls(transport, queue, codec)

    async def ask(self, request: Any, timeout: float = 10.0) -> tuple[Any, bytes]:
        self.transport.sendto(self.codec.send(request))
        async with asyncio.timeout(timeout):
            raw = await self.queue.get()
        self.codec.receive_data(raw)
        return self.codec.next_event(), raw

    async def aclose(self) -> None:
        self.transport.close()


@asynccontextmanager
async def s5_faces(
    poller: Poller, *, writable: str = "", read_previous: bool = False, mk: bool = False
) -> AsyncIterator[tuple[TcpSimulator, TcpSimulator, ClientStore, list[FaceWrite]]]:
    """S5-LAN and FETCH/WRITE faces of the poller's PLC ``kiln1``, as two ``[[gateway]]``
    entries run them (64 clients at once each), and the writes they told."""
    writes: list[FaceWrite] = []
    faces = [
        FaceSettings("s5lan", "127.0.0.1", 0, "kiln1", writable, max_connections=64),
        FaceSettings("fetchwrite", "127.0.0.1", 0, "kiln1", writable, mk=mk, max_connections=64),
    ]
    running = PlcFaces(
        "kiln1",
        poller.client("kiln1"),
        faces,
        read_previous=read_previous,
        on_write=writes.append,
    )
    async with running:
        lan, fw = running.servers
        (store,) = set(running.answering)  # one store serves both: one allow-list
        assert isinstance(lan, TcpSimulator) and isinstance(fw, TcpSimulator)
        assert isinstance(store, ClientStore)
        yield lan, fw, store, writes


@asynccontextmanager
async def e71_faces(
    poller: Poller, *, writable: str = "", read_previous: bool = False, max_wait: float = 2.0
) -> AsyncIterator[
    tuple[
        dict[tuple[Transport, Code], E71Face],
        E71Executor,
        list[FaceWrite],
    ]
]:
    """One E71 face of each transport and code in front of the poller's PLC ``kiln1``, as
    ``[[gateway]]`` entries run them (64 clients at once each)."""
    writes: list[FaceWrite] = []
    settings = [
        FaceSettings(
            "e71", "127.0.0.1", 0, "kiln1", writable, transport=transport, code=code.value,
            max_connections=64, max_wait=max_wait,
        )
        for transport, code in KINDS
    ]  # fmt: skip
    running = PlcFaces(
        "kiln1",
        poller.client("kiln1"),
        settings,
        max_wait=max_wait,
        read_previous=read_previous,
        on_write=writes.append,
    )
    async with running:
        faces: dict[tuple[Transport, Code], E71Face] = {}
        for kind, server in zip(KINDS, running.servers, strict=True):
            assert isinstance(server, e71server.E71TcpFace | e71server.E71UdpFace)
            faces[kind] = server
        (executor,) = set(running.answering)  # one executor serves all: one allow-list
        assert isinstance(executor, E71Executor)
        yield faces, executor, writes
