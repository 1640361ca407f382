"""The fast paths of the issue 8 follow-up must decide exactly as the slow paths they shortcut.

Each fast path is checked against its reference: the per-byte AS511 receive path, the per-value
write encoders, the field-wise S5-LAN echo check, the uncached address parsers, and the
one-timer-per-connection deadline against a silent or slow peer over real loopback sockets.
"""

from __future__ import annotations

import asyncio
import itertools
import struct
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.clients.fetchwrite import FetchWriteClient, _encode_values
from plcstack.clients.s5lan import S5LanClient
from plcstack.codecs import as511
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import Code, DeviceRef, WriteWords, encode_request, parse_address
from plcstack.codecs.s5lan import ClientConnection, Header, Request
from plcstack.errors import AddressError, LocalProtocolError, RemoteProtocolError
from plcstack.s5address import S5Unit, parse_s5_address
from plcstack.transports.tcp import TcpTransport
from plcstack.values import pack_ints, plain_words
from tests.aio_helpers import ends_quietly

values_st = st.lists(
    st.one_of(
        st.integers(-0x9000, 0x10100),
        st.integers(-200, 300),
        st.booleans(),
        st.floats(allow_nan=False, allow_infinity=False),
    ),
    min_size=0,
    max_size=70,
)


# -- write values ------------------------------------------------------------------------------
@settings(max_examples=200)
@given(values_st, st.sampled_from([S5Unit.WORD, S5Unit.BYTE]), st.booleans())
def test_pack_ints_agrees_with_the_per_value_encoder(
    values: list[Any], unit: S5Unit, as_tuple: bool
) -> None:
    seq = tuple(values) if as_tuple else values
    try:
        slow: bytes | None = _encode_values(unit, seq)
    except AddressError:
        slow = None
    fast = pack_ints(seq, ">", "H" if unit is S5Unit.WORD else "B")
    if fast is not None:
        assert fast == slow  # the fast path never accepts what the slow one refuses
    elif values and all(type(v) is int for v in values):
        assert slow is None  # plain ints are refused by the fast path only when out of range


@settings(max_examples=200)
@given(values_st)
def test_plain_words_agrees_with_the_range_rule(values: list[Any]) -> None:
    fast = plain_words(values)
    ok = bool(values) and all(type(v) is int and -0x8000 <= v <= 0xFFFF for v in values)
    assert (fast is not None) == ok
    if fast is not None:
        assert fast == tuple(v & 0xFFFF for v in values)


@settings(max_examples=200)
@given(
    st.lists(
        st.one_of(st.integers(-5, 0x10005), st.booleans(), st.just(1.5)), min_size=0, max_size=260
    )
)
def test_e71_write_words_fast_encoding_matches_the_frame_rule(values: list[Any]) -> None:
    req = WriteWords(parse_address("D100"), tuple(values))
    valid = 1 <= len(values) <= 256 and all(isinstance(v, int) and 0 <= v <= 0xFFFF for v in values)
    if not valid:
        with pytest.raises(LocalProtocolError):
            encode_request(req, Code.BINARY)
        return
    expected = struct.pack("<BBHIHBB", 0x03, 0xFF, 0x000A, 100, 0x4420, len(values) & 0xFF, 0)
    assert encode_request(req, Code.BINARY) == expected + struct.pack(f"<{len(values)}H", *values)


def test_e71_write_words_fast_path_keeps_head_and_ref_checks() -> None:
    m3 = DeviceRef(parse_address("M3").device, 3)  # bit device in word units: head % 16
    with pytest.raises(LocalProtocolError, match="multiple of 16"):
        encode_request(WriteWords(m3, (1,)), Code.BINARY)
    with pytest.raises(LocalProtocolError):
        encode_request(WriteWords("D100", (1,)), Code.BINARY)  # type: ignore[arg-type]


