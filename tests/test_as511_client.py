"""AS511 client against the AS511 simulator over real loopback TCP and a real pty pair."""

from __future__ import annotations

import asyncio
import os
import struct
import subprocess
import sys
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest

from plcstack.cli import main
from plcstack.clients import connect
from plcstack.clients.as511 import AS511Client
from plcstack.codecs.as511 import Job, PGState
from plcstack.errors import (
    AddressError,
    ConnectFailed,
    PlcErrorResponse,
    PlcTimeout,
    RemoteProtocolError,
)
from plcstack.s5address import S5Area
from plcstack.sim import as511 as sim_as511
from plcstack.sim.base import Simulator
from plcstack.sim.s5memory import Area, BlockType, S5Memory
from plcstack.transports.serial import SerialTransport, is_pty
from plcstack.url import parse_url
from tests.aio_helpers import ends_quietly
from tests.cli_helpers import cli_in_process

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(params=["tcp", "pty"])
async def sim(request: pytest.FixtureRequest) -> AsyncIterator[Simulator]:
    if request.param == "tcp":
        s: Simulator = await sim_as511.start()
    else:
        s = await sim_as511.start_pty()
    async with s:
        yield s


def machine(s: Simulator) -> sim_as511.AS511Machine:
    m = getattr(s, "machine", None)
    assert isinstance(m, sim_as511.AS511Machine)
    return m


def client_for(url: str, **options: Any) -> AS511Client:
    plc = connect(url, **options)
    assert isinstance(plc, AS511Client)
    return plc


def client(s: Simulator, **options: Any) -> AS511Client:
    return client_for(s.url, **options)


async def test_read_write_db_words(sim: Simulator) -> None:
    async with client(sim) as plc:
        assert await plc.read("DB5.DW0", 4) == [0x0500, 0x0501, 0x0502, 0x0503]
        await plc.write("DB5.DW2", [0x0102, 0x1003])  # B.11.3 data, with 10h bytes
        assert await plc.read("DB5.DW0", 4) == [0x0500, 0x0501, 0x0102, 0x1003]
        assert machine(sim).memory.read_db_words(5, 2, 2) == [0x0102, 0x1003]
        assert await plc.read_db(5, 3, 1) == [0x1003]
        await plc.write_db(5, 10, [-1, 0x1010])
        assert await plc.read_db(5, 10, 2) == [0xFFFF, 0x1010]
        assert await plc.read("DB5.DL3") == [0x10] and await plc.read("DB5.DR3") == [0x03]
        await plc.write("DX1.DW0", [7, 8])
        assert await plc.read_dx(1, 0, 2) == [7, 8]
        assert machine(sim).memory.read_db_words(1, 0, 2, BlockType.DX) == [7, 8]


async def test_areas_use_system_parameter_bases(sim: Simulator) -> None:
    mem = machine(sim).memory
    mem.write_area(Area.INPUTS, 0, b"\x11\x22")
    mem.write_area(Area.TIMERS, 10, b"\x12\x34")
    mem.write_area(Area.COUNTERS, 4, b"\x00\x99")
    async with client(sim) as plc:
        params = await plc.read_system_parameters()
        assert (params.inputs, params.outputs, params.flags) == (0xEF00, 0xEF80, 0xEE00)
        assert (params.timers, params.counters, params.system_data) == (0xED00, 0xEC00, 0xEA00)
        assert await plc.read("IB0", 2) == [0x11, 0x22]
        assert await plc.read("EW0") == [0x1122]
        assert await plc.read("T5") == [0x1234]
        assert await plc.read("Z2") == [0x0099] == await plc.read("C2")
        await plc.write("QB1", [0x10, 0x03])
        assert mem.read_area(Area.OUTPUTS, 1, 2) == b"\x10\x03"
        await plc.write("MB0", [1, 2, 3, 4])
        assert await plc.read("MW0", 2) == [0x0102, 0x0304]
        assert mem.read_absolute(0xEE00, 4) == b"\x01\x02\x03\x04"  # B.11.4 scenario
        assert await plc.read_bytes(S5Area.FLAGS, 0, 4) == b"\x01\x02\x03\x04"


