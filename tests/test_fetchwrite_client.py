"""FetchWriteClient against the FETCH/WRITE simulator over real loopback TCP, raw and with MK."""

from __future__ import annotations

import asyncio
import contextlib
import struct
import subprocess
import sys
from collections.abc import AsyncIterator, Callable

import pytest

from plcstack import clients as plcurl
from plcstack.clients.fetchwrite import FetchWriteClient
from plcstack.codecs import NEED_DATA
from plcstack.codecs.mk import LifeAck, MkConnection
from plcstack.errors import (
    AddressError,
    ConnectionLost,
    PlcErrorResponse,
    PlcTimeout,
)
from plcstack.sim import fetchwrite as fwsim
from plcstack.sim.s5memory import Area, BlockType
from tests.aio_helpers import ends_quietly

H = bytes.fromhex


def connect(url: str, **options: object) -> FetchWriteClient:
    client = plcurl.connect(url, **options)
    assert isinstance(client, FetchWriteClient)
    return client


@pytest.fixture(params=[False, True], ids=["raw", "mk"])
async def sim(request: pytest.FixtureRequest) -> AsyncIterator[fwsim.FetchWriteSimulator]:
    async with await fwsim.start(mk=request.param) as s:
        yield s


async def wait_for(cond: Callable[[], bool], limit: float = 5.0) -> None:
    """Poll ``cond`` (no wall-clock assertion: the limit only bounds a failing test)."""
    async with asyncio.timeout(limit):
        while not cond():  # noqa: ASYNC110 - the conditions are counters, not events
            await asyncio.sleep(0.01)


