"""S5-LAN client against the module simulator over real loopback TCP, plus the CLI."""

from __future__ import annotations

import asyncio
import json
import re
import struct
import sys
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import plcstack
from plcstack.clients.s5lan import S5LanClient
from plcstack.codecs.s5lan import HEADER_LEN, Header
from plcstack.errors import (
    AddressError,
    ConnectFailed,
    ConnectionLost,
    PlcErrorResponse,
    PlcTimeout,
    RemoteProtocolError,
)
from plcstack.s5address import S5Area, S5Unit
from plcstack.sim import s5lan
from plcstack.sim.s5memory import Area, BlockType, S5Memory
from plcstack.transports.backoff import Backoff
from tests.aio_helpers import ends_quietly, eventually
from tests.cli_helpers import cli_in_process

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
async def sim() -> AsyncIterator[s5lan.S5LanSimulator]:
    simulator = await s5lan.start()
    try:
        yield simulator
    finally:
        await simulator.aclose()


def client_for(sim: s5lan.S5LanSimulator, query: str = "", **options: Any) -> S5LanClient:
    url = sim.url + (f"?{query}" if query else "")
    client = plcstack.connect(url, **options)
    assert isinstance(client, S5LanClient)
    return client


# -- reads and writes of every area ------------------------------------------------------------
async def test_golden_a10_1_content(sim: s5lan.S5LanSimulator) -> None:
    sim.memory.write_db_words(10, 5, [0x1000 + i for i in range(20)])
    async with client_for(sim) as plc:
        assert await plc.read("DB10.DW5", 20) == [0x1000 + i for i in range(20)]
        assert await plc.read("db10.dw24") == [0x1013]


async def test_default_memory_has_db1_to_db10_and_dx1_dx2(sim: s5lan.S5LanSimulator) -> None:
    blocks = sim.memory.blocks()
    assert [n for t, n in blocks if t is BlockType.DB] == list(range(1, 11))
    assert [n for t, n in blocks if t is BlockType.DX] == [1, 2]
    async with client_for(sim) as plc:
        assert await plc.read("DB1.DW255") == [0]
        assert await plc.read("DX2.DW0", 3) == [0, 0, 0]


@pytest.mark.parametrize(
    ("address", "values", "area", "byte_offset", "image"),
    [
        ("MB100", [0xDE, 0xAD, 0xBE, 0xEF], Area.FLAGS, 100, "DEADBEEF"),
        ("MW10", [0x1234, 0xABCD], Area.FLAGS, 10, "1234ABCD"),
        ("MW11", [-1], Area.FLAGS, 11, "FFFF"),
        ("EB0", [1, 2], Area.INPUTS, 0, "0102"),
        ("IW4", [0x0102], Area.INPUTS, 4, "0102"),
        ("AB3", [255, -1, -128], Area.OUTPUTS, 3, "FFFF80"),
        ("QW6", [0x8000], Area.OUTPUTS, 6, "8000"),
        ("T5", [0x2123, 0x0001], Area.TIMERS, 10, "21230001"),
        ("Z3", [0x0999], Area.COUNTERS, 6, "0999"),
        ("C4", [7], Area.COUNTERS, 8, "0007"),
    ],
)
async def test_write_read_areas(
    sim: s5lan.S5LanSimulator,
    address: str,
    values: list[int],
    area: Area,
    byte_offset: int,
    image: str,
) -> None:
    async with client_for(sim) as plc:
        await plc.write(address, values)
        expected = bytes.fromhex(image)
        # stored in S5 (big-endian) order, although words travel low byte first
        assert sim.memory.read_area(area, byte_offset, len(expected)) == expected
        mask = 0xFFFF if address[1:2] == "W" or address[0] in "TZC" else 0xFF
        assert await plc.read(address, len(values)) == [v & mask for v in values]