async def test_big_read_is_split_into_512_byte_transactions(sim: Simulator) -> None:
    m = machine(sim)
    async with client(sim) as plc:
        before = m.requests
        words = await plc.read("DB1.DW0", 256)  # B_INFO + 512 bytes in one transaction
        assert words == [0x0100 | k for k in range(256)]
        assert m.requests - before == 2
        before = m.requests
        assert await plc.read("DB1.DW0", 256) == words  # cached: header + 502, then 10 bytes
        assert m.requests - before == 2
        big = bytes(range(256)) * 4
        await plc.write_absolute(0x6000, big)  # 1024 bytes -> 2 write transactions
        assert m.memory.read_absolute(0x6000, 1024) == big
        assert await plc.read_absolute(0x6000, 1024) == big


async def test_missing_block_is_a_nak_and_backs_off(sim: Simulator) -> None:
    async with client(sim) as plc:
        with pytest.raises(PlcErrorResponse) as info:
            await plc.read("DB50.DW0")
        err = info.value
        assert err.code == 0x15 and err.code_text == "DLE NAK"
        assert "DB50 does not exist" in str(err) and sim.url in str(err)
        assert "B_INFO DB50" in str(err)
        loop = asyncio.get_running_loop()
        assert plc.pg.ready_at > loop.time()  # B5.1: the next STX waits for 500 ms of silence
        t0 = loop.time()
        assert await plc.read("DB5.DW0") == [0x0500]
        assert loop.time() - t0 >= 0.45  # a lower bound only: the wait is the rule under test
        assert plc.stats.errors == 1


async def test_busy_and_refused_write_naks(sim: Simulator) -> None:
    m = machine(sim)
    async with client(sim, nak_backoff=0.05) as plc:
        m.busy = True
        with pytest.raises(PlcErrorResponse, match="busy"):
            await plc.read("MB0")
        m.busy = False
        # a write onto a block header is refused by the simulator (B.7.4)
        dw0, _ = m.memory.block_info(BlockType.DB, 5)
        with pytest.raises(PlcErrorResponse, match="refused the write") as info:
            await plc.write_absolute(dw0 - 10, b"\x00\x00")
        assert info.value.code == 0x15
        assert m.memory.block_info(BlockType.DB, 5)[1][:2] == b"\x70\x70"
        with pytest.raises(AddressError, match="has 256 data words"):
            await plc.read("DB5.DW250", 10)
        assert await plc.read("MB0") == [0]


async def test_dead_line_times_out_within_char_timeout(sim: Simulator) -> None:
    m = machine(sim)
    async with client(sim, char_timeout=0.2, nak_backoff=0.1) as plc:
        assert await plc.read("MB0") == [0]
        m.mute = True
        with pytest.raises(PlcTimeout) as info:
            await plc.read("MB0")
        assert "DLE ACK after STX" in str(info.value) and sim.url in str(info.value)
        with pytest.raises(PlcTimeout, match="nothing was written"):
            await plc.write("MB0", [5])
        assert plc.stats.timeouts == 2
        m.mute = False
        assert await plc.read("MB0") == [0]  # recovers (TCP: reconnects; serial: same port)


async def test_cache_invalidated_when_compress_moves_the_block(sim: Simulator) -> None:
    m = machine(sim)
    mem = m.memory
    async with client(sim) as plc:
        assert await plc.read("DB3.DW0", 2) == [0x0300, 0x0301]
        old = plc.block_cache[(1, 3)].dw0
        mem.delete_block(BlockType.DB, 1)
        mem.compress()
        new, _ = mem.block_info(BlockType.DB, 3)
        assert new != old
        # the stale address now holds another block: the signature check catches it
        assert await plc.read("DB3.DW0", 2) == [0x0300, 0x0301]
        assert plc.block_cache[(1, 3)].dw0 == new
        mem.delete_block(BlockType.DB, 2)
        mem.compress()
        await plc.write("DB3.DW1", [0xBEEF])  # writes always ask B_INFO first
        assert mem.read_db_words(3, 0, 2) == [0x0300, 0xBEEF]
        assert mem.read_db_words(4, 0, 1) == [0x0400]  # nothing else was hit
        # a block deleted since it was cached: NAK on the fresh B_INFO, cache entry gone
        mem.delete_block(BlockType.DB, 3)
        mem.compress()
        with pytest.raises(PlcErrorResponse, match="DB3 does not exist"):
            await plc.read("DB3.DW0")
        assert (1, 3) not in plc.block_cache


