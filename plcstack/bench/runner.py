"""Timing primitives: repeat a case, keep every latency, reduce to min/median/max and p50/p99.

Two shapes of case exist:

* synchronous micro-benchmarks (codecs): ``measure_sync`` calls a function in batches, like
  ``timeit``, and reports microseconds per call;
* asynchronous closed loops (one connection, fan-out): ``measure_workers`` runs one coroutine loop
  per connection until a stop flag is set, so N connections keep N requests in flight, and records
  the latency of every request with ``perf_counter_ns``.

Every case is repeated (``repeats``); ops/s is reported as the median over repeats with min and max,
latency percentiles over all requests of all repeats. Nothing here asserts a duration: the numbers
are results, not tests.
"""

from __future__ import annotations

import asyncio
import gc
import math
import statistics
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

__all__ = [
    "Result",
    "Sample",
    "Series",
    "measure_sync",
    "measure_workers",
    "percentile",
    "read_rss_kib",
]

#: the keys every JSON result row has; further keys are extras
JSON_KEYS = ("case", "loop", "n", "ops_per_s", "floor_ops_per_s", "ratio", "p99_ms")


def percentile(sorted_values: Sequence[float], q: float) -> float:
    """Nearest-rank percentile (``q`` in 0..100) of an already sorted, non-empty sequence."""
    if not sorted_values:
        raise ValueError("percentile of no values")
    rank = max(1, math.ceil(q / 100.0 * len(sorted_values)))
    return float(sorted_values[min(rank, len(sorted_values)) - 1])


@dataclass
class Sample:
    """One repeat of a case: how many operations completed in how many seconds."""

    ops: int
    seconds: float
    latencies_ns: list[int] = field(default_factory=list)
    #: process CPU seconds (``time.process_time``) over the same window, when measured: what
    #: other jobs on a shared machine barely move, unlike ``seconds``
    cpu_seconds: float | None = None

    @property
    def ops_per_s(self) -> float:
        return self.ops / self.seconds if self.seconds > 0 else 0.0

    @property
    def cpu_us_per_op(self) -> float | None:
        if self.cpu_seconds is None or not self.ops:
            return None
        return self.cpu_seconds / self.ops * 1e6


@dataclass
class Series:
    """All repeats of one case (one side: floor or stack), reduced on demand."""

    samples: list[Sample] = field(default_factory=list)
    rss_kib_per_conn: float | None = None

    def add(self, sample: Sample) -> None:
        self.samples.append(sample)

    @property
    def rates(self) -> list[float]:
        return [s.ops_per_s for s in self.samples]

    @property
    def median(self) -> float:
        return statistics.median(self.rates) if self.samples else 0.0

    @property
    def minimum(self) -> float:
        return min(self.rates) if self.samples else 0.0

    @property
    def maximum(self) -> float:
        return max(self.rates) if self.samples else 0.0

    def latency_ms(self, q: float) -> float | None:
        values = sorted(v for s in self.samples for v in s.latencies_ns)
        if not values:
            return None
        return percentile(values, q) / 1e6


@dataclass
class Result:
    """One row of the report. ``ops_per_s`` etc. are ``None`` for a skipped case (see ``note``)."""

    case: str
    loop: str
    n: int
    ops_per_s: float | None = None
    floor_ops_per_s: float | None = None
    ratio: float | None = None
    p99_ms: float | None = None
    # extras (not required by the JSON schema, useful in the table and the chart)
    group: str = ""
    ops_min: float | None = None
    ops_max: float | None = None
    p50_ms: float | None = None
    floor_p99_ms: float | None = None
    us_per_op: float | None = None
    floor_us_per_op: float | None = None
    rss_kib_per_conn: float | None = None
    floor_rss_kib_per_conn: float | None = None
    repeats: int = 0
    note: str = ""

    @classmethod
    def from_series(
        cls,
        case: str,
        loop: str,
        n: int,
        stack: Series,
        floor: Series | None,
        *,
        group: str,
        note: str = "",
    ) -> Result:
        stack_rate = stack.median
        floor_rate = floor.median if floor is not None and floor.samples else None
        ratio = stack_rate / floor_rate if floor_rate else None
        return cls(
            case=case,
            loop=loop,
            n=n,
            ops_per_s=stack_rate,
            floor_ops_per_s=floor_rate,
            ratio=ratio,
            p99_ms=stack.latency_ms(99),
            group=group,
            ops_min=stack.minimum,
            ops_max=stack.maximum,
            p50_ms=stack.latency_ms(50),
            floor_p99_ms=floor.latency_ms(99) if floor is not None else None,
            rss_kib_per_conn=stack.rss_kib_per_conn,
            floor_rss_kib_per_conn=floor.rss_kib_per_conn if floor is not None else None,
            repeats=len(stack.samples),
            note=note,
        )

    @classmethod
    def skipped(cls, case: str, loop: str, n: int, note: str, *, group: str) -> Result:
        return cls(case=case, loop=loop, n=n, group=group, note=note)

    @property
    def ran(self) -> bool:
        return self.ops_per_s is not None

    def to_json(self) -> dict[str, Any]:
        row = asdict(self)
        # required keys first, in the documented order
        return {**{k: row.pop(k) for k in JSON_KEYS}, **row}


