"""E71 client against the E71 simulator over real loopback TCP and UDP, binary and ASCII."""

from __future__ import annotations

import asyncio
import math
import socket
from collections.abc import AsyncIterator
from typing import Any

import pytest

import plcstack
from plcstack.clients.e71 import E71Client
from plcstack.codecs.e71 import CpuGroup
from plcstack.errors import (
    AddressError,
    ConnectionLost,
    LocalProtocolError,
    PlcErrorResponse,
    PlcTimeout,
)
from plcstack.sim import e71 as sim_e71
from plcstack.sim.melsec_memory import CpuState, MelsecMemory

VARIANTS = [("tcp", "binary"), ("tcp", "ascii"), ("udp", "binary"), ("udp", "ascii")]


@pytest.fixture(params=VARIANTS, ids=["tcp-binary", "tcp-ascii", "udp-binary", "udp-ascii"])
async def sim(request: pytest.FixtureRequest) -> AsyncIterator[sim_e71.E71TcpSimulator]:
    transport, code = request.param
    s = await sim_e71.start(transport=transport, code=code)
    try:
        yield s  # type: ignore[misc]
    finally:
        await s.aclose()


def client(url: str, **options: Any) -> E71Client:
    plc = plcstack.connect(url, **options)
    assert isinstance(plc, E71Client)
    return plc


async def test_url_matches_variant(sim: sim_e71.E71TcpSimulator) -> None:
    assert sim.url.startswith("e71+")
    assert ("code=ascii" in sim.url) == (sim.code.value == "ascii")


async def test_words_round_trip(sim: sim_e71.E71TcpSimulator) -> None:
    async with client(sim.url) as plc:
        await plc.write("D100", [0x1234, 0x9876, 0x0109, -1])
        assert await plc.read("D100", 4) == [0x1234, 0x9876, 0x0109, 0xFFFF]
        assert sim.memory.read_words("D", 100, 3) == [0x1234, 0x9876, 0x0109]
        await plc.write("W1F", [7])
        assert sim.memory.read_words("W", 0x1F, 1) == [7]
        await plc.write("R8191", [5])
        assert await plc.read("R8191") == [5]
        await plc.write("D0", list(range(256)))
        assert await plc.read("D0", 256) == list(range(256))


async def test_bits_round_trip(sim: sim_e71.E71TcpSimulator) -> None:
    pattern = [bool(i % 3 == 0) for i in range(256)]
    async with client(sim.url) as plc:
        await plc.write("M0", pattern)
        assert await plc.read("M0", 256) == pattern
        await plc.write("X1F", [True, False, True])
        assert sim.memory.read_bits("X", 0x1F, 3) == [True, False, True]
        assert await plc.read("X1F", 3) == [True, False, True]
        assert await plc.read("L0", 1) == [True]  # L is M
        await plc.write("Y7FF", [True])
        assert await plc.read("Y7FE", 2) == [False, True]


async def test_word_units_on_bit_devices(sim: sim_e71.E71TcpSimulator) -> None:
    sim.memory.write_bits("Y", 0x40, [bool((0x829D >> i) & 1) for i in range(16)])
    async with client(sim.url) as plc:
        assert await plc.read_words("Y40", 1) == [0x829D]
        await plc.write_words("M16", [0x8001])
        assert sim.memory.read_bits("M", 16, 16) == [True] + [False] * 14 + [True]
        with pytest.raises(AddressError, match="multiple of 16"):
            await plc.read_words("M8", 1)


async def test_int32_and_float(sim: sim_e71.E71TcpSimulator) -> None:
    async with client(sim.url) as plc:
        await plc.write_int32("D10", [-2, 0x12345678])
        assert sim.memory.read_words("D", 10, 4) == [0xFFFE, 0xFFFF, 0x5678, 0x1234]
        assert await plc.read_int32("D10", 2) == [-2, 0x12345678]
        await plc.write_float("D20", [0.75, -1.5])
        assert sim.memory.read_words("D", 20, 2) == [0x0000, 0x3F40]  # spec §3 rule 10
        values = await plc.read_float("D20", 2)
        assert values == [0.75, -1.5]
        with pytest.raises(AddressError):
            await plc.read_int32("M0")
        await plc.write_float("D30", [math.nan])
        assert math.isnan((await plc.read_float("D30"))[0])


async def test_test_and_monitor(sim: sim_e71.E71TcpSimulator) -> None:
    async with client(sim.url) as plc:
        with pytest.raises(LocalProtocolError):
            await plc.monitor_words()  # nothing registered through this client
        await plc.test_bits([("X94", True), ("M60", False), ("B26", True)])
        assert sim.memory.read_bits("X", 0x94, 1) == [True]
        assert sim.memory.read_bits("B", 0x26, 1) == [True]
        await plc.test_words([("Y80", 0x7B29), ("W26", 0x1234), ("CN18", 0x50)])
        assert sim.memory.read_words("Y", 0x80, 1) == [0x7B29]
        assert sim.memory.read_words("CN", 18, 1) == [0x50]
        await plc.register_monitor_bits(["Y46", "M12", "B2C"])
        sim.memory.write_bits("Y", 0x46, [True])
        sim.memory.write_bits("B", 0x2C, [True])
        assert await plc.monitor_bits() == [True, False, True]
        await plc.register_monitor_words(["Y50", "D38", "W1E"])
        sim.memory.write_words("D", 38, [0x1234])
        sim.memory.write_words("Y", 0x50, [0xE56D])
        assert await plc.monitor_words() == [0xE56D, 0x1234, 0]