async def test_db_and_dx_words_and_bytes(sim: s5lan.S5LanSimulator) -> None:
    async with client_for(sim) as plc:
        await plc.write("DB3.DW7", [0x1234, 0x5678, 0x9ABC])
        assert sim.memory.read_db_words(3, 7, 3) == [0x1234, 0x5678, 0x9ABC]
        await plc.write("DX1.DW0", [0xCAFE])
        assert sim.memory.read_db_words(1, 0, 1, BlockType.DX) == [0xCAFE]
        assert await plc.read("DX1.DW0") == [0xCAFE]
        assert await plc.read("DB1.DW0") == [0]  # DB1 and DX1 are different blocks
        # bytes of a DB are read through the covering words: DL7 = 12h, DR7 = 34h, ...
        assert await plc.read("DB3.DL7", 3) == [0x12, 0x34, 0x56]
        assert await plc.read("DB3.DR7", 2) == [0x34, 0x56]
        assert await plc.read("DB3.DBB15", 1) == [0x34]
        # MW100 read as words vs bytes (A.6 consequence)
        await plc.write("MB100", [0xAA, 0xBB])
        assert await plc.read("MW100") == [0xAABB]
        assert await plc.read("MB100", 2) == [0xAA, 0xBB]


# -- larger than 2048 bytes --------------------------------------------------------------------
async def test_read_and_write_larger_than_2048_bytes_are_split() -> None:
    mem = S5Memory()
    words = [(i * 7919) & 0xFFFF for i in range(2500)]
    mem.create_block(BlockType.DB, 20, 2500, struct.pack(">2500H", *words))
    async with await s5lan.start(mem) as sim, client_for(sim) as plc:
        assert await plc.read("DB20.DW0", 2500) == words
        assert plc.stats.requests == 3  # 1024 + 1024 + 452 words
        assert await plc.read("DB20.DL0", 2049) == list(struct.pack(">2500H", *words)[:2049])
        assert plc.stats.requests == 5  # 1025 words -> 1024 + 1
        new = [(0xFFFF - w) for w in words[:1500]]
        await plc.write("DB20.DW100", new)
        assert plc.stats.requests == 7
        assert mem.read_db_words(20, 100, 1500) == new


async def test_split_write_failing_part_way_says_what_was_written() -> None:
    mem = S5Memory(default_dbs={21: 1500})
    async with await s5lan.start(mem) as sim, client_for(sim) as plc:
        with pytest.raises(PlcErrorResponse) as err:
            await plc.write("DB21.DW0", list(range(2000)))
        assert err.value.code == 3
        assert "first 1024 of 2000 values were written and confirmed" in str(err.value)
        assert mem.read_db_words(21, 0, 3) == [0, 1, 2]
        assert mem.read_db_words(21, 1024, 1) == [0]  # the failed part changed nothing


# -- every Err code ----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("address", "count", "code", "fragment"),
    [
        ("DB99.DW0", 1, 2, "does not exist"),
        ("DX9.DW0", 1, 2, "does not exist"),
        ("DB10.DW255", 2, 3, "too small"),
        ("MB255", 2, 3, "too small"),
        ("T127", 2, 3, "too small"),
        ("EW127", 1, 3, "too small"),
    ],
)
async def test_err_codes_from_the_memory(
    sim: s5lan.S5LanSimulator, address: str, count: int, code: int, fragment: str
) -> None:
    async with client_for(sim) as plc:
        with pytest.raises(PlcErrorResponse) as err:
            await plc.read(address, count)
        assert err.value.code == code
        text = str(err.value)
        assert text.startswith(sim.url)
        assert f"read {address} x{count}" in text
        assert f"Err {code}" in text and fragment in text
        assert plc.stats.errors == 1
        # the connection is fine after a PLC error answer
        assert await plc.read("MB0") == [0]


@pytest.mark.parametrize(
    ("code", "fragment"),
    [
        (2, "does not exist"),
        (3, "too small"),
        (6, "incorrect request format"),
        (7, "max. 2048 bytes"),
        (9, "timeout in the communication between the module and the PLC"),
        (10, "too little data"),
        (42, "unknown error 42"),
        (-7, "unknown error -7"),
    ],
)
async def test_every_err_code_is_reported_with_its_meaning(
    sim: s5lan.S5LanSimulator, code: int, fragment: str
) -> None:
    async with client_for(sim) as plc:
        sim.inject_error(code)
        with pytest.raises(PlcErrorResponse) as err:
            await plc.write("MW0", [1])
        assert err.value.code == code
        assert err.value.plc == sim.url
        assert err.value.request == "write MW0 x1"
        assert fragment in str(err.value)
        assert sim.memory.read_area(Area.FLAGS, 0, 2) == b"\x00\x00"  # nothing written
        await plc.write("MW0", [1])
        assert sim.memory.read_area(Area.FLAGS, 0, 2) == b"\x00\x01"


