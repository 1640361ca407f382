"""Issue 11, item 6 (and item 1 for the simulators): connections expire, caps hold, a peer that
never reads is not answered into memory, the 62H count is checked before buffering."""

from __future__ import annotations

import asyncio

import pytest

from plcstack.clients import connect
from plcstack.codecs.e71 import E71ServerConnection
from plcstack.codecs.e71_events import BadRequest
from plcstack.sim import as511 as as511_sim
from plcstack.sim import e71 as e71_sim
from plcstack.sim import fetchwrite as fw_sim
from plcstack.sim import s5lan as s5lan_sim
from plcstack.sim.e71 import E71TcpSimulator
from plcstack.sim.e71_fixed import INBOX_BYTES, start_fixed_buffer
from tests.aio_helpers import eventually

IDLE = 0.3


async def _idle_sockets(port: int, n: int) -> list[asyncio.StreamWriter]:
    writers = []
    for _ in range(n):
        _reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writers.append(writer)
    return writers


async def _closed_by_peer(writer: asyncio.StreamWriter, reader: asyncio.StreamReader) -> bool:
    try:
        return await asyncio.wait_for(reader.read(1), 5) == b""
    except ConnectionError:
        return True


async def test_e71_idle_sockets_expire_and_free_the_eight_connections() -> None:
    """Before: 8 idle sockets locked an E71 simulator out for ever."""
    sim = await e71_sim.start(idle_timeout=IDLE)
    assert isinstance(sim, E71TcpSimulator)
    async with sim:
        writers = await _idle_sockets(sim.port, 8)
        await eventually(lambda: sim.connection_count.current == 8, "the eight are accepted")
        await eventually(
            lambda: sim.idle_closed == 8 and sim.connection_count.current == 0,
            "the idle sockets expired",
        )
        async with connect(sim.url + "?timeout=1") as plc:
            assert await plc.read("D0") == [0]
        for w in writers:
            w.close()


async def test_s5lan_idle_socket_and_incomplete_header_expire() -> None:
    """Before: 1 idle socket locked an S5-LAN simulator out for ever; an incomplete header
    never timed out."""
    async with await s5lan_sim.start(idle_timeout=IDLE, data_timeout=IDLE) as sim:
        reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
        assert await _closed_by_peer(writer, reader)
        assert sim.idle_closed == 1
        reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
        writer.write(b"S5\x10\x01")  # 4 of 26 header bytes, then nothing
        assert await _closed_by_peer(writer, reader)
        async with connect(sim.url + "?timeout=1") as plc:
            assert await plc.read("MB0") == [0]


@pytest.mark.parametrize("kind", ["fetchwrite", "as511"])
async def test_fetchwrite_and_as511_tcp_cap_their_connections(kind: str) -> None:
    """Before: FETCH/WRITE and AS511-over-TCP accepted unlimited connections."""
    if kind == "fetchwrite":
        sim: fw_sim.FetchWriteSimulator | as511_sim.AS511TcpSimulator = await fw_sim.start(
            max_connections=2
        )
    else:
        sim = await as511_sim.start(max_connections=2)
    async with sim:
        held = await _idle_sockets(sim.port, 2)
        await eventually(lambda: sim.connection_count.current == 2, "the two are accepted")
        reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
        assert await _closed_by_peer(writer, reader)
        assert sim.refused_connections == 1
        assert sim.connection_count.current == 2
        for w in held:
            w.close()


@pytest.mark.parametrize("kind", ["fetchwrite", "as511"])
async def test_fetchwrite_and_as511_idle_connections_expire(kind: str) -> None:
    if kind == "fetchwrite":
        sim: fw_sim.FetchWriteSimulator | as511_sim.AS511TcpSimulator = await fw_sim.start(
            idle_timeout=IDLE
        )
    else:
        sim = await as511_sim.start(idle_timeout=IDLE)
    async with sim:
        reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
        assert await _closed_by_peer(writer, reader)
        assert sim.idle_closed == 1


def test_e71_62h_count_is_checked_before_buffering() -> None:
    """Before: a 62H header claiming 65535 words made the codec wait for 128 KiB."""
    codec = E71ServerConnection("binary")
    codec.receive_data(bytes([0x62, 0x00, 0x00, 0x00, 0xFF, 0xFF]))
    event = codec.next_event()
    assert isinstance(event, BadRequest) and event.end_code == 0x52
    assert "65535 words" in event.reason
    assert codec.buffered == 0