async def test_read_many_splits(sim: sim_e71.E71TcpSimulator) -> None:
    sim.memory.write_words("D", 0, list(range(600)))
    async with client(sim.url) as plc:
        before = sim.requests
        words, bits = await plc.read_many([("D0", 600), ("M0", 300)])
        assert words == list(range(600))
        assert bits == [False] * 300
        assert sim.requests - before == 3 + 2


async def test_plc_errors_end_to_end(sim: sim_e71.E71TcpSimulator) -> None:
    async with client(sim.url + ("&" if "?" in sim.url else "?") + "pc=05") as plc:
        with pytest.raises(PlcErrorResponse) as err:
            await plc.read("D100")
        assert err.value.code == 0x5B and err.value.code_text == "5BH/10H"
        assert "wrong PC number" in str(err.value) and sim.url in str(err.value)
        assert "read D100 x1" in str(err.value)
        plc.pc = 0xFF  # the same connection goes on (the 00H after 5BH/10H is not misread)
        assert await plc.read("D100") == [0]
    sim.memory.write_in_run = False
    async with client(sim.url) as plc:
        with pytest.raises(PlcErrorResponse) as err:
            await plc.write("D0", [1])
        assert err.value.code == 0x55
        assert await plc.read("D0") == [0]  # the connection survived
        sim.memory.state = CpuState.STOP
        await plc.write("D0", [1])  # allowed in STOP
        assert await plc.read("D0") == [1]
        assert plc.stats.errors == 1


async def test_device_out_of_range_for_cpu_group() -> None:
    s = await sim_e71.start(MelsecMemory(CpuGroup.I))
    try:
        async with client(s.url) as plc:
            with pytest.raises(PlcErrorResponse) as err:
                await plc.read("D2000")
            assert err.value.code == 0x58
            with pytest.raises(PlcErrorResponse) as err:
                await plc.read("D1000", 100)
            assert err.value.code == 0x57
            with pytest.raises(PlcErrorResponse) as err:
                await plc.read("R0")  # no file registers on an A1(N)
            assert err.value.code == 0x58
            assert await plc.read("D1023") == [0]
    finally:
        await s.aclose()


async def test_address_errors_send_nothing(sim: sim_e71.E71TcpSimulator) -> None:
    async with client(sim.url) as plc:
        before = sim.requests
        for address, count in [("Z0", 1), ("D6144", 1), ("D6100", 100), ("D0", 257), ("D0", 0)]:
            with pytest.raises(AddressError) as err:
                await plc.read(address, count)
            assert sim.url in str(err.value)
        with pytest.raises(AddressError):
            await plc.write("D0", [70000])
        with pytest.raises(AddressError):
            await plc.write("D0", [True])
        with pytest.raises(AddressError):
            await plc.write("M0", [2])
        with pytest.raises(AddressError):
            await plc.test_bits([(f"M{i}", True) for i in range(81)])
        assert sim.requests == before


async def test_timeout_closes_connection_and_late_reply_is_never_used(
    sim: sim_e71.E71TcpSimulator,
) -> None:
    sim.memory.write_words("D", 0, [11])
    sim.memory.write_words("D", 1, [22])
    async with client(sim.url, timeout=0.2) as plc:
        sim.delay = 0.4
        with pytest.raises(PlcTimeout):
            await plc.read("D0")
        sim.delay = 0.0
        await asyncio.sleep(0.5)  # the late answer to D0 arrives now (at a closed socket)
        assert await plc.read("D1") == [22]
        assert plc.stats.timeouts == 1


async def test_url_options() -> None:
    plc = client("e71+tcp://127.0.0.1:5000?code=ascii&pc=05&monitoring_timer=20&timeout=3")
    assert (plc.code.value, plc.pc, plc.monitoring_timer, plc.timeout) == ("ascii", 5, 20, 3.0)
    assert client("e71+udp://127.0.0.1:5000").monitoring_timer == 7
    for bad in [
        "e71+tcp://127.0.0.1:5000?cdoe=ascii",
        "e71+tcp://127.0.0.1:5000?code=ebcdic",
        "e71+tcp://127.0.0.1:5000?pc=41",
        "e71+tcp://127.0.0.1:5000?pc=zz",
        "e71+tcp://127.0.0.1:5000?monitoring_timer=70000",
    ]:
        with pytest.raises(AddressError):
            client(bad)