async def test_cache_recovers_from_recreated_longer_block() -> None:
    mem = S5Memory(default_dbs={1: 4, 2: 4})
    async with await sim_as511.start(mem) as s, client(s) as plc:
        assert await plc.read("DB2.DW0") == [0]
        mem.create_block(BlockType.DB, 2, 40, b"\x00\x01" * 40)
        assert await plc.read("DB2.DW30") == [1]


async def test_stop_and_start_and_block_list(sim: Simulator) -> None:
    m = machine(sim)
    async with client(sim) as plc:
        listing = await plc.read_block_list("DB")
        assert sorted(listing) == list(range(1, 11))
        assert listing[5] == m.memory.block_info(BlockType.DB, 5)[0]
        assert list(await plc.read_block_list("DX")) == [1]
        await plc.stop()
        assert not m.running
        assert m.memory.read_absolute(0xEA0C, 2) == b"\x88\x04"
        await plc.start()
        assert m.running
        assert await plc.change_operating_mode(0) is None and not m.running
        assert await plc.change_operating_mode(1) == 0x25 and m.running
        with pytest.raises(AddressError):
            await plc.change_operating_mode(3)


async def test_garbage_from_the_peer_is_a_remote_protocol_error() -> None:
    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.read(1)
        writer.write(b"\x10\x06")
        await reader.read(1)
        writer.write(b"\x02\x10\x07")  # STX then a bad DLE pair where the accept frame goes
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(ends_quietly(handle), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with client_for(f"as511+tcp://127.0.0.1:{port}") as plc:
            with pytest.raises(RemoteProtocolError, match="accept frame") as info:
                await plc.write_absolute(0xEE00, b"\x01")
            assert "not been sent, nothing was written" in str(info.value)
            assert not plc.transport.is_open
    finally:
        server.close()
        await server.wait_closed()


async def test_address_and_url_errors_send_nothing() -> None:
    for url in (
        "as511+tcp://127.0.0.1:1?bogus=1",
        "as511:///dev/ttyS0?parity=X",
        "as511:///dev/ttyS0?stopbits=3",
    ):
        with pytest.raises(AddressError):
            connect(url)
    plc = connect("as511+tcp://127.0.0.1:1")
    for address, count in (("DB0.DW0", 1), ("M0.0", 1), ("MB200", 100), ("XYZ", 1), ("MB0", 0)):
        with pytest.raises(AddressError):
            await plc.read(address, count)
    for values in ([256], [True], [-1]):
        with pytest.raises(AddressError):
            await plc.write("MB0", values)
    with pytest.raises(AddressError):
        await plc.write("MW0", [0x10000])
    assert plc.stats.requests == 0


async def test_serial_open_errors_and_pty_parity_fallback() -> None:
    with pytest.raises(ConnectFailed):
        await connect("as511:///dev/nonexistent-tty").open()
    with pytest.raises(ConnectFailed):
        await connect("as511:///dev/null").open()  # not a tty: no fallback for non-ptys
    async with await sim_as511.start_pty() as s:
        assert isinstance(s, sim_as511.PtySimulator) and is_pty(s.path)
        transport = SerialTransport(s.path)
        for _ in range(2):  # the re-open is where this kernel answers EINVAL to PARENB
            await transport.open(1.0)
            assert transport.is_open
            await transport.aclose()
        assert transport.parity_fallback
        assert transport.byte_time == pytest.approx(11 / 9600)


async def test_the_pty_parity_fallback_is_said_as_the_readme_says() -> None:
    """README and as511.md: on a pty the transport retries without parity and logs it once at
    INFO, shown with -v, not on the default error output (before, the README said "on
    stderr", where it was never shown)."""
    async with await sim_as511.start_pty() as s:
        code, out, err = await cli_in_process("read", s.url, "MB0")
        assert (code, out) == (0, "MB0: 0\n") and "parity" not in err, err
        code, out, err = await cli_in_process("read", "-v", s.url, "MB0")
        assert code == 0 and err.count("rejects parity E") == 1, err
        assert "INFO" in next(line for line in err.splitlines() if "rejects parity" in line)


def test_poller_hooks() -> None:
    plc = connect("as511+tcp://127.0.0.1:1")
    area, index = plc.locate("DB5.DW10", 4)
    assert index == 10 and plc.address_at(area, 12) == "DB5.DW12"
    assert plc.locate("DB5.DW11")[0] == area
    assert plc.locate("DB6.DW11")[0] != area
    mw_area, mw_index = plc.locate("MW10")
    assert plc.address_at(mw_area, mw_index + 1) == "MW12"
    assert plc.locate("MW11")[0] != mw_area  # odd word starts are another grid
    assert plc.address_at(plc.locate("MW11")[0], 6) == "MW13"
    assert plc.max_points(area) == 251 and plc.max_points(plc.locate("MB0")[0]) == 512
    assert plc.address_at(*plc.locate("T5")) == "T5"
    assert isinstance(plc, AS511Client)
    assert plc.point_bits(area) == 16 and plc.point_bits(plc.locate("MB0")[0]) == 8
    with pytest.raises(AddressError):
        plc.locate("MB250", 10)


def test_url_options() -> None:
    plc = connect("as511:///dev/ttyS9?baud=19200&parity=N&stopbits=2&char_timeout=1.5&strict=1")
    assert isinstance(plc, AS511Client)
    assert isinstance(plc.transport, SerialTransport)
    assert plc.transport.baudrate == 19200 and plc.transport.stopbits == 2
    assert plc.line_byte_time == pytest.approx(11 / 19200)
    assert plc.pg.char_timeout == 1.5 and plc.strict
    assert parse_url("as511+tcp://h:1?cache=0").options == {"cache": "0"}
    assert not connect("as511+tcp://h:1?cache=0").cache_enabled  # type: ignore[attr-defined]
    assert PGState.W_ACK1.value == "W_ACK1"


@pytest.mark.parametrize("mode", ["--pty", "--port=0"])
def test_cli_sim_and_read(mode: str, capsys: pytest.CaptureFixture[str]) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "plcstack", "sim", "as511", mode],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline().strip()
        if mode == "--pty":
            assert line.startswith("serial port /dev/pts/")
            url = "as511://" + line.removeprefix("serial port ")
        else:
            assert line.startswith("listening on 127.0.0.1:") and line.endswith(" (TCP)")
            url = "as511+tcp://" + line.removeprefix("listening on ").removesuffix(" (TCP)")
        # the simulator is the command's own process (it takes signals); the read and the write
        # run the same main in this one, which saves an interpreter each
        capsys.readouterr()
        assert main(["read", url, "DB5.DW0", "4", "--json"]) == 0, capsys.readouterr().err
        out = capsys.readouterr().out
        assert out.strip() == '{"address": "DB5.DW0", "values": [1280, 1281, 1282, 1283]}'
        assert main(["write", url, "DB50.DW0", "1"]) == 1
        assert "DB50 does not exist" in capsys.readouterr().err
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        if proc.stdout is not None:
            proc.stdout.close()


