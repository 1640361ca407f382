"""Fan-out through ``plcstack.poll``: the adapter between the benchmark and the poller's API.

One :class:`~plcstack.poll.engine.Poller` over the N simulated PLCs, one tag of 64 words each (so
one request per scan), the default concurrency (no global cap) and a scan interval far shorter
than a round trip, so every PLC's task starts its next scan as soon as the last one finished: the
poller's maximum rate, the same closed loop the floor runs. A consumer task takes the samples off
the poller (``drain``), as an application would. ops = requests completed (from the poller's own
per-PLC counters); latencies are timed around each client read (perf_counter_ns).

Kept in one module so that a change of the poller's API touches one place.
"""

from __future__ import annotations

import asyncio
import gc
import importlib
import time
from typing import Any

from plcstack.bench.cases import WORDS, ProtocolCase, Unavailable, sample_words
from plcstack.bench.runner import Sample, Series, read_rss_kib

__all__ = ["run"]

#: seconds between scans: the shortest the poller accepts (1 ms). With the hundreds of PLCs
#: measured here one round of requests takes far longer, so every PLC's task scans back to back;
#: below about ten PLCs this caps the poller at 1000 scans/s per PLC.
INTERVAL = 0.001  # = plcstack.poll.config.MIN_INTERVAL (plcstack is imported lazily here)


def _time_reads(client: Any, latencies: list[int], recording: list[bool]) -> None:
    read = client.read
    clock = time.perf_counter_ns

    async def timed_read(address: str, count: int = 1) -> Any:
        t0 = clock()
        result = await read(address, count)
        if recording[0]:
            latencies.append(clock() - t0)
        return result

    client.read = timed_read


async def run(
    case: ProtocolCase,
    sims: list[Any],
    base_rss: int | None,
    *,
    repeats: int,
    duration: float,
    warmup: float,
) -> dict[str, Any]:
    try:
        engine = importlib.import_module("plcstack.poll.engine")
        config = importlib.import_module("plcstack.poll.config")
    except ModuleNotFoundError:
        raise Unavailable("plcstack.poll not merged yet") from None
    n = len(sims)
    plcs = tuple(
        config.PlcConfig(
            name=f"plc{i}",
            url=case.client_url(sim.url),
            tags=(config.TagConfig(name="words", address=case.read_address, count=WORDS),),
        )
        for i, sim in enumerate(sims)
    )
    poll_config = config.PollConfig(
        plcs=plcs, groups={config.DEFAULT_GROUP: INTERVAL}, queue=max(1000, 4 * n)
    )
    poller = engine.Poller(poll_config)
    # Latency is timed around each client read with perf_counter_ns, as the clients and floor
    # rows are (the poller's own window also uses perf_counter now, but keeps only the last
    # 4096 requests per PLC and cannot tell warm-up from measurement).
    latencies: list[int] = []
    recording = [False]
    for name in poller.plcs:
        _time_reads(poller.client(name), latencies, recording)
    samples_seen = 0
    bad: list[str] = []
    expected = sample_words()

    async def consume() -> None:
        nonlocal samples_seen
        async for first in poller:
            batch = [first, *poller.drain()]
            samples_seen += len(batch)
            for sample in batch:
                if sample.value is None or list(sample.value) != expected:
                    bad.append(f"{sample.plc}: {sample.error or sample.value!r:.120}")

    def requests() -> int:
        return sum(s.requests for s in poller.stats.values())

    consumer = asyncio.create_task(consume())
    try:
        await poller.start()
        # warm-up: every PLC connected and answered once
        async with asyncio.timeout(60):
            # the poller exposes counters, not events: poll them (bounded by the timeout)
            while min(s.requests for s in poller.stats.values()) < 1:  # noqa: ASYNC110
                await asyncio.sleep(0.01)
        t0, before = time.perf_counter(), requests()
        await asyncio.sleep(max(warmup, 0.05))
        warm_rate = (requests() - before) / (time.perf_counter() - t0)
        if bad:
            raise RuntimeError(f"poller delivered bad samples: {bad[:3]}")
        gc.collect()
        after = read_rss_kib()
        per_conn = (after - base_rss) / n if base_rss is not None and after is not None else None
        series = Series()
        recording[0] = True
        # Requests finish in waves of up to N (every PLC has one in flight), one wave per round
        # trip; a window shorter than a few waves would count 1000s or 2000s, not a rate.
        window = max(duration, min(3 * n / warm_rate, 2.0)) if warm_rate > 0 else duration
        for _ in range(repeats):
            before, t0 = requests(), time.perf_counter()
            await asyncio.sleep(window)
            series.add(Sample(requests() - before, time.perf_counter() - t0))
        recording[0] = False
        errors = sum(s.errors for s in poller.stats.values())
        drops = poller.dropped
        if bad:
            raise RuntimeError(f"poller delivered bad samples: {bad[:3]}")
    finally:
        await poller.aclose()
        consumer.cancel()
        await asyncio.gather(consumer, return_exceptions=True)
    series.samples[0].latencies_ns = sorted(latencies)
    return {
        "samples": [[s.ops, s.seconds] for s in series.samples],
        "p50_ms": series.latency_ms(50),
        "p99_ms": series.latency_ms(99),
        "rss_kib_per_conn": per_conn,
        "errors": errors,
        "drops": drops,
        "samples_delivered": samples_seen,
    }