# -- the module's own format checks, seen by a raw TCP peer ------------------------------------
async def _raw(sim: s5lan.S5LanSimulator) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    return await asyncio.open_connection(sim.host, sim.port)


async def _answer(reader: asyncio.StreamReader) -> Header:
    return Header.decode(await reader.readexactly(HEADER_LEN))


@pytest.mark.parametrize(
    ("request_bytes", "err", "closes"),
    [
        (Header("R", "W", "D", 10, 0, 1, plc_type=0x36).encode(), 6, True),
        (Header("R", "W", "D", 10, 0, 1, hd_len=30).encode(), 6, True),
        (Header("X", "W", "D", 10, 0, 1).encode(), 6, True),
        (Header("R", "B", "D", 10, 0, 1).encode(), 6, False),
        (Header("R", "W", "Q", 0, 0, 1).encode(), 6, False),
        (Header("R", "W", "M", 0, 0, 0).encode(), 6, False),
        (Header("R", "W", "D", 10, 0, 1025).encode(), 7, False),
        (Header("W", "B", "M", 0, 0, 2049).encode() + bytes(2049), 7, False),
        (Header("R", "W", "D", 0, 0, 1).encode(), 2, False),
        (Header("W", "W", "D", 10, 256, 1).encode() + b"\x01\x02", 3, False),
    ],
)
async def test_module_format_errors_raw(
    sim: s5lan.S5LanSimulator, request_bytes: bytes, err: int, closes: bool
) -> None:
    reader, writer = await _raw(sim)
    try:
        writer.write(request_bytes)
        answer = await _answer(reader)
        assert answer.err == err
        assert answer.version == 104
        if closes:
            assert await reader.read() == b""
        else:
            writer.write(Header("R", "B", "M", 0, 0, 1).encode())
            assert (await _answer(reader)).err == 0
            assert await reader.readexactly(1) == b"\x00"
    finally:
        writer.close()


async def test_err_10_when_write_data_stop_coming() -> None:
    async with await s5lan.start(data_timeout=0.2) as sim:
        reader, writer = await _raw(sim)
        try:
            writer.write(Header("W", "B", "M", 0, 0, 4).encode() + b"\x01\x02")
            answer = await asyncio.wait_for(_answer(reader), 10)
            assert answer.err == 10
            assert sim.memory.read_area(Area.FLAGS, 0, 4) == bytes(4)  # all or nothing
            writer.write(Header("R", "B", "M", 0, 0, 1).encode())
            assert (await _answer(reader)).err == 0
        finally:
            writer.close()


async def test_garbage_from_a_client_never_kills_the_simulator(
    sim: s5lan.S5LanSimulator,
) -> None:
    for junk in (b"\xff" * 100, b"GET / HTTP/1.0\r\n\r\n" + bytes(40), b"\x35" * 26):
        reader, writer = await _raw(sim)
        writer.write(junk)
        await writer.drain()
        await asyncio.wait_for(reader.read(), 10)  # answered and closed
        writer.close()
    async with client_for(sim) as plc:
        assert await plc.read("MB0") == [0]


# -- one connection at a time ------------------------------------------------------------------
async def test_second_connection_is_refused_and_reported(sim: s5lan.S5LanSimulator) -> None:
    async with client_for(sim) as first:
        assert await first.read("MB0") == [0]
        second = client_for(sim, backoff=Backoff(initial=30.0, maximum=60.0))
        try:
            await second.open()  # TCP accepts; the module closes at once
            # the request was sent, so this is a lost connection, not "never got in"; the hint
            # names the one-connection rule as a possibility without blaming another client
            with pytest.raises(ConnectionLost) as err:
                await second.read("MB0")
            assert type(err.value) is ConnectionLost
            text = str(err.value)
            assert "accepts one connection at a time" in text
            assert "another client" not in text
            assert text.startswith(sim.url)
            with pytest.raises(ConnectFailed) as werr:
                await second.write("MB0", [1])
            # a busy module is not hammered: the next attempt waits for the backoff, and this
            # write fails before a byte of it is sent
            assert "one connection" in str(werr.value)
            assert "next reconnect attempt in" in str(werr.value)
            assert second.stats.requests == 1
            assert sim.refused_connections >= 1
            assert sim.memory.read_area(Area.FLAGS, 0, 1) == b"\x00"
            # the first connection is unaffected
            assert await first.read("MB0") == [0]
        finally:
            await second.aclose()
    # once the first client is gone, another one gets in
    for _ in range(100):
        if sim.active_connections == 0:
            break
        await asyncio.sleep(0.01)
    async with client_for(sim) as third:
        assert await third.read("MB0") == [0]