def test_default_memory_layout() -> None:
    mem = sim_as511.default_memory()
    assert [n for t, n in mem.blocks() if t is BlockType.DB] == list(range(1, 11))
    assert mem.read_db_words(10, 255, 1) == [0x0AFF]
    raw = struct.pack(">H", 0x0500)
    assert mem.read_block(BlockType.DB, 5, 0, 2) == raw


# -- the simulator against a spec-exact peer: the B.11 goldens over a real wire --------------------
def golden_memory() -> S5Memory:
    """The B.11 scenario: DB5 header at 4A06h, DW0 at 4A10h, 16 data words; MB0..3 = 1 2 3 4."""
    mem = S5Memory(ram_start=0x4A06)
    mem.create_block(BlockType.DB, 5, 16, bytes.fromhex("1234 0010 ABCD 1010"))
    mem.image[0x4A06 + 4] = 0x00  # PG id as in the golden header (70 70 41 05 00 ...)
    mem.write_area(Area.FLAGS, 0, b"\x01\x02\x03\x04")
    return mem


GOLDEN_DIALOGUES = {
    "B.11.1": [
        ("02", "10 06"),
        ("1A", "02"),
        ("10 06", "16 10 03"),
        ("10 06 01 05 10 04", "10 06 02"),
        ("10 06", "00 4A 10 10 70 70 41 05 00 00 00 00 00 15 10 03"),
        ("10 06", "02"),
        ("10 06", "12 10 03"),
        ("10 06", ""),
    ],
    "B.11.2": [
        ("02", "10 06"),
        ("04", "02"),
        ("10 06", "16 10 03"),
        ("10 06 4A 10 10 4A 17 10 04", "10 06 02"),
        ("10 06", "00 00 00 00 00 12 34 00 10 10 AB CD 10 10 10 10 10 03"),
        ("10 06", "02"),
        ("10 06", "12 10 03"),
        ("10 06", ""),
    ],
    "B.11.3": [
        ("02", "10 06"),
        ("03", "02"),
        ("10 06", "16 10 03"),
        ("10 06 4A 14 01 02 10 10 03 10 04", "10 06 02"),
        ("10 06", "12 10 03"),
        ("10 06", ""),
        # B.11.3: a following read returns the written words on the wire
        ("02", "10 06"),
        ("04", "02"),
        ("10 06", "16 10 03"),
        ("10 06 4A 10 10 4A 17 10 04", "10 06 02"),
        ("10 06", "00 00 00 00 00 12 34 00 10 10 01 02 10 10 03 10 03"),
        ("10 06", "02"),
        ("10 06", "12 10 03"),
        ("10 06", ""),
    ],
    "B.11.4 MB0..3": [
        ("02", "10 06"),
        ("04", "02"),
        ("10 06", "16 10 03"),
        ("10 06 EE 00 EE 03 10 04", "10 06 02"),
        ("10 06", "00 00 00 00 00 01 02 03 04 10 03"),
        ("10 06", "02"),
        ("10 06", "12 10 03"),
        ("10 06", ""),
    ],
    "B.11.4 missing DB7": [
        ("02", "10 06"),
        ("1A", "02"),
        ("10 06", "16 10 03"),
        ("10 06 01 07 10 04", "10 15"),
    ],
}


