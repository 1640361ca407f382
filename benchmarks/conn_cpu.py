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
from typing import Any

from plcstack.bench.cases.conn import start_sim
from plcstack.bench.cases.protocols import by_key
from plcstack.bench.profiling import CpuPair, cpu_per_op


async def run(key: str, repeats: int, seconds: float, kind: Any) -> str:
    sim = await start_sim(by_key(key))
    try:
        pair = await CpuPair.open(key, sim.url, kind)
        try:

            async def window(op: Any) -> float:
                return (await cpu_per_op(op, seconds))[0]

            await window(pair.floor_op)
            await window(pair.stack_op)
            floors, stacks, ratios = [], [], []
            for _ in range(repeats):
                f, s = await window(pair.floor_op), await window(pair.stack_op)
                floors.append(f)
                stacks.append(s)
                ratios.append(f / s)
        finally:
            await pair.aclose()
    finally:
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