class Proxy:
    """A TCP relay between client and simulator that records both directions."""

    def __init__(self, port: int, s2c: Callable[[bytes], bytes] | None = None) -> None:
        self.target = port
        self.s2c = s2c
        self.c2s_bytes = bytearray()
        self.s2c_bytes = bytearray()
        self.server: asyncio.Server | None = None
        self.port = 0
        self._writers: list[asyncio.StreamWriter] = []

    async def start(self) -> int:
        self.server = await asyncio.start_server(ends_quietly(self._handle), "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]
        return self.port

    async def _handle(self, cr: asyncio.StreamReader, cw: asyncio.StreamWriter) -> None:
        sr, sw = await asyncio.open_connection("127.0.0.1", self.target)
        self._writers += [cw, sw]

        async def pump(
            r: asyncio.StreamReader,
            w: asyncio.StreamWriter,
            log: bytearray,
            f: Callable[[bytes], bytes] | None,
        ) -> None:
            with contextlib.suppress(ConnectionError):
                while data := await r.read(65536):
                    log += data
                    w.write(f(data) if f else data)
            w.close()

        await asyncio.gather(
            pump(cr, sw, self.c2s_bytes, None), pump(sr, cw, self.s2c_bytes, self.s2c)
        )

    async def aclose(self) -> None:
        if self.server is not None:
            self.server.close()
            for w in self._writers:
                w.transport.abort()
            await self.server.wait_closed()


# -- reads and writes of every area --------------------------------------------------------


async def test_read_golden_db_words(sim: fwsim.FetchWriteSimulator) -> None:
    async with connect(sim.url) as plc:
        assert await plc.read("DB10.DW5", 20) == [0x1000 + i for i in range(20)]
        assert await plc.read("DB20.DW100") == [100]


async def test_write_and_read_back_every_area(sim: fwsim.FetchWriteSimulator) -> None:
    mem = sim.memory
    async with connect(sim.url) as plc:
        await plc.write("DB1.DW3", [0x1234, 0xFFFF, -1])
        assert mem.read_db_words(1, 3, 3) == [0x1234, 0xFFFF, 0xFFFF]
        assert await plc.read("DB1.DW3", 3) == [0x1234, 0xFFFF, 0xFFFF]
        await plc.write("MB100", [0xDE, 0xAD, 0xBE, 0xEF])
        assert mem.read_area(Area.FLAGS, 100, 4) == H("DE AD BE EF")
        assert await plc.read("MW100", 2) == [0xDEAD, 0xBEEF]
        assert await plc.read("MW101") == [0xADBE]
        await plc.write("QW4", [0x0102])
        assert mem.read_area(Area.OUTPUTS, 4, 2) == H("01 02")
        assert await plc.read("AB4", 2) == [1, 2]
        mem.write_area(Area.INPUTS, 0, H("11 22 33"))
        assert await plc.read("IB0", 3) == [0x11, 0x22, 0x33]
        assert await plc.read("EW1") == [0x2233]
        await plc.write("T5", [0x0123, 0x0456])
        assert mem.read_area(Area.TIMERS, 10, 4) == H("01 23 04 56")
        assert await plc.read("T6") == [0x0456]
        await plc.write("Z2", [7])
        assert await plc.read("C2") == [7]
        assert mem.read_area(Area.COUNTERS, 4, 2) == H("00 07")
        await plc.write("DX3.DW1", [0xABCD])
        assert mem.read_db_words(3, 1, 1, BlockType.DX) == [0xABCD]
        assert await plc.read("DX3.DW0", 2) == [0, 0xABCD]


async def test_db_byte_reads_and_aligned_byte_writes(sim: fwsim.FetchWriteSimulator) -> None:
    async with connect(sim.url) as plc:
        assert await plc.read("DB10.DL5") == [0x10]
        assert await plc.read("DB10.DR5", 3) == [0x00, 0x10, 0x01]
        assert await plc.read("DB10.DBB13", 2) == [0x01, 0x10]
        await plc.write("DB1.DL2", [0x12, 0x34])
        assert sim.memory.read_db_words(1, 2, 1) == [0x1234]
        with pytest.raises(AddressError, match="whole words"):
            await plc.write("DB1.DR2", [1])


async def test_large_write_split_into_telegrams_over_mk() -> None:
    async with await fwsim.start(mk=True) as sim:
        proxy = Proxy(sim.port)
        await proxy.start()
        values = [(i * 37) & 0xFFFF for i in range(300)]
        try:
            async with connect(f"fetchwrite://127.0.0.1:{proxy.port}?mk=1") as plc:
                await plc.read("DB20.DW0")  # PC counter -> 1, as in C.10-6
                await plc.write("DB20.DW0", values)
                assert await plc.read("DB20.DW0", 300) == values
        finally:
            await proxy.aclose()
        wire = bytes(proxy.c2s_bytes)
        write_at = 8 + 16  # after the first (FETCH) telegram
        assert wire[write_at : write_at + 8] == H("4D 4B 00 02 01 00 01 00")
        assert wire[write_at + 8 : write_at + 24] == H(
            "53 35 10 01 03 03 03 08 01 14 00 00 01 2C FF 02"
        )
        second = write_at + 8 + 512
        assert wire[second : second + 8] == H("4D 4B 68 00 00 00 02 00")
        # the 600-byte FETCH answer comes back in two telegrams from the module
        assert sim.memory.read_db_words(20, 0, 300) == values


async def test_raw_wire_bytes_are_the_goldens() -> None:
    """Independent of our client: golden request bytes on a socket get golden answers."""
    async with await fwsim.start() as sim:
        r, w = await asyncio.open_connection(sim.host, sim.port)
        w.write(H("53 35 10 01 03 05 03 08 01 0A 00 05 00 14 FF 02"))
        ack = await r.readexactly(56)
        assert ack[:16] == H("53 35 10 01 03 06 0F 03 00 FF 07 00 00 00 00 00")
        assert ack[16:] == b"".join(struct.pack(">H", 0x1000 + i) for i in range(20))
        w.write(H("53 35 10 01 03 03 03 08 02 00 00 64 00 04 FF 02 DE AD BE EF"))
        assert await r.readexactly(16) == H("53 35 10 01 03 04 0F 03 00 FF 07 00 00 00 00 00")
        w.write(H("53 35 10 01 03 05 03 08 01 63 00 00 00 01 FF 02"))
        assert await r.readexactly(16) == H("53 35 10 01 03 06 0F 03 02 FF 07 00 00 00 00 00")
        w.close()


async def test_mk_wire_bytes_are_the_goldens() -> None:
    async with await fwsim.start(mk=True) as sim:
        r, w = await asyncio.open_connection(sim.host, sim.port)
        w.write(H("4D 4B 10 00 00 00 00 00 53 35 10 01 03 05 03 08 01 0A 00 05 00 14 FF 02"))
        ack = await r.readexactly(8 + 56)
        assert ack[:24] == H(
            "4D 4B 38 00 00 00 00 00 53 35 10 01 03 06 0F 03 00 FF 07 00 00 00 00 00"
        )
        w.write(H("4D 4B 00 00 00 00 01 00"))  # a life ack is never answered
        w.write(
            H("4D 4B 14 00 00 00 01 00 53 35 10 01 03 03 03 08 02 00 00 64 00 04 FF 02 DE AD BE EF")
        )
        assert await r.readexactly(24) == H(
            "4D 4B 10 00 00 00 01 00 53 35 10 01 03 04 0F 03 00 FF 07 00 00 00 00 00"
        )
        w.close()


async def test_new_connection_per_request_like_hsl(sim: fwsim.FetchWriteSimulator) -> None:
    for i in range(5):
        async with connect(sim.url) as plc:
            await plc.write("MB0", [i])
            assert await plc.read("MB0") == [i]
    assert sim.connections == 5


# -- errors end to end ---------------------------------------------------------------------


async def test_error_acks_end_to_end(sim: fwsim.FetchWriteSimulator) -> None:
    async with connect(sim.url) as plc:
        with pytest.raises(PlcErrorResponse) as missing:
            await plc.read("DB99.DW0")
        assert missing.value.code == 2
        text = str(missing.value)
        assert sim.url in text and "read DB99.DW0 x1" in text and "does not exist" in text
        with pytest.raises(PlcErrorResponse) as small:
            await plc.write("DB1.DW63", [1, 2])
        assert small.value.code == 3 and "too small" in str(small.value)
        assert "write DB1.DW63 x2" in str(small.value)
        with pytest.raises(PlcErrorResponse) as flags:
            await plc.read("MB250", 10)
        assert flags.value.code == 3
        sim.inject_error = 0x04
        with pytest.raises(PlcErrorResponse, match="QVZ"):
            await plc.read("MB0")
        sim.inject_error = 0x42
        with pytest.raises(PlcErrorResponse, match="42H: undocumented"):
            await plc.write("MB0", [1])
        sim.inject_error = None
        assert await plc.read("DB10.DW5") == [0x1000]  # the connection survived every error
        assert plc.stats.errors == 5 and sim.connections == 1


async def test_timeout_closes_the_connection_and_says_write_outcome_unknown(
    sim: fwsim.FetchWriteSimulator,
) -> None:
    async with connect(sim.url, timeout=0.2) as plc:
        sim.silent = True
        with pytest.raises(PlcTimeout) as rd:
            await plc.read("MB0")
        assert "connection closed" in str(rd.value)
        with pytest.raises(PlcTimeout, match="may or may not have been executed"):
            await plc.write("MB0", [1])
        sim.silent = False
        assert await plc.read("DB10.DW5") == [0x1000]
        assert sim.connections == 3


async def test_framing_mismatch_is_a_clear_connection_error() -> None:
    async with await fwsim.start(mk=True) as sim:
        plc = connect(f"fetchwrite://{sim.host}:{sim.port}", timeout=1.0)
        async with plc:
            with pytest.raises(ConnectionLost, match="read MB0 x1"):
                await plc.read("MB0")


async def test_simulator_survives_garbage(sim: fwsim.FetchWriteSimulator) -> None:
    junks = [
        b"\x00" * 40,
        b"S5" + bytes(30),
        b"MK\x04\x00\x00\x00\x00\x00XXXX" + bytes(8),
        b"GET / HTTP/1.0\r\n\r\n",
        H("53 35 10 01 03 06 03 08 01 0A 00 05 00 14 FF 02"),
    ]
    for junk in junks:
        r, w = await asyncio.open_connection(sim.host, sim.port)
        w.write(junk)
        assert await asyncio.wait_for(r.read(), 5) == b""  # closed without an answer (C.6.5)
        w.close()
    async with connect(sim.url) as plc:
        assert await plc.read("DB10.DW5") == [0x1000]


async def test_address_errors_send_nothing(sim: fwsim.FetchWriteSimulator) -> None:
    async with connect(sim.url) as plc:
        bad_reads = [("DB10.DBW10", 1), ("M10.3", 1), ("DB0.DW0", 1), ("MB0", 0), ("MB0", 5000),
                     ("DB1.DW0", 2049), ("XY1", 1)]  # fmt: skip
        for addr, count in bad_reads:
            with pytest.raises(AddressError) as exc:
                await plc.read(addr, count)
            assert sim.url in str(exc.value)
        bad_writes: list[tuple[str, list[object]]] = [
            ("MB0", [256]), ("MB0", [True]), ("MW0", [0x10000]), ("MW0", [-0x8001]),
            ("MB0", []), ("DB1.DL0", [1]), ("MB0", ["1"]),
        ]  # fmt: skip
        for addr, values in bad_writes:
            with pytest.raises(AddressError):
                await plc.write(addr, values)  # type: ignore[arg-type]
    assert sim.jobs == 0


@pytest.mark.parametrize(
    "query",
    [
        "x=1",
        "mk=maybe",
        "db_start=dword",
        "write_port=0",
        "life_ack=1",
        "mk=1&life_ack=-1",
        "mk=1&life_ack=abc",
        "timeout=0",
    ],
)
def test_bad_url_options(query: str) -> None:
    with pytest.raises(AddressError):
        plcurl.connect(f"fetchwrite://127.0.0.1:5030?{query}")


# -- variants ------------------------------------------------------------------------------


async def test_db_start_byte_variant() -> None:
    async with await fwsim.start(db_start_unit="byte") as sim:
        assert "db_start=byte" in sim.url
        async with connect(sim.url) as plc:
            assert await plc.read("DB10.DW5", 2) == [0x1000, 0x1001]
            await plc.write("DB1.DW7", [0x7777])
            assert sim.memory.read_db_words(1, 7, 1) == [0x7777]
        # a Siemens-style client against a byte-addressed CP reads the wrong words: the option
        # matters and is not guessed
        async with connect(f"fetchwrite://{sim.host}:{sim.port}") as plc:
            assert await plc.read("DB10.DW10") == [0x1000]


async def test_separate_write_port() -> None:
    async with await fwsim.start(write_port=0, mk=True) as sim:
        assert sim.write_port is not None and f"write_port={sim.write_port}" in sim.url
        async with connect(sim.url) as plc:
            await plc.write("DB1.DW0", [1, 2, 3])
            assert await plc.read("DB1.DW0", 3) == [1, 2, 3]
        assert sim.connections == 2
        # without the option, WRITE reaches the FETCH port, which refuses it (error 01)
        async with connect(f"fetchwrite://{sim.host}:{sim.port}?mk=1") as plc:
            with pytest.raises(PlcErrorResponse) as exc:
                await plc.write("DB1.DW0", [9])
            assert exc.value.code == 1
        async with connect(f"fetchwrite://{sim.host}:{sim.write_port}?mk=1") as plc:
            with pytest.raises(PlcErrorResponse):
                await plc.read("DB1.DW0")


async def test_write_port_failure_names_the_write_connection() -> None:
    async with await fwsim.start(write_port=0) as sim:
        sim.write_server.close()  # type: ignore[union-attr]
        await sim.write_server.wait_closed()  # type: ignore[union-attr]
        with pytest.raises(ConnectionLost, match="write connection"):
            async with connect(sim.url):
                pass


# -- life acks -------------------------------------------------------------------------------


async def test_life_acks_keep_an_idle_connection_alive() -> None:
    async with await fwsim.start(mk=True, life_ack=0.1) as sim, connect(sim.url) as plc:
        assert "life_ack=0.1" in sim.url and plc.life_timeout == pytest.approx(0.3)
        await plc.read("MB0")
        await wait_for(lambda: sim.life_acks_received >= 3 and sim.life_acks_sent >= 3)
        assert plc.codec.mk is not None and plc.codec.mk.life_acks_received >= 1
        assert await plc.read("DB10.DW5") == [0x1000]
        assert plc.dead_peers == 0 and sim.dropped_dead == 0 and sim.connections == 1


async def test_missing_life_acks_declare_the_peer_dead() -> None:
    async with await fwsim.start(mk=True) as sim:  # this CP does not send life acks
        plc = connect(sim.url + "&life_ack=0.05")
        async with plc:
            await plc.read("MB0")
            await wait_for(lambda: plc.dead_peers == 1)
            assert not plc.transport.is_open
            with pytest.raises(ConnectionLost) as exc:
                await plc.read("MB0")
            assert "peer dead" in str(exc.value) and "life ack" in str(exc.value)
            assert sim.url in str(exc.value)
            assert await plc.read("DB10.DW5") == [0x1000]  # reconnects afterwards
            assert sim.life_acks_received >= 1


async def test_simulator_drops_a_client_without_life_acks() -> None:
    async with await fwsim.start(mk=True, life_ack=0.05) as sim:
        plc = connect(f"fetchwrite://{sim.host}:{sim.port}?mk=1")
        async with plc:
            await plc.read("MB0")
            await wait_for(lambda: sim.dropped_dead == 1)
            # the simulator's close reaches the client a loop pass or two later; a read sent
            # before that meets the closing socket (ConnectionLost), which is not this test
            await wait_for(lambda: not plc.transport.is_open)
            assert await plc.read("DB10.DW5") == [0x1000]  # transparently reconnected
            assert sim.connections == 2


async def test_life_acks_stopped_by_the_peer_mid_session() -> None:
    async with await fwsim.start(mk=True, life_ack=0.05) as sim, connect(sim.url) as plc:
        await plc.read("MB0")
        sim.send_life_acks = False
        await wait_for(lambda: plc.dead_peers == 1)
        with pytest.raises(ConnectionLost, match="peer dead"):
            await plc.write("MB0", [1])
        assert sim.memory.read_area(Area.FLAGS, 0, 1) == b"\x00"


# -- poller hooks --------------------------------------------------------------------------


def test_poller_hooks() -> None:
    plc = connect("fetchwrite://127.0.0.1:5030")
    for addr in ["DB10.DW5", "MW10", "MW11", "MB3", "T5", "Z7", "DX3.DW0", "DB10.DR2", "QW4"]:
        area, index = plc.locate(addr)
        assert plc.address_at(area, index) == str(plc_addr(addr))
    area, index = plc.locate("MW10", 3)
    assert plc.address_at(area, index + 2) == "MW14"
    assert plc.locate("MW11")[0] != area
    assert plc.locate("DB10.DW5")[0] != plc.locate("DB11.DW5")[0]
    assert plc.max_points(plc.locate("DB1.DW0")[0]) == 2048
    assert plc.max_points(plc.locate("MB0")[0]) == 4096
    assert plc.max_points(plc.locate("MW0")[0]) == 2048
    with pytest.raises(AddressError):
        plc.locate("MB0", 4097)
    with pytest.raises(AddressError):
        plc.max_points("DB1")


def plc_addr(text: str) -> object:
    from plcstack.s5address import parse_s5_address

    return parse_s5_address(text)


# -- CLI -------------------------------------------------------------------------------------


def test_cli_sim_and_read_write(capsys: pytest.CaptureFixture[str]) -> None:
    from plcstack.cli import main

    proc = subprocess.Popen(
        [sys.executable, "-m", "plcstack", "sim", "fetchwrite", "--port", "0", "--mk"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("listening on 127.0.0.1:")
        assert line.endswith(" (TCP)\n")
        url = f"fetchwrite://{line.split()[2]}?mk=1"
        assert main(["read", url, "DB10.DW5", "3", "--json"]) == 0
        assert capsys.readouterr().out.strip() == (
            '{"address": "DB10.DW5", "values": [4096, 4097, 4098]}'
        )
        assert main(["write", url, "MW20", "0x1234", "-2"]) == 0
        capsys.readouterr()
        assert main(["read", url, "MB20", "4"]) == 0
        assert capsys.readouterr().out.strip() == "MB20: 18 52 255 254"
        assert main(["read", url, "DB99.DW0"]) == 1
        assert "02H: requested block or area does not exist" in capsys.readouterr().err
        assert main(["read", url, "DB10.DBW4"]) == 2
    finally:
        proc.terminate()
        proc.wait(10)


async def test_cli_serve_cli_in_process() -> None:
    import argparse

    parser = argparse.ArgumentParser()
    fwsim.add_cli_arguments(parser)
    args = parser.parse_args(["--port", "0", "--write-port", "0", "--mk", "--db-start", "byte"])
    lines: list[str] = []
    task = asyncio.create_task(fwsim.serve_cli(args, lines.append))
    await wait_for(lambda: bool(lines))
    assert lines[0].startswith("listening on 127.0.0.1:") and "(TCP, WRITE)" in lines[0]
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


def test_mk_connection_used_by_the_client_is_strict_when_asked() -> None:
    plc = connect("fetchwrite://127.0.0.1:5030?mk=1&strict=1")
    codec = plc.new_codec()
    assert isinstance(codec.mk, MkConnection) and codec.mk.strict


async def test_idle_close_by_the_peer_is_not_an_error_with_keep_alive() -> None:
    async with await fwsim.start(mk=True, life_ack=0.05, life_timeout=0.1) as sim:
        plc = connect(f"fetchwrite://{sim.host}:{sim.port}?mk=1&life_ack=0.3")
        async with plc:
            await plc.read("MB0")
            await wait_for(lambda: sim.dropped_dead == 1 and plc._keeper is None)
            assert plc.dead_peers == 0
            assert await plc.read("DB10.DW5") == [0x1000]  # reconnects, no error
            assert sim.connections == 2


async def test_raw_org_access(sim: fwsim.FetchWriteSimulator) -> None:
    mem = sim.memory
    async with connect(sim.url) as plc:
        mem.write_area(Area.INPUTS, 2, b"\x42")
        assert await plc.fetch_org(0x05, 0, 2, 1) == b"\x42"  # PB reads the input image [R]
        await plc.write_org(0x05, 0, 3, b"\x24")  # PB writes go to the output image [R]
        assert mem.read_area(Area.OUTPUTS, 3, 1) == b"\x24"
        await plc.write_org(0x08, 0, 1, b"\x12\x34")  # BS: system data words
        assert mem.read_area(Area.SYSTEM, 2, 2) == b"\x12\x34"
        dw0, _ = mem.block_info(BlockType.DB, 10)
        assert await plc.fetch_org(0x09, 0, dw0 + 10, 1) == b"\x10\x00"  # AS: DB10.DW5
        for org in (0x10, 0x11):  # DE, QB: not modelled by the simulator -> error 01
            with pytest.raises(PlcErrorResponse) as exc:
                await plc.fetch_org(org, 1, 0, 1)
            assert exc.value.code == 1 and "wrong ORG format" in str(exc.value)
        with pytest.raises(AddressError, match="ORG"):
            await plc.fetch_org(0x0B, 0, 0, 1)
        with pytest.raises(AddressError):
            await plc.fetch_org(0x01, 1, 0, 0)
        with pytest.raises(AddressError):
            await plc.write_org(0x01, 1, 0, b"\x00")


# -- client against a scripted CP built from the spec's bytes, not from our codec --------------

DATA_40 = b"".join(struct.pack(">H", 0x1000 + i) for i in range(20))
SCRIPT_RAW = [
    (H("53 35 10 01 03 05 03 08 01 0A 00 05 00 14 FF 02"),
     H("53 35 10 01 03 06 0F 03 00 FF 07 00 00 00 00 00") + DATA_40),
    (H("53 35 10 01 03 03 03 08 02 00 00 64 00 04 FF 02 DE AD BE EF"),
     H("53 35 10 01 03 04 0F 03 00 FF 07 00 00 00 00 00")),
    (H("53 35 10 01 03 05 03 08 01 63 00 00 00 01 FF 02"),
     H("53 35 10 01 03 06 0F 03 02 FF 07 00 00 00 00 00")),
    (H("53 35 10 01 03 03 03 08 01 0A 00 05 00 02 FF 02 12 34 10 03"),
     H("53 35 10 01 03 04 0F 03 00 FF 07 00 00 00 00 00")),
]  # fmt: skip


def _mk(seq: int, payload: bytes) -> bytes:
    return b"MK" + struct.pack("<HHH", len(payload), 0, seq) + payload


@pytest.mark.parametrize("mk", [False, True], ids=["raw", "mk"])
async def test_client_against_scripted_cp(mk: bool) -> None:
    received: list[bytes] = []

    async def cp(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        for seq, (request, answer) in enumerate(SCRIPT_RAW):
            want = _mk(seq, request) if mk else request
            received.append(await r.readexactly(len(want)))
            # answer in two pieces to exercise reassembly across reads
            wire = _mk(seq, answer) if mk else answer
            w.write(wire[:5])
            await w.drain()
            w.write(wire[5:])
        await r.read()
        w.close()

    server = await asyncio.start_server(ends_quietly(cp), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with connect(f"fetchwrite://127.0.0.1:{port}" + ("?mk=1" if mk else "")) as plc:
            assert await plc.read("DB10.DW5", 20) == [0x1000 + i for i in range(20)]
            await plc.write("MB100", [0xDE, 0xAD, 0xBE, 0xEF])
            with pytest.raises(PlcErrorResponse) as exc:
                await plc.read("DB99.DW0")
            assert exc.value.code == 2
            await plc.write("DB10.DW5", [0x1234, 0x1003])
    finally:
        server.close()
        await server.wait_closed()
    expected = [_mk(i, req) if mk else req for i, (req, _) in enumerate(SCRIPT_RAW)]
    assert received == expected


async def test_life_ack_wire_format_both_sides() -> None:
    """Life acks carry the sender's current counter (C.10-5) and are never answered."""
    async with await fwsim.start(mk=True, life_ack=0.05) as sim:
        proxy = Proxy(sim.port)
        await proxy.start()
        try:
            async with connect(f"fetchwrite://127.0.0.1:{proxy.port}?mk=1&life_ack=0.05") as plc:
                await plc.read("DB10.DW5")
                await plc.write("MB100", [1])
                await wait_for(lambda: proxy.c2s_bytes.endswith(H("4D 4B 00 00 00 00 02 00")))
                await wait_for(lambda: proxy.s2c_bytes.endswith(H("4D 4B 00 00 00 00 02 00")))
        finally:
            await proxy.aclose()
    for wire in (bytes(proxy.c2s_bytes), bytes(proxy.s2c_bytes)):
        rx = MkConnection(strict=True)
        rx.receive_data(wire)
        data_seqs: list[int] = []
        ack_seqs: list[int] = []
        while (event := rx.next_event()) is not NEED_DATA:
            if isinstance(event, LifeAck):
                # the counter: the number of data telegrams this side sent before the ack
                assert event.seq == len(data_seqs)
                ack_seqs.append(event.seq)
            else:
                data_seqs.append(event.first_seq)
        assert data_seqs == [0, 1] and ack_seqs and ack_seqs[-1] == 2


async def test_life_timeout_alone_supervises_without_sending() -> None:
    async with await fwsim.start(mk=True) as sim:
        plc = connect(sim.url + "&life_timeout=0.1")
        async with plc:
            await plc.read("MB0")
            await wait_for(lambda: plc.dead_peers == 1)
            assert sim.life_acks_received == 0
            with pytest.raises(ConnectionLost, match="peer dead"):
                await plc.read("MB0")
