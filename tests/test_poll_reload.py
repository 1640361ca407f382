"""The Poller changed while it runs, over real simulators: PLCs added, removed, reconnected and
planned again on their open connections; every other PLC keeps its connection and schedule.

Before, a changed file changed nothing until the process was restarted, and a restart cost every
PLC its connection (an S5-LAN module takes one at a time) and every face its state.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

import pytest

from plcstack import values as vt
from plcstack.errors import AddressError, LocalProtocolError
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.diff import plc_changes
from plcstack.poll.engine import Applied, Poller, Quality
from plcstack.poll.samples import Scan
from plcstack.sim import e71, s5lan
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.sim.s5memory import S5Memory
from tests.aio_helpers import eventually

INTERVAL = 0.02


def _plc(name: str, url: str, *tags: TagConfig) -> PlcConfig:
    return PlcConfig(name, url, tags or (TagConfig("x", "D100", vt.UINT16),), timeout=2.0)


class Watch:
    """The scans a poller delivers, taken as they come: per PLC the times and the tags seen."""

    def __init__(self, poller: Poller) -> None:
        self.poller = poller
        self.scans: list[tuple[float, Scan]] = []
        self.task = asyncio.create_task(self._take())

    async def _take(self) -> None:
        async for batch in self.poller.scans():
            now = time.perf_counter()
            self.scans.extend((now, s) for s in batch)

    def of(self, plc: str, since: float = 0.0) -> list[Scan]:
        return [s for t, s in self.scans if s.plc == plc and t >= since]

    def tags(self, plc: str, since: float = 0.0) -> set[str]:
        return {x.tag for s in self.of(plc, since) for x in s.samples}

    def bad(self, plc: str) -> list[str]:
        return [f"{x.tag}: {x.error}" for s in self.of(plc) for x in s.samples
                if x.quality is not Quality.GOOD]  # fmt: skip

    def largest_gap(self, plc: str) -> float:
        times = sorted(s.source_time for s in self.of(plc))
        return max((b - a for a, b in itertools.pairwise(times)), default=0.0)

    async def until(self, what: Callable[[], bool], timeout: float = 5.0) -> None:
        await eventually(what, "the scans awaited", timeout)

    async def close(self) -> None:
        await self.poller.aclose()
        await asyncio.wait_for(self.task, 5)


@asynccontextmanager
async def polling(config: PollConfig) -> AsyncIterator[Watch]:
    poller = Poller(config)
    await poller.start()
    watch = Watch(poller)
    try:
        yield watch
    finally:
        await watch.close()


@asynccontextmanager
async def sims(n: int) -> AsyncIterator[list[e71.E71TcpSimulator]]:
    memory = MelsecMemory()
    memory.write_words("D", 100, [1, 2, 3, 4])
    started = []
    for _ in range(n):
        sim = await e71.start(memory)
        assert isinstance(sim, e71.E71TcpSimulator)
        started.append(sim)
    try:
        yield started
    finally:
        for sim in started:
            await sim.aclose()


async def _apply(watch: Watch, new: PollConfig) -> Applied:
    return await watch.poller.apply(plc_changes(watch.poller.config, new))


async def test_tags_changed_are_planned_again_on_the_open_connection() -> None:
    async with sims(2) as (sim_a, sim_b):
        old = PollConfig((_plc("a", sim_a.url), _plc("b", sim_b.url)), {"default": INTERVAL})
        async with polling(old) as watch:
            await watch.until(lambda: len(watch.of("a")) > 5 and len(watch.of("b")) > 5)
            more = _plc("a", sim_a.url, TagConfig("x", "D100", vt.UINT16),
                        TagConfig("y", "D101", vt.UINT16))  # fmt: skip
            new = dataclasses.replace(old, plcs=(more, old.plcs[1]))
            applied = await _apply(watch, new)
            after = time.perf_counter()
            await watch.until(
                lambda: "y" in watch.tags("a", after) and len(watch.of("b", after)) > 5
            )
            assert watch.poller.config is new
            assert watch.poller.plan("a", "default").requests[0].count == 2  # D100..D101
            stats = watch.poller.stats
        assert applied.replanned == ("a",) and not applied.added and not applied.removed
        # neither PLC reconnected: one connection each, all along
        assert sim_a.connection_count.total == 1 and sim_b.connection_count.total == 1
        assert stats["a"].reconnects == 0 and stats["b"].reconnects == 0
        assert not watch.bad("a") and not watch.bad("b")
        assert watch.largest_gap("b") <= 2 * INTERVAL + 0.1  # b's schedule went on


async def test_a_replan_never_cuts_a_request_on_a_one_connection_module() -> None:
    """An S5-LAN module takes one connection: planning its PLC again many times while its
    requests are in flight (awaited scans) keeps that one connection and loses no scan to a
    cut request."""
    memory = S5Memory(default_dbs={10: 16})
    sim = await s5lan.start(memory, max_connections=1)
    try:
        tags = [TagConfig(f"w{i}", f"DB10.DW{i}", vt.UINT16) for i in range(8)]
        config = PollConfig((PlcConfig("kiln", sim.url, (tags[0],)),), {"default": 0.005})
        async with polling(config) as watch:
            await watch.until(lambda: len(watch.of("kiln")) > 3)
            for i in range(1, 8):
                new = dataclasses.replace(
                    watch.poller.config, plcs=(PlcConfig("kiln", sim.url, tuple(tags[: i + 1])),)
                )
                await _apply(watch, new)
                await asyncio.sleep(0.003 * i)  # now and then with a request in flight
            after = time.perf_counter()
            await watch.until(lambda: "w7" in watch.tags("kiln", after))
            reconnects = watch.poller.stats["kiln"].reconnects
        assert sim.connection_count.total == 1 and reconnects == 0
        assert not watch.bad("kiln")
    finally:
        await sim.aclose()


async def test_an_added_plc_starts_and_a_removed_one_stops_the_others_untouched() -> None:
    async with sims(3) as (sim_a, sim_b, sim_c):
        old = PollConfig((_plc("a", sim_a.url), _plc("b", sim_b.url)), {"default": INTERVAL})
        async with polling(old) as watch:
            await watch.until(lambda: len(watch.of("a")) > 5 and len(watch.of("b")) > 5)
            new = dataclasses.replace(old, plcs=(old.plcs[0], _plc("c", sim_c.url)))
            applied = await _apply(watch, new)
            done, done_wall = time.perf_counter(), time.time()
            assert watch.poller.client("a")  # a is still there; b's connection closed:
            await watch.until(lambda: sim_b.connection_count.current == 0, 2.0)
            await watch.until(lambda: len(watch.of("c", done)) > 5 and len(watch.of("a", done)) > 5)
            late = [s for s in watch.of("b", done) if s.source_time > done_wall]
            assert watch.poller.plcs == ["a", "c"]
            with pytest.raises(AddressError, match="no PLC named 'b'"):
                watch.poller.client("b")
        assert applied.added == ("c",) and list(applied.removed) == ["b"]
        last = applied.removed["b"]
        assert last.scans > 5 and last.samples > 5  # its last statistics
        assert not late
        assert sim_a.connection_count.total == 1  # a kept its connection
        assert watch.largest_gap("a") <= 2 * INTERVAL + 0.1


async def test_a_changed_url_reconnects_and_its_counters_go_on() -> None:
    async with sims(2) as (sim_a, sim_b):
        old = PollConfig((_plc("a", sim_a.url),), {"default": INTERVAL})
        async with polling(old) as watch:
            await watch.until(lambda: len(watch.of("a")) > 3)
            before = watch.poller.stats["a"].scans
            applied = await _apply(watch, PollConfig((_plc("a", sim_b.url),), old.groups))
            await watch.until(lambda: sim_a.connection_count.current == 0, 2.0)
            await watch.until(lambda: sim_b.connection_count.total == 1 and len(watch.of("a")) > 10)
            stats = watch.poller.stats["a"]
            assert stats.reconnects == 1 and stats.scans > before  # never back to 0
        assert applied.reconnected == ("a",)


async def test_a_change_that_cannot_be_planned_changes_nothing() -> None:
    async with sims(2) as (sim_a, sim_b):
        old = PollConfig((_plc("a", sim_a.url),), {"default": INTERVAL})
        async with polling(old) as watch:
            await watch.until(lambda: len(watch.of("a")) > 3)
            bad = PollConfig(
                (
                    _plc("a", sim_a.url, TagConfig("x", "D100", vt.UINT16), TagConfig("z", "X1G")),
                    _plc("b", sim_b.url),
                ),
                old.groups,
            )
            with pytest.raises(AddressError, match="X1G"):
                await _apply(watch, bad)
            assert watch.poller.config is old and watch.poller.plcs == ["a"]
            assert sim_b.connection_count.total == 0
            count = len(watch.of("a"))
            await watch.until(lambda: len(watch.of("a")) > count + 3)  # still polling
            with pytest.raises(LocalProtocolError, match="another configuration"):
                await watch.poller.apply(plc_changes(bad, old))
        assert sim_a.connection_count.total == 1


async def test_poller_settings_are_said_not_applied_and_apply_before_start_works() -> None:
    async with sims(1) as (sim_a,):
        old = PollConfig((_plc("a", sim_a.url),), {"default": INTERVAL})
        poller = Poller(old)
        try:
            new = PollConfig((_plc("a", sim_a.url), _plc("a2", sim_a.url)), old.groups, queue=99)
            applied = await poller.reconfigure(new)
            assert applied.added == ("a2",) and applied.not_applied == ("queue",)
            await poller.start()
            watch = Watch(poller)
            await watch.until(lambda: len(watch.of("a2")) > 3 and len(watch.of("a")) > 3)
        finally:
            await poller.aclose()
        await asyncio.wait_for(watch.task, 5)
        with pytest.raises(LocalProtocolError, match="closed"):
            await poller.reconfigure(old)


async def test_a_reconnect_to_a_one_connection_module_closes_the_old_connection_first() -> None:
    """A changed deadline is a new connection; an S5-LAN module takes one at a time, so the old
    one must be gone before the new one is opened, or every scan after the reload fails."""
    memory = S5Memory(default_dbs={10: 4})
    sim = await s5lan.start(memory, max_connections=1)
    try:
        tags = (TagConfig("w", "DB10.DW0", vt.UINT16),)
        old = PollConfig((PlcConfig("kiln", sim.url, tags, timeout=2.0),), {"default": INTERVAL})
        async with polling(old) as watch:
            await watch.until(lambda: len(watch.of("kiln")) > 3)
            new = PollConfig((PlcConfig("kiln", sim.url, tags, timeout=3.0),), old.groups)
            applied = await _apply(watch, new)
            after = time.perf_counter()
            await watch.until(lambda: len(watch.of("kiln", after)) > 5)
            reconnects = watch.poller.stats["kiln"].reconnects
        assert applied.reconnected == ("kiln",) and reconnects == 1
        assert sim.connection_count.total == 2 and sim.connection_count.peak == 1
        assert not watch.bad("kiln")
    finally:
        await sim.aclose()
