"""The Poller against in-memory fake clients: scheduling, failures, accounting, writes."""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack import values as vt
from plcstack.clients.base import Client
from plcstack.errors import AddressError, ConnectionLost, PlcError, PlcTimeout
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller, Quality, Sample, format_stats
from tests.aio_helpers import eventually
from tests.poll_fakes import FakeClient

URL = "e71+tcp://127.0.0.1:1"  # never dialled: the fakes stand in for the client


def tag(
    name: str, address: str, type: str = "raw", count: int = 1, group: str = "default"
) -> TagConfig:
    return TagConfig(name, address, vt.value_type(type), count, group)


def make(
    plcs: dict[str, list[TagConfig]],
    *,
    interval: float = 0.01,
    groups: dict[str, float] | None = None,
    queue: int = 10_000,
    concurrency: int | None = None,
    max_gap: int = 8,
) -> tuple[Poller, dict[str, FakeClient]]:
    fakes: dict[str, FakeClient] = {}

    def factory(plc: PlcConfig) -> Client:
        fakes[plc.name] = FakeClient(f"fake://{plc.name}")
        return fakes[plc.name]

    config = PollConfig(
        tuple(PlcConfig(name, URL, tuple(tags), max_gap=max_gap) for name, tags in plcs.items()),
        {"default": interval, **(groups or {})},
        concurrency=concurrency,
        queue=queue,
    )
    return Poller(config, client_factory=factory), fakes


async def collect(
    poller: Poller, until: Callable[[list[Sample]], bool], limit: int = 10_000
) -> list[Sample]:
    out: list[Sample] = []
    async with asyncio.timeout(10):
        async for sample in poller:
            out.append(sample)
            if until(out) or len(out) >= limit:
                break
    return out


def of(samples: list[Sample], plc: str, tag: str | None = None) -> list[Sample]:
    return [s for s in samples if s.plc == plc and (tag is None or s.tag == tag)]


async def test_values_types_and_merged_requests() -> None:
    poller, fakes = make(
        {
            "p1": [
                tag("count", "D100", "uint16"),
                tag("temp", "D102", "float32"),
                tag("run", "M5", "bool"),
            ],
            "p2": [tag("level", "D0", "int16")],
        }
    )
    fakes["p1"].memory["D"].update({100: 7, 102: 0x0000, 103: 0x3FC0})  # 1.5, low word first
    fakes["p1"].memory["M"][5] = True
    fakes["p2"].memory["D"][0] = 0xFFFF
    async with poller:
        samples = await collect(poller, lambda s: len(of(s, "p1")) >= 9 and len(of(s, "p2")) >= 3)
    latest = {(s.plc, s.tag): s for s in samples}
    assert latest["p1", "count"].value == 7
    assert latest["p1", "temp"].value == 1.5
    assert latest["p1", "run"].value is True
    assert latest["p2", "level"].value == -1
    assert all(s.quality is Quality.GOOD and s.error is None for s in samples)
    assert all(s.error_type is None for s in samples)
    assert all(s.source_time <= s.receive_time for s in samples)
    # D100..D103 in one request, M5 in another: two frames per scan for three tags
    assert set(fakes["p1"].reads) == {("D100", 4), ("M5", 1)}
    stats = poller.stats["p1"]
    assert stats.requests >= 6 and stats.errors == 0 and stats.percentile(50) is not None
    assert fakes["p1"].max_in_flight == 1