async def _request_frames(url: str, action: str, count: int) -> bytes:
    """One real request frame of ``url``'s client (captured from its transport); a read of
    ``count`` points, so that every answer is much longer than its request."""
    plc = connect(url)
    sent: list[bytes] = []
    await plc.open()
    original = plc.transport.write
    plc.transport.write = lambda data: (sent.append(data), original(data))[1]  # type: ignore[method-assign]
    try:
        await plc.read(action, count)
    finally:
        await plc.aclose()
    return sent[0]


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["e71", "fetchwrite", "as511"])
async def test_a_peer_that_never_reads_is_not_answered_into_memory(kind: str) -> None:
    """Before: E71 +267 MB in 20 s, FETCH/WRITE +1.5 GB in 17 s, and FETCH/WRITE deaf for more
    than 30 s after the peer left. After: the simulator stops reading while its write buffer is
    above the high-water mark, and serves a new client at once after the peer is gone."""
    if kind == "e71":
        sim = await e71_sim.start()
        frame = await _request_frames(sim.url, "D0", 256)
        request = frame * 64
    elif kind == "fetchwrite":
        sim = await fw_sim.start()
        frame = await _request_frames(sim.url, "MB0", 256)
        request = frame * 64
    else:
        sim = await as511_sim.start()
        request = b"\x02" * 4096  # STX floods: every one is answered with DLE ACK
    async with sim:
        _reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
        sent = 0
        transports_seen = False
        try:
            while sent < 8 * 1024 * 1024:  # 8 MB of requests, never reading an answer
                writer.write(request)
                sent += len(request)
                try:
                    await asyncio.wait_for(writer.drain(), 0.3)
                except TimeoutError:
                    break  # the simulator stopped reading: TCP pushes back on us
            await asyncio.sleep(0.2)
            transports = _server_transports(sim)  # the simulator's side of the connection
            transports_seen = bool(transports)
            held = max((t.get_write_buffer_size() for t in transports), default=0)
            print(f"{kind}: sent {sent} bytes, simulator write buffer {held} bytes")
            assert held <= 1024 * 1024, held
        finally:
            writer.transport.abort()
        # gone: the next client is served at once, not after working off a backlog
        url = sim.url + ("&" if "?" in sim.url else "?") + "timeout=2"
        async with connect(url) as plc:
            address = {"e71": "D0", "fetchwrite": "DB10.DW0", "as511": "MB0"}[kind]
            await plc.read(address)
    assert transports_seen


def _server_transports(sim: object) -> list[asyncio.WriteTransport]:
    """The simulator-side transports of its open connections: the E71 keeps its protocol
    objects in ``connections``; the stream-based simulators hold a ``writer`` in the frame of
    each tracked connection task, the AS511 one (a protocol per line) its ``transport``."""
    out: list[asyncio.WriteTransport] = []
    if isinstance(sim, E71TcpSimulator):
        out += [c.transport for c in sim.connections if c.transport is not None]
    for task in getattr(sim, "_conn_tasks", ()):
        frame = task.get_coro().cr_frame
        names = frame.f_locals if frame is not None else {}
        if names.get("writer") is not None:
            out.append(names["writer"].transport)
        elif names.get("transport") is not None:
            out.append(names["transport"])
    return out


@pytest.mark.slow
async def test_fixed_buffer_simulator_without_procedure_holds_a_bounded_inbox() -> None:
    """Without procedure a partner sends at will; a PLC program that does not receive makes
    the simulated E71 stop reading (TCP) above INBOX_BYTES, instead of queueing everything."""
    sim = await start_fixed_buffer(procedure=False)
    async with sim:
        _reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
        block = b"\x5a" * 2046
        sent = 0
        try:
            while sent < 16 * 1024 * 1024:
                writer.write(block)
                sent += len(block)
                try:
                    await asyncio.wait_for(writer.drain(), 0.3)
                except TimeoutError:
                    break
            await asyncio.sleep(0.1)
            assert sim.inbox_bytes <= INBOX_BYTES + 256 * 1024  # the bound plus one chunk
            assert sent < 16 * 1024 * 1024
            taken = await sim.receive(timeout=1)  # the program takes one: still works
            assert taken
        finally:
            writer.transport.abort()
