"""The concurrency cap (``poll.concurrency``) holds with callback scans on, as on the PLC tasks.

Six E71 PLCs answer slowly, so that scans queue for the cap's two slots. The peers count the
requests they are working on across all of them: never more than two at any moment, on either
path, and two are reached (else the cap was never tested). Under the cap the callback path must
really be taken (``start_read`` said True). ``aclose`` with requests in flight, callback ones
among them, must leave every slot free and log nothing at ERROR.

That the cap changes no sample: tests/test_scanner.py runs its fleet under a cap as well.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Any

import pytest

from plcstack.clients.flight import Slots
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import Code, E71ServerConnection
from plcstack.codecs.e71_commands import DECODERS
from plcstack.poll.config import PlcConfig, PollConfig
from plcstack.poll.engine import Poller
from plcstack.poll.samples import Quality, Sample
from plcstack.sim import e71 as sim_e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.aio_helpers import ends_quietly, eventually, poll_tasks_left
from tests.test_poll_engine import tag
from tests.test_scanner import Counting
from tests.test_slots import _free

WORDS = [0x1234, 0, 0xFFFF, 7]
CAP = 2
PLCS = 6


class Meter:
    """Requests being worked on across every peer, and the most there ever were at once."""

    def __init__(self) -> None:
        self.now = 0
        self.most = 0
        self.answered = 0
        #: which PLC's requests to hold (unanswered until ``gate`` is set), asked as each arrives
        self.hold: Callable[[str], bool] = lambda name: False
        self.held = 0
        self.gate = asyncio.Event()


class SlowE71:
    """An E71 (binary 1E frame, TCP) that answers each request after ``delay`` seconds. A
    request counts as in flight from its arrival until just before its answer is written, so
    the client cannot have sent its next one while this one still counts."""

    def __init__(self, name: str, meter: Meter, delay: float) -> None:
        self.name = name
        self.meter = meter
        self.delay = delay
        self.memory = MelsecMemory()
        self.memory.write_words("D", 0, WORDS)
        self._server: asyncio.Server | None = None
        self.port = 0

    async def start(self) -> SlowE71:
        self._server = await asyncio.start_server(ends_quietly(self._serve), "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        codec = E71ServerConnection(Code.BINARY, extensions=DECODERS)
        meter = self.meter
        try:
            while data := await reader.read(4096):
                codec.receive_data(data)
                while (event := codec.next_event()) is not NEED_DATA:
                    meter.now += 1
                    meter.most = max(meter.most, meter.now)
                    try:
                        if meter.hold(self.name):
                            meter.held += 1
                            await meter.gate.wait()
                        else:
                            await asyncio.sleep(self.delay)
                    finally:
                        meter.now -= 1
                    meter.answered += 1
                    writer.write(codec.send(sim_e71.execute(self.memory, event, Code.BINARY)))
        except ConnectionError:
            pass
        finally:
            writer.close()

    async def aclose(self) -> None:
        self.meter.gate.set()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._server.wait_closed(), 1)


async def _fleet(
    meter: Meter, delay: float, plcs: int = PLCS, cap: int = CAP
) -> tuple[list[SlowE71], Poller]:
    """PLC ``i`` answers after ``(i + 1) * delay``: with 30 ms scans and ``delay`` = 2 ms the
    six ask for 1.4 slots on average, so the cap is sometimes full and sometimes not, and both
    the callback path and the queue for a slot are taken."""
    peers = [await SlowE71(f"p{i}", meter, (i + 1) * delay).start() for i in range(plcs)]
    configs = tuple(
        PlcConfig(
            f"p{i}",
            f"e71+tcp://127.0.0.1:{peer.port}",
            (tag("a", "D0", count=4, group="fast"),),
            timeout=5.0,
        )
        for i, peer in enumerate(peers)
    )
    return peers, Poller(PollConfig(configs, {"fast": 0.03}, concurrency=cap, queue=100_000))


def _slots(poller: Poller) -> Slots:
    slots = poller._slots
    assert slots is not None
    return slots


def _holding_of(poller: Poller, name: str) -> bool:
    """Whether the PLC's callback request holds a slot now (it has one scan group)."""
    return poller._plc(name).scanners[0]._holding