async def test_dead_plc_reports_bad_quality_and_does_not_hold_up_others() -> None:
    poller, fakes = make(
        {"dead": [tag("a", "D0")], "slow": [tag("b", "D0")], "ok": [tag("c", "D0")]}
    )
    fakes["dead"].up = False
    fakes["slow"].gate = asyncio.Event()  # never answers: every request runs into its deadline
    async with poller:
        samples = await collect(poller, lambda s: len(of(s, "slow")) >= 1)
    # 'ok' scanned many times while 'slow' waited for its first deadline (0.5 s at 10 ms scans)
    assert len(of(samples, "ok")) >= 10
    assert all(s.quality is Quality.GOOD for s in of(samples, "ok"))
    dead = of(samples, "dead")
    assert dead and all(s.quality is Quality.BAD and s.value is None for s in dead)
    assert dead[0].error is not None and "fake://dead" in dead[0].error
    assert "connection refused" in dead[0].error
    slow = of(samples, "slow")
    assert slow[0].quality is Quality.BAD and "no answer within" in (slow[0].error or "")
    # the error's type travels with its text, for consumers that map kinds of failure
    assert slow[0].error_type is PlcTimeout
    assert dead[0].error_type is not None and issubclass(dead[0].error_type, ConnectionLost)
    assert poller.stats["dead"].errors >= 1
    assert poller.stats["dead"].connect_failures >= 1


async def test_restarting_plc_goes_bad_then_good_and_counts_a_reconnect() -> None:
    poller, fakes = make({"p": [tag("a", "D0"), tag("b", "D1")]})
    fake = fakes["p"]
    fake.memory["D"][0] = 11
    seen: list[Sample] = []
    async with poller:
        seen += await collect(poller, lambda s: len(s) >= 4)
        fake.kill()
        seen += await collect(
            poller, lambda s: len([x for x in s if x.quality is Quality.BAD]) >= 4
        )
        fake.revive()
        seen += await collect(poller, lambda s: s[-1].quality is Quality.GOOD and len(s) >= 2)
    qualities = [s.quality for s in seen if s.tag == "a"]
    first_bad = qualities.index(Quality.BAD)
    assert Quality.GOOD in qualities[:first_bad]
    assert qualities[-1] is Quality.GOOD and seen[-1].value in (11, 0)
    bad = [s for s in seen if s.quality is Quality.BAD]
    assert all(s.error and "fake://p" in s.error for s in bad)
    stats = poller.stats["p"]
    assert stats.reconnects >= 1
    assert stats.errors >= 1


async def test_overrun_is_counted_not_queued() -> None:
    poller, fakes = make({"p": [tag("a", "D0")]}, interval=0.01)
    fake = fakes["p"]
    fake.gate = asyncio.Event()
    fake.timeout = 5.0
    async with poller:
        await asyncio.sleep(0.15)  # the first scan hangs for ~15 intervals
        assert poller.stats["p"].scans == 1
        fake.gate.set()
        await collect(poller, lambda s: len(s) >= 2)
        stats = poller.stats["p"]
        assert stats.overruns >= 5
        # the missed ticks were not made up in a burst: at most a few scans since the release
        assert stats.scans <= 4


async def test_slow_consumer_drops_oldest_and_counts() -> None:
    poller, _ = make({"p1": [tag("a", "D0")], "p2": [tag("b", "D0")]}, queue=5)
    async with poller:
        for _ in range(500):  # nobody consumes: wait until plenty were dropped
            if poller.dropped >= 20:
                break
            await asyncio.sleep(0.01)
        produced = sum(s.samples for s in poller.stats.values())
        assert poller.pending() == 5
        assert sum(s.drops for s in poller.stats.values()) == poller.dropped
        assert produced - poller.dropped == 5
        kept = poller.drain()
    # the newest were kept: receive times are the latest and in order
    assert [s.receive_time for s in kept] == sorted(s.receive_time for s in kept)


async def test_writes_share_the_single_flight_connection() -> None:
    poller, fakes = make(
        {"p": [tag("a", "D0"), tag("f", "D10", "float32"), tag("m", "M3", "bool", 2)]}
    )
    fake = fakes["p"]
    fake.delay = 0.002
    async with poller:
        await asyncio.gather(*(poller.write_tag("p", "a", i) for i in range(10)))
        await poller.write_tag("p", "f", 1.5)
        await poller.write_tag("p", "m", [True, False])
        await poller.write("p", "D20", [1, 2])
    assert fake.max_in_flight == 1
    assert ("D10", [0x0000, 0x3FC0]) in fake.writes  # MELSEC: low word first
    assert ("M3", [True, False]) in fake.writes
    assert fake.memory["D"][0] == 9 and fake.memory["D"][21] == 2
    assert poller.stats["p"].writes == 13


