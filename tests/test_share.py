"""SharedConnection: the native faces' queue on a PLC's one connection, against an E71
simulator over real sockets. Fair between face clients, fair with the poll, bounded, and a
request that waited past its limit (or whose client went away) is never sent."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.clients import connect
from plcstack.clients.e71 import E71Client
from plcstack.clients.share import QueueFull, SharedConnection, WaitedTooLong
from plcstack.codecs.e71 import Device
from plcstack.sim import e71 as e71_sim
from tests.aio_helpers import eventually
from tests.faces_helpers import polled


@asynccontextmanager
async def shared(
    delay: float = 0.0, **options: float
) -> AsyncIterator[tuple[e71_sim.E71TcpSimulator, E71Client, SharedConnection]]:
    sim = await e71_sim.start()
    assert isinstance(sim, e71_sim.E71TcpSimulator)
    sim.delay = delay
    client = connect(sim.url, timeout=5.0)
    assert isinstance(client, E71Client)
    share = SharedConnection(client, name="press", **options)  # type: ignore[arg-type]
    async with sim, client, share:
        yield sim, client, share


def _read(client: E71Client, log: list[str], name: str) -> Callable[[], Awaitable[list[int]]]:
    async def job() -> list[int]:
        log.append(name)
        return await client.read_words("D0", 1)

    return job


async def test_clients_take_turns_whatever_each_has_waiting() -> None:
    async with shared() as (_sim, client, share):
        order: list[str] = []
        async with client.turn():  # the connection is busy while the requests queue
            tasks = [
                asyncio.create_task(share.run(source, _read(client, order, name)))
                for source, name in (("a", "a1"), ("a", "a2"), ("b", "b1"), ("c", "c1"))
            ]
            await asyncio.sleep(0)
        await asyncio.wait_for(asyncio.gather(*tasks), 10)
        # a1 was on its way when the others queued; then every client in turn
        assert order == ["a1", "b1", "c1", "a2"]
        assert share.stats.executed == 4 and share.stats.queue_peak >= 3


async def test_a_full_queue_or_line_answers_busy_at_once_and_sends_nothing() -> None:
    async with shared(queue_size=4, per_source=2) as (sim, client, share):
        order: list[str] = []

        def submit(source: str, name: str) -> asyncio.Task[list[int]]:
            return asyncio.create_task(share.run(source, _read(client, order, name)))

        async with client.turn():
            waiting = [submit("a", "a1"), submit("a", "a2"), submit("b", "b")]
            # a1 left the queue to wait for its turn on the connection
            await eventually(lambda: share.waiting == 2, "a1 out of the queue")
            waiting.append(submit("a", "a3"))
            await asyncio.sleep(0)
            with pytest.raises(QueueFull, match="already has 2 requests"):
                await share.run("a", _read(client, order, "a4"))
            waiting.append(submit("c", "c"))
            await asyncio.sleep(0)
            assert share.waiting == 4
            with pytest.raises(QueueFull, match="already wait"):
                await share.run("d", _read(client, order, "d"))
        await asyncio.wait_for(asyncio.gather(*waiting), 10)
        assert order == ["a1", "b", "a2", "c", "a3"]  # each client in turn
        assert share.stats.busy == 2 and sim.requests == 5


async def test_a_request_that_waited_past_its_limit_is_not_sent() -> None:
    async with shared(max_wait=0.1) as (sim, client, share):
        sim.memory.write_words(Device.D, 10, [1])

        def write(value: int) -> Callable[[], Awaitable[None]]:
            async def job() -> None:
                await client.write_words("D10", [value])

            return job

        async with client.turn():  # a long request of someone else's
            # the first waits for the connection itself, the second behind it in the queue
            first = asyncio.create_task(share.run("a", write(2)))
            second = asyncio.create_task(share.run("b", write(3)))
            await asyncio.sleep(0.3)
            requests = sim.requests
        for task in (first, second):
            with pytest.raises(WaitedTooLong, match="not sent"):
                await asyncio.wait_for(task, 10)
        assert sim.requests == requests and sim.memory.read_words(Device.D, 10, 1) == [1]
        assert share.stats.expired == 2 and share.stats.executed == 0
        # the connection is fine afterwards
        await share.run("a", write(4))
        assert sim.memory.read_words(Device.D, 10, 1) == [4]


async def test_a_request_whose_client_went_away_is_skipped_a_started_one_completes() -> None:
    async with shared(delay=0.2) as (sim, client, share):
        started = asyncio.Event()

        async def slow_write() -> None:
            started.set()
            await client.write_words("D20", [7])

        running = asyncio.create_task(share.run("a", slow_write))
        await started.wait()
        queued = asyncio.create_task(share.run("b", _write_job(client, "D21", 8)))
        await asyncio.sleep(0)
        running.cancel()  # its client went away after the write was sent
        queued.cancel()  # and this one's before its turn
        await asyncio.gather(running, queued, return_exceptions=True)
        await eventually(lambda: sim.memory.read_words(Device.D, 20, 1) == [7], "D20 written")
        await eventually(lambda: share.waiting == 0 and share.stats.skipped == 1, "skipped")
        assert sim.memory.read_words(Device.D, 21, 1) == [0]
        assert client.transport.is_open  # the poller's connection was not cut


def _write_job(client: E71Client, address: str, value: int) -> Callable[[], Awaitable[None]]:
    async def job() -> None:
        await client.write_words(address, [value])

    return job


async def test_faces_and_the_poll_take_turns_on_the_connection() -> None:
    """A flood of face requests does not starve the scans, nor the scans the faces."""
    sim = await e71_sim.start()
    assert isinstance(sim, e71_sim.E71TcpSimulator)
    sim.delay = 0.01  # every answer takes 10 ms: the connection is the bottleneck
    async with sim, polled(sim.url, 'd = "D0"', interval=0.005) as poller:
        client = poller.client("kiln1")
        assert isinstance(client, E71Client)
        async with SharedConnection(client, name="kiln1") as share:
            done = 0

            async def face_client(k: int) -> None:
                nonlocal done
                while True:
                    await share.run(k, _write_job(client, f"D{100 + k}", k))
                    done += 1

            await eventually(lambda: poller.stats["kiln1"].requests > 0, "first scan")
            scans_before = poller.stats["kiln1"].requests
            flood = [asyncio.create_task(face_client(k)) for k in range(8)]
            try:
                await eventually(lambda: done >= 40, "40 face requests", timeout=30)
            finally:
                for task in flood:
                    task.cancel()
                await asyncio.gather(*flood, return_exceptions=True)
            scans = poller.stats["kiln1"].requests - scans_before
            # alternating: about one scan per face request, never one side alone
            assert scans >= 0.5 * done and done >= 40, (scans, done)
            assert share.stats.busy == share.stats.expired == 0
            assert poller.stats["kiln1"].bad_samples == 0


@settings(max_examples=25, deadline=None)
@given(
    st.lists(st.integers(0, 4), min_size=1, max_size=16),
    st.integers(1, 8),
    st.integers(1, 3),
)
def test_the_queue_serves_sources_in_turn_and_refuses_beyond_its_bounds(
    sources: list[int], queue_size: int, per_source: int
) -> None:
    """Requests of random sources, all submitted while the connection is busy: those beyond
    the queue or a source's line are refused busy; the rest run each source in turn (in the
    order the sources first came), each source's own in the order they came."""
    # the model: a line per source, refusals at the bounds, round robin
    lines: dict[int, list[int]] = {}
    waiting = 0
    busy = set()
    for index, source in enumerate(sources):
        line = lines.setdefault(source, [])
        if waiting >= queue_size or len(line) >= min(per_source, queue_size):
            busy.add(index)
            if not line:
                del lines[source]
            continue
        line.append(index)
        waiting += 1
    expected: list[int] = []
    while lines:
        for source in list(lines):
            expected.append(lines[source].pop(0))
            if not lines[source]:
                del lines[source]

    async def run() -> tuple[list[int], set[int]]:
        async with shared(queue_size=queue_size, per_source=per_source) as (_, client, share):
            order: list[int] = []

            def job(index: int) -> Callable[[], Awaitable[None]]:
                async def read() -> None:
                    order.append(index)
                    await client.read_words("D0", 1)

                return read

            async with client.turn():  # busy while everything is submitted
                tasks = [
                    asyncio.create_task(share.run(source, job(i)))
                    for i, source in enumerate(sources)
                ]
                await asyncio.sleep(0)
            results = await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), 10)
            refused = {i for i, r in enumerate(results) if isinstance(r, QueueFull)}
            assert all(r is None or isinstance(r, QueueFull) for r in results), results
            return order, refused

    order, refused = asyncio.run(run())
    assert refused == busy
    assert order == expected