def _holding(poller: Poller) -> int:
    """Callback requests holding a slot now."""
    return sum(s._holding for name in poller.plcs for s in poller._plc(name).scanners)


async def test_never_more_requests_in_flight_than_the_cap(
    caplog: pytest.LogCaptureFixture,
) -> None:
    meter = Meter()
    peers, poller = await _fleet(meter, delay=0.002)
    counting = Counting(poller)
    per_plc: dict[str, list[Sample]] = {}
    try:
        with caplog.at_level(logging.ERROR):
            async with asyncio.timeout(20):
                await poller.start()
                async for sample in poller:
                    per_plc.setdefault(sample.plc, []).append(sample)
                    enough = len(per_plc) == PLCS and all(len(s) >= 8 for s in per_plc.values())
                    if enough and sum(counting.started.values()) >= 3 * PLCS:
                        break
            await poller.aclose()
        assert [r for r in caplog.records if r.levelno >= logging.ERROR] == []
    finally:
        await poller.aclose()
        for peer in peers:
            await peer.aclose()
    assert meter.most == CAP, meter.most  # reached, never passed
    assert all(s.quality is Quality.GOOD and s.value == WORDS for v in per_plc.values() for s in v)
    # not vacuous: under the cap, most PLCs' plain scans were started as callbacks
    assert sum(n >= 1 for n in counting.started.values()) >= PLCS // 2, counting.started
    assert _free(_slots(poller)) == CAP


async def test_aclose_with_requests_in_flight_frees_every_slot(
    caplog: pytest.LogCaptureFixture,
) -> None:
    meter = Meter()
    peers, poller = await _fleet(meter, delay=0.002)
    counting = Counting(poller)
    slots = _slots(poller)
    try:
        with caplog.at_level(logging.ERROR):
            await poller.start()
            await eventually(
                lambda: sum(n >= 2 for n in counting.started.values()) >= PLCS // 2,
                "callback scans ran under the cap",
            )
            # From the next callback request on, no answer comes before aclose: that one holds a
            # slot, the next request of any path the other; the other PLCs' scans then queue.
            meter.hold = lambda name: meter.held > 0 or _holding_of(poller, name)
            await eventually(
                lambda: meter.held == CAP and slots._waiters,
                "requests in flight on every slot, with scans waiting for one",
            )
            assert meter.now == CAP and _holding(poller) >= 1
            assert slots.locked() and not slots.try_acquire()
            await poller.aclose()
            assert _free(slots) == CAP  # all given back: callback, task path and waiters
            assert _holding(poller) == 0 and not slots._waiters
            assert poll_tasks_left() == []
        assert [r for r in caplog.records if r.levelno >= logging.ERROR] == []
    finally:
        await poller.aclose()
        for peer in peers:
            await peer.aclose()


async def test_a_start_read_that_raises_gives_its_slot_back() -> None:
    """A client bug in ``start_read`` is that scan's failure (a bad sample); with one slot, a
    slot kept by it would stop every scan after it."""
    meter = Meter()
    peers, poller = await _fleet(meter, delay=0.001, plcs=1, cap=1)
    client = poller.client("p0")
    start_read = client.start_read
    calls = 0

    def flaky(address: str, count: int, done: Callable[[Any], None]) -> bool:
        nonlocal calls
        calls += 1
        if calls % 2 == 0:
            raise RuntimeError("a broken start_read")
        return start_read(address, count, done)

    client.start_read = flaky  # type: ignore[method-assign]
    samples: list[Sample] = []
    try:
        async with asyncio.timeout(10):
            await poller.start()
            async for sample in poller:
                samples.append(sample)
                if sum(s.quality is Quality.BAD for s in samples) >= 3 and calls >= 8:
                    break
        await poller.aclose()
    finally:
        await poller.aclose()
        await peers[0].aclose()
    bad = [s for s in samples if s.quality is Quality.BAD]
    assert all("a broken start_read" in (s.error or "") for s in bad)
    assert _free(_slots(poller)) == 1