async def _read_exactly(reader: asyncio.StreamReader, n: int) -> bytes:
    async with asyncio.timeout(5):
        return await reader.readexactly(n)


@pytest.mark.parametrize("name", sorted(GOLDEN_DIALOGUES))
@pytest.mark.parametrize("wire", ["tcp", "pty"])
async def test_simulator_answers_golden_dialogues_on_the_wire(name: str, wire: str) -> None:
    """A PG that is not our client: it writes the spec's PG bytes and expects the AG bytes."""
    mem = golden_memory()
    send: Callable[[bytes], None]
    if wire == "tcp":
        s: Simulator = await sim_as511.start(mem)
        assert isinstance(s, sim_as511.AS511TcpSimulator)
        reader, writer = await asyncio.open_connection(s.host, s.port)
        send = writer.write
    else:
        s = await sim_as511.start_pty(mem)
        assert isinstance(s, sim_as511.PtySimulator)
        fd = os.open(s.path, os.O_RDWR | os.O_NOCTTY)
        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader()
        rfile = os.fdopen(os.dup(fd), "rb", buffering=0)
        pipe, _ = await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), rfile)

        def send(data: bytes) -> None:
            os.write(fd, data)

    try:
        for pg_bytes, ag_bytes in GOLDEN_DIALOGUES[name]:
            send(bytes.fromhex(pg_bytes))
            expected = bytes.fromhex(ag_bytes)
            if expected:
                assert (await _read_exactly(reader, len(expected))).hex(" ") == expected.hex(" ")
        if name == "B.11.3":
            assert mem.read_db_words(5, 2, 2) == [0x0102, 0x1003]
    finally:
        if wire == "tcp":
            writer.close()
        else:
            pipe.close()
            os.close(fd)
        await s.aclose()


async def test_largest_transactions_at_emulated_9600_baud() -> None:
    """512-byte read and write take ~0.6 s of line time each: longer than the 500 ms character
    timeout, so both sides must count line time, not just wait for whole frames."""
    async with await sim_as511.start_pty(baud=9600) as s, client(s) as plc:
        data = bytes(range(256)) * 2
        await plc.write_absolute(0x6000, data)
        assert await plc.read_absolute(0x6000, 512) == data
        assert plc.stats.errors == 0


async def test_concurrent_requests_share_one_line(sim: Simulator) -> None:
    async with client(sim) as plc:
        results = await asyncio.gather(*(plc.read(f"DB{n}.DW{n}", 3) for n in range(1, 11)))
        assert results == [[(n << 8) | (n + k) for k in range(3)] for n in range(1, 11)]
        assert plc.stats.errors == 0


async def test_unsupported_function_is_refused_at_step_4(sim: Simulator) -> None:
    async with client(sim, nak_backoff=0.05) as plc:
        with pytest.raises(PlcErrorResponse, match="does not support function 07h"):
            await plc.transact(Job(0x07, b"", False), "compress memory")
        assert await plc.read("MB0") == [0]
