"""MelsecMemory (the API the demo's PLC program uses) and E71 simulator behaviour: CPU state and
write-during-RUN gating (§1.2, §7.1), end-code precedence (§10.3), incomplete TCP requests (A15),
ASCII strictness (A7), shared monitor registration (A10)."""

from __future__ import annotations

import asyncio

import pytest

from plcstack.codecs.e71 import (
    BadRequest,
    CpuGroup,
    DeviceRef,
    ErrorResponse,
    MonitorBits,
    MonitorWords,
    OpaqueRequest,
    ReadBits,
    ReadWords,
    RegisterMonitorBits,
    RegisterMonitorWords,
    Request,
    TestBits,
    TestWords,
    WriteBits,
    WriteWords,
    parse_address,
)
from plcstack.sim import e71 as sim_e71
from plcstack.sim.e71 import execute
from plcstack.sim.melsec_memory import CpuState, MelsecAccessError, MelsecMemory
from tests.aio_helpers import eventually


def ref(text: str) -> DeviceRef:
    return parse_address(text)


def test_memory_words_bits_and_aliases() -> None:
    mem = MelsecMemory()
    mem.write_words("D", 100, [1, 2, 3])
    assert mem.read_words("D", 100, 3) == [1, 2, 3]
    mem.write_bits("M", 0, [True, False, True])
    assert mem.read_bits("L", 0, 3) == [True, False, True]  # L is M
    assert mem.read_words("M", 0, 1) == [0b101]
    mem.write_words("Y", 0x40, [0x829D])
    assert mem.read_bits("Y", 0x47, 2) == [True, False]  # 9DH: Y47 = 1, Y48 from 82H = 0
    mem.write_words("TN", 5, [100])
    assert mem.read_words("tn", 5, 1) == [100]
    mem.write_words("D", 9000, [7])
    assert mem.read_words("D", 9000, 1) == [7]


@pytest.mark.parametrize(
    ("call", "code"),
    [
        (lambda m: m.read_words("Z", 0, 1), 0x56),
        (lambda m: m.read_words("D", 6144, 1), 0x58),
        (lambda m: m.read_words("D", 6140, 5), 0x57),
        (lambda m: m.read_bits("D", 0, 1), 0x58),
        (lambda m: m.read_words("D", 8999, 2), 0x58),
        (lambda m: m.read_words("D", 9250, 7), 0x57),
        (lambda m: m.read_words("M", 8176, 2), 0x57),
    ],
)
def test_memory_access_errors(call: object, code: int) -> None:
    mem = MelsecMemory()
    with pytest.raises(MelsecAccessError) as err:
        call(mem)  # type: ignore[operator]
    assert err.value.end_code == code


def test_memory_group_ranges() -> None:
    small = MelsecMemory(CpuGroup.I)
    with pytest.raises(MelsecAccessError):
        small.read_words("R", 0, 1)
    with pytest.raises(MelsecAccessError):
        small.read_bits("X", 0x100, 1)
    assert small.read_bits("X", 0xFF, 1) == [False]
    assert MelsecMemory("IV").read_words("R", 8191, 1) == [0]


WRITES: list[Request] = [
    WriteBits(ref("M0"), (True,)),
    WriteWords(ref("D0"), (1,)),
    TestBits(((ref("M0"), True),)),
    TestWords(((ref("D0"), 1),)),
]
READS: list[Request] = [
    ReadBits(ref("M0"), 1),
    ReadWords(ref("D0"), 1),
    RegisterMonitorWords((ref("D0"),)),
    RegisterMonitorBits((ref("M0"),)),
]


@pytest.mark.parametrize(
    ("state", "write_in_run", "writes_ok"),
    [
        (CpuState.STOP, False, True),
        (CpuState.STOP, True, True),
        (CpuState.RUN, True, True),
        (CpuState.RUN, False, False),
        (CpuState.PAUSE, False, False),
        (CpuState.PAUSE, True, True),
    ],
)
def test_cpu_mode_gating(state: CpuState, write_in_run: bool, writes_ok: bool) -> None:
    mem = MelsecMemory(state=state, write_in_run=write_in_run)
    for req in WRITES:
        resp = execute(mem, req)
        assert (resp == ErrorResponse(req.COMMAND, 0x55)) is not writes_ok
    for req in READS:  # reads, registration and monitoring work in every mode
        assert not isinstance(execute(mem, req), ErrorResponse)


