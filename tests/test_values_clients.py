"""read_as/write_as on every client against its simulator over real sockets; the poller's typed
tags (KG, bit of a word, scaling); refusals before anything is sent."""

from __future__ import annotations

import math
import struct
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any

import pytest

import plcstack
from plcstack.clients.base import Client
from plcstack.errors import AddressError, ValueDecodeError, ValueEncodeError
from plcstack.poll import PlcConfig, PollConfig, Poller, TagConfig
from plcstack.sim import as511 as sim_as511
from plcstack.sim import e71 as sim_e71
from plcstack.sim import fetchwrite as sim_fw
from plcstack.sim import s5lan as sim_s5lan
from plcstack.sim.s5memory import Area, S5Memory
from plcstack.values import (
    BCD16,
    BOOL,
    FLOAT32,
    INT16,
    INT32,
    KG,
    KT,
    KZ,
    UINT16,
    Scale,
    ValueType,
    string,
)

S5_SIMS: dict[str, Callable[..., Any]] = {
    "s5lan": sim_s5lan.start,
    "fetchwrite": sim_fw.start,
    "as511": sim_as511.start,
}


@asynccontextmanager
async def s5_plc(kind: str) -> AsyncIterator[tuple[S5Memory, Client]]:
    memory = S5Memory(default_dbs={10: 64})
    async with await S5_SIMS[kind](memory) as sim:
        url = sim.url.replace("as511://", "as511+tcp://") if kind == "as511" else sim.url
        async with plcstack.connect(url, timeout=5) as plc:
            yield memory, plc


@pytest.mark.parametrize("kind", list(S5_SIMS))
async def test_s5_typed_values_round_trip_through_the_wire(kind: str) -> None:
    async with s5_plc(kind) as (memory, plc):
        await plc.write_as("DB10.DW4", KG, 10.0)
        # spec F: 10.0 is 04 50 00 00 in S5 memory
        assert memory.read_block(memory_db(), 10, 8, 4) == bytes.fromhex("04500000")
        value = await plc.read_as("DB10.DW4", KG)
        assert value == 10.0
        await plc.write_as("DB10.DW6", KT, 123.0)
        assert memory.read_db_words(10, 6, 1) == [0x2123]
        assert await plc.read_as("DB10.DW6", KT) == 123.0
        await plc.write_as("DB10.DW7", KZ, [42, 999])
        assert await plc.read_as("DB10.DW7", KZ, 2) == [42, 999]
        await plc.write_as("DB10.DW9", INT32, -2)
        assert memory.read_db_words(10, 9, 2) == [0xFFFF, 0xFFFE]  # high word first
        await plc.write_as("DB10.DW12", string(5), "PUMP")
        assert memory.read_block(memory_db(), 10, 24, 6) == b"PUMP\0\0"
        assert await plc.read_as("DB10.DW12", string(5)) == "PUMP"
        # a bit of a word, STEP 5 notation and ours
        memory.write_db_words(10, 20, [0b1000])
        assert await plc.read_as("DB10.DW20.3", BOOL) is True
        assert await plc.read_as("DB10.D20.2", BOOL) is False
        memory.write_area(Area.FLAGS, 10, bytes([0x80]))
        assert await plc.read_as("M10.7", BOOL) is True
        assert await plc.read_as("MB10.6", BOOL) is False
        assert await plc.read_as("MB10", INT16) == struct.unpack(">h", bytes([0x80, 0]))[0]
        # one naming for DB and flag access on every S5 client
        assert await plc.read_db(10, 6, 1) == [0x2123]  # type: ignore[attr-defined]
        assert await plc.read_bytes("M", 10, 1) == bytes([0x80])  # type: ignore[attr-defined]
        # scalar writes
        await plc.write("DB10.DW30", 7)
        assert memory.read_db_words(10, 30, 1) == [7]


def memory_db() -> Any:
    from plcstack.sim.s5memory import BlockType

    return BlockType.DB


