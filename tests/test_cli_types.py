"""``plcstack read/write --type``: multi-word values from the command line, per PLC family."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest

from plcstack.cli import build_parser
from plcstack.sim import e71, fetchwrite
from plcstack.sim.s5memory import Area
from tests.cli_helpers import cli_in_process

ROOT = Path(__file__).resolve().parent.parent


async def cli(*args: str) -> tuple[int, str, str]:
    # plcstack.cli.main in this process (tests/cli_helpers.py): a new interpreter per command
    # proves nothing more about --type than test_cli_basic's subprocess tests already do
    return await cli_in_process(*args)


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


def test_8_bit_types_on_word_devices_are_refused() -> None:
    """int8/uint8 on a 16-bit word: which byte is meant is not said, so it is refused (exit 2)
    before anything is sent; on a byte area (S5 MB) they are fine."""
    from plcstack.cli import main

    for argv in (
        ["read", "e71+tcp://127.0.0.1:1", "D100", "--type", "int8"],
        ["write", "s5lan://127.0.0.1:1", "DB10.DW0", "5", "--type", "uint8"],
    ):
        assert main(argv) == 2


async def test_negative_values_are_values_not_options(capsys: pytest.CaptureFixture[str]) -> None:
    from plcstack.cli.io import run_read, run_write
    from plcstack.sim import e71 as e71_sim

    parser = build_parser()
    async with await e71_sim.start() as sim:
        args = parser.parse_args(
            ["write", sim.url, "D0", "3.14", "-2.5e3", "-inf", "--type", "float32"]
        )
        assert args.values == ["3.14", "-2.5e3", "-inf"]
        assert await run_write(args) == 0
        assert (
            await run_read(
                parser.parse_args(["read", sim.url, "D0", "3", "--type", "float32", "--json"])
            )
            == 0
        )
    out = capsys.readouterr().out.splitlines()[-1]
    assert out == '{"address": "D0", "values": [3.14, -2500.0, "-Infinity"]}'