def test_precedence() -> None:
    mem = MelsecMemory(state=CpuState.RUN, write_in_run=False)
    # PC number first, even before a format error found by the codec
    assert execute(mem, BadRequest(1, 0x56, 0x05)) == ErrorResponse(1, 0x5B, 0x10)
    assert execute(mem, BadRequest(1, 0x54, None)) == ErrorResponse(1, 0x54)
    # head out of range (58H) before count (57H) before mode (55H)
    assert execute(mem, WriteWords(ref("D6143"), (0,) * 300)) == ErrorResponse(3, 0x57)
    big = WriteWords(DeviceRef(ref("D0").device, 7000), (0,) * 300)
    assert execute(mem, big) == ErrorResponse(3, 0x58)
    assert execute(mem, WriteWords(ref("D6143"), (0, 0))) == ErrorResponse(3, 0x57)
    assert execute(mem, WriteWords(ref("D6143"), (0,))) == ErrorResponse(3, 0x55)
    # word device with a bit command, bit device head not on 16
    assert execute(mem, ReadBits(ref("D0"), 1)) == ErrorResponse(0, 0x58)
    assert execute(mem, ReadWords(ref("M5"), 1)) == ErrorResponse(1, 0x58)
    assert execute(mem, OpaqueRequest(0x13, b"13FF000A")) == ErrorResponse(0x13, 0x50)


def test_monitor_registration_is_shared_and_kind_checked() -> None:
    mem = MelsecMemory()
    assert execute(mem, MonitorWords()) == ErrorResponse(9, 0x57)
    execute(mem, RegisterMonitorBits((ref("M0"),)))
    assert execute(mem, MonitorWords()) == ErrorResponse(9, 0x57)  # 09H after 06H: §13 A10
    execute(mem, RegisterMonitorWords((ref("D5"),)))
    assert execute(mem, MonitorBits()) == ErrorResponse(8, 0x57)  # 08H after 07H
    mem.write_words("D", 5, [42])
    assert execute(mem, MonitorWords()).values == (42,)  # type: ignore[union-attr]


def _buffered(sim: sim_e71.E71TcpSimulator) -> bool:
    """Whether a connection of ``sim`` holds part of a request."""
    return any(conn.codec.buffered for conn in sim.connections)


async def test_incomplete_tcp_request_is_discarded_after_timeout() -> None:
    sim = await sim_e71.start(incomplete_timeout=0.05)
    assert isinstance(sim, sim_e71.E71TcpSimulator)
    try:
        reader, writer = await asyncio.open_connection(sim.host, sim.port)
        writer.write(bytes.fromhex("01 FF 0A 00 64 00"))  # half a request
        await eventually(lambda: _buffered(sim), "the half request arrived")
        await eventually(lambda: not _buffered(sim), "the half request was discarded")
        writer.write(bytes.fromhex("01 FF 0A 00 64 00 00 00 20 44 01 00"))
        assert await asyncio.wait_for(reader.readexactly(4), 5) == bytes.fromhex("81 00 00 00")
        writer.close()
        await writer.wait_closed()
    finally:
        await sim.aclose()


async def test_strict_ascii_simulator_answers_lower_case_with_54h() -> None:
    sim = await sim_e71.start(code="ascii", lower_ok=False)
    try:
        reader, writer = await asyncio.open_connection(sim.host, sim.port)
        writer.write(b"01ff000a4420000000640100")
        assert await asyncio.wait_for(reader.readexactly(4), 5) == b"8154"
        writer.write(b"01FF000A4420000000640100")
        assert await asyncio.wait_for(reader.readexactly(8), 5) == b"81000000"
        writer.close()
        await writer.wait_closed()
    finally:
        await sim.aclose()


async def test_q_series_5bh_form_option() -> None:
    sim = await sim_e71.start(abnormal_trailer=False)
    try:
        reader, writer = await asyncio.open_connection(sim.host, sim.port)
        writer.write(bytes.fromhex("01 05 0A 00 64 00 00 00 20 44 01 00"))
        assert await asyncio.wait_for(reader.readexactly(3), 5) == bytes.fromhex("81 5B 10")
        writer.close()
        await writer.wait_closed()
    finally:
        await sim.aclose()
