"""Fixed buffer communication (spec §8): codec golden vectors and properties, client against the
fixed-buffer simulator in both directions over TCP and UDP, binary and ASCII, the answer
handshake and its error end codes, without procedure, UDP broadcast."""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import AsyncIterator
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.clients.e71 import E71Client
from plcstack.clients.e71_fixed import E71BroadcastReceiver, E71FixedBufferClient
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import Code
from plcstack.codecs.e71_buffers import (
    FixedBufferAck,
    FixedBufferConnection,
    FixedBufferData,
    FixedBufferError,
    RawBufferConnection,
)
from plcstack.errors import (
    AddressError,
    LocalProtocolError,
    PlcErrorResponse,
    PlcTimeout,
    RemoteProtocolError,
)
from plcstack.sim.e71_fixed import FixedBufferSimulator, start_fixed_buffer
from plcstack.transports.tcp import TcpTransport
from plcstack.url import parse_url
from tests.aio_helpers import ends_quietly, eventually

B, A = Code.BINARY, Code.ASCII


def hx(text: str) -> bytes:
    return bytes.fromhex(text)


# -- codec: §12 #28 both directions, both roles -------------------------------------------------

GOLDEN_28 = [
    (B, hx("60 00 03 00 01 00 02 00 03 00"), hx("E0 00")),
    (A, b"60000003000100020003", b"E000"),
]


@pytest.mark.parametrize(("code", "telegram", "answer"), GOLDEN_28, ids=["binary", "ascii"])
@pytest.mark.parametrize(("sender", "receiver"), [("partner", "e71"), ("e71", "partner")])
def test_golden_28_both_directions(
    code: Code, telegram: bytes, answer: bytes, sender: str, receiver: str
) -> None:
    tx = FixedBufferConnection(code, role=sender)  # type: ignore[arg-type]
    rx = FixedBufferConnection(code, role=receiver)  # type: ignore[arg-type]
    assert tx.send_data([1, 2, 3]) == telegram
    for i in range(len(telegram)):
        assert rx.next_event() is NEED_DATA
        rx.receive_data(telegram[i : i + 1])
    assert rx.next_event() == FixedBufferData((1, 2, 3))
    assert rx.send_ack() == answer
    tx.receive_data(answer)
    assert tx.next_event() == FixedBufferAck(0)
    assert not tx.awaiting_ack and not rx.owe_ack


@pytest.mark.parametrize(
    ("code", "data", "answer", "end"),
    [
        (B, hx("60 00 00 00"), hx("E0 52"), 0x52),  # length 0
        (B, hx("60 00 FA 03"), hx("E0 52"), 0x52),  # 1018 words
        (A, b"600001FD", b"E052", 0x52),  # 509 words in ASCII
        (B, hx("65 00 01 00"), hx("E5 50"), 0x50),  # undefined subheader (§2)
        (A, b"6000000X", b"E054", 0x54),  # non-hex length
        (A, b"ZZ000001", b"FF54", 0x54),
    ],
)
def test_e71_refuses_malformed_telegrams(code: Code, data: bytes, answer: bytes, end: int) -> None:
    e71 = FixedBufferConnection(code, role="e71")
    e71.receive_data(data)
    event = e71.next_event()
    assert isinstance(event, FixedBufferError) and event.end_code == end
    assert e71.refuse(event) == answer
    assert e71.next_event() is NEED_DATA  # input dropped, nothing stored
    assert not e71.owe_ack


@pytest.mark.parametrize(
    ("answer", "event"),
    [(hx("E0 00"), FixedBufferAck(0)), (hx("E0 52"), FixedBufferAck(0x52))],
)
def test_partner_decodes_answers(answer: bytes, event: FixedBufferAck) -> None:
    partner = FixedBufferConnection(B)
    partner.send_data([1])
    partner.receive_data(answer)
    assert partner.next_event() == event
    assert event.meaning in ("normal completion", "data length wrong")


@pytest.mark.parametrize("data", [hx("E0 00"), hx("65 00"), hx("60 00 00 00")])
def test_partner_raises_on_protocol_errors(data: bytes) -> None:
    partner = FixedBufferConnection(B)  # nothing sent: an answer is unexpected
    partner.receive_data(data)
    with pytest.raises(RemoteProtocolError):
        partner.next_event()


def test_next_telegram_is_held_until_answered() -> None:
    e71 = FixedBufferConnection(B, role="e71")
    e71.receive_data(hx("60 00 01 00 01 00 60 00 01 00 02 00"))
    assert e71.next_event() == FixedBufferData((1,))
    assert e71.next_event() is NEED_DATA
    e71.send_ack()
    assert e71.next_event() == FixedBufferData((2,))


