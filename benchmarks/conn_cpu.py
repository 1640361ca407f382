"""One connection against an in-process simulator: process CPU per request, floor vs stack,
many short alternating windows (issue 16, item 3).

    python -m benchmarks.conn_cpu as511+tcp [REPEATS] [SECONDS] [read|write]

The same setup as the ``conn/*`` rows of ``plcstack bench`` (simulator, floor and stack on one
thread); prints the medians of CPU per request and of the per-window ratio floor/stack. For
comparisons run it under ``taskset -c 0`` with ``MALLOC_MMAP_THRESHOLD_=1048576
MALLOC_TRIM_THRESHOLD_=67108864`` (see README, "Allocator luck").
"""

from __future__ import annotations

import asyncio
import statistics
import sys
import time
from typing import Any

import plcstack
from plcstack.bench.cases.conn import check_floor, check_stack, open_stack, stack_op, start_sim
from plcstack.bench.cases.protocols import by_key
from plcstack.bench.floor import open_floor
from plcstack.bench.runner import measure_workers


async def run(key: str, repeats: int, seconds: float, kind: Any) -> str:
    case = by_key(key)
    builder = case.floor_read if kind == "read" else case.floor_write
    assert builder is not None
    job = builder()
    sim = await start_sim(case)
    url = plcstack.parse_url(sim.url)
    assert url.host is not None and url.port is not None
    floor = await open_floor(url.host, url.port, udp=case.udp)
    client = await open_stack(case, sim.url)
    try:
        await check_floor(floor, job)
        await check_stack(client, case, kind)
        stack = stack_op(client, case, kind)

        def floor_op() -> Any:
            return floor.run(job)

        async def window(op: Any) -> float:
            started = time.process_time()
            sample = await measure_workers([op], duration=seconds)
            return (time.process_time() - started) / max(1, sample.ops) * 1e6

        await window(floor_op)
        await window(stack)
        floors, stacks, ratios = [], [], []
        for _ in range(repeats):
            f, s = await window(floor_op), await window(stack)
            floors.append(f)
            stacks.append(s)
            ratios.append(f / s)
    finally:
        await client.aclose()
        await floor.aclose()
        await sim.aclose()
    return (
        f"{key} {kind}: floor {statistics.median(floors):.1f} us/req, stack "
        f"{statistics.median(stacks):.1f} us/req, CPU floor/stack median "
        f"{statistics.median(ratios):.2f} ({min(ratios):.2f}..{max(ratios):.2f})"
    )


if __name__ == "__main__":
    args = sys.argv[1:]
    print(
        asyncio.run(
            run(
                args[0] if args else "as511+tcp",
                int(args[1]) if len(args) > 1 else 41,
                float(args[2]) if len(args) > 2 else 0.06,
                args[3] if len(args) > 3 else "read",
            )
        )
    )
