"""``plcstack read/write --type``: multi-word values from the command line, per PLC family."""

from __future__ import annotations

import asyncio
import json
import struct
import sys
from pathlib import Path

from plcstack.sim import e71, fetchwrite
from plcstack.sim.s5memory import Area

ROOT = Path(__file__).resolve().parent.parent


async def cli(*args: str) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "plcstack",
        *args,
        cwd=ROOT,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(proc.communicate(), 30)
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


async def test_e71_float32_and_int32_low_word_first() -> None:
    async with await e71.start() as sim:
        sim.memory.write_words("D", 0, [0x0000, 0x3F40, 0x5678, 0x1234])  # 0.75; 0x12345678
        code, out, _ = await cli("read", sim.url, "D0", "1", "--type", "float32", "--json")
        assert code == 0 and json.loads(out) == {"address": "D0", "values": [0.75]}
        code, out, _ = await cli("read", sim.url, "D2", "--type", "int32")
        assert (code, out.strip()) == (0, f"D2: {0x12345678}")
        code, _, err = await cli("write", sim.url, "D10", "-1.5", "2", "--type", "float32")
        assert code == 0, err
        words = sim.memory.read_words("D", 10, 4)
        assert words == [0x0000, 0xBFC0, 0x0000, 0x4000]
        code, out, _ = await cli("read", sim.url, "D0", "2", "--type", "int16", "--word-order",
                                 "big")  # fmt: skip
        assert (code, out.strip()) == (0, "D0: 0 16192")


async def test_s5_int16_over_bytes_is_big_endian_and_bit_areas_refuse_words() -> None:
    async with await fetchwrite.start() as sim:
        sim.memory.write_area(Area.FLAGS, 10, struct.pack(">hI", -2, 70000))
        code, out, _ = await cli("read", sim.url, "MB10", "--type", "int16", "--json")
        assert code == 0 and json.loads(out)["values"] == [-2]
        code, out, _ = await cli("read", sim.url, "MB12", "--type", "uint32")
        assert (code, out.strip()) == (0, "MB12: 70000")
        code, _, err = await cli("write", sim.url, "MB20", "-300", "--type", "int16")
        assert code == 0, err
        assert sim.memory.read_area(Area.FLAGS, 20, 2) == struct.pack(">h", -300)
    async with await e71.start() as sim:
        code, _, err = await cli("read", sim.url, "M0", "--type", "float32")
        assert code == 2
        assert err.strip().splitlines() == [
            f"plcstack: error: {sim.url}: read M0 as float32 x1: M0: "
            "type float32 cannot be read from a bit area"
        ]
        code, _, err = await cli("write", sim.url, "D0", "70000", "--type", "int16")
        assert code == 2
        assert err.startswith(
            f"plcstack: error: {sim.url}: write D0 as int16 x1: "
            "70000 cannot be written as int16: outside -32768..32767"
        )
