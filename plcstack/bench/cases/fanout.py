"""Case 3 (and 4): fan-out to N simulated PLCs, and thread-per-PLC peers.

Each measurement runs in a **fresh child process** (``python -m plcstack.bench.cases.fanout``):
memory per connection is only meaningful from a clean baseline (a process that already opened and
closed 1000 connections keeps most of that memory), file descriptors are released for sure, and
the event loop is chosen in the child. The child starts N simulators in-process (one listening
socket each, as N real PLCs have; they share one memory image), reads ``VmRSS``, opens N
connections, warms up, reads ``VmRSS`` again (delta / N = memory per connection, client and
simulator side together, the same for every kind), then runs the repeats and prints one JSON line.

Kinds:

* ``floor``   -- N raw asyncio clients (:mod:`plcstack.bench.floor`), one closed loop each
* ``clients`` -- N plcstack clients from ``plcstack.connect``, one closed loop each
* ``poll``    -- one ``plcstack.poll`` poller over the N PLCs, one 64-word tag each, scan interval
  so short that every PLC is always busy; ops = samples delivered
* ``peer-hsl`` -- N threads, each with a blocking ``hslcommunication`` client (only if installed)
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import importlib
import json
import os
import resource
import subprocess
import sys
import threading
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import plcstack
from plcstack.bench.cases import ProtocolCase, Unavailable, sample_words
from plcstack.bench.cases.conn import CHECK_TIMEOUT, check_floor, check_stack, stack_op, start_sim
from plcstack.bench.floor import FloorTcp, FloorUdp, open_floor
from plcstack.bench.runner import Sample, Series, measure_workers, read_rss_kib

__all__ = ["KINDS", "raise_fd_limit", "run_child", "spawn"]

KINDS = ("floor", "clients", "poll", "peer-hsl")
# The directory that holds the running ``plcstack`` package (a source checkout or site-packages):
# child processes get it first on PYTHONPATH and as their working directory, so they import the
# very same plcstack as the parent, installed from a wheel or not.
PACKAGE_PARENT = Path(__file__).resolve().parents[3]


def raise_fd_limit(needed: int) -> int:
    """Raise the soft RLIMIT_NOFILE to the hard limit; returns the new soft limit."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < hard and (hard == resource.RLIM_INFINITY or soft < needed):
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
        soft = hard
    if soft != resource.RLIM_INFINITY and soft < needed:
        raise Unavailable(f"needs {needed} file descriptors, RLIMIT_NOFILE hard limit is {hard}")
    return soft