# -- S5-LAN echo check ---------------------------------------------------------------------------
@settings(max_examples=200)
@given(st.integers(0, 25), st.integers(1, 255), st.booleans())
def test_s5lan_byte_echo_check_matches_the_field_check(pos: int, xor: int, strict: bool) -> None:
    """Corrupt one byte of the answer header: the codec raises (strict) or lists a mismatch
    exactly when the field-wise comparison of the reference ``_check_reply`` finds one."""
    request = Request.read("D", "W", 0, 4, db=10, user_code=b"\x07\x00\x00\x00")
    codec = ClientConnection(strict=strict)
    sent = codec.send(request)
    answer = bytearray(request.header.response(0).encode())
    answer[pos] ^= xor
    reference = ClientConnection(strict=strict)
    reference.send(request)
    try:
        reference._check_reply(request.header, Header.decode(bytes(answer)))
        ref_error = False
    except RemoteProtocolError:
        ref_error = True
    assert sent[:26] == request.header.encode()
    codec.receive_data(bytes(answer) + bytes(8))
    try:
        event = codec.next_event()
    except RemoteProtocolError as exc:
        if "byte(s) more than" not in exc.message:  # an Err answer carries no data
            assert ref_error
            return
        event = None
    assert not ref_error
    if event is not None:
        assert getattr(event, "echo_mismatch", ()) == reference._mismatch


# -- AS511 run-wise de-stuffing --------------------------------------------------------------
def _events(pg: as511.PGConnection) -> list[Any]:
    out: list[Any] = []
    while True:
        try:
            event = pg.next_event()
        except RemoteProtocolError as exc:
            out.append(("error", exc.message))
            continue
        if event is NEED_DATA:
            return out
        out.append(event)


def _snapshot(pg: as511.PGConnection) -> tuple[Any, ...]:
    return (pg.state, pg.deadline, pg.ready_at, pg.data_to_send(), _events(pg))


@settings(max_examples=200, deadline=None)
@given(
    st.binary(min_size=1, max_size=80),
    st.lists(st.integers(0, 200), max_size=6),
    st.lists(st.tuples(st.integers(0, 400), st.integers(0, 255)), max_size=3),
    st.sampled_from([0.0, 0.2, 0.7]),
)
def test_as511_bulk_receive_equals_byte_by_byte(
    data: bytes, cuts: list[int], corrupt: list[tuple[int, int]], late: float
) -> None:
    """The AG's whole answer to a read (optionally corrupted), in arbitrary chunks, some of them
    late: ``receive_data`` must leave the PG exactly as feeding the same bytes one at a time."""
    job = as511.read_job(0x1000, len(data))
    ag_stream = bytearray(
        as511.DLE_ACK
        + bytes([as511.STX])
        + as511.ACCEPT_FRAME
        + as511.DLE_ACK
        + bytes([as511.STX])
        + as511.stuff(bytes(5) + data)
        + bytes([as511.DLE, as511.ETX, as511.STX, 0x12, as511.DLE, as511.ETX])
    )
    for where, value in corrupt:
        if ag_stream:
            ag_stream[where % len(ag_stream)] = value
    bounds = sorted({0, len(ag_stream), *(c % (len(ag_stream) + 1) for c in cuts)})
    chunks = [bytes(ag_stream[a:b]) for a, b in itertools.pairwise(bounds)]
    bulk, ref = as511.PGConnection(), as511.PGConnection()
    for pg in (bulk, ref):
        pg.submit(job, 0.0)
    now = 0.0
    events: list[Any] = []
    for i, chunk in enumerate(chunks):
        now += late if i % 2 else 0.01
        bulk.receive_data(chunk, now)
        for byte in chunk:
            ref.receive_data(bytes([byte]), now)
        got = _snapshot(bulk)
        assert got == _snapshot(ref)
        events += got[-1]
    if not corrupt and late < as511.DEFAULT_CHAR_TIMEOUT:  # the clean answer decodes
        assert events == [as511.Response(0x04, bytes(5) + data)]


