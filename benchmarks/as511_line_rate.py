"""Time of a 64-word DB read over AS511 at emulated 9600 baud, next to the line-rate limit.

The simulator emulates the line (``baud=9600``: every chunk is delayed by 11 bits per byte, in
both directions, as on a half-duplex 8E1 line). The client counts the bytes it sends and receives;
the line-rate limit is that count times 11 / 9600 s, i.e. the time the bytes alone need on the
wire. The difference is handshake turnaround and asyncio latency.

    python -m benchmarks.as511_line_rate [--wire pty|tcp] [--baud 9600] [--rounds 5]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import time

from plcstack.clients import connect
from plcstack.clients.as511 import AS511Client
from plcstack.sim import as511 as sim_as511
from plcstack.sim.base import Simulator

BITS_PER_BYTE = 11  # 8E1: start, 8 data, parity, stop


class Counter:
    def __init__(self, plc: AS511Client) -> None:
        self.sent = 0
        self.received = 0
        transport = plc.transport
        write, read = transport.write, transport.read

        def counting_write(data: bytes) -> None:
            self.sent += len(data)
            write(data)

        async def counting_read(deadline: float | None = None) -> bytes:
            data = await read(deadline)
            self.received += len(data)
            return data

        transport.write = counting_write  # type: ignore[method-assign]
        transport.read = counting_read  # type: ignore[method-assign]

    def take(self) -> int:
        total = self.sent + self.received
        self.sent = self.received = 0
        return total


async def measure(wire: str, baud: int, rounds: int) -> None:
    sim: Simulator
    if wire == "pty":
        sim = await sim_as511.start_pty(baud=baud)
    else:
        sim = await sim_as511.start(baud=baud)
    byte_time = BITS_PER_BYTE / baud
    async with sim:
        plc = connect(sim.url)
        assert isinstance(plc, AS511Client)
        async with plc:
            counter = Counter(plc)
            await plc.read_system_parameters()  # not part of a DB read
            counter.take()
            rows: list[tuple[str, float, int]] = []
            for label, cold in (("cold (B_INFO + read)", True), ("cached (header-checked)", False)):
                times, wire_bytes = [], 0
                for _ in range(rounds):
                    if cold:
                        plc.invalidate()
                    t0 = time.perf_counter()
                    words = await plc.read("DB5.DW0", 64)
                    times.append(time.perf_counter() - t0)
                    wire_bytes = counter.take()
                    assert words == [0x0500 | k for k in range(64)]
                rows.append((label, statistics.median(times), wire_bytes))
    print(f"AS511 64-word DB read over {wire} at emulated {baud} baud 8E1 ({rounds} rounds)")
    for label, measured, nbytes in rows:
        limit = nbytes * byte_time
        print(
            f"  {label:26s} measured {measured * 1000:7.1f} ms   line-rate limit "
            f"{limit * 1000:7.1f} ms ({nbytes} bytes on the wire)   ratio {measured / limit:.3f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--wire", choices=("pty", "tcp"), default="pty")
    parser.add_argument("--baud", type=int, default=9600)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    asyncio.run(measure(args.wire, args.baud, args.rounds))


if __name__ == "__main__":
    main()