# -- synchronous micro-benchmarks ------------------------------------------------------------------
def measure_sync(
    fn: Callable[[], object], *, repeats: int, min_time: float, max_number: int = 1_000_000
) -> Series:
    """Call ``fn`` in batches; each repeat lasts about ``min_time`` seconds (at least one call).

    Times are process CPU seconds (``time.process_time``): a batch preempted by another job on a
    shared machine is not charged for the wait (the codec rows swung 2x with wall-clock time).
    The batch size is calibrated once (doubling until a batch takes >= min_time / 4) so the timer
    overhead is negligible; garbage collection is disabled while a batch runs, as ``timeit`` does.
    """
    number = 1
    while True:
        elapsed = _time_batch(fn, number)
        if elapsed >= min_time / 4 or number >= max_number:
            break
        number *= 2
    per_repeat = max(1, min(max_number, int(number * min_time / max(elapsed, 1e-9))))
    series = Series()
    for _ in range(repeats):
        elapsed = _time_batch(fn, per_repeat)
        series.add(Sample(per_repeat, elapsed))
    return series


def _time_batch(fn: Callable[[], object], number: int) -> float:
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        start = time.process_time()
        for _ in range(number):
            fn()
        return time.process_time() - start
    finally:
        if gc_was_enabled:
            gc.enable()


# -- asynchronous closed loops ---------------------------------------------------------------------
Op = Callable[[], Awaitable[object]]


class _Stop:
    __slots__ = ("flag",)

    def __init__(self) -> None:
        self.flag = False


async def _worker(op: Op, stop: _Stop, latencies: list[int]) -> int:
    clock = time.perf_counter_ns
    append = latencies.append
    done = 0
    while not stop.flag:
        t0 = clock()
        await op()
        append(clock() - t0)
        done += 1
    return done


async def measure_workers(
    ops: Sequence[Op], *, duration: float, warmup: float = 0.0, drain_timeout: float = 30.0
) -> Sample:
    """Run one closed loop per op (= per connection) for ``duration`` seconds, return one sample
    (with the process CPU time of the window).

    Every loop awaits its op, records the latency, and starts the next op at once, so ``len(ops)``
    requests are in flight all the time. The sample's time runs until the last in-flight op has
    finished, so no completed work is counted against too short a time. An op that raises ends the
    measurement with that exception (a benchmark that fails must not report a number); ops still
    unfinished ``drain_timeout`` seconds after the stop raise ``TimeoutError`` (a hung peer).
    """
    if warmup > 0:
        await _run(ops, warmup, [], drain_timeout)
    latencies: list[int] = []
    cpu = time.process_time()
    ops_done, seconds = await _run(ops, duration, latencies, drain_timeout)
    return Sample(ops_done, seconds, latencies, time.process_time() - cpu)


async def _run(
    ops: Sequence[Op], duration: float, latencies: list[int], drain_timeout: float
) -> tuple[int, float]:
    stop = _Stop()
    start = time.perf_counter()
    tasks = [asyncio.ensure_future(_worker(op, stop, latencies)) for op in ops]
    try:
        done, _pending = await asyncio.wait(tasks, timeout=duration)
        stop.flag = True
        for task in done:  # a worker that ended early ended by an exception
            task.result()
        async with asyncio.timeout(drain_timeout):
            counts = await asyncio.gather(*tasks)
    except BaseException:
        stop.flag = True
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        raise
    return sum(counts), time.perf_counter() - start


def read_rss_kib() -> int | None:
    """Resident set size of this process in KiB from ``/proc/self/status`` (``None`` elsewhere)."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None
