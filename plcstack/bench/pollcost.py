"""The poller's own CPU per request, without sockets: ``python -m plcstack.bench.pollcost``.

    python -m plcstack.bench.pollcost                      # 1000 PLCs, 64-word raw tag, 5 repeats
    python -m plcstack.bench.pollcost --plcs 100 --type int16 --repeats 3

The fan-out case (``plcstack bench``) prices the poller together with sockets, the E71 codec and
an in-process simulator, on a machine shared with other jobs: its ratios move by 0.15 between runs.
This measures only what the poller adds. N in-memory clients answer every read after one pass of
the event loop (a future resolved by ``call_soon``, the same suspension a socket read costs the
task); the same N clients are driven once by N bare closed loops (``await client.read(...)``) and
once by a :class:`~plcstack.poll.engine.Poller` (one tag per PLC, scan interval 1 ms, a consumer
draining the samples once per loop pass). Both sides are timed in **CPU seconds of this
process** (``time.process_time``), which other processes on the machine barely move, alternating
bare and poller windows; the difference of the medians is the poller's cost per request:
scheduling, timing, the split into tag values, the Sample objects, the buffer, the consumer
wakeups and the garbage collector's extra work for samples waiting in the buffer (reported
separately, measured with ``gc.callbacks``).
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import statistics
import sys
import time
from collections.abc import Hashable, Sequence
from typing import Any, Self

from plcstack.clients.base import Client, Points
from plcstack.poll.config import DEFAULT_GROUP, MIN_INTERVAL, PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.transports.base import Transport
from plcstack.url import PlcUrl
from plcstack.values import TYPES, ValueType, value_type

__all__ = ["main", "measure"]

#: seconds between scans: the shortest the poller accepts (1 ms). With the hundreds of PLCs
#: measured here one round of requests takes far longer, so every PLC's task scans back to back;
#: below about ten PLCs this caps the poller at 1000 scans/s per PLC.
INTERVAL = MIN_INTERVAL


class _Nothing(Transport):
    peer = "memory"

    @property
    def is_open(self) -> bool:
        return True

    async def open(self, timeout: float | None) -> None:
        return None

    def write(self, data: bytes) -> None:
        return None

    async def read(self, deadline: float | None = None) -> bytes:
        return b""

    def abort(self) -> None:
        return None


def _resolve(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_result(None)


class MemoryClient(Client):
    """Answers ``read`` with fixed words after one pass of the event loop; ``D<n>`` addresses."""

    def __init__(self, name: str, words: Sequence[int]) -> None:
        super().__init__(name, _Nothing())
        self.words = list(words)

    @classmethod
    def from_url(cls, url: PlcUrl, **options: Any) -> Self:
        raise NotImplementedError

    def locate(self, address: str, count: int = 1) -> tuple[Hashable, int]:
        return "D", int(address[1:])

    def address_at(self, area: Hashable, index: int) -> str:
        return f"D{index}"

    def max_points(self, area: Hashable) -> int:
        return 960

    async def read(self, address: str, count: int = 1) -> list[int] | list[bool]:
        loop = asyncio.get_running_loop()
        waiter = loop.create_future()
        loop.call_soon(_resolve, waiter)
        await waiter
        return self.words[:count]

    async def write(self, address: str, values: Points) -> None:
        raise NotImplementedError


class _GcClock:
    """Seconds spent in the garbage collector since creation (``gc.callbacks``)."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self._start = 0.0
        gc.callbacks.append(self._callback)

    def _callback(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self._start = time.perf_counter()
        else:
            self.seconds += time.perf_counter() - self._start

    def close(self) -> None:
        gc.callbacks.remove(self._callback)


async def _bare_window(clients: list[MemoryClient], words: int, seconds: float) -> int:
    done = 0
    stop = False

    async def worker(client: MemoryClient) -> None:
        nonlocal done
        while not stop:
            await client.read("D0", words)
            done += 1

    tasks = [asyncio.create_task(worker(c)) for c in clients]
    await asyncio.sleep(seconds)
    stop = True
    await asyncio.gather(*tasks)
    return done


async def _poll_window(
    clients: list[MemoryClient], tags: tuple[TagConfig, ...], seconds: float, gc_clock: _GcClock
) -> tuple[float, float]:
    by_name = {f"plc{i}": c for i, c in enumerate(clients)}
    config = PollConfig(
        plcs=tuple(
            PlcConfig(name=name, url="e71+tcp://127.0.0.1:1", tags=tags) for name in by_name
        ),
        groups={DEFAULT_GROUP: INTERVAL},
        queue=max(1000, 4 * len(clients)),
    )
    poller = Poller(config, client_factory=lambda plc: by_name[plc.name])

    async def consume() -> None:
        async for _first in poller:
            poller.drain()

    def requests() -> int:
        return sum(s.requests for s in poller.stats.values())

    consumer = asyncio.create_task(consume())
    try:
        await poller.start()
        await asyncio.sleep(min(seconds, 0.1))  # every task scanning
        r0, c0, g0 = requests(), time.process_time(), gc_clock.seconds
        await asyncio.sleep(seconds)
        n = max(1, requests() - r0)
        return (time.process_time() - c0) / n, (gc_clock.seconds - g0) / n
    finally:
        await poller.aclose()
        consumer.cancel()
        await asyncio.gather(consumer, return_exceptions=True)


async def measure(
    plcs: int, *, words: int, dtype: ValueType[Any], seconds: float, repeats: int, tags: int = 1
) -> dict[str, list[tuple[float, float]]]:
    """Alternating bare and poller windows: (CPU, GC) seconds per request of each window.

    ``tags`` adjacent tags of ``words`` points per PLC, merged by the poller into one request
    of ``tags * words`` points (the bare loops read the same).
    """
    span = words * dtype.points_per_value(16)  # points of one tag
    points = span * tags
    values = [(1000 + i) & 0xFFFF for i in range(points)]
    clients = [MemoryClient(f"mem{i}", values) for i in range(plcs)]
    configs = tuple(
        TagConfig(name=f"t{k}", address=f"D{k * span}", type=dtype, count=words)
        for k in range(tags)
    )
    gc_clock = _GcClock()
    bare: list[tuple[float, float]] = []
    poll: list[tuple[float, float]] = []
    try:
        await _bare_window(clients, points, min(seconds, 0.2))  # warm-up
        for _ in range(repeats):
            c0, g0 = time.process_time(), gc_clock.seconds
            n = max(1, await _bare_window(clients, points, seconds))
            bare.append(((time.process_time() - c0) / n, (gc_clock.seconds - g0) / n))
            poll.append(await _poll_window(clients, configs, seconds, gc_clock))
    finally:
        gc_clock.close()
    return {"bare": bare, "poll": poll}


def report(result: dict[str, list[tuple[float, float]]], plcs: int, what: str) -> str:
    def us(values: list[float]) -> str:
        med = statistics.median(values) * 1e6
        return f"{med:7.2f} us  ({min(values) * 1e6:.2f}..{max(values) * 1e6:.2f})"

    bare_cpu = [c for c, _ in result["bare"]]
    poll_cpu = [c for c, _ in result["poll"]]
    own = statistics.median(poll_cpu) - statistics.median(bare_cpu)
    lines = [
        f"CPU per request, {plcs} in-memory PLCs, {what}, {len(bare_cpu)} windows each "
        "(median (min..max))",
        f"  bare closed loops     {us(bare_cpu)}   gc {us([g for _, g in result['bare']])}",
        f"  poller                {us(poll_cpu)}   gc {us([g for _, g in result['poll']])}",
        f"  poller's own cost     {own * 1e6:7.2f} us per request (difference of the medians)",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m plcstack.bench.pollcost")
    parser.add_argument("--plcs", type=int, default=1000)
    parser.add_argument("--words", type=int, default=64, help="points of each tag")
    parser.add_argument("--tags", type=int, default=1, help="adjacent tags per PLC (one request)")
    parser.add_argument("--type", default="raw", choices=list(TYPES))
    parser.add_argument("--seconds", type=float, default=1.0)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    dtype = value_type(args.type)
    result = asyncio.run(
        measure(
            args.plcs,
            words=args.words,
            dtype=dtype,
            seconds=args.seconds,
            repeats=args.repeats,
            tags=args.tags,
        )
    )
    what = f"{args.tags} x {args.words}-value {dtype.name} tags each, one request"
    print(report(result, args.plcs, what))
    return 0


if __name__ == "__main__":
    sys.exit(main())