async def test_poller_hooks() -> None:
    plc = client("e71+tcp://127.0.0.1:5000")
    area, index = plc.locate("X1F", 4)
    assert plc.address_at(area, index + 1) == "X20"
    assert plc.locate("D100") == plc.locate("D100", 3)
    assert plc.locate("D100")[0] != plc.locate("W100")[0]
    assert plc.address_at(*plc.locate("CN18")) == "CN18"
    assert plc.max_points(area) == 256
    with pytest.raises(AddressError):
        plc.locate("D6143", 2)


async def test_eight_tcp_connections_at_once_ninth_refused() -> None:
    s = await sim_e71.start()
    plcs = [client(s.url) for _ in range(8)]
    try:
        for i, plc in enumerate(plcs):
            await plc.open()
            await plc.write(f"D{i}", [i])
        results = await asyncio.gather(*(plc.read(f"D{i}") for i, plc in enumerate(plcs)))
        assert results == [[i] for i in range(8)]
        ninth = client(s.url, timeout=1.0)
        await ninth.open()
        with pytest.raises(ConnectionLost):
            await ninth.read("D0")
        await ninth.aclose()
    finally:
        for plc in plcs:
            await plc.aclose()
        await s.aclose()


async def test_simulator_answers_garbage_and_keeps_connection() -> None:
    s = await sim_e71.start()
    try:
        reader, writer = await asyncio.open_connection(s.host, s.port)
        writer.write(bytes.fromhex("65 FF 0A 00"))
        assert await reader.readexactly(2) == bytes.fromhex("E5 50")
        writer.write(bytes.fromhex("01 FF 0A 00 00 00 00 00 20 5A 01 00"))
        assert await reader.readexactly(2) == bytes.fromhex("81 56")
        writer.write(bytes.fromhex("01 FF 0A 00 05 00 00 00 20 4D 01 00"))
        assert await reader.readexactly(2) == bytes.fromhex("81 58")
        writer.write(bytes.fromhex("15 FF 0A 00"))  # issue 3: implemented (A3A-class model)
        assert await reader.readexactly(4) == bytes.fromhex("95 00 94 00")
        writer.write(bytes.fromhex("08 FF 0A 00"))  # monitor without registration: 57H
        assert await reader.readexactly(2) == bytes.fromhex("88 57")
        # two requests in one segment, answered in order
        writer.write(bytes.fromhex("01 FF 0A 00 64 00 00 00 20 44 01 00") * 2)
        assert await reader.readexactly(8) == bytes.fromhex("81 00 00 00 81 00 00 00")
        writer.close()
        await writer.wait_closed()
    finally:
        await s.aclose()


async def test_udp_simulator_replies_to_source_and_survives_garbage() -> None:
    s = await sim_e71.start(transport="udp", code="ascii")
    try:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        sock.connect((s.host, s.port))
        loop = asyncio.get_running_loop()
        for request, answer in [
            (b"65FF000A", b"E550"),
            (b"01FF000A44200000006401", b"8157"),
            (b"01FF000A4420000000640100", b"81000000"),
        ]:
            await loop.sock_sendall(sock, request)
            async with asyncio.timeout(5):
                assert await loop.sock_recv(sock, 100) == answer
        sock.close()
    finally:
        await s.aclose()


async def test_slow_cpu_gives_60h_within_the_monitoring_timer(
    sim: sim_e71.E71TcpSimulator,
) -> None:
    sim.cpu_time = 0.3  # the simulator compares it with the timer: no race, a small margin does
    sep = "&" if "?" in sim.url else "?"
    async with client(sim.url + sep + "monitoring_timer=1") as plc:  # 0.25 s
        with pytest.raises(PlcErrorResponse) as err:
            await plc.write("D0", [5])
        assert err.value.code == 0x60 and "monitoring timer" in str(err.value)
        assert sim.memory.read_words("D", 0, 1) == [0]  # not executed
    async with client(sim.url) as plc:  # default timer 1.75 s > 0.3 s: the CPU answers
        await plc.write("D0", [5])
        sim.cpu_time = 0.0  # the read only shows the write was executed: no need to wait again
        assert await plc.read("D0") == [5]


async def test_pipelined_requests_are_answered_in_order_with_cpu_time() -> None:
    s = await sim_e71.start()
    s.cpu_time = 0.3
    try:
        reader, writer = await asyncio.open_connection(s.host, s.port)
        patient = bytes.fromhex("01 FF 00 00 64 00 00 00 20 44 01 00")  # timer 0: wait forever
        hasty = bytes.fromhex("01 FF 01 00 64 00 00 00 20 44 01 00")  # 0.25 s < CPU: 60H
        # the hasty answer (due sooner) must still come after the patient one (§4.1)
        writer.write(patient + hasty + bytes.fromhex("15 FF 0A 00"))
        got = await asyncio.wait_for(reader.readexactly(4 + 2 + 4), 5)
        assert got == bytes.fromhex("81 00 00 00 81 60 95 00 94 00")  # 15H: issue 3
        writer.close()
        await writer.wait_closed()
    finally:
        await s.aclose()
