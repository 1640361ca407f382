"""Workers in one process over a simulator fleet, with real mosquitto and nats-server.

The multi-process failover tests (``kill -9``) are in ``test_scale_failover.py``; these check
the same rules quickly: one poller per PLC, release before handover, fencing before the ttl.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
from collections.abc import AsyncIterator, Callable

import pytest

from plcstack.north.writes import WritePath
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.scale.hrw import owner
from plcstack.scale.worker import Worker, WorkerOptions
from tests.scale_helpers import CutProxy, Fleet
from tests.servers import Mosquitto, NatsServer

TTL = 2.0  # guard 0.5 s: larger than the stalls of a loaded 2-core machine
INTERVAL = 0.1


def fleet_config(fleet: Fleet) -> PollConfig:
    tags = (TagConfig("x", "D0"),)
    plcs = tuple(PlcConfig(name, w.sim.url, tags, timeout=0.5) for name, w in fleet.watch.items())
    return PollConfig(plcs=plcs, groups={"default": INTERVAL})


async def until(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not predicate():
        assert loop.time() < deadline, "condition not reached in time"
        await asyncio.sleep(0.02)


@contextlib.asynccontextmanager
async def worker(
    config: PollConfig, name: str, mqtt: str, nats: str | None, events: list[str] | None = None
) -> AsyncIterator[Worker]:
    options = WorkerOptions(
        worker=name, mqtt=mqtt, nats=nats, lease_ttl=TTL, retry=0.05, keepalive=2
    )
    w = Worker(config, options, on_event=(events.append if events is not None else None))
    drain = None
    try:
        await w.start()
        drain = asyncio.get_running_loop().create_task(_consume(w))
        yield w
    finally:
        await w.aclose()
        if drain is not None:
            drain.cancel()


async def _consume(w: Worker) -> None:
    async for _ in w:
        pass


async def test_two_workers_split_the_fleet_and_hand_over(
    mosquitto: Mosquitto, nats_server: NatsServer
) -> None:
    async with Fleet(8, interval=INTERVAL) as fleet:
        config = fleet_config(fleet)
        async with worker(config, "a", mosquitto.url, nats_server.url) as a:
            await until(lambda: len(a.owned) == 8)  # alone: everything
            async with worker(config, "b", mosquitto.url, nats_server.url) as b:
                expect_b = {p for p in fleet.watch if owner(p, ["a", "b"]) == "b"}
                assert expect_b and len(expect_b) < 8
                # a stops and releases first; b starts only then
                await until(lambda: b.owned == expect_b and a.owned.isdisjoint(expect_b))
                assert a.owned | b.owned == set(fleet.watch)
                assert b.leases is not None
                holders = await b.leases.holders()
                assert holders == {f"plc.{p}": owner(p, ["a", "b"]) for p in fleet.watch}
            # b left cleanly: it released its leases (deleted them, so no ttl wait), and a takes
            # its PLCs back. The release is checked in the bucket, not by how soon a is done: a
            # bound of half a ttl on a's takeover failed on a loaded machine.
            assert a.leases is not None
            assert "b" not in (await a.leases.holders()).values()
            await until(lambda: len(a.owned) == 8)
            loop = asyncio.get_running_loop()
            mark = loop.time()
            await fleet.wait_all_polled(mark, timeout=2)
        assert set(fleet.peaks().values()) == {1}, fleet.peaks()  # never two connections


async def test_a_worker_cut_from_nats_stops_before_the_ttl(
    mosquitto: Mosquitto, nats_server: NatsServer
) -> None:
    proxy = CutProxy(nats_server.host, nats_server.port)
    await proxy.start()
    events: list[str] = []
    try:
        async with Fleet(6, interval=INTERVAL) as fleet:
            config = fleet_config(fleet)
            cut_url = f"nats://127.0.0.1:{proxy.port}"
            async with (
                worker(config, "a", mosquitto.url, cut_url, events) as a,
                worker(config, "b", mosquitto.url, nats_server.url) as b,
            ):
                mine = {p for p in fleet.watch if owner(p, ["a", "b"]) == "a"}
                await until(lambda: a.owned == mine and b.owned == set(fleet.watch) - mine)
                loop = asyncio.get_running_loop()
                cut = loop.time()
                proxy.cut()
                # fencing: a stops by itself (at most 0.75 ttl after its last renew); the proof
                # that it stopped before b started is the peak of 1 connection asserted below
                await until(lambda: not a.owned, timeout=2 * TTL)
                assert loop.time() > cut
                # a closed its connections; the simulators see the close a few loop passes
                # later (same event loop). That this was before b connected is the peak of one
                # connection per PLC asserted below (a bound of a quarter ttl here was a
                # wall-clock claim a loaded machine broke).
                await until(
                    lambda: all(fleet.watch[n].sim.connection_count.current == 0 for n in mine)
                )
                # a withdrew (standby), so b takes a's PLCs once the leases expired
                await until(lambda: b.owned == set(fleet.watch), timeout=3 * TTL)
            assert set(fleet.peaks().values()) == {1}, fleet.peaks()
        assert any("fence" in e or "stop" in e for e in events), events
    finally:
        await proxy.aclose()


@pytest.mark.slow  # about 8 s: it watches for three lease times that nothing moves
async def test_a_worker_cut_from_the_broker_keeps_its_plcs(
    mosquitto: Mosquitto, nats_server: NatsServer
) -> None:
    proxy = CutProxy(mosquitto.host, mosquitto.port)
    await proxy.start()
    try:
        async with Fleet(6, interval=INTERVAL) as fleet:
            config = fleet_config(fleet)
            async with (
                worker(config, "a", f"mqtt://127.0.0.1:{proxy.port}", nats_server.url) as a,
                worker(config, "b", mosquitto.url, nats_server.url) as b,
            ):
                mine = {p for p in fleet.watch if owner(p, ["a", "b"]) == "a"}
                await until(lambda: a.owned == mine and b.owned == set(fleet.watch) - mine)
                proxy.cut()  # the broker sends a's Will; b now wants every PLC
                await until(lambda: b.presence.live == {"b"})
                loop = asyncio.get_running_loop()
                mark = loop.time()
                await asyncio.sleep(3 * TTL)
                # a still renews its leases, so b cannot take them: a keeps polling
                assert a.owned == mine and b.owned.isdisjoint(mine)
                gaps = fleet.longest_gap(mark, loop.time())
                assert max(gaps.values()) < 0.5, gaps
                proxy.restore()
                await until(lambda: b.presence.live == {"a", "b"})
                assert a.owned == mine
            assert set(fleet.peaks().values()) == {1}, fleet.peaks()
    finally:
        await proxy.aclose()


async def test_a_worker_writes_the_plcs_it_holds_through_the_one_write_path(
    mosquitto: Mosquitto,
) -> None:
    """Before: a worker refused every write ("this poller takes no writes"). After: a write to
    a PLC it polls goes through the write path and that PLC's one connection; a write to a PLC
    another worker polls is refused before anything is sent, naming that worker."""
    async with Fleet(4, interval=INTERVAL) as fleet:
        tags = (TagConfig("x", "D0", writable=True),)
        plcs = tuple(PlcConfig(n, w.sim.url, tags, timeout=0.5) for n, w in fleet.watch.items())
        config = PollConfig(plcs=plcs, groups={"default": INTERVAL})
        async with (
            worker(config, "a", mosquitto.url, None) as a,
            worker(config, "b", mosquitto.url, None) as b,
        ):
            await until(lambda: len(a.owned) + len(b.owned) == 4 and bool(a.owned and b.owned))
            mine, theirs = sorted(a.owned)[0], sorted(b.owned)[0]
            writes = WritePath(a)
            ok = await writes.write("mqtt", None, mine, "x", 4321, peer=None)
            refused = await writes.write("mqtt", None, theirs, "x", 1, peer=None)
        assert ok.ok, ok.message
        assert fleet.watch[mine].sim.memory.read_words("D", 0, 1) == [4321]
        assert (refused.ok, refused.code, refused.may_have_executed) == (
            False,
            "unknown_plc",
            False,
        )
        assert "does not poll it now (worker b does)" in refused.message
        assert fleet.watch[theirs].sim.memory.read_words("D", 0, 1) == [0]


async def test_a_worker_applies_a_reloaded_file_to_the_plcs_it_polls(
    mosquitto: Mosquitto,
) -> None:
    """SIGHUP in a worker: the fleet's new file applied as a Poller applies it. A removed PLC
    stops, an added one starts (alone, this worker owns every PLC), a changed one is planned
    again on its open connection; the others keep their connection."""
    from plcstack.poll.diff import plc_changes

    async with Fleet(4, interval=INTERVAL) as fleet:
        config = fleet_config(fleet)
        first = dataclasses.replace(config, plcs=config.plcs[:3])
        async with worker(first, "a", mosquitto.url, None) as a:
            await until(lambda: a.owned == {"plc00", "plc01", "plc02"})
            await until(lambda: all(a.stats[p].scans >= 2 for p in a.owned))
            changed = dataclasses.replace(
                config.plcs[2], tags=(TagConfig("x", "D0"), TagConfig("y", "D10"))
            )
            new = dataclasses.replace(
                config, plcs=(config.plcs[0], changed, config.plcs[3])
            )  # plc01 removed, plc02 changed, plc03 added
            applied = await a.apply(plc_changes(first, new))
            assert (applied.added, tuple(applied.removed), applied.replanned) == (
                ("plc03",),
                ("plc01",),
                ("plc02",),
            )
            await until(lambda: a.owned == {"plc00", "plc02", "plc03"})
            assert set(a.tags("plc02")) == {"x", "y"}
            await until(lambda: fleet.watch["plc01"].sim.connection_count.current == 0)
            for plc in ("plc00", "plc02"):  # one connection all along
                assert fleet.watch[plc].sim.connection_count.total == 1, plc
            await until(lambda: a.stats["plc03"].scans >= 2)
