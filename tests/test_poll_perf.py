"""What the poller's fast paths changed: decoders, clocks, yielding, latency window, batching.

Every fast path is checked against the slow, obvious one it replaced, and every scheduling
shortcut against the promise it must keep (no starved loop, no lost sample, no leaked slot).
"""

from __future__ import annotations

import asyncio
import collections
import dataclasses
import math
import struct
import sys
import time
from collections.abc import Callable

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack import values as vt
from plcstack.clients.base import Client
from plcstack.poll.config import MIN_INTERVAL, PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import (
    LATENCY_WINDOW,
    LatencyWindow,
    PlcStats,
    Poller,
    Quality,
    Sample,
    timer_resolution,
)
from plcstack.poll.plan import build_plan, decoder
from plcstack.poll.samples import make_sample as _sample
from plcstack.values import WordOrder
from tests.poll_fakes import FakeClient

URL = "e71+tcp://127.0.0.1:1"  # never dialled: the fakes stand in for the client
BIG, LITTLE = WordOrder.BIG, WordOrder.LITTLE

#: the types whose decoders take the struct fast paths (and RAW/BOOL)
PLAIN_TYPES = [
    vt.value_type(n)
    for n in ("raw", "bool", "int8", "uint8", "int16", "uint16", "int32", "uint32", "float32")
]


def tag(name: str, address: str, type: str = "raw", count: int = 1) -> TagConfig:
    return TagConfig(name, address, vt.value_type(type), count)


def make(
    plcs: dict[str, list[TagConfig]],
    *,
    interval: float = 0.01,
    queue: int = 10_000,
    concurrency: int | None = None,
    fake: Callable[[str], FakeClient] = FakeClient,
) -> tuple[Poller, dict[str, FakeClient]]:
    fakes: dict[str, FakeClient] = {}

    def factory(plc: PlcConfig) -> Client:
        fakes[plc.name] = fake(f"fake://{plc.name}")
        return fakes[plc.name]

    config = PollConfig(
        tuple(PlcConfig(name, URL, tuple(tags)) for name, tags in plcs.items()),
        {"default": interval},
        concurrency=concurrency,
        queue=queue,
    )
    return Poller(config, client_factory=factory), fakes


class Ticker:
    """Counts passes of the event loop (a task that yields once per pass)."""

    def __init__(self) -> None:
        self.ticks = 0
        self._task: asyncio.Task[None] | None = None

    async def _run(self) -> None:
        while True:
            self.ticks += 1
            await asyncio.sleep(0)

    def __enter__(self) -> Ticker:
        self._task = asyncio.get_running_loop().create_task(self._run())
        return self

    def __exit__(self, *exc: object) -> None:
        assert self._task is not None
        self._task.cancel()


class Starved(BaseException):
    """Raised by a fake when the poller ran far too many reads without letting the loop run.

    A BaseException, so the poller's ``except Exception`` does not turn it into a bad sample:
    the task ends, the loop is free again and the test fails instead of hanging.
    """


#: reads in one loop pass after which a RunawayFake calls the loop starved
STARVED_AFTER = 160

#: wall time one RunawayFake read takes: longer than the shortest scan interval the poller allows
READ_COST = 1.2 * MIN_INTERVAL


class RunawayFake(FakeClient):
    """Answers without ever suspending; records how many reads ran within one loop pass."""

    ticker: Ticker

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.per_tick: collections.Counter[int] = collections.Counter()

    async def read(self, address: str, count: int = 1) -> list[int] | list[bool]:
        # Each read costs a little more than the shortest scan interval, so the next scan is
        # always due at once: the poller never needs a timer and only its own yields let the
        # loop turn (an interval below one read cost is what these tests are about).
        time.sleep(READ_COST)  # noqa: ASYNC251 - blocking the loop is the point here
        tick = self.ticker.ticks
        self.per_tick[tick] += 1
        if self.per_tick[tick] > STARVED_AFTER:
            raise Starved(f"{self.per_tick[tick]} reads in one loop pass")
        await self._ensure_open(f"read {address}")  # fails at once when down (backoff)
        return [7] * count


async def take(poller: Poller, n: int) -> list[Sample]:
    out: list[Sample] = []
    async with asyncio.timeout(10):
        async for sample in poller:
            out.append(sample)
            if len(out) >= n:
                break
    return out


