"""Typed values: floats, 32-bit integers, text and S5 formats over plain PLC words.

A PLC keeps a float in two words, an S5 real (KG) in two words of its own format, text as bytes
in words. ``read_as``/``write_as`` do the packing, with the PLC family's word order.

    plcstack sim e71 & plcstack sim s5lan &
    python examples/typed_values.py            # e71+tcp://127.0.0.1:5000 s5lan://127.0.0.1:5010
"""

from __future__ import annotations

import asyncio
import sys

import plcstack
from plcstack.values import FLOAT32, INT32, KG, string


async def main(e71_url: str, s5_url: str) -> None:
    async with plcstack.connect(e71_url) as plc:
        await plc.write_as("D200", FLOAT32, 21.5)  # D200 low word, D201 high word
        await plc.write_as("D202", INT32, [-100000, 70000])  # a list: one value after the other
        await plc.write_as("D210", string(8), "PRESS 1")  # 8 characters in 4 words
        force: float = await plc.read_as("D200", FLOAT32)
        counts: list[int] = await plc.read_as("D202", INT32, 2)
        name: str = await plc.read_as("D210", string(8))
        print("float32:", force)
        print("int32:  ", counts)
        print("text:   ", name)
        print("by name:", await plc.read_as("D200", "float32"))  # the names the CLI takes
    async with plcstack.connect(s5_url) as plc:
        await plc.write_as("DB10.DW4", KG, 10.0)  # an S5 real: exponent byte, 24-bit mantissa
        level = await plc.read_as("DB10.DW4", KG)  # a float, to mypy too
        print("KG:     ", level)


if __name__ == "__main__":
    urls = sys.argv[1:] or ["e71+tcp://127.0.0.1:5000", "s5lan://127.0.0.1:5010"]
    asyncio.run(main(*urls))
