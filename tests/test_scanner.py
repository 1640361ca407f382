"""The scan driver (poll/scanner.py) over a fleet of simulated E71s.

One fleet (steady PLCs over TCP and UDP with two scan groups, a plan of several requests, a PLC
that is down, one that stops answering, one that starts refusing a merged read, a consumer
write in between) is polled; the samples per tag (runs of equal samples collapsed, so that how
many scans fit in the run does not matter) must be what each simulator's script makes them,
and each PLC's counters must agree with the samples it produced. Both ways of running a scan
must really have been taken: callbacks (``start_read`` said True) for the plain scans, awaited
reads for the rest.

Also: ``aclose`` while a callback request is in flight, and ``Ticker.call_at``.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from collections.abc import Callable
from typing import Any

import pytest

from plcstack.clients.base import Client
from plcstack.codecs.e71 import CpuGroup, Device, device_ranges
from plcstack.poll.config import PlcConfig, PollConfig
from plcstack.poll.engine import Poller
from plcstack.poll.samples import Quality, Sample
from plcstack.poll.ticker import Ticker
from plcstack.sim import e71 as sim_e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.aio_helpers import eventually, poll_tasks_left
from tests.ports import free_port
from tests.test_poll_engine import tag

GROUPS = {"fast": 0.01, "slow": 0.03}
WORDS = [0x1234, 0, 0xFFFF, 7]
#: the steady PLC's D0 after the consumer's write
WRITTEN = [99, *WORDS[1:]]
#: the answers the "mute" PLC gives before it stops answering
ANSWERS_BEFORE_MUTE = 3


class _MuteAfter(sim_e71.E71TcpSimulator):
    """Answers the first ``ANSWERS_BEFORE_MUTE`` requests, then none (a PLC that hangs): the
    timeout then hits a request on the callback path (connected, quiet, read done once)."""

    @property
    def mute(self) -> bool:
        return self.requests > ANSWERS_BEFORE_MUTE

    @mute.setter
    def mute(self, value: bool) -> None:  # pragma: no cover - set by nobody
        raise AttributeError("mute follows the request count")


def _memory() -> MelsecMemory:
    memory = MelsecMemory()
    memory.write_words("D", 0, WORDS)
    memory.write_words("D", 100, [42])
    memory.write_words("D", 1022, [5, 0, 0, 6])
    memory.write_bits("M", 0, [True])
    return memory


class Fleet:
    """Fresh simulators and the poller's config for one run."""

    def __init__(self) -> None:
        self.sims: dict[str, Any] = {}

    async def start(self, concurrency: int | None = None) -> PollConfig:
        self.sims["steady1"] = await sim_e71.start(_memory())
        self.sims["steady2"] = await sim_e71.start(_memory(), transport="udp")
        self.sims["multi"] = await sim_e71.start(_memory())
        self.sims["mute"] = await sim_e71.start(_memory())
        self.sims["mute"].__class__ = _MuteAfter
        self.sims["isolate"] = await sim_e71.start(_memory())
        down = f"e71+tcp://127.0.0.1:{free_port()}"
        url = {name: sim.url for name, sim in self.sims.items()}
        plcs = (
            PlcConfig(
                "steady1",
                url["steady1"],
                (tag("a", "D0", count=4, group="fast"), tag("b", "D100", group="slow")),
            ),
            PlcConfig("steady2", url["steady2"], (tag("a", "D0", count=4, group="fast"),)),
            PlcConfig(
                "multi",
                url["multi"],
                (tag("a", "D0", "int16", group="fast"), tag("m", "M0", "bool", group="fast")),
            ),
            PlcConfig("down", down, (tag("a", "D0", group="fast"),), backoff_max=0.05),
            PlcConfig("mute", url["mute"], (tag("a", "D0", count=4, group="fast"),), timeout=0.1),
            PlcConfig(
                "isolate",
                url["isolate"],
                (tag("a", "D1022", group="fast"), tag("b", "D1025", group="fast")),
            ),
        )
        return PollConfig(plcs, GROUPS, concurrency=concurrency, queue=100_000)

    def shrink_isolate(self) -> None:
        """The isolate PLC now has only D0-D1023 (CPU group I): the merged read D1022 x4 is
        refused (57H) and the poller reads its two tags apart (D1025 then fails alone)."""
        memory = self.sims["isolate"].memory
        memory.last = dict(memory.last)
        memory.last[Device.D] = device_ranges(CpuGroup.I)[Device.D]

    async def aclose(self) -> None:
        for sim in self.sims.values():
            await sim.aclose()