# -- decoders -------------------------------------------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(
    dtype=st.sampled_from(list(PLAIN_TYPES)),
    bits=st.sampled_from([8, 16]),
    order=st.sampled_from([BIG, LITTLE]),
    data=st.data(),
)
def test_decoder_agrees_with_value_by_value_even_for_points_out_of_range(
    dtype: vt.ValueType, bits: int, order: WordOrder, data: st.DataObject
) -> None:
    # A client may hand out signed or oversized words: the struct path must fall back and mask
    # them exactly as vt.ValueType.decode does, never raise.
    count = data.draw(st.integers(1, 12))
    n = dtype.points_per_value(bits)
    limit = 1 << bits
    points: list[int | bool] = list(
        data.draw(
            st.lists(
                st.integers(-2 * limit, 2 * limit) | st.integers(0, limit - 1),
                min_size=n * count,
                max_size=n * count,
            )
        )
    )
    expected = [dtype.decode(points[i * n : (i + 1) * n], bits, order) for i in range(count)]
    got = decoder(dtype, count, bits)(points, order)
    assert repr(got) == repr(expected[0] if count == 1 else expected)


@pytest.mark.parametrize(
    ("dtype", "points", "order", "expected"),
    [
        # golden values, both word orders (MELSEC low word first, S5 high word first)
        (vt.INT16, [0xFFFE, 0x8000, 0x7FFF], BIG, [-2, -32768, 32767]),
        (vt.UINT16, [0xFFFE, 0], LITTLE, [65534, 0]),
        (vt.INT32, [0xFFFF, 0xFFFE], BIG, [-2]),
        (vt.INT32, [0xFFFE, 0xFFFF], LITTLE, [-2]),
        (vt.UINT32, [0x0001, 0x0002], BIG, [0x00010002]),
        (vt.UINT32, [0x0001, 0x0002], LITTLE, [0x00020001]),
        (vt.FLOAT32, [0x3FC0, 0x0000, 0xC020, 0x0000], BIG, [1.5, -2.5]),
        (vt.FLOAT32, [0x0000, 0x3FC0], LITTLE, [1.5]),
        # out of range: masked like the value-by-value path (-1 & 0xFFFF = 0xFFFF)
        (vt.INT16, [-1, 65536 + 5], BIG, [-1, 5]),
        (vt.UINT16, [-1], BIG, [65535]),
    ],
)
def test_decoder_golden(
    dtype: vt.ValueType, points: list[int], order: WordOrder, expected: list[object]
) -> None:
    count = len(expected)
    value = decoder(dtype, count, 16)(list(points), order)
    assert value == (expected[0] if count == 1 else expected)


def test_equal_tags_share_one_decoder() -> None:
    a = decoder(vt.FLOAT32, 4, 16)
    assert decoder(vt.FLOAT32, 4, 16) is a
    assert decoder(vt.FLOAT32, 5, 16) is not a


def test_tag_split_over_frames_with_bits_in_a_later_piece_is_refused() -> None:
    # 150 words: three requests. A client returning bools for one of them (it lied about the
    # area) makes the tag bad, whichever piece carries them.
    plan = build_plan(FakeClient(), [tag("big", "D0", "int16", 150)])
    assert [r.count for r in plan.requests] == [64, 64, 22]
    replies: list[list[int] | list[bool]] = [[1] * 64, [True] * 64, [2] * 22]
    (result,) = plan.split(replies, BIG)
    assert result.value is None and "bit area" in str(result.error)
    (good,) = plan.split([[1] * 64, [0xFFFF] * 64, [2] * 22], BIG)
    assert good.value == [1] * 64 + [-1] * 64 + [2] * 22


# -- samples -------------------------------------------------------------------------------------
def test_fast_sample_constructor_builds_the_same_frozen_sample() -> None:
    args = ("p", "t", [1, 2], Quality.GOOD, 1.5, 2.5, None)
    fast, slow = _sample(*args), Sample(*args)
    assert fast == slow and repr(fast) == repr(slow) and type(fast) is Sample
    bad = _sample("p", "t", None, Quality.BAD, 1.0, 1.0, "why")
    assert bad == Sample("p", "t", None, Quality.BAD, 1.0, 1.0, "why")
    with pytest.raises(dataclasses.FrozenInstanceError):
        fast.value = 3  # type: ignore[misc]


# -- latency window -------------------------------------------------------------------------------
def test_latency_window_keeps_the_most_recent_values_oldest_first() -> None:
    window = LatencyWindow(maxlen=3)
    assert not window and len(window) == 0
    for value in (1.0, 2.0, 3.0, 4.0, 5.0):
        window.append(value)
    assert list(window) == [3.0, 4.0, 5.0] and len(window) == 3
    window.append(6.0)
    assert list(window) == [4.0, 5.0, 6.0]
    assert list(LatencyWindow([0.5, 0.25])) == [0.5, 0.25]
    with pytest.raises(ValueError):
        LatencyWindow(maxlen=0)