def test_local_misuse() -> None:
    partner = FixedBufferConnection(B)
    partner.send_data([1])
    with pytest.raises(LocalProtocolError):
        partner.send_data([2])  # previous telegram not answered
    with pytest.raises(LocalProtocolError):
        partner.send_ack()  # nothing to acknowledge
    with pytest.raises(LocalProtocolError):
        FixedBufferConnection(A).send_data(list(range(509)))
    with pytest.raises(LocalProtocolError):
        RawBufferConnection().send(bytes(2047))


def test_udp_datagram_must_hold_exactly_one_telegram() -> None:
    e71 = FixedBufferConnection(B, role="e71", transport="udp")
    e71.receive_data(hx("60 00 02 00 01 00"))
    event = e71.next_event()
    assert isinstance(event, FixedBufferError) and event.end_code == 0x52


@settings(max_examples=150, deadline=None)
@given(
    code=st.sampled_from([B, A]),
    telegrams=st.lists(
        st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=60).map(tuple), min_size=1, max_size=4
    ),
    cuts=st.lists(st.integers(0, 2000), max_size=8),
)
def test_any_split_gives_the_same_telegrams(
    code: Code, telegrams: list[tuple[int, ...]], cuts: list[int]
) -> None:
    stream = b""
    for words in telegrams:
        stream += FixedBufferConnection(code).send_data(words)
    e71 = FixedBufferConnection(code, role="e71")
    bounds = sorted({0, len(stream), *(c % (len(stream) + 1) for c in cuts)})
    got: list[object] = []
    for lo, hi in itertools.pairwise(bounds):
        e71.receive_data(stream[lo:hi])
        while (event := e71.next_event()) is not NEED_DATA:
            got.append(event)
            e71.send_ack()
    assert got == [FixedBufferData(w) for w in telegrams]


@settings(max_examples=150, deadline=None)
@given(data=st.binary(max_size=80), code=st.sampled_from([B, A]))
def test_random_bytes(data: bytes, code: Code) -> None:
    e71 = FixedBufferConnection(code, role="e71")
    e71.receive_data(data)
    for _ in range(len(data) + 1):  # the E71 side never raises
        event = e71.next_event()
        if event is NEED_DATA:
            break
        if isinstance(event, FixedBufferData):
            e71.send_ack()
    partner = FixedBufferConnection(code)
    partner.send_data([1])
    partner.receive_data(data)
    try:
        for _ in range(len(data) + 1):
            event = partner.next_event()
            if event is NEED_DATA:
                break
            if isinstance(event, FixedBufferData):
                partner.send_ack()
    except RemoteProtocolError:
        pass


# -- client against the simulator ---------------------------------------------------------------

VARIANTS = [("tcp", "binary"), ("tcp", "ascii"), ("udp", "binary"), ("udp", "ascii")]


@pytest.fixture(params=VARIANTS, ids=["tcp-binary", "tcp-ascii", "udp-binary", "udp-ascii"])
async def sim(request: pytest.FixtureRequest) -> AsyncIterator[FixedBufferSimulator]:
    transport, code = request.param
    s = await start_fixed_buffer(transport=transport, code=code, ack_timeout=5)
    try:
        yield s
    finally:
        await s.aclose()


def fixed_client(url: str, **options: object) -> E71FixedBufferClient:
    return E71FixedBufferClient.from_url(parse_url(url), **options)


async def settle() -> None:
    for _ in range(20):
        await asyncio.sleep(0)
    await asyncio.sleep(0.05)


async def test_partner_to_plc_waits_for_the_plc_program(sim: FixedBufferSimulator) -> None:
    async with fixed_client(sim.url, timeout=5) as fb:
        send = asyncio.create_task(fb.send([0x0001, 0x0002, 0x0003]))
        await eventually(lambda: sim.pending() == 1, "the PLC received the data")
        await settle()  # an early E0 00 (there must be none) would arrive now
        assert sim.pending() == 1
        assert not send.done()  # E0 00 only after "received data taken" (§8.1)
        assert await sim.receive(timeout=5) == (1, 2, 3)
        await asyncio.wait_for(send, 5)
        words = list(range(1017 if sim.code is B else 508))
        send = asyncio.create_task(fb.send(words))
        assert await sim.receive(timeout=5) == tuple(words)
        await asyncio.wait_for(send, 5)


async def test_plc_to_partner_as_async_iterator(sim: FixedBufferSimulator) -> None:
    async with fixed_client(sim.url, timeout=5) as fb:
        if sim.transport_kind == "udp":  # the simulator learns the partner from a datagram
            send = asyncio.create_task(fb.send([0]))
            await sim.receive(timeout=5)
            await send
        results = []
        for k in range(3):
            results.append(asyncio.create_task(sim.send([k, k + 1])))
            await settle()
        got = []
        async for message in fb.messages():
            got.append(message)
            if len(got) == 3:
                break
        assert got == [(0, 1), (1, 2), (2, 3)]
        assert [await asyncio.wait_for(r, 5) for r in results] == [0, 0, 0]
        assert sim.errors == []