async def test_max_connections_is_configurable() -> None:
    sim = await s5lan.start(max_connections=2)
    async with sim, client_for(sim) as a, client_for(sim) as b:
        await a.write("MB1", [5])
        assert await b.read("MB1") == [5]


async def test_module_reset_mid_session_reconnects(sim: s5lan.S5LanSimulator) -> None:
    async with client_for(sim) as plc:
        assert await plc.read("MB0") == [0]
        sim.close_clients()
        await eventually(lambda: not plc.transport.is_open, "the client saw the module close")
        assert await plc.read("MB0") == [0]
        assert plc.stats.connects == 2


# -- deadlines and bad peers -------------------------------------------------------------------
async def _fake_module(
    respond: Callable[[bytes, asyncio.StreamWriter], Awaitable[None]],
) -> tuple[asyncio.Server, str]:
    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while data := await reader.read(65536):
                await respond(data, writer)
        except ConnectionError:
            pass
        finally:
            writer.close()

    server = await asyncio.start_server(ends_quietly(handle), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    return server, f"s5lan://127.0.0.1:{port}"


async def test_silent_module_times_out_and_closes() -> None:
    async def silent(data: bytes, writer: asyncio.StreamWriter) -> None:
        return None

    server, url = await _fake_module(silent)
    try:
        async with plcstack.connect(url, timeout=0.1) as plc:
            with pytest.raises(PlcTimeout) as err:
                await plc.write("MB0", [1])
            assert "may or may not have been executed" in str(err.value)
            assert not plc.transport.is_open
            assert plc.stats.timeouts == 1
    finally:
        server.close()
        await server.wait_closed()


async def test_answer_to_another_request_is_rejected() -> None:
    async def stale(data: bytes, writer: asyncio.StreamWriter) -> None:
        h = Header.decode(data[:HEADER_LEN])
        other = Header(h.cmd, h.data_type, h.area, h.db, h.start, h.count, user_code=b"zzzz")
        writer.write(other.response(0).encode() + bytes(h.data_len or 0))

    server, url = await _fake_module(stale)
    try:
        async with plcstack.connect(url) as plc:
            with pytest.raises(RemoteProtocolError, match="user_code") as err:
                await plc.read("MW0", 2)
            assert str(err.value).startswith(url)
            assert not plc.transport.is_open
    finally:
        server.close()
        await server.wait_closed()


async def test_lenient_mode_accepts_and_logs_echo_differences(
    caplog: pytest.LogCaptureFixture,
) -> None:
    async def lower_case_cmd(data: bytes, writer: asyncio.StreamWriter) -> None:
        h = Header.decode(data[:HEADER_LEN])
        echo = Header("r", h.data_type, h.area, h.db, h.start, h.count, user_code=h.user_code)
        writer.write(echo.response(0).encode() + b"\x34\x12")

    server, url = await _fake_module(lower_case_cmd)
    try:
        async with plcstack.connect(url + "?strict=0") as plc:
            assert await plc.read("MW0") == [0x1234]
        assert "echoes cmd differently" in caplog.text
        async with plcstack.connect(url) as plc:
            with pytest.raises(RemoteProtocolError, match="cmd 'r' instead of 'R'"):
                await plc.read("MW0")
    finally:
        server.close()
        await server.wait_closed()


async def test_header_byte_order_option_end_to_end() -> None:
    async with await s5lan.start(header_byte_order="big") as sim:
        async with client_for(sim, "header_byte_order=big") as plc:
            await plc.write("DB10.DW5", [0x0102])
            assert await plc.read("DB10.DW5") == [0x0102]
        async with client_for(sim) as plc:
            # DBNo 10 arrives as 0A00h (no such DB): Err 2 comes back as 0200h = 512
            with pytest.raises(PlcErrorResponse, match="header_byte_order=big") as err:
                await plc.read("DB10.DW5", 1)
            assert err.value.code == 512


async def test_realistic_timing_still_answers() -> None:
    async with await s5lan.start(realistic_timing=True) as sim, client_for(sim) as plc:
        assert await plc.read("DB10.DW0", 20) == [0] * 20


# -- refused before anything is sent -----------------------------------------------------------
@pytest.mark.parametrize(
    ("address", "count_or_values", "fragment"),
    [
        ("D100", 1, "not an S5 address"),
        ("DB10.DBW10", 1, "DB10.DW5"),
        ("MB0", 0, "positive integer"),
        ("MB65535", 2, "16-bit Start"),
        ("DB10.DW65535", 2, "16-bit Start"),
        ("MW0", [True], "not an integer"),
        ("MW0", [0x10000], "-32768..65535"),
        ("MB0", [256], "-128..255"),
        ("MB0", [-129], "-128..255"),
        ("DB10.DL0", [1], "whole data words"),
        ("MB0", [], "positive integer"),
    ],
)
async def test_address_and_value_errors_send_nothing(
    sim: s5lan.S5LanSimulator, address: str, count_or_values: int | list[int], fragment: str
) -> None:
    async with client_for(sim) as plc:
        with pytest.raises(AddressError) as err:
            if isinstance(count_or_values, int):
                await plc.read(address, count_or_values)
            else:
                await plc.write(address, count_or_values)
        assert fragment in str(err.value)
        assert plc.stats.requests == 0


def test_url_options() -> None:
    with pytest.raises(AddressError, match="unknown option"):
        plcstack.connect("s5lan://127.0.0.1:5010?byteorder=big")
    with pytest.raises(AddressError, match="missing port"):
        plcstack.connect("s5lan://127.0.0.1")
    with pytest.raises(AddressError):
        plcstack.connect("s5lan://127.0.0.1:5010?header_byte_order=middle")
    plc = plcstack.connect("s5lan://127.0.0.1:5010?strict=0&header_byte_order=big&timeout=5")
    assert isinstance(plc, S5LanClient)
    assert (plc.strict, plc.header_byte_order, plc.timeout) == (False, "big", 5.0)


# -- poller hooks ------------------------------------------------------------------------------
def test_locate_address_at_max_points() -> None:
    plc = plcstack.connect("s5lan://127.0.0.1:5010")
    cases = ["DB10.DW5", "DX3.DW0", "MB100", "MW10", "MW11", "EB0", "AW4", "T5", "Z5", "DB1.DR3"]
    for text in cases:
        area, index = plc.locate(text)
        assert plc.address_at(area, index) == str(plcstack.s5address.parse_s5_address(text))
        # point k of a read is index + k
        area2, index2 = plc.locate(plc.address_at(area, index + 3))
        assert (area2, index2) == (area, index + 3)
    assert plc.locate("MW10")[0] != plc.locate("MW11")[0]  # overlapping words never merge
    assert plc.locate("MW10")[1] + 1 == plc.locate("MW12")[1]
    assert plc.locate("DB10.DW5")[0] != plc.locate("DB11.DW5")[0]
    assert plc.locate("EB0")[0] == plc.locate("IB7")[0]
    assert plc.max_points(plc.locate("DB1.DW0")[0]) == 1024
    assert plc.max_points(plc.locate("MB0")[0]) == 2048
    assert plc.max_points(plc.locate("DB1.DL0")[0]) == 2046
    assert plc.locate("MB0")[0] == (S5Area.FLAGS, S5Unit.BYTE, None, 0)
    assert plc.point_bits(plc.locate("MB0")[0]) == 8
    assert plc.point_bits(plc.locate("DB1.DL0")[0]) == 8
    assert plc.point_bits(plc.locate("MW0")[0]) == 16
    assert plc.point_bits(plc.locate("T0")[0]) == 16
    with pytest.raises(AddressError):
        plc.locate("X0")
    with pytest.raises(AddressError):
        plc.address_at("nonsense", 1)


# -- CLI (read/write through plcstack.cli.main in this process: tests/cli_helpers.py) --------
async def test_cli_read_json_and_write(sim: s5lan.S5LanSimulator) -> None:
    sim.memory.write_db_words(10, 5, [0x1000 + i for i in range(20)])
    code, out, _ = await cli_in_process("read", sim.url, "DB10.DW5", "20", "--json")
    assert code == 0
    assert json.loads(out) == {"address": "DB10.DW5", "values": [0x1000 + i for i in range(20)]}
    code, out, _ = await cli_in_process("write", sim.url, "MW10", "0x1234", "-1")
    assert code == 0
    assert sim.memory.read_area(Area.FLAGS, 10, 4) == bytes.fromhex("1234FFFF")
    code, _, err = await cli_in_process("read", sim.url, "DB99.DW0")
    assert code == 1
    assert "Err 2" in err and "does not exist" in err
    code, _, err = await cli_in_process("read", sim.url, "DB10.DBW10")
    assert code == 2
    assert "DB10.DW5" in err


async def test_cli_sim_serves_until_stopped() -> None:
    # --port 0: the CLI prints the port it bound (a port picked here first could be taken by
    # another test's process before the simulator binds it).
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "plcstack",
        "sim",
        "s5lan",
        "--port",
        "0",
        cwd=ROOT,
        stdout=asyncio.subprocess.PIPE,
    )
    try:
        assert proc.stdout is not None
        line = (await asyncio.wait_for(proc.stdout.readline(), 30)).decode().strip()
        match = re.fullmatch(r"listening on 127\.0\.0\.1:(\d+) \(TCP\)", line)
        assert match is not None, line
        port = int(match.group(1))
        assert port != 0
        async with plcstack.connect(f"s5lan://127.0.0.1:{port}") as plc:
            await plc.write("DB10.DW5", [7, 8])
            assert await plc.read("DB10.DW5", 2) == [7, 8]
    finally:
        proc.terminate()
        await proc.wait()