# -- parent side ----------------------------------------------------------------------------------
def spawn(
    protocol: str,
    kind: str,
    n: int,
    *,
    loop: str,
    repeats: int,
    duration: float,
    warmup: float,
    timeout: float = 120.0,
) -> dict[str, Any]:
    """Run one measurement in a child process; returns its JSON summary (or ``{"note": ...}``)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(PACKAGE_PARENT), *filter(None, [env.get("PYTHONPATH", "")])]
    )
    cmd = [
        sys.executable,
        "-m",
        "plcstack.bench.cases.fanout",
        protocol,
        kind,
        str(n),
        "--loop",
        loop,
        "--repeats",
        str(repeats),
        "--duration",
        str(duration),
        "--warmup",
        str(warmup),
    ]
    try:
        proc = subprocess.run(
            cmd, capture_output=True, text=True, timeout=timeout, env=env, cwd=str(PACKAGE_PARENT)
        )
    except subprocess.TimeoutExpired:
        return {"note": f"child timed out after {timeout:g} s"}
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return {"note": f"child failed (exit {proc.returncode}): {tail}"}
    summary: dict[str, Any] = json.loads(lines[-1])
    return summary


def series_from_summary(summary: dict[str, Any]) -> Series:
    series = Series()
    for ops, seconds in summary.get("samples", []):
        series.add(Sample(int(ops), float(seconds)))
    series.rss_kib_per_conn = summary.get("rss_kib_per_conn")
    return series


# -- child side -----------------------------------------------------------------------------------
async def _measure(
    ops: list[Callable[[], Awaitable[object]]], repeats: int, duration: float, warmup: float
) -> tuple[list[Sample], list[int]]:
    samples: list[Sample] = []
    latencies: list[int] = []
    for index in range(repeats):
        sample = await measure_workers(ops, duration=duration, warmup=warmup if index == 0 else 0.0)
        latencies.extend(sample.latencies_ns)
        sample.latencies_ns = []
        samples.append(sample)
    return samples, latencies


def _summary(
    samples: list[Sample], latencies: list[int], rss_per_conn: float | None, **extra: Any
) -> dict[str, Any]:
    series = Series(samples)
    series.samples[0].latencies_ns = latencies  # percentiles over all repeats
    return {
        "samples": [[s.ops, s.seconds] for s in samples],
        "p50_ms": series.latency_ms(50),
        "p99_ms": series.latency_ms(99),
        "rss_kib_per_conn": rss_per_conn,
        **extra,
    }


async def run_child(
    case: ProtocolCase, kind: str, n: int, *, repeats: int, duration: float, warmup: float
) -> dict[str, Any]:
    case.check()
    raise_fd_limit(3 * n + 64)
    sim_mod = case.sim()
    memory = case.make_memory(sim_mod)
    sims = [await start_sim(case, memory) for _ in range(n)]
    hsl_factory = None
    if kind == "peer-hsl":  # import the peer library before the memory baseline
        from plcstack.bench.cases import peers

        hsl_factory = peers.hsl_reader(case)
    closers: list[Callable[[], Awaitable[None]]] = []
    try:
        gc.collect()
        base = read_rss_kib()
        if kind == "floor":
            ops = await _open_floor_ops(case, sims, closers)
        elif kind == "clients":
            ops = await _open_client_ops(case, sims, closers)
        elif kind == "poll":
            return await _run_poll(
                case, sims, base, repeats=repeats, duration=duration, warmup=warmup
            )
        elif hsl_factory is not None:
            return await _run_hsl(
                hsl_factory, sims, base, repeats=repeats, duration=duration, warmup=warmup
            )
        else:
            raise ValueError(f"unknown kind {kind!r}")
        # one round on every connection before the memory reading: buffers are allocated lazily
        async with asyncio.timeout(30):
            await asyncio.gather(*(op() for op in ops))
        gc.collect()
        after = read_rss_kib()
        per_conn = (after - base) / n if base is not None and after is not None else None
        samples, latencies = await _measure(ops, repeats, duration, warmup)
        return _summary(samples, latencies, per_conn)
    finally:
        for close in closers:
            await close()
        await asyncio.gather(*(sim.aclose() for sim in sims), return_exceptions=True)


async def _open_floor_ops(
    case: ProtocolCase, sims: list[Any], closers: list[Callable[[], Awaitable[None]]]
) -> list[Callable[[], Awaitable[object]]]:
    assert case.floor_read is not None
    job = case.floor_read()
    ops: list[Callable[[], Awaitable[object]]] = []
    for index, sim in enumerate(sims):
        url = plcstack.parse_url(sim.url)
        assert url.host is not None and url.port is not None
        floor: FloorTcp | FloorUdp = await open_floor(url.host, url.port, udp=case.udp)
        closers.append(floor.aclose)
        if index == 0:
            async with asyncio.timeout(CHECK_TIMEOUT):
                await check_floor(floor, job)
        ops.append(_bind_floor(floor, job))
    return ops


def _bind_floor(floor: FloorTcp | FloorUdp, job: Any) -> Callable[[], Awaitable[object]]:
    def op() -> Awaitable[object]:
        return floor.run(job)

    return op


async def _open_client_ops(
    case: ProtocolCase, sims: list[Any], closers: list[Callable[[], Awaitable[None]]]
) -> list[Callable[[], Awaitable[object]]]:
    ops: list[Callable[[], Awaitable[object]]] = []
    for index, sim in enumerate(sims):
        client = plcstack.connect(case.client_url(sim.url))
        await client.open()
        closers.append(client.aclose)
        if case.prepare_client is not None:
            await case.prepare_client(client)
        if index == 0:
            async with asyncio.timeout(CHECK_TIMEOUT):
                await check_stack(client, case, "read")
        ops.append(stack_op(client, case, "read"))
    return ops


async def _run_poll(
    case: ProtocolCase,
    sims: list[Any],
    base: int | None,
    *,
    repeats: int,
    duration: float,
    warmup: float,
) -> dict[str, Any]:
    from plcstack.bench.cases import pollbench  # the poller's API lives in one adapter module

    return await pollbench.run(case, sims, base, repeats=repeats, duration=duration, warmup=warmup)


async def _run_hsl(
    make: Callable[[str, int], Callable[[], list[int]]],
    sims: list[Any],
    base: int | None,
    *,
    repeats: int,
    duration: float,
    warmup: float,
) -> dict[str, Any]:
    readers = []
    # Blocking calls go to threads: the simulators that must answer them run on this loop.
    for sim in sims:
        url = plcstack.parse_url(sim.url)
        assert url.host is not None and url.port is not None
        readers.append(await asyncio.to_thread(make, url.host, url.port))
    expected = sample_words()
    if await asyncio.to_thread(readers[0]) != expected:
        raise RuntimeError("hslcommunication read returned different values than the simulator")
    gc.collect()
    after = read_rss_kib()
    per_conn = (after - base) / len(sims) if base is not None and after is not None else None
    samples: list[Sample] = []
    latencies: list[int] = []
    for index in range(repeats):
        if index == 0 and warmup > 0:
            await _threads(readers, warmup, [])
        lat: list[int] = []
        ops, seconds = await _threads(readers, duration, lat)
        samples.append(Sample(ops, seconds))
        latencies.extend(lat)
    return _summary(samples, latencies, per_conn)


async def _threads(
    readers: list[Callable[[], list[int]]], duration: float, latencies: list[int]
) -> tuple[int, float]:
    """One OS thread per PLC, each reading in a loop; the event loop keeps serving the sims."""
    stop = threading.Event()
    counts = [0] * len(readers)
    lock = threading.Lock()
    errors: list[BaseException] = []

    def worker(index: int, read: Callable[[], list[int]]) -> None:
        local: list[int] = []
        try:
            while not stop.is_set():
                t0 = time.perf_counter_ns()
                read()
                local.append(time.perf_counter_ns() - t0)
                counts[index] += 1
        except BaseException as exc:  # reported after the run
            errors.append(exc)
        with lock:
            latencies.extend(local)

    threads = [
        threading.Thread(target=worker, args=(i, r), daemon=True) for i, r in enumerate(readers)
    ]
    start = time.perf_counter()
    for thread in threads:
        thread.start()
    await asyncio.sleep(duration)
    stop.set()
    for thread in threads:  # each stops within one request after the flag
        await asyncio.to_thread(thread.join)
    elapsed = time.perf_counter() - start
    if errors:
        raise RuntimeError(f"peer thread failed: {errors[0]!r}")
    return sum(counts), elapsed


def _loop_factory(name: str) -> Callable[[], asyncio.AbstractEventLoop]:
    if name == "uvloop":
        factory: Callable[[], asyncio.AbstractEventLoop] = importlib.import_module(
            "uvloop"
        ).new_event_loop
        return factory
    return asyncio.new_event_loop


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m plcstack.bench.cases.fanout")
    parser.add_argument("protocol")
    parser.add_argument("kind", choices=KINDS)
    parser.add_argument("n", type=int)
    parser.add_argument("--loop", default="asyncio", choices=("asyncio", "uvloop"))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--duration", type=float, default=1.0)
    parser.add_argument("--warmup", type=float, default=0.2)
    args = parser.parse_args(argv)
    from plcstack.bench.cases.protocols import by_key

    case = by_key(args.protocol)
    try:
        with asyncio.Runner(loop_factory=_loop_factory(args.loop)) as runner:
            summary = runner.run(
                run_child(
                    case,
                    args.kind,
                    args.n,
                    repeats=args.repeats,
                    duration=args.duration,
                    warmup=args.warmup,
                )
            )
    except Unavailable as exc:
        summary = {"note": str(exc)}
    print(json.dumps(summary), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
