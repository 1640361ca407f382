"""Where a request's time goes: cProfile of the one-connection stack path, client side only.

    python -m plcstack.bench.profiling e71+tcp [--seconds 3] [--kind read|write] [--top 25]
    python -m plcstack.bench.profiling e71+tcp --poll 100     # the poller over 100 PLCs instead

The simulator runs in a **child process** (``python -m plcstack.bench.profiling --serve KEY``, which
prints the URL once it accepts clients), so the profile shows only what the client side costs:
plcstack's client, codec and transport plus the event loop. The output is the usual ``pstats``
table sorted by own time, then a summary per layer (own time of functions grouped by file), in
microseconds per request.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import cProfile
import importlib
import os
import pstats
import statistics
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import plcstack
from plcstack.bench.cases.conn import (
    Kind,
    check_floor,
    check_stack,
    open_stack,
    stack_op,
    start_sim,
)
from plcstack.bench.cases.fanout import PACKAGE_PARENT
from plcstack.bench.cases.protocols import by_key
from plcstack.bench.floor import open_floor
from plcstack.bench.runner import measure_workers

__all__ = ["layer_of", "main"]


def layer_of(filename: str) -> str:
    """Group a profiled file into a layer for the per-layer summary."""
    path = filename.replace("\\", "/")
    for marker in ("plcstack/codecs/", "plcstack/clients/", "plcstack/transports/",
                   "plcstack/poll/", "plcstack/bench/"):  # fmt: skip
        if marker in path:
            return marker.rstrip("/") + "/" + path.split(marker, 1)[1]
    if "asyncio/" in path or "uvloop" in path:
        return "asyncio (event loop, futures, timeouts, locks)"
    if path.startswith("~") or path.startswith("<"):
        return "builtins (struct, bytes, socket calls, ...)"
    return "other python"


def _cpus() -> list[int]:
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return []


def _pin(cpu: int) -> None:
    with contextlib.suppress(AttributeError, OSError):
        os.sched_setaffinity(0, {cpu})


async def _serve(key: str, count: int) -> None:
    cpus = _cpus()
    if len(cpus) >= 2:
        _pin(cpus[-1])  # the simulator on its own CPU, the measured process on the first
    case = by_key(key)
    memory = case.make_memory(case.sim())
    sims = [await start_sim(case, memory) for _ in range(count)]
    print(" ".join(sim.url for sim in sims), flush=True)
    try:
        await asyncio.Event().wait()
    finally:
        for sim in sims:
            await sim.aclose()


async def _poller(urls: list[str], key: str, seconds: float) -> tuple[Any, int]:
    """The poller over ``len(urls)`` PLCs, one 64-word tag each, as the fan-out case runs it."""
    config_mod: Any = importlib.import_module("plcstack.poll.config")
    engine_mod: Any = importlib.import_module("plcstack.poll.engine")
    PlcConfig, PollConfig, TagConfig = (
        config_mod.PlcConfig,
        config_mod.PollConfig,
        config_mod.TagConfig,
    )

    from plcstack.bench.cases import WORDS
    from plcstack.bench.cases.pollbench import INTERVAL

    case = by_key(key)
    tag = TagConfig(name="words", address=case.read_address, count=WORDS)
    config = PollConfig(
        plcs=tuple(PlcConfig(name=f"plc{i}", url=u, tags=(tag,)) for i, u in enumerate(urls)),
        groups={config_mod.DEFAULT_GROUP: INTERVAL},
        queue=max(1000, 4 * len(urls)),
    )
    poller = engine_mod.Poller(config)

    async def consume() -> None:
        async for _first in poller:
            poller.drain()

    consumer = asyncio.create_task(consume())
    await poller.start()
    await asyncio.sleep(1.0)  # connect and warm up, unprofiled
    before = sum(s.requests for s in poller.stats.values())
    profiler = cProfile.Profile()
    profiler.enable()
    await asyncio.sleep(seconds)
    profiler.disable()
    done = sum(s.requests for s in poller.stats.values()) - before
    await poller.aclose()
    consumer.cancel()
    await asyncio.gather(consumer, return_exceptions=True)
    return profiler, done


async def _client(url: str, key: str, kind: Kind, seconds: float) -> tuple[Any, int]:
    case = by_key(key)
    client = await open_stack(case, url)
    try:
        await check_stack(client, case, kind)
        op = stack_op(client, case, kind)
        await measure_workers([op], duration=0.3)  # warm-up, unprofiled
        profiler = cProfile.Profile()
        profiler.enable()
        sample = await measure_workers([op], duration=seconds)
        profiler.disable()
    finally:
        await client.aclose()
    return profiler, sample.ops


class CpuPair:
    """One checked floor connection and one checked stack client to the same PLC, with the
    operation each repeats: what the CPU comparisons of one connection measure (``_cpu`` here,
    ``benchmarks/conn_cpu.py`` with the simulator in the same process)."""

    def __init__(self, floor: Any, client: Any, floor_op: Any, stack_op: Any) -> None:
        self.floor, self.client = floor, client
        self.floor_op, self.stack_op = floor_op, stack_op

    @classmethod
    async def open(cls, key: str, url: str, kind: Kind) -> CpuPair:
        case = by_key(key)
        job_builder = case.floor_read if kind == "read" else case.floor_write
        assert job_builder is not None
        job = job_builder()
        parsed = plcstack.parse_url(url)
        assert parsed.host is not None and parsed.port is not None
        floor = await open_floor(parsed.host, parsed.port, udp=case.udp)
        client = await open_stack(case, url)
        try:
            await check_floor(floor, job)
            await check_stack(client, case, kind)
        except BaseException:
            await client.aclose()
            await floor.aclose()
            raise

        def floor_op() -> Any:
            return floor.run(job)

        return cls(floor, client, floor_op, stack_op(client, case, kind))

    async def aclose(self) -> None:
        await self.client.aclose()
        await self.floor.aclose()


async def cpu_per_op(op: Any, seconds: float) -> tuple[float, float]:
    """Process CPU per operation (us) and operations per second of ``op`` repeated for
    ``seconds``: CPU time, which load on a shared machine barely moves."""
    started = time.process_time()
    sample = await measure_workers([op], duration=seconds)
    cpu = (time.process_time() - started) / max(1, sample.ops) * 1e6
    return cpu, sample.ops / sample.seconds


async def _cpu(url: str, key: str, kind: Kind, seconds: float, repeats: int) -> str:
    """Process CPU per request of the floor and the stack, alternating, one connection each,
    the simulator in another process: a ratio that load on a shared machine barely moves
    (wall-clock ops/s of the ``conn`` rows swing by 0.3 there)."""
    pair = await CpuPair.open(key, url, kind)
    lines = [
        f"{'floor us/req':>13} {'stack us/req':>13} {'floor/stack':>12}"
        f" {'floor req/s':>12} {'stack req/s':>12} {'stack/floor':>12}"
    ]
    try:
        await measure_workers([pair.floor_op], duration=0.2)  # warm-up
        await measure_workers([pair.stack_op], duration=0.2)
        ratios, rates = [], []
        for _ in range(repeats):
            f, f_rate = await cpu_per_op(pair.floor_op, seconds)
            st, s_rate = await cpu_per_op(pair.stack_op, seconds)
            ratios.append(f / st)
            rates.append(s_rate / f_rate)
            lines.append(
                f"{f:13.1f} {st:13.1f} {f / st:12.2f}"
                f" {f_rate:12.0f} {s_rate:12.0f} {s_rate / f_rate:12.2f}"
            )
        lines.append(
            f"median CPU ratio floor/stack {statistics.median(ratios):.2f}, "
            f"median rate ratio stack/floor {statistics.median(rates):.2f}"
        )
    finally:
        await pair.aclose()
    return "\n".join(lines)


def report(profiler: Any, requests: int, top: int) -> str:
    stats = pstats.Stats(profiler)
    lines = [f"{requests} requests profiled"]
    per_layer: dict[str, float] = defaultdict(float)
    rows = []
    raw: dict[Any, Any] = stats.stats  # type: ignore[attr-defined]
    for (filename, line, func), (_cc, ncalls, tottime, cumtime, _callers) in raw.items():
        per_layer[layer_of(filename)] += tottime
        rows.append((tottime, ncalls, cumtime, f"{Path(filename).name}:{line}({func})"))
    total = sum(per_layer.values())
    lines.append(
        f"own time per request: {total / requests * 1e6:.1f} us (profiler overhead included)"
    )
    lines.append("")
    lines.append("top functions by own time, us per request:")
    for tottime, ncalls, cumtime, name in sorted(rows, reverse=True)[:top]:
        lines.append(
            f"  {tottime / requests * 1e6:8.2f}  cum {cumtime / requests * 1e6:8.2f}  "
            f"calls/req {ncalls / requests:5.1f}  {name}"
        )
    lines.append("")
    lines.append("own time by layer, us per request:")
    for layer, seconds in sorted(per_layer.items(), key=lambda kv: -kv[1]):
        share = seconds / total * 100 if total else 0.0
        lines.append(f"  {seconds / requests * 1e6:8.2f}  {share:5.1f}%  {layer}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m plcstack.bench.profiling")
    parser.add_argument("protocol", help="e.g. e71+tcp, fetchwrite, s5lan, as511+tcp")
    parser.add_argument("--kind", choices=("read", "write"), default="read")
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--poll", type=int, metavar="N", help="profile the poller over N PLCs")
    parser.add_argument("--serve", type=int, metavar="N", help=argparse.SUPPRESS)
    parser.add_argument(
        "--cpu",
        type=int,
        metavar="REPEATS",
        help="no profile: process CPU per request of floor and stack, alternating REPEATS times",
    )
    args = parser.parse_args(argv)
    if args.serve:
        asyncio.run(_serve(args.protocol, args.serve))
        return 0
    path = [str(PACKAGE_PARENT), *filter(None, [os.environ.get("PYTHONPATH")])]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(path))
    server = subprocess.Popen(
        [sys.executable, "-m", "plcstack.bench.profiling", args.protocol,
         "--serve", str(args.poll or 1)],
        stdout=subprocess.PIPE, text=True, env=env, cwd=str(PACKAGE_PARENT),
    )  # fmt: skip
    try:
        assert server.stdout is not None
        urls = server.stdout.readline().split()
        for url in urls:
            plcstack.parse_url(url)
        if args.cpu:
            cpus = _cpus()
            if len(cpus) >= 2:
                _pin(cpus[0])
            print(
                f"{args.protocol} {args.kind} x64, one connection, simulator in another process"
                + (f" (pinned: CPU {cpus[0]}, simulator CPU {cpus[-1]})" if len(cpus) >= 2 else "")
            )
            print(asyncio.run(_cpu(urls[0], args.protocol, args.kind, args.seconds, args.cpu)))
            return 0
        if args.poll:
            profiler, requests = asyncio.run(_poller(urls, args.protocol, args.seconds))
        else:
            profiler, requests = asyncio.run(
                _client(urls[0], args.protocol, args.kind, args.seconds)
            )
    finally:
        server.terminate()
        server.wait(timeout=10)
    what = f"poller over {args.poll} PLCs" if args.poll else f"{args.kind} x64"
    print(f"{args.protocol} {what}, simulator(s) in another process")
    print(report(profiler, max(1, requests), args.top))
    return 0


if __name__ == "__main__":
    sys.exit(main())
