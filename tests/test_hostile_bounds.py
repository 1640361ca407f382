"""Issue 11, item 1: memory bounded by the protocol, never by the peer.

Each test floods a real socket (or a codec) and asserts the bound on the transport's or codec's
own counters, the error type and its wording. Floods of megabytes are marked slow.
"""

from __future__ import annotations

import asyncio
import socket

import pytest

from plcstack.clients import connect
from plcstack.clients.e71_fixed import INBOX_MAX, E71BroadcastReceiver, E71FixedBufferClient
from plcstack.codecs.e71_buffers import FixedBufferConnection
from plcstack.codecs.e71_commands import FixedBufferData
from plcstack.errors import PlcError, RemoteProtocolError
from plcstack.transports.base import MAX_QUEUED
from plcstack.transports.tcp import RECEIVE_BUFFER, TcpTransport
from plcstack.transports.udp import UdpTransport
from plcstack.url import parse_url
from tests.aio_helpers import ends_quietly, eventually

FLOOD = 100 * 1024 * 1024  # what the peer tries to push: 100 MB


class _Streamer:
    """Accepts connections and streams ``total`` bytes to each without reading anything."""

    def __init__(self, total: int = FLOOD) -> None:
        self.total = total
        self.sent = 0
        self.server: asyncio.Server | None = None
        self.port = 0
        self.stalled = asyncio.Event()

    async def __aenter__(self) -> _Streamer:
        self.server = await asyncio.start_server(ends_quietly(self._handle), "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self.server is not None
        self.server.close()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        block = b"\xa5" * 65536
        try:
            while self.sent < self.total:
                writer.write(block)
                try:
                    await asyncio.wait_for(writer.drain(), 0.5)
                except TimeoutError:
                    self.stalled.set()  # the client stopped reading: TCP pushes back
                    await asyncio.sleep(3600)
                self.sent += len(block)
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            writer.transport.abort()


@pytest.mark.slow
async def test_tcp_peer_streaming_to_an_idle_client_is_held_to_the_queue_bound() -> None:
    """Before: every byte was queued (2 GB in 10 s). After: reading pauses at MAX_QUEUED and
    the kernel's buffers push back on the peer."""
    async with _Streamer() as peer:
        transport = TcpTransport("127.0.0.1", peer.port)
        await transport.open(1.0)
        try:
            await asyncio.wait_for(peer.stalled.wait(), 30)
            counters = transport.counters
            assert counters.pauses >= 1
            assert counters.peak <= MAX_QUEUED + RECEIVE_BUFFER
            assert counters.queued <= MAX_QUEUED + RECEIVE_BUFFER
            assert peer.sent < FLOOD  # the peer was stopped long before its 100 MB
        finally:
            transport.abort()


@pytest.mark.slow
async def test_a_request_after_a_flood_reconnects_and_reads_the_truth() -> None:
    """The flooded bytes are unsolicited: the next request drops that connection first."""
    async with _Streamer() as peer:
        plc = connect(f"e71+tcp://127.0.0.1:{peer.port}?timeout=0.3")
        await plc.open()
        try:
            await asyncio.wait_for(peer.stalled.wait(), 30)
            peak = plc.transport.counters.peak  # type: ignore[attr-defined]
            assert peak <= MAX_QUEUED + RECEIVE_BUFFER
            with pytest.raises(PlcError):
                await plc.read("D0")  # a fresh connection, flooded again: not an answer
        finally:
            await plc.aclose()


async def test_udp_datagrams_beyond_the_bound_are_dropped_and_counted() -> None:
    """Before: 0.8 GB queued in 10 s over UDP. After: at most MAX_QUEUED bytes, the rest
    counted as dropped."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    port = rx.getsockname()[1]
    transport = UdpTransport("127.0.0.1", port)
    await transport.open(1.0)
    try:
        local = transport._transport.get_extra_info("sockname")  # type: ignore[union-attr]
        sent = 0
        for _ in range(200):  # 200 x 1400 bytes = 280 KB > 4 x MAX_QUEUED
            rx.sendto(b"\x5a" * 1400, local)
            sent += 1400
            if sent % (40 * 1400) == 0:
                await asyncio.sleep(0.01)  # let the loop take them
        await eventually(
            lambda: not transport.input_waiting(), "the loop took every datagram the kernel held"
        )
        counters = transport.counters
        assert counters.queued <= MAX_QUEUED
        assert counters.peak <= MAX_QUEUED
        assert counters.dropped >= 1
        assert counters.dropped_bytes + counters.queued <= sent + 1
    finally:
        transport.abort()
        rx.close()


def test_fixed_buffer_codec_holds_one_telegram_and_an_answer_while_an_ack_is_owed() -> None:
    """Before: a fixed-buffer connection buffered without limit while our acknowledgement was
    owed (1.7 GB). After: a RemoteProtocolError naming the procedure, ``held`` bounded."""
    codec = FixedBufferConnection("binary", role="partner")
    codec.receive_data(FixedBufferData((1, 2, 3)).encode(codec.code))
    assert isinstance(codec.next_event(), FixedBufferData)  # now we owe the answer
    telegram = FixedBufferData(tuple(range(1017))).encode(codec.code)
    codec.receive_data(telegram)  # one more telegram may wait (a peer resending)
    with pytest.raises(RemoteProtocolError, match="one telegram at a time") as info:
        for _ in range(1000):
            codec.receive_data(telegram)
    assert codec.held <= codec.max_held
    assert "while our answer to its telegram was still owed" in info.value.message


def test_fixed_buffer_codec_udp_refuses_a_third_datagram_while_an_ack_is_owed() -> None:
    codec = FixedBufferConnection("binary", role="partner", transport="udp")
    one = FixedBufferData((1,)).encode(codec.code)
    codec.receive_data(one)
    assert isinstance(codec.next_event(), FixedBufferData)
    codec.receive_data(one)
    codec.receive_data(one)
    with pytest.raises(RemoteProtocolError, match="third datagram"):
        codec.receive_data(one)


@pytest.mark.slow
async def test_fixed_buffer_client_without_procedure_stops_reading_for_a_slow_consumer() -> None:
    """Without procedure the PLC sends at will; messages nobody took are held to INBOX_MAX and
    then the socket is paused (the transport's queue bound)."""
    async with _Streamer(total=20 * 1024 * 1024) as peer:
        client = E71FixedBufferClient.from_url(
            parse_url(f"e71+tcp://127.0.0.1:{peer.port}"), procedure=False
        )
        await client.open()
        try:
            await asyncio.wait_for(peer.stalled.wait(), 30)
            assert client._inbox.qsize() <= INBOX_MAX
            peak = client.transport.counters.peak  # type: ignore[attr-defined]
            assert peak <= MAX_QUEUED + RECEIVE_BUFFER
        finally:
            await client.aclose()


async def test_broadcast_receiver_binds_loopback_and_bounds_its_queue() -> None:
    """Before: bound every interface by default, with an unbounded queue."""
    async with E71BroadcastReceiver(0, max_queued=8) as rx:
        assert rx.host == "127.0.0.1"
        assert rx._transport is not None
        assert rx._transport.get_extra_info("sockname")[0] == "127.0.0.1"
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            for i in range(50):
                tx.sendto(bytes([i]), ("127.0.0.1", rx.port))
            await eventually(lambda: rx.dropped == 50 - 8, "the surplus datagrams were dropped")
        finally:
            tx.close()
        first, _ = await rx.receive(timeout=1)
        assert first == b"\x00"  # the oldest are kept, the surplus is dropped and counted
