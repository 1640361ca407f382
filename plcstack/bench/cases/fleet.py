"""The fleet case: N E71 PLCs polled at 10 Hz, the PLCs' side in another process on its own CPU.

What a plant pays per PLC. The PLCs are cheap fixed-reply responders (not our simulators: no
codec, no memory image, every 12-byte request answered with the same 130-byte 64-word reply) in a
separate process, pinned with ``os.sched_setaffinity`` to the last CPU when the machine has two or
more, so their cost never lands on the measured side. The measured process is pinned to another
CPU and runs one of:

* ``floor``   -- a raw-asyncio fleet of the same shape: per PLC one connection and one task that
  sends pre-built request bytes on a 10 Hz schedule (start times spread over the interval, missed
  ticks counted as overruns and skipped, as the poller does) and awaits the known reply length;
* ``decoded`` -- the floor, but each reply turned into its 64 words as a list of Python ints with
  one ``struct`` call: the least any word read must do for its caller (the stack hands out those
  ints; the floor's bytes are not yet values). Allocating 64 ints per request in a heap of a
  thousand connections is a cost of its own, so the stack is reported against both;
* ``clients`` -- the same schedule, each task calling ``plcstack`` ``client.read("D0", 64)``;
* ``ring``    -- ``poll`` with the flight recorder on: each PLC's connection records its last
  ``FLEET_RING`` frames (default 64, as ``[trace] ring = 64``) in a
  :class:`~plcstack.wire.ring.FrameRing`, which is what the recorder costs per request;
* ``poll``    -- :class:`plcstack.poll.Poller`, one 64-word tag per PLC, interval 0.1 s, and a
  consumer that takes the samples in batches as ``plcstack poll``'s north side does: each
  gathers for ``[poll] batch_wait`` (10 ms) after its first sample. ``FLEET_CONSUMER_WAIT``
  seconds replaces that (0: a batch per event-loop pass, the consumer of earlier runs).

Reported per kind: process CPU per completed request (``time.process_time``: CPU time of this
process only, which other jobs on a shared machine barely move, unlike wall-clock rates),
requests/s achieved against the target N x 10, the share of one core, overruns, p50/p99 of the
request latency. The ratio floor/stack is of CPU per request.

Run one measurement (a JSON line on stdout)::

    python -m plcstack.bench.cases.fleet poll 1000 --loop asyncio --duration 5

or several kinds in one process, alternating, with the ratio of each base to the last kind per
round (``alternate``; ``plcstack bench`` runs floor, decoded and poll this way)::

    python -m plcstack.bench.cases.fleet alternate 1000 --kinds floor,decoded,poll --rounds 6
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import importlib
import json
import os
import resource
import statistics
import struct
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable, Iterator
from typing import Any, cast

from plcstack.bench import frames
from plcstack.bench.cases import WORDS, sample_words
from plcstack.bench.cases.fanout import PACKAGE_PARENT, raise_fd_limit
from plcstack.bench.opcodes import OpcodeCounter
from plcstack.poll.config import DEFAULT_BATCH_WAIT

__all__ = ["KINDS", "REPLY", "REQUEST", "spawn"]

KINDS = ("floor", "decoded", "clients", "ring", "poll")
#: frames each PLC's ring keeps in the ``ring`` kind (``FLEET_RING``)
RING = int(os.environ.get("FLEET_RING") or 64)
#: 10 Hz
INTERVAL = 0.1
#: how long the poll kind's consumer lets a batch gather (``Poller.scans(wait=...)``): the
#: default ``[poll] batch_wait``, as the north side uses it (the fleet's poller keeps the
#: default); ``FLEET_CONSUMER_WAIT`` sets it (0 is a batch per loop pass, which with callback
#: scans cost about 9 us per request more)
_wait = os.environ.get("FLEET_CONSUMER_WAIT")
CONSUMER_WAIT = float(_wait) if _wait else DEFAULT_BATCH_WAIT
REQUEST = frames.e71_read_words("D", 0, WORDS)
REPLY = frames.e71_reply_words(sample_words())
#: the reply's words, little-endian after the 2-byte header (the ``decoded`` kind)
_WORDS = struct.Struct(f"<{WORDS}H")


# -- the PLCs' side -------------------------------------------------------------------------------
class _Responder(asyncio.Protocol):
    """Answers every complete request with the fixed reply; knows nothing else."""

    __slots__ = ("_pending", "_transport")

    def __init__(self) -> None:
        self._pending = 0
        self._transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = cast(asyncio.Transport, transport)

    def data_received(self, data: bytes) -> None:
        self._pending += len(data)
        if self._pending >= len(REQUEST):
            count, self._pending = divmod(self._pending, len(REQUEST))
            assert self._transport is not None
            self._transport.write(REPLY * count)


def _cpus() -> list[int]:
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return []


def _pin(cpu: int | None) -> None:
    if cpu is not None:
        with contextlib.suppress(AttributeError, OSError):
            os.sched_setaffinity(0, {cpu})


#: PLCs that share one listening socket of the responders. Each PLC still has a connection of
#: its own (the measured side is unchanged); sharing the listener keeps the responders at about
#: one descriptor per PLC instead of two, so 10,000 PLCs fit a 20,000-descriptor limit.
PLCS_PER_LISTENER = 50


def listener_count(n: int) -> int:
    """How many listening sockets serve ``n`` PLCs."""
    return -(-n // PLCS_PER_LISTENER)


async def _serve(n: int) -> None:
    loop = asyncio.get_running_loop()
    servers = [
        await loop.create_server(_Responder, "127.0.0.1", 0, backlog=2 * PLCS_PER_LISTENER)
        for _ in range(listener_count(n))
    ]
    listening = [s.sockets[0].getsockname()[1] for s in servers]
    ports = [listening[i // PLCS_PER_LISTENER] for i in range(n)]
    print(json.dumps({"ports": ports}), flush=True)
    stop = loop.create_future()

    # the parent closes our stdin (or dies): that is the end
    def end() -> None:
        if not stop.done():
            stop.set_result(None)

    loop.add_reader(sys.stdin.fileno(), end)
    await stop


def _serve_main(n: int, cpu: int | None) -> int:
    _pin(cpu)
    raise_fd_limit(n + listener_count(n) + 64)
    try:  # the cheapest loop there is: the responders must not be the bottleneck
        uvloop = importlib.import_module("uvloop")
        factory: Callable[[], asyncio.AbstractEventLoop] = uvloop.new_event_loop
    except ImportError:
        factory = asyncio.new_event_loop
    with asyncio.Runner(loop_factory=factory) as runner:
        runner.run(_serve(n))
    return 0


def _start_responders(n: int, cpu: int | None) -> tuple[subprocess.Popen[str], list[int]]:
    cmd = [sys.executable, "-m", "plcstack.bench.cases.fleet", "serve", str(n)]
    if cpu is not None:
        cmd += ["--cpu", str(cpu)]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(PACKAGE_PARENT), env.get("PYTHONPATH", "")])
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line:
        proc.wait(5)
        raise RuntimeError(f"responder process exited ({proc.returncode}) before listening")
    ports: list[int] = json.loads(line)["ports"]
    return proc, ports


# -- the measured side ----------------------------------------------------------------------------
class _Counters:
    __slots__ = ("latencies", "overruns", "recording", "requests")

    def __init__(self) -> None:
        self.requests = 0
        self.overruns = 0
        self.latencies: list[float] = []
        self.recording = False


class _FloorConn(asyncio.BufferedProtocol):
    """The thinnest client: one future per request, resolved when the known length is in.

    A ``BufferedProtocol`` receiving into one reused buffer, as the stack's TCP transport does:
    with a plain ``Protocol`` asyncio receives every reply into a fresh 256 KiB buffer, which
    costs the floor more than the stack (measured 20-30 us per request here) and would flatter
    the ratio.
    """

    #: hand out the reply's words as ints (``decoded``) instead of its bytes (``floor``)
    decode = False

    def __init__(self) -> None:
        self.buffer = bytearray(4096)
        self.view = memoryview(self.buffer)
        self.have = 0
        self.waiter: asyncio.Future[bytes | list[int]] | None = None
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)

    def get_buffer(self, sizehint: int) -> memoryview:
        return self.view[self.have :]

    def buffer_updated(self, nbytes: int) -> None:
        self.have += nbytes
        if self.have >= len(REPLY) and self.waiter is not None and not self.waiter.done():
            reply: bytes | list[int] = (
                list(_WORDS.unpack_from(self.view, 2))
                if self.decode
                else bytes(self.view[: len(REPLY)])
            )
            self.have = 0
            self.waiter.set_result(reply)

    def connection_lost(self, exc: Exception | None) -> None:
        if self.waiter is not None and not self.waiter.done():
            self.waiter.set_exception(ConnectionError("responder closed the connection"))


async def _schedule(
    first_due: float, counters: _Counters, request: Callable[[], Any], checked: list[bool]
) -> None:
    """One PLC's 10 Hz loop, the poller's schedule rules, around ``await request()``."""
    clock = time.perf_counter
    next_due = first_due
    while True:
        delay = next_due - clock()
        if delay > 0:
            await asyncio.sleep(delay)
        start = clock()
        reply = await request()
        end = clock()
        if not checked[0]:
            checked[0] = True
            if list(reply) != sample_words() and reply != REPLY:
                raise RuntimeError(f"unexpected reply {reply!r:.80}")
        counters.requests += 1
        if counters.recording:
            counters.latencies.append(end - start)
        next_due += INTERVAL
        if next_due <= end:
            missed = int((end - next_due) // INTERVAL) + 1
            counters.overruns += missed
            next_due += missed * INTERVAL


async def _floor_fleet(
    ports: list[int], counters: _Counters, decode: bool = False
) -> tuple[list[asyncio.Task[None]], list[Closer]]:
    loop = asyncio.get_running_loop()
    now = time.perf_counter()
    tasks = []
    closers: list[Closer] = []
    for i, port in enumerate(ports):
        transport, conn = await loop.create_connection(_FloorConn, "127.0.0.1", port)
        closers.append(_closer(transport))
        conn.decode = decode

        def make(conn: _FloorConn = conn) -> Callable[[], asyncio.Future[bytes | list[int]]]:
            def request() -> asyncio.Future[bytes | list[int]]:
                conn.waiter = waiter = loop.create_future()
                assert conn.transport is not None
                conn.transport.write(REQUEST)
                return waiter

            return request

        due = now + 0.2 + INTERVAL * i / len(ports)
        tasks.append(asyncio.create_task(_schedule(due, counters, make(), [False])))
    return tasks, closers


#: closes one connection or client of a fleet when its run ends
Closer = Callable[[], Awaitable[None]]


def _closer(transport: asyncio.BaseTransport) -> Closer:
    async def close() -> None:
        transport.close()

    return close


async def _client_fleet(
    ports: list[int], counters: _Counters
) -> tuple[list[asyncio.Task[None]], list[Closer]]:
    import plcstack

    clients = [plcstack.connect(f"e71+tcp://127.0.0.1:{port}") for port in ports]
    for client in clients:
        await client.read("D0", WORDS)  # connected before the schedule starts
    now = time.perf_counter()
    tasks = []
    for i, client in enumerate(clients):

        def make(client: Any = client) -> Callable[[], Any]:
            return lambda: client.read("D0", WORDS)

        due = now + INTERVAL * i / len(clients)
        tasks.append(asyncio.create_task(_schedule(due, counters, make(), [False])))
    return tasks, [client.aclose for client in clients]


@contextlib.contextmanager
def _responders(n: int) -> Iterator[tuple[list[int], bool]]:
    """Pin this process, start the responders on the other CPU; their ports, and whether the
    two are pinned apart. Stops the responders at the end."""
    cpus = _cpus()
    responder_cpu = cpus[-1] if len(cpus) >= 2 else None
    _pin(cpus[0] if len(cpus) >= 2 else None)
    raise_fd_limit(n + 64)
    proc, ports = _start_responders(n, responder_cpu)
    try:
        yield ports, responder_cpu is not None
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()


async def _measure(
    kind: str,
    n: int,
    duration: float,
    warmup: float,
    profile: str | None = None,
    opcodes: str | None = None,
) -> dict[str, Any]:
    with _responders(n) as (ports, pinned):
        summary = await _run_kind(kind, ports, duration, warmup, profile, opcodes)
    summary["pinned"] = pinned
    return summary


async def _measure_alternating(
    kinds: tuple[str, ...], n: int, rounds: int, duration: float, warmup: float
) -> dict[str, Any]:
    """Every kind in this one process against one set of responders, in alternating runs.

    Separate processes a few minutes apart gave the same kind CPU costs 15 % apart on this
    two-core VM (the host's load moves them), more than the differences measured; the ratio
    of two such runs moved by 0.15. Here each round runs every kind back to back, in the
    reverse order every other round (ABBA: the last of a round is the first of the next, so
    a slow drift charges all alike), and a ratio is taken per round: the last kind is the one
    measured, every other one a base, and ``ratio[base]`` is the median over the rounds of
    ``base / last`` CPU per request.
    """
    measured = kinds[-1]
    runs: list[dict[str, Any]] = []
    with _responders(n) as (ports, pinned):
        for r in range(rounds):
            for kind in kinds if r % 2 == 0 else kinds[::-1]:
                run = await _run_kind(kind, ports, duration, warmup)
                run["round"] = r
                runs.append(run)
                gc.collect()  # the last fleet's garbage is not the next one's cost

    def cost(kind: str) -> list[float]:
        return [run["cpu_us_per_request"] or 0.0 for run in runs if run["kind"] == kind]

    ratios = {
        base: [b / m for b, m in zip(cost(base), cost(measured), strict=True) if b and m]
        for base in kinds[:-1]
    }
    return {
        "kind": "alternate",
        "kinds": list(kinds),
        "n": n,
        "rounds": rounds,
        "pinned": pinned,
        "ratio": {base: statistics.median(r) for base, r in ratios.items() if r},
        "ratios": ratios,
        "cpu_us_per_request": {k: statistics.median(cost(k)) for k in kinds if cost(k)},
        "runs": runs,
    }


async def _run_kind(
    kind: str,
    ports: list[int],
    duration: float,
    warmup: float,
    profile: str | None = None,
    opcodes: str | None = None,
) -> dict[str, Any]:
    """Start a fleet of ``kind`` against the responders' ``ports``, measure it, close it."""
    n = len(ports)
    counters = _Counters()
    tasks: list[asyncio.Task[None]] = []
    closers: list[Closer] = []
    poller: Any = None
    consumer: asyncio.Task[None] | None = None
    bad: list[str] = []
    try:
        if kind in ("floor", "decoded"):
            tasks, closers = await _floor_fleet(ports, counters, decode=kind == "decoded")
        elif kind == "clients":
            tasks, closers = await _client_fleet(ports, counters)
        else:
            poller, consumer = await _start_poller(ports, bad, RING if kind == "ring" else 0)
        if poller is not None:

            def requests() -> int:
                return sum(s.requests for s in poller.stats.values())

            def overruns() -> int:
                return sum(s.overruns for s in poller.stats.values())
        else:

            def requests() -> int:
                return counters.requests

            def overruns() -> int:
                return counters.overruns

        await asyncio.sleep(warmup)  # first scans done, steady state reached
        for task in tasks:
            if task.done():
                task.result()  # a failed check: raise it here
        gc.collect()
        if os.environ.get("FLEET_GC_FREEZE"):
            gc.freeze()
        per_plc_before = (
            {name: s.requests for name, s in poller.stats.items()} if poller is not None else {}
        )
        counters.recording = True
        gc_before = _gc_seconds[0]
        collections_before = [g["collections"] for g in gc.get_stats()]
        profiler = None
        if profile:
            import cProfile

            profiler = cProfile.Profile(time.process_time)  # CPU, not wall: shared machines
            profiler.enable()
        passes = _count_passes(asyncio.get_running_loop())
        u0 = resource.getrusage(resource.RUSAGE_SELF)
        p0 = passes[0]
        r0, o0, c0, t0 = requests(), overruns(), time.process_time(), time.perf_counter()
        # bytecodes of exactly the window, not of the counting around it (bench/opcodes.py)
        counter = OpcodeCounter() if opcodes else None
        if counter is not None:
            counter.enable()
        await asyncio.sleep(duration)
        # A window in which no request completed measured nothing (no CPU per request, no
        # latency): a loaded machine stalled this process or the responders through all of it.
        # The window then runs on until the first request completes, for up to ten more
        # windows; its figures stay per request over the whole window. (The check is outside
        # the opcode count, as the counting around the window is.)
        if counter is not None:
            counter.disable()
        for _ in range(100):
            if requests() != r0:
                break
            if counter is not None:
                counter.enable()
            await asyncio.sleep(duration / 10)
            if counter is not None:
                counter.disable()
        r1, o1, c1, t1 = requests(), overruns(), time.process_time(), time.perf_counter()
        if counter is not None:
            counter.dump(cast(str, opcodes), r1 - r0)
        u1 = resource.getrusage(resource.RUSAGE_SELF)
        p1 = passes[0]
        if profiler is not None:
            profiler.disable()
            profiler.dump_stats(cast(str, profile))
        counters.recording = False
        gc_seconds = _gc_seconds[0] - gc_before
        collections = [
            g["collections"] - c for g, c in zip(gc.get_stats(), collections_before, strict=True)
        ]
        tracked = len(gc.get_objects())
        if poller is not None:
            latencies: list[float] = []
            for name, stats in poller.stats.items():
                k = stats.requests - per_plc_before[name]
                window = list(stats.latencies)
                latencies += window[len(window) - min(k, len(window)) :]
        else:
            latencies = counters.latencies
        if bad:
            raise RuntimeError(f"poller delivered bad samples: {bad[:3]}")
        for task in tasks:
            if task.done():
                task.result()
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for close in closers:
            await close()
        if poller is not None:
            await poller.aclose()
        if consumer is not None:
            consumer.cancel()
            await asyncio.gather(consumer, return_exceptions=True)
    done = r1 - r0
    latencies.sort()

    def pct(q: float) -> float | None:
        if not latencies:
            return None
        return 1000 * latencies[min(len(latencies) - 1, int(q / 100 * len(latencies)))]

    return {
        "kind": kind,
        "n": n,
        "seconds": t1 - t0,
        "requests": done,
        "rate": done / (t1 - t0),
        "target": n / INTERVAL,
        "cpu_s": c1 - c0,
        "cpu_us_per_request": 1e6 * (c1 - c0) / done if done else None,
        "cpu_share": (c1 - c0) / (t1 - t0),
        "gc_us_per_request": 1e6 * gc_seconds / done if done else None,
        "gc_collections": collections,
        "gc_tracked_objects": tracked,
        "user_us_per_request": 1e6 * (u1.ru_utime - u0.ru_utime) / done if done else None,
        "sys_us_per_request": 1e6 * (u1.ru_stime - u0.ru_stime) / done if done else None,
        "sleeps_per_request": (u1.ru_nvcsw - u0.ru_nvcsw) / done if done else None,
        "preempted_per_request": (u1.ru_nivcsw - u0.ru_nivcsw) / done if done else None,
        #: the process's peak resident memory so far (the responders are another process)
        "max_rss_mib": u1.ru_maxrss / 1024,
        "passes_per_request": (p1 - p0) / done if done and p1 >= 0 else None,
        "overruns": o1 - o0,
        "p50_ms": pct(50),
        "p99_ms": pct(99),
        "consumer_wait": CONSUMER_WAIT if kind in ("poll", "ring") else None,
        "ring": RING if kind == "ring" else None,
    }


async def _start_poller(
    ports: list[int], bad: list[str], ring: int = 0
) -> tuple[Any, asyncio.Task[None]]:
    from plcstack.poll.config import DEFAULT_GROUP, PlcConfig, PollConfig, TagConfig
    from plcstack.poll.engine import Poller
    from plcstack.poll.samples import each_sample
    from plcstack.wire.ring import FlightRecorder

    plcs = tuple(
        PlcConfig(
            name=f"plc{i}",
            url=f"e71+tcp://127.0.0.1:{port}",
            tags=(TagConfig(name="words", address="D0", count=WORDS),),
        )
        for i, port in enumerate(ports)
    )
    poller = Poller(
        PollConfig(plcs=plcs, groups={DEFAULT_GROUP: INTERVAL}, queue=max(1000, 4 * len(ports)))
    )
    expected = sample_words()
    if ring:
        recorder = FlightRecorder(size=ring)
        for plc in poller.plcs:
            poller.client(plc).transport.record_to(recorder.ring(plc))

    checked: set[str] = set()

    async def consume() -> None:
        # As the north side does: take what is there in one batch per wake-up, gathered for
        # CONSUMER_WAIT.
        # Every sample's quality is checked; its 64 values only for the first sample of each
        # PLC (the responders send one fixed reply), as the floor checks its first reply: a
        # per-sample list comparison would be the consumer's cost, not the poller's.
        async for batch in poller.scans(wait=CONSUMER_WAIT):
            for sample in each_sample(batch):
                if sample.value is None:
                    bad.append(f"{sample.plc}: {sample.error}")
                elif sample.plc not in checked:
                    checked.add(sample.plc)
                    if list(cast(Any, sample.value)) != expected:
                        bad.append(f"{sample.plc}: {sample.value!r:.120}")

    consumer = asyncio.create_task(consume())
    await poller.start()
    return poller, consumer


def _count_passes(loop: asyncio.AbstractEventLoop) -> list[int]:
    """A counter of the loop's passes (selector polls); ``[-1]`` where it cannot be counted
    (uvloop runs its passes in C)."""
    selector = getattr(loop, "_selector", None)
    if selector is None:
        return [-1]
    count = [0]
    select = selector.select

    def counted(timeout: float | None = None) -> Any:
        count[0] += 1
        return select(timeout)

    selector.select = counted
    return count


_gc_seconds = [0.0]
_gc_started = [0.0]


def _gc_callback(phase: str, info: dict[str, Any]) -> None:
    if phase == "start":
        _gc_started[0] = time.process_time()
    else:
        _gc_seconds[0] += time.process_time() - _gc_started[0]


def run_child(
    kind: str,
    n: int,
    *,
    loop: str,
    duration: float,
    warmup: float,
    profile: str | None = None,
    opcodes: str | None = None,
    kinds: tuple[str, ...] = ("floor", "poll"),
    rounds: int = 4,
) -> dict[str, Any]:
    """One kind's measurement, or with ``kind`` ``"alternate"`` every kind of ``kinds`` in
    alternating runs (:func:`_measure_alternating`)."""
    factory: Callable[[], asyncio.AbstractEventLoop] = asyncio.new_event_loop
    if loop == "uvloop":
        factory = importlib.import_module("uvloop").new_event_loop
    gc.callbacks.append(_gc_callback)
    with asyncio.Runner(loop_factory=factory) as runner:
        if kind == "alternate":
            summary = runner.run(_measure_alternating(kinds, n, rounds, duration, warmup))
        else:
            summary = runner.run(_measure(kind, n, duration, warmup, profile, opcodes))
    summary["loop"] = loop
    return summary


def _set_interval(seconds: float) -> None:
    """The schedule of every kind in this process (the module's ``INTERVAL``)."""
    global INTERVAL  # one child process measures one schedule
    INTERVAL = seconds


# -- parent side ----------------------------------------------------------------------------------
def spawn(
    kind: str,
    n: int,
    *,
    loop: str,
    duration: float,
    warmup: float,
    kinds: tuple[str, ...] = ("floor", "poll"),
    rounds: int = 1,
    timeout: float = 120.0,
) -> dict[str, Any]:
    """One measurement in a fresh child process; its JSON summary, or ``{"note": ...}``.
    With ``kind`` ``"alternate"``: ``rounds`` rounds of ``kinds`` (``timeout`` per run)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(PACKAGE_PARENT), env.get("PYTHONPATH", "")])
    cmd = [sys.executable, "-m", "plcstack.bench.cases.fleet", kind, str(n), "--loop", loop]
    cmd += ["--duration", str(duration), "--warmup", str(warmup)]
    if kind == "alternate":
        cmd += ["--kinds", ",".join(kinds), "--rounds", str(rounds)]
        timeout *= rounds * len(kinds)
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return {"note": f"child timed out after {timeout:g} s"}
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return {"note": f"child failed (exit {proc.returncode}): {tail}"}
    summary: dict[str, Any] = json.loads(lines[-1])
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m plcstack.bench.cases.fleet")
    parser.add_argument("kind", choices=(*KINDS, "alternate", "serve"))
    parser.add_argument("n", type=int)
    parser.add_argument("--loop", choices=("asyncio", "uvloop"), default="asyncio")
    parser.add_argument("--duration", type=float, default=3.0)
    parser.add_argument("--warmup", type=float, default=0.5)
    parser.add_argument("--cpu", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--profile", metavar="FILE", help="cProfile the measured window into FILE")
    parser.add_argument(
        "--opcodes",
        metavar="FILE",
        help="count the window's bytecodes per function into FILE (python -m "
        "plcstack.bench.opcodes FILE... compares them per request; use a small N)",
    )
    parser.add_argument(
        "--kinds",
        default="floor,poll",
        help="with kind 'alternate': the kinds to alternate, comma-separated, the measured one "
        "last and the bases before it (default floor,poll)",
    )
    parser.add_argument("--rounds", type=int, default=4, help="with kind 'alternate' (default 4)")
    parser.add_argument(
        "--interval",
        type=float,
        default=INTERVAL,
        help=f"seconds between one PLC's requests (default {INTERVAL:g}: 10 Hz)",
    )
    args = parser.parse_args(argv)
    kinds = tuple(args.kinds.split(","))
    if len(kinds) < 2 or len(set(kinds)) != len(kinds) or not set(kinds) <= set(KINDS):
        parser.error(f"--kinds takes two or more of {', '.join(KINDS)}, comma-separated")
    if args.rounds < 1:
        parser.error("--rounds must be at least 1")
    if not 0.001 <= args.interval <= 60:
        parser.error("--interval must be 0.001..60 seconds")
    _set_interval(args.interval)
    if args.kind == "serve":
        return _serve_main(args.n, args.cpu)
    summary = run_child(args.kind, args.n, loop=args.loop, duration=args.duration,
                        warmup=args.warmup, profile=args.profile, opcodes=args.opcodes,
                        kinds=kinds, rounds=args.rounds)  # fmt: skip
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