def _normal(sample: Sample) -> tuple[object, ...]:
    """A sample without its times, its error text with ports and seconds masked."""
    error = sample.error
    if error is not None:
        error = re.sub(r"\b\d{4,5}\b", "PORT", error)
        error = re.sub(r"\d+(\.\d+)? s\b", "N s", error)
    kind = None if sample.error_type is None else sample.error_type.__name__
    return sample.plc, sample.tag, sample.value, sample.quality.name, kind, error


def _collapsed(samples: list[tuple[object, ...]]) -> list[tuple[object, ...]]:
    out: list[tuple[object, ...]] = []
    for s in samples:
        if not out or out[-1] != s:
            out.append(s)
    return out


class Counting:
    """Wraps each client's ``start_read`` (how often it said True / False) and ``read`` (the
    awaited reads of scans that did not run as callbacks), per PLC."""

    def __init__(self, poller: Poller) -> None:
        self.started: dict[str, int] = {}
        self.refused: dict[str, int] = {}
        self.awaited: dict[str, int] = {}
        for name in poller.plcs:
            self._wrap(name, poller.client(name))

    def _wrap(self, name: str, client: Client) -> None:
        start_read = client.start_read
        read = client.read

        async def awaited(address: str, count: int = 1) -> list[int] | list[bool]:
            self.awaited[name] = self.awaited.get(name, 0) + 1
            return await read(address, count)

        client.read = awaited  # type: ignore[method-assign]

        def counted(address: str, count: int, done: Callable[[Any], None]) -> bool:
            started = start_read(address, count, done)
            table = self.started if started else self.refused
            table[name] = table.get(name, 0) + 1
            return started

        client.start_read = counted  # type: ignore[method-assign]


#: samples each tag must have at least before a run ends
ENOUGH = 6


async def _run(
    concurrency: int | None = None,
) -> tuple[dict[tuple[str, str], Any], dict[str, Any], Counting]:
    fleet = Fleet()
    config = await fleet.start(concurrency)
    poller = Poller(config)
    counting = Counting(poller)
    seen: list[Sample] = []
    per_tag: dict[tuple[str, str], list[Sample]] = {}
    write: asyncio.Task[None] | None = None
    try:
        async with asyncio.timeout(20):
            await poller.start()
            async for sample in poller:
                seen.append(sample)
                per_tag.setdefault((sample.plc, sample.tag), []).append(sample)
                steady = per_tag.get(("steady1", "a"), [])
                if write is None and len(steady) >= 3:
                    write = asyncio.create_task(poller.write("steady1", "D0", [99]))
                isolate = per_tag.get(("isolate", "a"), [])
                if len(isolate) == 3:
                    fleet.shrink_isolate()
                if (
                    len(per_tag) == 9
                    and all(len(s) >= ENOUGH for s in per_tag.values())
                    and write is not None
                    and write.done()
                    and sum(s.value == WRITTEN for s in steady) >= 2
                    and sum(s.error_type is not None for s in per_tag["isolate", "a"]) >= 1
                    and sum(s.quality is Quality.GOOD for s in per_tag["isolate", "a"]) >= 5
                    and sum(s.quality is Quality.BAD for s in per_tag["mute", "a"]) >= 2
                ):
                    break
            await poller.aclose()
            async for sample in poller:  # the buffered rest
                seen.append(sample)
        assert write is not None
        await write
    finally:
        await poller.aclose()
        await fleet.aclose()
    tags = {key: _collapsed([_normal(s) for s in seen if (s.plc, s.tag) == key]) for key in per_tag}
    # the down PLC's failures alternate (a refused connect, then fast failures inside the
    # backoff) as often as time allows: its first sample and the kinds of failure are compared
    down = tags["down", "a"]
    tags["down", "a"] = [down[0], *sorted(set(down), key=repr)]
    counters = {
        name: _counters(poller, name, [s for s in seen if s.plc == name]) for name in poller.plcs
    }
    return tags, counters, counting