async def test_both_directions_at_once() -> None:
    async with await start_fixed_buffer() as sim, fixed_client(sim.url, timeout=5) as fb:
        plc_send = asyncio.create_task(sim.send([7]))
        our_send = asyncio.create_task(fb.send([8]))
        assert await fb.receive(timeout=5) == (7,)
        assert await sim.receive(timeout=5) == (8,)
        assert await asyncio.wait_for(plc_send, 5) == 0
        await asyncio.wait_for(our_send, 5)


async def test_client_timeout_when_plc_never_takes_the_data() -> None:
    async with await start_fixed_buffer() as sim, fixed_client(sim.url, timeout=0.3) as fb:
        with pytest.raises(PlcTimeout, match="may or may not have taken"):
            await fb.send([1])
        assert sim.pending() == 1


async def test_client_reports_error_end_codes() -> None:
    """A scripted E71 answers E0 52: PlcErrorResponse with the Tab. 7-2 meaning."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.readexactly(6)
        writer.write(hx("E0 52"))
        await reader.readexactly(6)
        writer.write(hx("E0 00"))
        await reader.read()

    server = await asyncio.start_server(ends_quietly(handle), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with fixed_client(f"e71+tcp://127.0.0.1:{port}", timeout=5) as fb:
            with pytest.raises(PlcErrorResponse, match="data length wrong") as info:
                await fb.send([1])
            assert info.value.code == 0x52
            await fb.send([2])  # the connection is still in step
    finally:
        server.close()


async def test_simulator_records_62h_and_70h() -> None:
    async with await start_fixed_buffer(ack_timeout=0.3) as sim:
        reader, writer = await asyncio.open_connection(sim.host, sim.port)
        await eventually(lambda: sim.connected, "the simulator accepted its partner")
        send = asyncio.create_task(sim.send([1, 2]))
        assert await reader.readexactly(8) == hx("60 00 02 00 01 00 02 00")
        writer.write(hx("E0 52"))
        assert await asyncio.wait_for(send, 5) == 0x52
        assert sim.errors == [0x62] and sim.partner_end_code == 0x52
        with pytest.raises(TimeoutError):
            await sim.send([3])  # nobody answers
        assert sim.errors == [0x62, 0x70]
        await reader.readexactly(6)
        writer.write(hx("65 00 01 00"))
        assert await reader.readexactly(2) == hx("E5 50")
        writer.close()


async def test_second_tcp_partner_is_refused() -> None:
    async with await start_fixed_buffer() as sim, fixed_client(sim.url, timeout=5):
        reader, _ = await asyncio.open_connection(sim.host, sim.port)
        assert await asyncio.wait_for(reader.read(), 5) == b""


# -- without procedure and broadcast ------------------------------------------------------------


@pytest.mark.parametrize("transport", ["tcp", "udp"])
async def test_without_procedure(transport: str) -> None:
    async with await start_fixed_buffer(transport=transport, procedure=False) as sim:  # type: ignore[arg-type]
        assert "procedure=0" in sim.url
        async with fixed_client(sim.url, timeout=5) as fb:
            await fb.send_raw(b"\x00\x01hello")
            assert await sim.receive(timeout=5) == b"\x00\x01hello"
            await sim.send(bytes(range(256)) * 7 + bytes(254))  # 2046 bytes
            assert len(await fb.receive(timeout=5)) >= 1
            with pytest.raises(AddressError):
                await fb.send_raw(bytes(2047))
            with pytest.raises(AddressError):
                await fb.send([1])
    with pytest.raises(AddressError):
        fixed_client("e71+tcp://127.0.0.1:1?procedure=0&code=ascii")


async def test_udp_broadcast_receive() -> None:
    # real broadcasts need every interface bound, which is an explicit choice (default: loopback)
    async with E71BroadcastReceiver(0, host="0.0.0.0") as rx:
        sim = await start_fixed_buffer(
            transport="udp", procedure=False, broadcast=("127.255.255.255", rx.port)
        )
        try:
            await sim.send(b"\x01\x02 status")
            data, (ip, _port) = await rx.receive(timeout=5)
            assert data == b"\x01\x02 status"
            assert ip == "127.0.0.1"
            await sim.send(b"again")
            async for data, _ in rx:
                assert data == b"again"
                break
        finally:
            await sim.aclose()
        with pytest.raises(PlcTimeout):
            await rx.receive(timeout=0.05)


@pytest.mark.parametrize("client_class", [E71FixedBufferClient, E71Client])
def test_both_e71_clients_take_the_code_one_way(client_class: type[Any]) -> None:
    # the fixed-buffer client and the E71 client read their ``code`` option alike
    transport = TcpTransport("127.0.0.1", 5000)
    assert client_class("plc1", transport, code="ascii").code is Code.ASCII
    assert client_class("plc1", transport, code=Code.BINARY).code is Code.BINARY
    with pytest.raises(AddressError, match="plc1: code must be binary or ascii, not 'ebcdic'"):
        client_class("plc1", transport, code="ebcdic")
