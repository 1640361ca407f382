"""Read and write words with the async client.

Start a simulator first (or pass the URL of a real E71):

    plcstack sim e71 &
    python examples/read_write.py                       # e71+tcp://127.0.0.1:5000
    python examples/read_write.py e71+tcp://10.0.0.5:5000
"""

from __future__ import annotations

import asyncio
import sys

import plcstack


async def main(url: str) -> None:
    # `async with` opens the connection and closes it again, also after an error
    async with plcstack.connect(url, timeout=2.0) as plc:
        await plc.write("D100", [1, 2, 3, 4])  # four data registers, one request
        words = await plc.read("D100", 4)
        print(f"D100..D103: {words}")
        await plc.write("M0", [True, False, True])  # bit devices take bools
        print(f"M0..M2: {await plc.read('M0', 3)}")


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1] if len(sys.argv) > 1 else "e71+tcp://127.0.0.1:5000"))