def test_a_full_latency_window_takes_four_bytes_per_request() -> None:
    window = LatencyWindow()
    for i in range(3 * LATENCY_WINDOW):
        window.append(i * 1e-6)
    assert len(window) == LATENCY_WINDOW
    assert sys.getsizeof(window._data) <= 4 * LATENCY_WINDOW + 1024


def _f32(x: float) -> float:
    value: float = struct.unpack("f", struct.pack("f", x))[0]
    return value


@settings(max_examples=200, deadline=None)
@given(
    values=st.lists(st.floats(0.0, 10.0), max_size=60),
    maxlen=st.integers(1, 20),
    q=st.sampled_from([0, 1, 50, 90, 99, 100]),
)
def test_percentiles_match_a_deque_of_the_same_window(
    values: list[float], maxlen: int, q: int
) -> None:
    reference: collections.deque[float] = collections.deque(maxlen=maxlen)
    stats = PlcStats(latencies=LatencyWindow(maxlen=maxlen))
    for v in values:
        reference.append(_f32(v))  # stored as float32: a tenth of a microsecond at 1 s
        stats.latencies.append(v)
    assert sorted(stats.latencies) == sorted(reference)
    if not reference:
        assert stats.percentile(q) is None
        return
    data = sorted(reference)
    rank = max(0, min(len(data) - 1, int(q / 100.0 * len(data) + 0.5) - 1))
    assert stats.percentile(q) == data[rank]


# -- clocks ---------------------------------------------------------------------------------------
async def test_latency_is_timed_finer_than_a_millisecond_loop_clock() -> None:
    # Under uvloop loop.time() moves in whole milliseconds; a fake answering within one loop
    # pass then took "0 ms" by the loop's clock. The poller's latencies come from perf_counter.
    loop = asyncio.get_running_loop()
    real = loop.time
    loop.time = lambda: math.floor(real() * 1000) / 1000  # type: ignore[method-assign]
    try:
        before = time.time()
        poller, _ = make({"p": [tag("a", "D0")]}, interval=0.001)
        async with poller:
            samples = await take(poller, 20)
        after = time.time()
    finally:
        loop.time = real  # type: ignore[method-assign]
    latencies = list(poller.stats["p"].latencies)
    assert len(latencies) >= 20
    assert all(x > 0 for x in latencies)
    assert any(x * 1000 != round(x * 1000) for x in latencies)
    for s in samples:
        assert before <= s.source_time <= s.receive_time <= after


def test_timer_resolution_of_asyncio_and_other_loops() -> None:
    loop = asyncio.new_event_loop()
    try:
        assert 0 < timer_resolution(loop) <= 1e-6
    finally:
        loop.close()

    class OtherLoop(asyncio.AbstractEventLoop):  # e.g. uvloop: not a BaseEventLoop
        pass

    assert timer_resolution(OtherLoop()) == 1e-3  # type: ignore[abstract]


# -- yielding -------------------------------------------------------------------------------------
async def test_a_client_that_never_suspends_cannot_starve_the_loop() -> None:
    ticker = Ticker()

    def fake(name: str) -> FakeClient:
        client = RunawayFake(name)
        client.ticker = ticker
        return client

    with ticker:
        # interval below a read's cost: every scan is due at once and no timer is ever needed
        poller, fakes = make({"p": [tag("a", "D0")]}, interval=MIN_INTERVAL, fake=fake)
        async with poller:
            for _ in range(50):
                await asyncio.sleep(0)
            other_task_ran = ticker.ticks
            samples = await take(poller, 200)
    runaway = fakes["p"]
    assert isinstance(runaway, RunawayFake)
    assert other_task_ran >= 50
    assert all(s.quality is Quality.GOOD for s in samples)
    # every scan is a ticker callback or a task of its own: the loop turns between scans
    assert max(runaway.per_tick.values()) <= 2