async def test_write_failures_are_raised_not_retried() -> None:
    poller, fakes = make({"p": [tag("a", "D0", "int16")]})
    async with poller:
        with pytest.raises(AddressError, match="outside"):
            await poller.write_tag("p", "a", 70000)
        with pytest.raises(AddressError, match="no tag"):
            await poller.write_tag("p", "zz", 1)
        with pytest.raises(AddressError, match="no PLC"):
            await poller.write("nope", "D0", [1])
        fakes["p"].kill()
        with pytest.raises(ConnectionLost) as err:
            await poller.write_tag("p", "a", 5)
        assert "fake://p" in str(err.value)
    assert fakes["p"].writes == []


async def test_rejected_merged_request_is_split_from_the_next_scan_on() -> None:
    poller, fakes = make({"p": [tag("a", "D100"), tag("b", "D104"), tag("c", "D110")]})
    fake = fakes["p"]
    fake.reject_above["D"] = 110  # D110 is "beyond the device range"
    fake.memory["D"][104] = 4
    assert [(r.address, r.count) for r in poller.plan("p", "default").requests] == [("D100", 11)]
    async with poller:
        samples = await collect(poller, lambda s: len(s) >= 9)
    first = samples[:3]
    assert all(s.quality is Quality.BAD for s in first)
    last = {s.tag: s for s in samples[-3:]}
    assert last["a"].quality is Quality.GOOD and last["b"].value == 4
    assert last["c"].quality is Quality.BAD and "57H" in (last["c"].error or "")
    assert len(poller.plan("p", "default").requests) == 3


async def test_concurrency_limit_bounds_requests_in_flight() -> None:
    poller, fakes = make({f"p{i}": [tag("a", "D0")] for i in range(8)}, concurrency=3)
    gate = asyncio.Event()
    for fake in fakes.values():
        fake.gate = gate
        fake.timeout = 5.0
    async with poller:
        for _ in range(20):
            await asyncio.sleep(0.01)
            assert sum(f.in_flight for f in fakes.values()) <= 3
        await eventually(
            lambda: sum(f.in_flight for f in fakes.values()) == 3, "three requests in flight"
        )
        gate.set()
        await collect(poller, lambda s: len({x.plc for x in s}) == 8)


async def test_by_default_many_hung_plcs_do_not_hold_up_a_healthy_one() -> None:
    # 100 PLCs that never answer (each would hold a slot of a global cap for a whole deadline)
    # next to one healthy PLC: with the default config the healthy one keeps its schedule.
    poller, fakes = make(
        {f"hung{i}": [tag("a", "D0")] for i in range(100)} | {"ok": [tag("a", "D0")]}
    )
    hang = asyncio.Event()
    for name, fake in fakes.items():
        if name != "ok":
            fake.gate = hang
            fake.timeout = 60.0
    async with poller:
        samples = await collect(poller, lambda s: len(of(s, "ok")) >= 5)
        assert sum(f.in_flight for name, f in fakes.items() if name != "ok") == 100
    assert {s.plc for s in samples} == {"ok"}


async def test_scan_groups_run_on_their_own_intervals() -> None:
    poller, _ = make(
        {"p": [tag("fast", "D0"), tag("slow", "D500", group="slow")]},
        interval=0.005,
        groups={"slow": 10.0},
    )
    async with poller:
        samples = await collect(poller, lambda s: len(of(s, "p", "fast")) >= 10)
    assert len(of(samples, "p", "slow")) == 1


async def test_client_bug_becomes_bad_sample_and_polling_goes_on() -> None:
    poller, fakes = make({"p": [tag("a", "D0")]})
    fake = fakes["p"]
    calls = 0
    real_read = fake.read

    async def flaky(address: str, count: int = 1) -> list[int] | list[bool]:
        nonlocal calls
        calls += 1
        if calls == 1:
            raise KeyError("oops")
        return await real_read(address, count)

    fake.read = flaky  # type: ignore[method-assign]
    async with poller:
        samples = await collect(poller, lambda s: len(s) >= 2)
    assert samples[0].quality is Quality.BAD and "unexpected KeyError" in (samples[0].error or "")
    assert samples[1].quality is Quality.GOOD