def _counters(poller: Poller, name: str, samples: list[Sample]) -> dict[str, Any]:
    """The PLC's counters checked against its samples; returns their proportions."""
    stats = poller.stats[name]
    plc = poller._plc(name)
    completed = 0
    for group in plc.groups:
        names = {t.name for t in group.tags}
        of_group = sum(s.tag in names for s in samples)
        assert of_group % len(names) == 0, (name, group.name)
        completed += of_group // len(names)
    bad = sum(s.quality is Quality.BAD for s in samples)
    # every sample is counted, and only those (nothing dropped: the queue is large)
    assert stats.samples == len(samples) and stats.bad_samples == bad, (name, stats)
    # a scan of each group may have been in flight at aclose: counted, never delivered
    in_flight = stats.scans - completed
    assert 0 <= in_flight <= len(plc.groups), (name, stats.scans, completed)
    assert stats.requests >= completed and stats.drops == 0
    return {
        "bad_share": round(bad / len(samples), 1),
        "errors": stats.errors > 0,
        "requests_per_scan": round(stats.requests / max(completed, 1)),
        "writes": stats.writes,
    }


@pytest.mark.parametrize("concurrency", [None, 2], ids=["no-cap", "cap-2"])
async def test_every_scan_gives_what_the_plcs_hold(concurrency: int | None) -> None:
    """Also under a concurrency cap smaller than the fleet: scans that find no slot free run
    awaited, queued for one."""
    tasks_tags, counters, cb_count = await _run(concurrency)
    assert counters["steady1"]["writes"] == 1 and counters["down"]["errors"]
    # both ways of running a scan ran: callbacks for the plain scans, awaited reads the rest
    plain = ("steady1", "steady2", "mute", "isolate")
    if concurrency is None:
        for name in plain:
            assert cb_count.started.get(name, 0) >= 2, (name, cb_count.started)
    else:
        # under a cap, a scan that finds no slot free runs awaited: how many of one PLC's scans
        # took a slot depends on which scans held them (a loaded machine gave the mute PLC one),
        # so the callbacks are counted over the fleet's plain scans
        assert sum(cb_count.started.get(name, 0) for name in plain) >= 2 * len(plain), (
            cb_count.started
        )
    assert "multi" not in cb_count.started and "multi" not in cb_count.refused
    assert cb_count.awaited["multi"] >= ENOUGH  # several requests: always awaited
    assert "down" not in cb_count.started  # never connected: never quiet
    steady = [s[2] for s in tasks_tags["steady1", "a"]]
    assert steady == [WORDS, WRITTEN]
    assert [s[2] for s in tasks_tags["steady1", "b"]] == [42]
    assert [s[2] for s in tasks_tags["steady2", "a"]] == [WORDS]
    assert [s[2] for s in tasks_tags["multi", "m"]] == [True]
    mute = tasks_tags["mute", "a"]
    # the first timeout on the connection that answered before (the callback path), then the
    # fresh connections' (the task path), one and the same: this PLC answered before, so its
    # silence is a hang, and no hint points at the port or the protocol
    assert [s[3:5] for s in mute] == [("GOOD", None), ("BAD", "PlcTimeout")], mute
    assert "Hint" not in str(mute[1][5])
    a, b = tasks_tags["isolate", "a"], tasks_tags["isolate", "b"]
    assert [s[2:5] for s in a] == [
        (5, "GOOD", None),
        (None, "BAD", "PlcErrorResponse"),
        (5, "GOOD", None),
    ]
    assert [s[3:5] for s in b] == [("GOOD", None), *[("BAD", "PlcErrorResponse")] * 2], b
    assert "57H" in str(a[1][5]) and "58H" in str(b[-1][5])
    down = tasks_tags["down", "a"]
    assert all(s[3] == "BAD" and s[4] == "ConnectFailed" for s in down), down