@pytest.mark.parametrize("kind", ["fetchwrite"])
async def test_refused_values_send_nothing(kind: str) -> None:
    async with s5_plc(kind) as (_memory, plc):
        before = plc.stats.requests
        cases: list[tuple[ValueType[Any], object]] = [
            (KG, math.nan),
            (BCD16, 10000),
            (KT, 10000.0),
            (UINT16, -1),
        ]
        for vtype, bad in cases:
            with pytest.raises(ValueEncodeError) as info:
                await plc.write_as("DB10.DW0", vtype, bad)
            assert vtype.name in str(info.value) and "DB10.DW0" in str(info.value)
        with pytest.raises(AddressError, match="read-modify-write"):
            await plc.write_as("DB10.DW0.3", BOOL, True)
        with pytest.raises(AddressError, match="bit 8 is not a bit of a 8-bit point"):
            await plc.read_as("M10.8", BOOL)
        with pytest.raises(AddressError, match="as BOOL"):
            await plc.read_as("DB10.DW0.3", INT16)
        assert plc.stats.requests == before


async def test_e71_typed_values_and_aliases() -> None:
    async with await sim_e71.start() as sim, plcstack.connect(sim.url) as plc:
        await plc.write_as("D10", FLOAT32, 0.75)
        assert sim.memory.read_words("D", 10, 2) == [0x0000, 0x3F40]  # seed §10.5.5
        assert await plc.read_as("D10", FLOAT32) == 0.75
        await plc.write_as("D20", string(4), "12AB")
        assert sim.memory.read_words("D", 20, 2) == [0x3231, 0x4241]  # seed §10.5.5
        await plc.write_as("D30", BCD16, 1234)
        assert sim.memory.read_words("D", 30, 1) == [0x1234]
        sim.memory.write_words("D", 31, [0x1A00])
        with pytest.raises(ValueDecodeError, match="1A00h"):
            await plc.read_as("D31", BCD16)
        sim.memory.write_words("D", 40, [0x8008])
        assert await plc.read_as("D40.3", BOOL) is True
        assert await plc.read_as("D40.F", BOOL) is True
        assert await plc.read_as("D40.E", BOOL) is False
        assert await plc.read_as("D40.3", BOOL, 2) == [True, False]
        await plc.write("M5", True)
        assert await plc.read_as("M5", BOOL) is True
        await plc.write("D50", -1)
        assert await plc.read_as("D50", INT16) == -1
        e71 = plc
        assert hasattr(e71, "read_int32")
        await e71.write_int32("D60", [-2, 0x12345678])  # type: ignore[attr-defined]
        assert await e71.read_int32("D60", 2) == [-2, 0x12345678]
        assert sim.memory.read_words("D", 60, 2) == [0xFFFE, 0xFFFF]  # low word first


async def test_poller_typed_tags_kg_bits_and_scaling() -> None:
    memory = S5Memory(default_dbs={10: 64})
    memory.write_block(memory_db(), 10, 0, bytes.fromhex("07640000"))  # KG 100.0 (spec F)
    memory.write_db_words(10, 2, [0b0100, 2000, 0x2123])
    async with await sim_fw.start(memory) as sim:
        tags = (
            TagConfig("temp", "DB10.DW0", KG),
            TagConfig("door", "DB10.DW2.2", BOOL),
            TagConfig("level", "DB10.DW3", INT16, scale=Scale(0, 4000, 0.0, 100.0)),
            TagConfig("timer", "DB10.DW4", KT),
        )
        config = PollConfig((PlcConfig("s5", sim.url, tags),), {"default": 0.05})
        async with Poller(config) as poller:
            seen: dict[str, Any] = {}
            async for sample in poller:
                seen[sample.tag] = sample.value
                if len(seen) == 4:
                    break
            assert seen == {"temp": 100.0, "door": True, "level": 50.0, "timer": 123.0}
            assert len(poller.plan("s5", "default").requests) == 1  # merged into one read
            await poller.write_tag("s5", "level", 25.0)
            assert memory.read_db_words(10, 3, 1) == [1000]
            await poller.write_tag("s5", "temp", 10.0)
            assert memory.read_block(memory_db(), 10, 0, 4) == bytes.fromhex("04500000")
            with pytest.raises(ValueEncodeError, match="kg"):
                await poller.write_tag("s5", "temp", math.inf)
            with pytest.raises(AddressError, match="read-only"):
                await poller.write_tag("s5", "door", False)