async def test_a_dead_plc_polled_without_pause_yields_after_every_failed_scan() -> None:
    # Down and backing off: each read fails at once without suspending. One bad scan per loop
    # pass at most, so a dead PLC cannot flood the buffer faster than the loop turns.
    ticker = Ticker()

    def fake(name: str) -> FakeClient:
        client = RunawayFake(name)
        client.ticker = ticker
        client.up = False
        client.backoff.initial = client.backoff.maximum = 60.0
        return client

    with ticker:
        poller, fakes = make({"dead": [tag("a", "D0")]}, interval=MIN_INTERVAL, fake=fake)
        async with poller:
            bad = await take(poller, 30)
    runaway = fakes["dead"]
    assert isinstance(runaway, RunawayFake)
    assert all(s.quality is Quality.BAD for s in bad)
    assert max(runaway.per_tick.values()) <= 2


# -- scans ----------------------------------------------------------------------------------------
async def test_a_timeout_ends_a_multi_request_scan_and_its_tags_share_the_error() -> None:
    poller, fakes = make({"p": [tag("a", "D0"), tag("b", "D500"), tag("c", "M0", "bool")]})
    assert len(poller.plan("p", "default").requests) == 3
    fake = fakes["p"]
    fake.gate = asyncio.Event()  # never set: the first request runs into its deadline
    fake.timeout = 0.05
    attempts: list[str] = []
    real_read = fake.read

    async def counting(address: str, count: int = 1) -> list[int] | list[bool]:
        attempts.append(address)
        return await real_read(address, count)

    fake.read = counting  # type: ignore[method-assign]
    async with poller:
        samples = await take(poller, 3)
    assert attempts[:1] == ["D0"] and len(attempts) == 1  # the other two were not tried
    assert all(s.quality is Quality.BAD for s in samples)
    assert len({s.error for s in samples}) == 1 and "no answer within" in (samples[0].error or "")
    assert len({(s.source_time, s.receive_time) for s in samples[1:]}) == 1
    stats = poller.stats["p"]
    assert stats.requests == 1 and stats.errors == 1 and stats.scans == 1


async def test_a_global_cap_slot_comes_back_after_failed_requests() -> None:
    poller, fakes = make({"dead": [tag("a", "D0")], "ok": [tag("a", "D0")]}, concurrency=1)
    fakes["dead"].up = False
    async with poller:
        samples = await take(poller, 40)
        assert poller.stats["dead"].errors >= 1
    assert len([s for s in samples if s.plc == "ok" and s.quality is Quality.GOOD]) >= 5


async def test_a_scan_with_more_tags_than_the_buffer_is_kept_whole_and_older_ones_dropped() -> None:
    tags = [tag(f"t{i}", f"D{100 * i}") for i in range(6)]  # six requests per scan
    poller, _ = make({"p": tags}, queue=2)
    async with poller:
        async with asyncio.timeout(10):
            # counters, not events: poll them (bounded by the timeout)
            while poller.stats["p"].samples < 18:  # noqa: ASYNC110
                await asyncio.sleep(0.001)
        await poller.aclose()
        kept = poller.drain()
    stats = poller.stats["p"]
    # a scan is never cut: the newest is kept whole, every older one dropped whole, counted
    assert [[s.tag for s in scan.samples] for scan in kept] == [[f"t{i}" for i in range(6)]]
    assert stats.samples - stats.drops == 6 and stats.drops % 6 == 0 and stats.drops >= 12
    assert poller.pending() == 0
    assert poller.dropped == stats.drops and poller.queue.dropped_scans == stats.drops // 6


async def test_receive_time_is_source_time_plus_the_measured_latency() -> None:
    poller, fakes = make({"p": [tag("a", "D0")]})
    fakes["p"].delay = 0.003
    async with poller:
        samples = await take(poller, 5)
    latencies = sorted(poller.stats["p"].latencies)
    for s in samples:
        elapsed = s.receive_time - s.source_time
        # the same perf_counter interval, once as float32 in the window: equal to ~1e-6 s
        assert any(abs(elapsed - x) < 1e-6 for x in latencies)


# -- the overhead benchmark -----------------------------------------------------------------------
def test_pollcost_benchmark_measures_both_sides(capsys: pytest.CaptureFixture[str]) -> None:
    from plcstack.bench import pollcost

    assert pollcost.main(["--plcs", "3", "--seconds", "0.05", "--repeats", "2"]) == 0
    out = capsys.readouterr().out
    assert "bare closed loops" in out and "poller's own cost" in out
    result = asyncio.run(
        pollcost.measure(3, words=4, dtype=vt.FLOAT32, seconds=0.05, repeats=1, tags=3)
    )
    assert len(result["bare"]) == len(result["poll"]) == 1
    for cpu, gc_seconds in result["bare"] + result["poll"]:
        assert cpu > 0 and gc_seconds >= 0