async def test_aclose_during_a_callback_request(caplog: pytest.LogCaptureFixture) -> None:
    sim = await sim_e71.start(_memory())
    config = PollConfig(
        (PlcConfig("p", sim.url, (tag("a", "D0", count=4, group="fast"),)),),
        GROUPS,
        concurrency=None,
    )
    poller = Poller(config)
    counting = Counting(poller)
    client = poller.client("p")
    try:
        with caplog.at_level(logging.ERROR):
            await poller.start()
            await eventually(lambda: counting.started.get("p", 0) >= 2, "callback scans ran")
            sim.delay = 0.2  # the next answer comes late: aclose finds the request in flight
            started = counting.started["p"]
            await eventually(lambda: counting.started["p"] > started, "a slow callback scan")
            assert client._lock.locked()  # in flight
            samples = poller.stats["p"].samples
            errors = (client.stats.errors, client.stats.timeouts)
            await poller.aclose()
            assert not client.transport.is_open and not client._lock.locked()
            # given up, not failed: closing is no error of the PLC's (abandon_exchange)
            assert (client.stats.errors, client.stats.timeouts) == errors
            await asyncio.sleep(0.3)  # the answer would have come by now
            assert poller.stats["p"].samples == samples
            left = [s async for s in poller]
            assert len(left) <= samples
            assert poll_tasks_left() == []
        assert [r for r in caplog.records if r.levelno >= logging.ERROR] == []
    finally:
        await poller.aclose()
        await sim.aclose()


# -- Ticker.call_at ------------------------------------------------------------------------------
async def test_ticker_calls_back_in_due_order_never_early(caplog: pytest.LogCaptureFixture) -> None:
    clock = time.perf_counter
    ticker = Ticker(asyncio.get_running_loop(), clock, 0.0)
    start = clock()
    called: list[tuple[str, float, float]] = []

    def at(name: str, due: float, then: Callable[[], None] | None = None) -> Callable[[], None]:
        def callback() -> None:
            called.append((name, due, clock()))
            if then is not None:
                then()

        return callback

    def broken() -> None:
        called.append(("broken", start + 0.02, clock()))
        raise RuntimeError("a broken callback")

    for name, ms in [("c", 30), ("a", 10), ("e", 50), ("b", 20)]:
        ticker.call_at(start + ms / 1000, at(name, start + ms / 1000))
    ticker.call_at(start + 0.02, broken)
    # a callback that schedules another, due at once (as a scanner does after a late scan)
    ticker.call_at(start + 0.04, at("d", start + 0.04, lambda: ticker.call_at(0.0, at("d2", 0.0))))
    ticker.call_at(start + 1.0, at("never", start + 1.0))
    with caplog.at_level(logging.ERROR, logger="plcstack.poll.ticker"):
        await eventually(lambda: len(called) == 7, "the due callbacks ran")
    ticker.close()
    assert [n for n, _, _ in called] == ["a", "b", "broken", "c", "d", "d2", "e"]
    for name, due, when in called:
        assert when >= due - 0.002, (name, when - due)  # asyncio timers: clock resolution
    assert any("broken" in r.getMessage() or r.exc_info for r in caplog.records)
    assert len(ticker) == 0  # close() dropped "never"
    await asyncio.sleep(0.05)
    assert "never" not in [n for n, _, _ in called]
