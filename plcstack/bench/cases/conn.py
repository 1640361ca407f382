"""Case 2: one connection, floor vs stack, against the same in-process simulator.

Both clients talk to one simulator started in this process on the current event loop; each repeat
times the floor and then the stack for the same duration, alternating, so drift (CPU frequency,
other engineers' jobs on the shared machine) hits both sides alike. The row's ratio is process
CPU per operation, floor / stack, the median over the repeats (:func:`cpu_row`); the suite pins
the process to one CPU for these cases. Before timing, one floor reply
is compared byte for byte with the spec-built expectation and one stack read with the values the
simulator was filled with: a benchmark that reads garbage must fail, not report a number.
"""

from __future__ import annotations

import asyncio
import statistics
from typing import Any, Literal

import plcstack
from plcstack.bench.cases import WORDS, ProtocolCase, sample_words
from plcstack.bench.floor import FloorError, FloorTcp, FloorUdp, open_floor
from plcstack.bench.runner import Result, Series, measure_workers

__all__ = ["CHECK_TIMEOUT", "cpu_row", "open_stack", "run_conn_case", "start_sim"]

Kind = Literal["read", "write"]

#: seconds for the one checked exchange before timing (a simulator that fails fails fast)
CHECK_TIMEOUT = 5.0


async def start_sim(case: ProtocolCase, memory: Any = None) -> Any:
    sim_mod = case.sim()
    if memory is None:
        memory = case.make_memory(sim_mod)
    return await sim_mod.start(memory, host="127.0.0.1", port=0, **case.sim_kwargs)


async def open_stack(case: ProtocolCase, sim_url: str) -> Any:
    client = plcstack.connect(case.client_url(sim_url))
    await client.open()
    if case.prepare_client is not None:
        await case.prepare_client(client)
    return client


async def check_floor(floor: FloorTcp | FloorUdp, job: Any) -> None:
    reply = await floor.run(job)
    if job.expect is not None and reply != job.expect:
        raise FloorError(
            f"floor reply differs from the spec-built expectation:\n  got      {reply.hex(' ')}"
            f"\n  expected {job.expect.hex(' ')}"
        )
    if len(reply) == 0 and not getattr(job, "steps", None):
        raise FloorError("floor got an empty reply")


def stack_op(client: Any, case: ProtocolCase, kind: Kind) -> Any:
    if kind == "read":
        address = case.read_address

        def read() -> Any:
            return client.read(address, WORDS)

        return read
    values = sample_words(seed=0x3003)
    waddress = case.write_address

    def write() -> Any:
        return client.write(waddress, values)

    return write


async def check_stack(client: Any, case: ProtocolCase, kind: Kind) -> None:
    if kind == "read":
        got = list(await client.read(case.read_address, WORDS))
        if got != sample_words():
            raise FloorError(f"stack read {case.read_address} x{WORDS} returned {got[:8]}...")
    else:
        await stack_op(client, case, kind)()


def cpu_row(row: Result, stack: Series, floor: Series) -> Result:
    """Give a one-connection row its CPU figures: process CPU per operation of stack and floor
    (medians) and, as its ratio, the median over the alternating repeats of floor CPU / stack
    CPU. Simulator, floor and stack share one thread, so the simulator's CPU is on both sides;
    CPU time is what other jobs on a shared machine barely move, where the ops/s of a window
    swing with them (the wall-clock ratio stays in the note)."""
    pairs = [
        (f.cpu_us_per_op, s.cpu_us_per_op)
        for f, s in zip(floor.samples, stack.samples, strict=False)
        if f.cpu_us_per_op and s.cpu_us_per_op
    ]
    if not pairs:
        return row
    ratios = sorted(f / s for f, s in pairs)
    wall = row.ratio
    row.us_per_op = statistics.median(s for _, s in pairs)
    row.floor_us_per_op = statistics.median(f for f, _ in pairs)
    row.ratio = statistics.median(ratios)
    row.note = (
        f"ratio = CPU floor/stack ({ratios[0]:.2f}..{ratios[-1]:.2f})"
        + (f", wall-clock {wall:.2f}" if wall is not None else "")
        + (f"; {row.note}" if row.note else "")
    )
    return row


async def run_conn_case(
    case: ProtocolCase,
    kind: Kind,
    *,
    loop_name: str,
    repeats: int,
    duration: float,
    warmup: float,
) -> Result:
    """Floor and stack against one simulator; returns the stack row with the floor beside it."""
    name = f"conn/{case.key}/{kind}{WORDS}"
    case.check()
    job_builder = case.floor_read if kind == "read" else case.floor_write
    assert job_builder is not None
    job = job_builder()
    sim = await start_sim(case)
    floor: FloorTcp | FloorUdp | None = None
    client: Any = None
    try:
        url = plcstack.parse_url(sim.url)
        assert url.host is not None and url.port is not None
        floor = await open_floor(url.host, url.port, udp=case.udp)
        async with asyncio.timeout(CHECK_TIMEOUT):
            await check_floor(floor, job)
        client = await open_stack(case, sim.url)
        async with asyncio.timeout(CHECK_TIMEOUT):
            await check_stack(client, case, kind)
        fl = floor
        floor_series, stack_series = Series(), Series()
        op = stack_op(client, case, kind)

        def floor_op() -> Any:
            return fl.run(job)

        for index in range(repeats):
            first = warmup if index == 0 else 0.0
            floor_series.add(await measure_workers([floor_op], duration=duration, warmup=first))
            stack_series.add(await measure_workers([op], duration=duration, warmup=first))
        return cpu_row(
            Result.from_series(name, loop_name, 1, stack_series, floor_series, group="conn"),
            stack_series,
            floor_series,
        )
    finally:
        if client is not None:
            await client.aclose()
        if floor is not None:
            await floor.aclose()
        await sim.aclose()
        await asyncio.sleep(0)