@settings(max_examples=200)
@given(st.binary(max_size=120), st.integers(0, 120), st.one_of(st.none(), st.integers(0, 60)))
def test_unstuffer_feed_from_equals_feed(data: bytes, start: int, limit: int | None) -> None:
    start = min(start, len(data))
    bulk, ref = as511.Unstuffer(as511.ETX, limit), as511.Unstuffer(as511.ETX, limit)
    try:
        end: int | str = bulk.feed_from(data, start)
    except RemoteProtocolError as exc:
        end = exc.message
    expected: int | str = -1
    try:
        for i in range(start, len(data)):
            if ref.feed(data[i]):
                expected = i + 1
                break
    except RemoteProtocolError as exc:
        expected = exc.message
    assert end == expected
    if isinstance(end, int):
        assert bulk.payload() == ref.payload()


# -- cached address parsing and read plans -----------------------------------------------------
def test_cached_s5_parser_still_refuses_and_never_caches_errors() -> None:
    assert parse_s5_address("db10.dw5") is parse_s5_address("db10.dw5")
    for _ in range(2):
        with pytest.raises(AddressError, match="S7 notation"):
            parse_s5_address("DB10.DBW10")
        with pytest.raises(AddressError, match="not a string"):
            parse_s5_address(["DB10.DW5"])  # type: ignore[arg-type]


@pytest.mark.parametrize("cls", [FetchWriteClient, S5LanClient])
async def test_read_plan_cache_keeps_count_checks(cls: Any) -> None:
    client = cls("test://plc", "127.0.0.1", 1, timeout=0.5, connect_timeout=0.5)
    for bad in (True, 0, -1, 1.0):
        with pytest.raises(AddressError):
            await client.read("DB10.DW0", bad)
    with pytest.raises(AddressError):
        await client.read(["DB10.DW0"], 1)


# -- one deadline timer per connection -------------------------------------------------------
async def test_deadline_timer_rearms_earlier_and_later_over_loopback() -> None:
    replies: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while True:
            delay, data = await replies.get()
            await asyncio.sleep(delay)
            writer.write(data)

    server = await asyncio.start_server(ends_quietly(handle), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with server:
        t = TcpTransport("127.0.0.1", port)
        await t.open(2.0)
        loop = asyncio.get_running_loop()
        # 1. the timer is armed for a short deadline by a read that is answered at once ...
        await replies.put((0.0, b"a"))
        assert await t.read(loop.time() + 0.05) == b"a"
        # 2. ... and fires while the next read (long deadline) waits: it re-arms, no timeout
        await replies.put((0.3, b"b"))
        assert await t.read(loop.time() + 10.0) == b"b"
        # 3. a long deadline is armed; a later short deadline must still expire on its own
        await replies.put((0.0, b"c"))
        assert await t.read(loop.time() + 30.0) == b"c"
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(t.read(loop.time() + 0.05), 10.0)
        # 4. after a timeout the connection still works for a read without deadline
        await replies.put((0.0, b"d"))
        assert await asyncio.wait_for(t.read(), 10.0) == b"d"
        t.abort()


@pytest.mark.parametrize("sim_name", ["fetchwrite", "s5lan", "as511"])
async def test_cached_plans_still_check_every_value_and_count(sim_name: str) -> None:
    """After a good write and read have cached their plans, bad values, counts and types at the
    same address are still refused before anything is sent, and the PLC memory is unchanged."""
    import importlib

    import plcstack
    from plcstack.sim.s5memory import S5Memory

    memory = S5Memory(default_dbs={10: 16})
    sim = await importlib.import_module(f"plcstack.sim.{sim_name}").start(memory)
    try:
        async with plcstack.connect(sim.url, timeout=5.0) as plc:
            await plc.write("DB10.DW2", [1, 2])
            assert await plc.read("DB10.DW2", 2) == [1, 2]
            for bad in ([True, 2], [1, 0x10000], [1, -0x8001], [1, 2.0], (1, "2")):
                with pytest.raises(AddressError):
                    await plc.write("DB10.DW2", bad)  # type: ignore[arg-type]
            for count in (True, 0, 2.0):
                with pytest.raises(AddressError):
                    await plc.read("DB10.DW2", count)  # type: ignore[arg-type]
            await plc.write("DB10.DW2", [-1, 0xFFFF])  # two's complement, same plan
            assert memory.read_db_words(10, 2, 2) == [0xFFFF, 0xFFFF]
    finally:
        await sim.aclose()
