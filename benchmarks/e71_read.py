"""Reads per second of ``read("D0", 64)`` through plcstack vs. a raw asyncio floor.

Both run against the same in-process E71 simulator (TCP, binary), in the same event loop, one
after the other, several alternating rounds; the best round of each is reported. The raw client
sends pre-built request bytes and waits for the known reply length (2 + 128 bytes) on a plain
``asyncio.Protocol``: no codec, no error handling, the floor the stack cannot beat.

    python -m benchmarks.e71_read [--seconds 1.0] [--rounds 3] [--code binary|ascii]
    python -m benchmarks.e71_read --profile      # cProfile of the stack path, top entries
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import pstats
import time

import plcstack
from plcstack.codecs.e71 import Code, Device, DeviceRef, E71ClientConnection, ReadWords
from plcstack.sim import e71 as sim_e71


class _RawProtocol(asyncio.Protocol):
    def __init__(self, need: int) -> None:
        self.need = need
        self.buf = bytearray()
        self.waiter: asyncio.Future[bytes] | None = None

    def data_received(self, data: bytes) -> None:
        self.buf += data
        if len(self.buf) >= self.need and self.waiter is not None and not self.waiter.done():
            out = bytes(self.buf[: self.need])
            del self.buf[: self.need]
            self.waiter.set_result(out)


async def raw_rate(host: str, port: int, request: bytes, reply_len: int, seconds: float) -> float:
    loop = asyncio.get_running_loop()
    transport, proto = await loop.create_connection(lambda: _RawProtocol(reply_len), host, port)
    try:
        n = 0
        end = time.perf_counter() + seconds
        start = time.perf_counter()
        while time.perf_counter() < end:
            proto.waiter = loop.create_future()
            transport.write(request)
            await proto.waiter
            n += 1
        return n / (time.perf_counter() - start)
    finally:
        transport.close()


async def stack_rate(url: str, seconds: float) -> float:
    async with plcstack.connect(url) as plc:
        n = 0
        end = time.perf_counter() + seconds
        start = time.perf_counter()
        while time.perf_counter() < end:
            await plc.read("D0", 64)
            n += 1
        return n / (time.perf_counter() - start)


async def main(args: argparse.Namespace) -> None:
    code = Code(args.code)
    sim = await sim_e71.start(code=code)
    sim.memory.write_words("D", 0, list(range(64)))
    try:
        request = E71ClientConnection(code).send(
            ReadWords(DeviceRef(Device.D, 0), 64, timer=plcstack.connect(sim.url).monitoring_timer)  # type: ignore[attr-defined]
        )
        reply_len = (2 + 128) * (2 if code is Code.ASCII else 1)
        if args.profile:
            prof = cProfile.Profile()
            prof.enable()
            rate = await stack_rate(sim.url, args.seconds)
            prof.disable()
            print(f"stack under cProfile: {rate:,.0f} reads/s")
            pstats.Stats(prof).sort_stats("tottime").print_stats(15)
            return
        raws, stacks = [], []
        for _ in range(args.rounds):
            raws.append(await raw_rate(sim.host, sim.port, request, reply_len, args.seconds))
            stacks.append(await stack_rate(sim.url, args.seconds))
        raw, stack = max(raws), max(stacks)
        print(f"E71 {code.value} TCP, read('D0', 64), in-process simulator, {args.rounds} rounds")
        print(f"  raw asyncio floor : {raw:10,.0f} reads/s")
        print(f"  plcstack          : {stack:10,.0f} reads/s")
        print(f"  ratio stack/floor : {stack / raw:10.2f}")
    finally:
        await sim.aclose()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=1.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--code", choices=("binary", "ascii"), default="binary")
    parser.add_argument("--profile", action="store_true")
    asyncio.run(main(parser.parse_args()))