async def test_deadline_scales_with_the_size_of_the_request() -> None:
    # 256 words = 512 bytes take the module 50 ms + 768 ms: longer than timeout=0.3, which is
    # therefore stretched to 2 * 0.818 s + 1 s for this request instead of killing it.
    async with await s5lan.start(realistic_timing=True) as sim:
        sim.memory.write_db_words(10, 0, list(range(256)))
        async with client_for(sim, timeout=0.3) as plc:
            assert await plc.read("DB10.DW0", 256) == list(range(256))
            assert await plc.read("MB0", 200) == [0] * 200
            assert plc.stats.timeouts == 0


_AREA_SPANS = {"MB": 256, "MW": 256, "EB": 128, "IW": 128, "AB": 128, "QW": 128}


@settings(max_examples=40, deadline=None)
@given(st.data())
def test_property_write_then_read_matches_the_s5_image(data: st.DataObject) -> None:
    kind = data.draw(st.sampled_from(["MB", "MW", "EB", "IW", "AB", "QW", "DB", "T", "Z"]))
    if kind in _AREA_SPANS:
        unit = 2 if kind[1] == "W" else 1
        size = _AREA_SPANS[kind]
        start = data.draw(st.integers(0, size - unit))
        count = data.draw(st.integers(1, (size - start) // unit))
        address = f"{kind}{start}"
        byte_offset = start
        area = {"M": Area.FLAGS, "E": Area.INPUTS, "I": Area.INPUTS}.get(kind[0], Area.OUTPUTS)
    elif kind == "DB":
        unit, start = 2, data.draw(st.integers(0, 255))
        count = data.draw(st.integers(1, 256 - start))
        address, byte_offset, area = f"DB7.DW{start}", 2 * start, None
    else:
        unit, start = 2, data.draw(st.integers(0, 127))
        count = data.draw(st.integers(1, 128 - start))
        address, byte_offset = f"{kind}{start}", 2 * start
        area = Area.TIMERS if kind == "T" else Area.COUNTERS
    top = 0xFFFF if unit == 2 else 0xFF
    values = data.draw(st.lists(st.integers(0, top), min_size=count, max_size=count))
    image = b"".join(v.to_bytes(unit, "big") for v in values)

    async def scenario() -> None:
        async with await s5lan.start() as sim, client_for(sim) as plc:
            await plc.write(address, values)
            if area is None:
                stored = sim.memory.read_block(BlockType.DB, 7, byte_offset, len(image))
            else:
                stored = sim.memory.read_area(area, byte_offset, len(image))
            assert stored == image
            assert await plc.read(address, count) == values

    asyncio.run(scenario())
