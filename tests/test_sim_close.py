"""A simulator takes how each client connection ended, so a reset is never reported as a
"Future exception was never retrieved" when the garbage collector frees the connection."""

from __future__ import annotations

import asyncio
import socket
import struct
from types import ModuleType

import pytest

from plcstack.sim import as511, s5lan
from plcstack.sim.base import close_writer
from tests.aio_helpers import eventually


def _closed_future(writer: asyncio.StreamWriter) -> asyncio.Future[None]:
    """The future asyncio keeps the connection's end in (only ``wait_closed`` reads it)."""
    future: asyncio.Future[None] = writer._protocol._closed  # type: ignore[attr-defined]
    return future


def _reset(sock: socket.socket) -> None:
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()  # RST, not FIN


async def test_a_reset_connection_is_read_by_close_writer() -> None:
    accepted: asyncio.Queue[asyncio.StreamWriter] = asyncio.Queue()

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await accepted.put(writer)
        with pytest.raises(ConnectionResetError):
            await reader.read(100)

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    async with server:
        client = socket.create_connection(server.sockets[0].getsockname())
        writer = await accepted.get()
        _reset(client)
        closed = _closed_future(writer)
        await eventually(closed.done, "the reset reached the server")
        assert closed._log_traceback  # a reset, not read yet
        await close_writer(writer)
        assert not closed._log_traceback  # read: nothing to report


async def test_close_writer_aborts_a_peer_that_reads_nothing(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr("plcstack.sim.base.CLOSE_LINGER", 0.2)
    accepted: asyncio.Queue[asyncio.StreamWriter] = asyncio.Queue()

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await accepted.put(writer)

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    async with server:
        client = socket.create_connection(server.sockets[0].getsockname())
        client.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        try:
            writer = await accepted.get()
            writer.write(b"x" * 8_000_000)  # more than the kernel buffers: the close must wait
            await close_writer(writer)  # ends after the linger, by an abort
            assert writer.transport.is_closing() and _closed_future(writer).done()
        finally:
            client.close()


@pytest.mark.parametrize("module", [s5lan], ids=["s5lan"])
async def test_a_simulator_reads_the_end_of_a_reset_connection(
    module: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    ended: list[asyncio.Future[None]] = []

    async def watched(writer: asyncio.StreamWriter) -> None:
        await close_writer(writer)
        ended.append(_closed_future(writer))

    monkeypatch.setattr(module, "close_writer", watched)
    async with await module.start() as sim:
        client = socket.create_connection((sim.host, sim.port))
        client.sendall(b"\x10")
        _reset(client)
        await eventually(lambda: ended, "the simulator closed the connection")
        assert ended[0].done() and not ended[0]._log_traceback


async def test_the_as511_simulator_ends_a_reset_line() -> None:
    """The AS511 simulator's lines are protocols (their end comes to ``connection_lost``, no
    future to leave unread): a reset ends the line and frees its slot."""
    async with await as511.start() as sim:
        client = socket.create_connection((sim.host, sim.port))
        client.sendall(b"\x10")
        await eventually(lambda: sim.connection_count.total == 1, "the simulator accepted")
        _reset(client)
        await eventually(lambda: sim.connection_count.current == 0, "the line ended")
