"""The E71 client against a scripted peer on real sockets: the peer checks the exact request bytes
of spec §12 and answers with the exact golden response bytes (what an independent 1E server does),
plus malformed and split answers."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import pytest

import plcstack
from plcstack.clients.e71 import E71Client
from plcstack.errors import PlcErrorResponse, RemoteProtocolError
from tests.aio_helpers import ends_quietly

Script = list[tuple[bytes, list[bytes]]]  # expected request -> answer chunks


class ScriptedPeer:
    """Answers each expected request with its chunks; records any unexpected request."""

    def __init__(self, script: Script, pause: float = 0.0) -> None:
        self.script = list(script)
        self.pause = pause
        self.unexpected: list[bytes] = []
        self.connections = 0

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        try:
            while self.script:
                expected, chunks = self.script[0]
                data = await reader.readexactly(len(expected))
                if data != expected:
                    self.unexpected.append(data)
                    return
                self.script.pop(0)
                for chunk in chunks:
                    writer.write(chunk)
                    await writer.drain()
                    if self.pause:
                        await asyncio.sleep(self.pause)
            await reader.read()  # hold the connection until the client closes it
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()


@pytest.fixture
async def tcp_peer() -> AsyncIterator[Callable[[Script, float], Awaitable[tuple[str, Any]]]]:
    servers: list[asyncio.Server] = []

    async def make(script: Script, pause: float = 0.0) -> tuple[str, ScriptedPeer]:
        peer = ScriptedPeer(script, pause)
        server = await asyncio.start_server(ends_quietly(peer.handle), "127.0.0.1", 0)
        servers.append(server)
        port = server.sockets[0].getsockname()[1]
        return f"e71+tcp://127.0.0.1:{port}?monitoring_timer=10", peer

    yield make
    for server in servers:
        server.close()


class _UdpPeer(asyncio.DatagramProtocol):
    def __init__(self, script: Script) -> None:
        self.script = list(script)
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: Any) -> None:
        self.transport = transport

    def datagram_received(self, data: bytes, addr: Any) -> None:
        expected, chunks = self.script.pop(0)
        assert self.transport is not None
        if data == expected:
            for chunk in chunks:
                self.transport.sendto(chunk, addr)


def h(text: str) -> bytes:
    return bytes.fromhex(text)


async def e71(url: str, **kw: Any) -> E71Client:
    plc = plcstack.connect(url, **kw)
    assert isinstance(plc, E71Client)
    await plc.open()
    return plc


async def test_binary_golden_exchange_over_tcp(tcp_peer: Any) -> None:
    url, peer = await tcp_peer(
        [
            (h("00 FF 0A 00 64 00 00 00 20 4D 08 00"), [h("80 00 10 10 01 10")]),
            (h("01 FF 0A 00 40 00 00 00 20 59 02 00"), [h("81 00 9D 82 3E 55")]),
            (h("01 FF 0A 00 64 00 00 00 20 44 03 00"), [h("81 00"), h("34 12 76"), h("98 09 01")]),
            (h("02 FF 0A 00 32 00 00 00 20 4D 03 00 10 10"), [h("82 00")]),
            (h("03 FF 0A 00 64 00 00 00 20 44 03 00 34 12 76 98 09 01"), [h("83 00")]),
            (
                h("04 FF 0A 00 03 00 94 00 00 00 20 58 01")
                + h("3C 00 00 00 20 4D 00 26 00 00 00 20 42 01"),
                [h("84 00")],
            ),
            (
                h("07 FF 0A 00 03 00 50 00 00 00 20 59 26 00 00 00 20 44 1E 00 00 00 20 57"),
                [h("87 00")],
            ),
            (h("09 FF 0A 00"), [h("89 00 6D E5 34 12 78 56")]),
        ]
    )
    plc = await e71(url)
    try:
        assert await plc.read("M100", 8) == [True, False, True, False, False, True, True, False]
        assert await plc.read_words("Y40", 2) == [0x829D, 0x553E]
        assert await plc.read("D100", 3) == [0x1234, 0x9876, 0x0109]
        await plc.write("M50", [True, False, True])
        await plc.write("D100", [0x1234, 0x9876, 0x0109])
        await plc.test_bits([("X94", True), ("M60", False), ("B26", True)])
        await plc.register_monitor_words(["Y50", "D38", "W1E"])
        assert await plc.monitor_words() == [0xE56D, 0x1234, 0x5678]
    finally:
        await plc.aclose()
    assert peer.unexpected == [] and peer.script == []


async def test_ascii_golden_exchange_over_tcp(tcp_peer: Any) -> None:
    url, peer = await tcp_peer(
        [
            (b"00FF000A4D20000000640300", [b"80001010"]),
            (b"01FF000A4420000000640300", [b"8100123498760109"]),
            (b"02FF000A4D20000000320C00011101000001", [b"8200"]),
            (b"05FF000A03005920000000807B295720000000261234434E000000120050", [b"8500"]),
            (b"06FF000A03005920000000464D200000000C42200000002C", [b"8600"]),
            (b"08FF000A", [b"8800", b"1010"]),
        ]
    )
    plc = await e71(url + "&code=ascii")
    try:
        assert await plc.read("M100", 3) == [True, False, True]
        assert await plc.read("D100", 3) == [0x1234, 0x9876, 0x0109]
        await plc.write("M50", [bool(int(c)) for c in "011101000001"])
        await plc.test_words([("Y80", 0x7B29), ("W26", 0x1234), ("CN18", 0x50)])
        await plc.register_monitor_bits(["Y46", "M12", "B2C"])
        assert await plc.monitor_bits() == [True, False, True]
    finally:
        await plc.aclose()
    assert peer.unexpected == [] and peer.script == []


async def test_5bh_trailer_in_a_later_segment_is_not_misread(tcp_peer: Any) -> None:
    url, peer = await tcp_peer(
        [
            (h("01 05 0A 00 64 00 00 00 20 44 01 00"), [h("81 5B 10")]),
            (h("01 05 0A 00 64 00 00 00 20 44 01 00"), [h("00 81 00 34 12")]),
        ]
    )
    plc = await e71(url + "&pc=05")
    try:
        with pytest.raises(PlcErrorResponse) as err:
            await plc.read("D100")
        assert err.value.code_text == "5BH/10H"
        assert await plc.read("D100") == [0x1234]
    finally:
        await plc.aclose()
    assert peer.connections == 1


async def test_malformed_answer_closes_and_next_request_reconnects(tcp_peer: Any) -> None:
    url, peer = await tcp_peer(
        [
            (h("01 FF 0A 00 64 00 00 00 20 44 01 00"), [h("83 00")]),  # wrong subheader
        ]
    )
    plc = await e71(url)
    try:
        with pytest.raises(RemoteProtocolError) as err:
            await plc.read("D100")
        assert "does not answer" in str(err.value) and url in str(err.value)
        peer.script.append((h("01 FF 0A 00 64 00 00 00 20 44 01 00"), [h("81 00 01 00")]))
        assert await plc.read("D100") == [1]
        assert peer.connections == 2
    finally:
        await plc.aclose()


async def test_golden_over_udp() -> None:
    loop = asyncio.get_running_loop()
    transport, _ = await loop.create_datagram_endpoint(
        lambda: _UdpPeer(
            [
                (h("01 FF 0A 00 64 00 00 00 20 44 03 00"), [h("81 00 34 12 76 98 09 01")]),
                (h("01 05 0A 00 64 00 00 00 20 44 01 00"), [h("81 5B 10 00")]),
            ]
        ),
        local_addr=("127.0.0.1", 0),
    )
    port = transport.get_extra_info("sockname")[1]
    try:
        plc = await e71(f"e71+udp://127.0.0.1:{port}?monitoring_timer=10")
        try:
            assert await plc.read("D100", 3) == [0x1234, 0x9876, 0x0109]
            plc.pc = 5
            with pytest.raises(PlcErrorResponse):
                await plc.read("D100")
        finally:
            await plc.aclose()
    finally:
        transport.close()