async def test_iteration_ends_after_close_and_stats_table() -> None:
    poller, _ = make({"p1": [tag("a", "D0")], "p2": [tag("b", "D0")]})
    async with poller:
        await collect(poller, lambda s: len(s) >= 4)
    rest = [s async for s in poller]  # buffered samples, then the end
    assert all(isinstance(s, Sample) for s in rest)
    table = format_stats(poller.stats, dropped_total=poller.dropped)
    assert "p50 ms" in table and "TOTAL (2 PLCs)" in table and "dropped" in table


def test_bad_address_in_config_fails_before_anything_is_sent() -> None:
    with pytest.raises(PlcError) as err:
        make({"press": [tag("speed", "D0"), tag("oops", "Q1")]})
    assert "press" in str(err.value) and "oops" in str(err.value)


@settings(max_examples=25, deadline=None)
@given(queue=st.integers(1, 20), plcs=st.integers(1, 4), take=st.integers(0, 30))
def test_every_sample_is_delivered_dropped_or_pending(queue: int, plcs: int, take: int) -> None:
    """Accounting invariant: produced = consumed + dropped + still buffered, per PLC too."""

    async def run() -> None:
        tags = {f"p{i}": [tag("a", "D0"), tag("b", "D500")] for i in range(plcs)}
        poller, _ = make(tags, queue=queue, interval=0.001)
        consumed = 0
        async with poller:
            if take:
                async for _ in poller:
                    consumed += 1
                    if consumed >= take:
                        break
            await asyncio.sleep(0.02)
        stats = poller.stats
        produced = sum(s.samples for s in stats.values())
        assert produced == consumed + poller.dropped + poller.pending()
        assert sum(s.drops for s in stats.values()) == poller.dropped
        # whole scans are dropped, never the newest: at most the limit or that one scan
        assert poller.queue.held <= max(queue, 2)

    asyncio.run(run())


def test_tags_gives_each_tag_with_the_width_of_its_points() -> None:
    poller, _ = make({"p": [tag("word", "D0", "int16"), tag("bits", "M0", "bool", 4)]})
    tags = poller.tags("p")
    assert {name: bits for name, (_, bits) in tags.items()} == {"word": 16, "bits": 1}
    assert tags["bits"][0].count == 4
    with pytest.raises(AddressError, match="no PLC named"):
        poller.tags("nope")


def test_stats_table_fits_80_columns() -> None:
    from plcstack.poll.stats import PlcStats

    big = PlcStats()
    big.requests, big.errors, big.samples = 12_345_678, 1_234, 98_765_432
    table = format_stats(
        {"a-plc-with-a-very-long-name-from-the-config-file": big, "p2": PlcStats()},
        dropped_total=0,
    )
    lines = table.splitlines()
    assert all(len(line) < 80 for line in lines), table
    assert lines[1].split()[0].endswith("~") and lines[1].split()[1] == "12345678"
    assert lines[2].startswith("p2 ")


def test_the_poller_spaces_its_clients_connects_with_one_set_of_turns() -> None:
    """Every client of one poller waits for the same connect turns (ConnectTurns): a fleet
    started at once connects CONNECTS_AT_ONCE at a time, not all in one loop backlog."""
    from plcstack.clients.flight import ConnectTurns
    from plcstack.poll.engine import CONNECT_TURN_HOLD, CONNECTS_AT_ONCE

    poller, _ = make({"a": [tag("a", "D0")], "b": [tag("b", "D0")]})
    turns = poller.client("a").connect_turns
    assert isinstance(turns, ConnectTurns) and poller.client("b").connect_turns is turns
    assert repr(turns) == (
        f"<ConnectTurns <Slots {CONNECTS_AT_ONCE}/{CONNECTS_AT_ONCE} free, 0 waiting>, "
        f"hold {CONNECT_TURN_HOLD:g} s>"
    )
    other, _ = make({"c": [tag("c", "D0")]})
    assert other.client("c").connect_turns is not turns  # per poller, not per process
