"""The Poller: many PLCs, scan groups on intervals, samples out as an async iterator.

```python
async with Poller(load_config("plant.toml")) as poller:
    async for s in poller:
        print(s.plc, s.tag, s.value, s.quality)
```

How it behaves, and why:

* One client (one connection) per PLC. The client's lock keeps one request in flight per
  connection, so replies are never mixed up; the consumer's writes go through the same client and
  simply take the next turn.
* Scans of a client that can start reads without awaiting (E71: ``Client.callback_reads``) run as
  callbacks (:mod:`.scanner`): the shared timer starts the request, the transport hands the answer
  back, and the sample is queued in the same loop pass, with no task step and no future per
  request. Anything else (connecting, a stale-input check, a request queued behind a write, a scan
  of several requests) runs that scan through the same code the PLC tasks use, in a task of its
  own. Other clients scan in one task per PLC.
* An optional cap bounds how many requests are in flight across all PLCs (``poll.concurrency``;
  no cap by default, since a cap lets enough hung PLCs, each holding a slot for a whole
  deadline, delay the healthy ones). A slot (:class:`~plcstack.clients.flight.Slots`, FIFO) is
  held only around one request, never while a scan waits for its time, so a dead PLC costs a slot
  for at most one connect attempt, and while its client backs off, its requests fail at once.
  A callback scan
  takes a free slot without waiting; when none is free, that scan runs on the task path, which
  queues for a slot in arrival order. So a cap keeps the callback scans.
* When a request fails on the connection (timeout, connection lost, connect failed), the rest of
  that scan is not attempted: those tags get the same error, and a slow PLC costs one deadline
  per scan instead of one per request.
* A scan that runs past its next due time is not queued: the missed ticks are counted as overruns
  and the schedule moves to the next tick in the future.
* Samples wait in a bounded buffer for the consumer; when it is full, the oldest sample is dropped
  and counted (per PLC and in total). Nothing is dropped silently.
* A merged request that the PLC rejects with an error code (e.g. a gap that crosses the end of a
  data block) is not retried in that scan; from the next scan on, its tags are read separately so
  one bad address does not blank its neighbours.

Cost (``plcstack bench``, the fleet case): with a thousand E71 PLCs at 10 Hz the poller
spends about what a raw asyncio loop spends on the same requests once that loop also turns each
reply into its words as Python ints; the rest of the difference to a loop that keeps the bytes is
allocating those ints. The north side takes samples in batches gathered for ``poll.batch_wait``
(a consumer woken once per loop pass cost more than the requests). The poller never touches
global GC settings.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Self

from plcstack.clients import connect
from plcstack.clients.base import Client
from plcstack.clients.flight import Slots
from plcstack.errors import (
    AddressError,
    ConnectionLost,
    PlcError,
    PlcErrorResponse,
    PlcTimeout,
)
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.plan import ScanPlan, TagPlan, build_plan, describe, encode_tag
from plcstack.poll.samples import Quality, Sample, make_sample
from plcstack.poll.scanner import Scanner, advance
from plcstack.poll.stats import LATENCY_WINDOW, LatencyWindow, PlcStats, format_stats
from plcstack.poll.ticker import Ticker
from plcstack.resource import AsyncResource
from plcstack.transports.backoff import Backoff
from plcstack.values import ByteOrder, Endian, WordOrder

_log = logging.getLogger(__name__)

__all__ = [
    "LATENCY_WINDOW",
    "MAX_SCANS_WITHOUT_YIELD",
    "LatencyWindow",
    "PlcStats",
    "Poller",
    "Quality",
    "Sample",
    "format_stats",
    "timer_resolution",
]

#: a task whose client never suspends (every request fails at once, or an in-memory fake) still
#: lets the event loop run other tasks after this many scans in a row
MAX_SCANS_WITHOUT_YIELD = 16


@dataclass(slots=True)
class _Group:
    name: str
    interval: float
    tags: tuple[TagConfig, ...]
    plan: ScanPlan
    next_due: float = 0.0
    isolate: frozenset[str] = frozenset()


@dataclass(slots=True)
class _Plc:
    config: PlcConfig
    client: Client
    groups: list[_Group]
    stats: PlcStats
    tags: dict[str, TagPlan]  # name -> the tag's plan (point bits, bit of a word)
    order: WordOrder = Endian.BIG
    byte_order: ByteOrder = Endian.BIG
    task: asyncio.Task[None] | None = None
    scanners: list[Scanner] = field(default_factory=list)


ClientFactory = Callable[[PlcConfig], Client]


def default_client_factory(plc: PlcConfig) -> Client:
    options: dict[str, Any] = {}
    if plc.timeout is not None:
        options["timeout"] = plc.timeout
    if plc.connect_timeout is not None:
        options["connect_timeout"] = plc.connect_timeout
    client = connect(plc.url, **options)
    if plc.backoff_max is not None:
        client.backoff = Backoff(initial=min(0.2, plc.backoff_max), maximum=plc.backoff_max)
    return client


class Poller(AsyncResource):
    """Polls every PLC of a :class:`PollConfig`; iterate over it for :class:`Sample` objects.

    Clients and read plans are built in the constructor, so every bad URL or address raises
    :class:`AddressError` (naming PLC and tag) before anything is sent. ``client_factory`` builds
    the client of one PLC (tests pass in-memory fakes; the default is :func:`plcstack.connect`).
    """

    #: a scan of one request runs inline in ``_run`` (see there); tests turn this off to run the
    #: same scans through ``_scan`` and prove both give the same samples and counters
    inline_single_request = True
    #: the PLC tasks wait for their next scan on one shared :class:`Ticker` instead of one
    #: ``asyncio.sleep`` timer each; tests turn it off to compare both
    shared_timer = True
    #: scans run as callbacks where they can (:mod:`.scanner`: no task step per scan) when
    #: the shared timer is on and the PLC's client can start reads (``Client.callback_reads``:
    #: E71), with or without a concurrency cap; tests turn this off to run every scan in the
    #: PLC's task and compare
    callback_scans = True
    #: a scan whose one tag is the whole reply of its one request (``ScanPlan.whole_reply_tag``)
    #: hands the reply out as the sample's value without ``_deliver``; tests turn this off to
    #: compare both
    whole_reply_samples = True

    def __init__(self, config: PollConfig, *, client_factory: ClientFactory | None = None) -> None:
        self.config = config
        factory = client_factory or default_client_factory
        self.dropped = 0
        self._queue: collections.deque[Sample] = collections.deque()
        self._wakeup = asyncio.Event()
        #: the concurrency cap's slots (``poll.concurrency``), shared by both kinds of scan
        self._slots: Slots | None = (
            Slots(config.concurrency) if config.concurrency is not None else None
        )
        self._resolution = 0.0  # the running loop's timer resolution, set by start()
        self._ticker: Ticker | None = None  # set by start()
        self._running = False
        self._closed = False
        self._plcs: dict[str, _Plc] = {}
        try:
            for plc_config in config.plcs:
                self._plcs[plc_config.name] = self._prepare(plc_config, factory)
        except BaseException:
            for plc in self._plcs.values():
                plc.client.transport.abort()
            raise

    def _prepare(self, plc: PlcConfig, factory: ClientFactory) -> _Plc:
        try:
            client = factory(plc)
        except AddressError as exc:
            raise AddressError(exc.message, plc=plc.name, request=exc.request) from None
        groups: list[_Group] = []
        tags: dict[str, TagPlan] = {}
        for name, interval in self.config.groups.items():
            members = tuple(t for t in plc.tags if t.group == name)
            if not members:
                continue
            try:
                plan = build_plan(client, members, max_gap=plc.max_gap)
            except AddressError as exc:
                exc.plc = plc.name
                raise
            groups.append(_Group(name, interval, members, plan))
            for tag_plan in plan.tags:
                tags[tag_plan.tag.name] = tag_plan
        return _Plc(plc, client, groups, PlcStats(), tags, plc.order, client.byte_order)

    # -- life cycle -------------------------------------------------------------------------
    @property
    def plcs(self) -> list[str]:
        return list(self._plcs)

    def plan(self, plc: str, group: str) -> ScanPlan:
        """The current read plan of one scan group (to inspect merging)."""
        for g in self._plc(plc).groups:
            if g.name == group:
                return g.plan
        raise KeyError(group)

    def client(self, plc: str) -> Client:
        return self._plc(plc).client

    def tags(self, plc: str) -> dict[str, tuple[TagConfig, int]]:
        """Each tag of one PLC with the width of its points in bits (1 bit, 8 byte, 16 word area).

        What a north-side server needs to give a tag its type before the first sample arrives
        (a ``raw`` tag is a bool, a byte or a word depending on the area).
        """
        return {name: (p.tag, p.point_bits) for name, p in self._plc(plc).tags.items()}

    async def start(self) -> None:
        if self._running or self._closed:
            return
        self._running = True
        loop = asyncio.get_running_loop()
        self._resolution = timer_resolution(loop)
        self._ticker = Ticker(loop, time.perf_counter, self._resolution)
        # Schedules run on time.perf_counter (monotonic, sub-microsecond), not loop.time()
        # (millisecond resolution under uvloop); asyncio.sleep only ever gets relative delays.
        now = time.perf_counter()
        count = len(self._plcs)
        for i, plc in enumerate(self._plcs.values()):
            for group in plc.groups:
                # Spread the first scans (over one interval, at most a second) so hundreds of PLCs
                # configured alike do not all send in the same millisecond, every interval.
                spread = min(group.interval, 1.0)
                group.next_due = now + spread * (i / count if count > 1 else 0.0)
        for plc in self._plcs.values():
            if self.callback_scans and self.shared_timer and plc.client.callback_reads:
                plc.scanners = [Scanner(self, plc, g, self._ticker) for g in plc.groups]
                for scanner in plc.scanners:
                    scanner.start()
            else:
                plc.task = asyncio.create_task(self._run(plc), name=f"poll {plc.config.name}")

    async def aclose(self) -> None:
        """Stop polling, close every connection; iteration ends after the buffered samples."""
        if self._closed:
            return
        self._closed = True
        tasks = [p.task for p in self._plcs.values() if p.task is not None]
        for task in tasks:
            task.cancel()
        for plc in self._plcs.values():
            for scanner in plc.scanners:
                scan = scanner.close()
                if scan is not None:
                    tasks.append(scan)
            # a callback request in flight dies with its connection, as a cancelled read does
            plc.client.abandon_exchange()
        await asyncio.gather(*tasks, return_exceptions=True)
        if self._ticker is not None:
            self._ticker.close()
        await asyncio.gather(
            *(p.client.aclose() for p in self._plcs.values()), return_exceptions=True
        )
        self._update_connection_stats()
        self._wakeup.set()

    async def aopen(self) -> None:
        await self.start()

    # -- samples ----------------------------------------------------------------------------
    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> Sample:
        while not self._queue:
            if self._closed:
                raise StopAsyncIteration
            self._wakeup.clear()
            await self._wakeup.wait()
        return self._queue.popleft()

    async def batches(self, wait: float = 0.0) -> AsyncIterator[list[Sample]]:
        """Every sample, in the order ``async for sample in poller`` gives them, as lists: all
        that is buffered at each wake-up (never an empty list). Ends like the sample iterator.

        For consumers of many PLCs: one wake-up and one list per event-loop pass instead of
        one ``__anext__`` per sample (at 1000 PLCs, 10 Hz: 10,000 coroutine steps a second).
        ``wait`` (seconds) lets a batch gather for that long after its first sample: fewer,
        larger batches (a historian or a broker sink loses nothing by a few milliseconds; the
        samples keep their own times). Keep it well below the time the buffer (``poll.queue``
        samples) takes to fill, or the oldest are dropped (and counted).
        """
        if not (wait >= 0.0 and wait < float("inf")):
            raise ValueError(f"wait must be a finite number of seconds >= 0, not {wait!r}")
        queue = self._queue
        while True:
            while not queue:
                if self._closed:
                    return
                self._wakeup.clear()
                await self._wakeup.wait()
            if wait and not self._closed:
                await asyncio.sleep(wait)  # let more samples join this batch
            batch = list(queue)
            queue.clear()
            yield batch

    def pending(self) -> int:
        """Samples buffered and not yet taken by the consumer."""
        return len(self._queue)

    def drain(self) -> list[Sample]:
        """Take every buffered sample at once (for consumers that batch)."""
        out = list(self._queue)
        self._queue.clear()
        return out

    def _trim(self) -> None:
        """Drop the oldest samples beyond the buffer's size, counting each against its PLC."""
        queue = self._queue
        excess = len(queue) - self.config.queue
        while excess > 0:
            oldest = queue.popleft()
            excess -= 1
            self.dropped += 1
            owner = self._plcs.get(oldest.plc)
            if owner is not None:
                owner.stats.drops += 1

    # -- statistics -------------------------------------------------------------------------
    def _update_connection_stats(self) -> None:
        for plc in self._plcs.values():
            cs = plc.client.stats
            plc.stats.reconnects = max(0, cs.connects - 1)
            plc.stats.connect_failures = cs.connect_failures

    @property
    def stats(self) -> dict[str, PlcStats]:
        """Per-PLC statistics (live objects; connection counters refreshed on access)."""
        self._update_connection_stats()
        return {name: plc.stats for name, plc in self._plcs.items()}

    # -- writes -----------------------------------------------------------------------------
    def _plc(self, name: str) -> _Plc:
        try:
            return self._plcs[name]
        except KeyError:
            raise AddressError(f"no PLC named {name!r} in this poller", plc=name) from None

    async def write(self, plc: str, address: str, values: Sequence[int] | Sequence[bool]) -> None:
        """Write through the PLC's polling connection; returns once the PLC confirmed it.

        Never retried: a failure raises the client's :class:`PlcError` (for a timeout the message
        says the outcome is unknown).
        """
        state = self._plc(plc)
        state.stats.writes += 1
        try:
            await state.client.write(address, values)
        except PlcError:
            state.stats.errors += 1
            raise

    async def write_tag(self, plc: str, tag: str, value: object) -> None:
        """Write a configured tag by name, encoding ``value`` with the tag's type.

        ``value`` is a scalar for ``count = 1`` tags, else a sequence of ``count`` scalars.
        """
        state = self._plc(plc)
        try:
            tag_plan = state.tags[tag]
        except KeyError:
            raise AddressError(f"no tag named {tag!r}", plc=plc, request=f"write {tag}") from None
        config, bits = tag_plan.tag, tag_plan.point_bits
        if tag_plan.bit is not None:
            raise AddressError(
                f"tag {tag!r} is a bit of a word ({config.address}) and is read-only: writing "
                "one bit of a word would be a read-modify-write racing the PLC program",
                plc=plc,
                request=f"write {tag}",
            )
        items: Sequence[object]
        if config.count == 1:
            items = [value]
        elif isinstance(value, Sequence) and not isinstance(value, str | bytes):
            items = value
        else:
            raise AddressError(
                f"tag {tag!r} has {config.count} values; pass a list",
                plc=plc,
                request=f"write {tag}",
            )
        if len(items) != config.count:
            raise AddressError(
                f"tag {tag!r} takes {config.count} values, got {len(items)}",
                plc=plc,
                request=f"write {tag}",
            )
        try:
            points = encode_tag(config, items, bits, state.order, state.byte_order)
        except AddressError as exc:
            raise type(exc)(
                f"tag {tag!r}: {exc.message}", plc=plc, request=f"write {tag}"
            ) from None
        if all(isinstance(p, bool) for p in points):
            await self.write(plc, config.address, [bool(p) for p in points])
        else:
            await self.write(plc, config.address, [int(p) for p in points])

    # -- the polling task -------------------------------------------------------------------
    #
    # Clocks: one time.time() per scan; each request is timed with perf_counter (its latency),
    # and its wall-clock send/receive times are that time.time() plus perf_counter offsets, so
    # receive_time >= source_time even if the wall clock steps. Schedules use perf_counter too.
    #
    # A scan of one request (one merged read covers the group: the usual case) runs inline in
    # _run: no coroutine, list or tuple per scan; objects that live across the await of a read
    # are what the garbage collector keeps traversing while a thousand reads are in flight.

    async def _run(self, plc: _Plc) -> None:
        """The PLC's scans in a task (when callback scans are off, see :attr:`callback_scans`)."""
        groups = plc.groups
        if not groups:
            return
        clock = time.perf_counter
        resolution = self._resolution
        # one loop timer for every PLC's next scan (see ticker.py); tests may switch it off to
        # compare with asyncio.sleep
        ticker = self._ticker if self.shared_timer else None
        unyielded = 0  # scans since this task last slept
        while True:
            due = min(g.next_due for g in groups)
            now = clock()
            if due - now > resolution:
                if ticker is not None:
                    await ticker.wait_until(due)
                else:
                    await asyncio.sleep(due - now)
                unyielded = 0
                now = clock()
            elif unyielded >= MAX_SCANS_WITHOUT_YIELD:
                # Due already (or within the timer resolution, where a timer would fire in the
                # very next loop pass anyway): no timer. But a client that never suspends must
                # not starve the loop, so yield once in a while.
                await asyncio.sleep(0)
                unyielded = 0
                now = clock()
            ready = now + resolution
            for group in sorted(groups, key=_due) if len(groups) > 1 else groups:
                if group.next_due > ready:
                    continue
                if await self._scan_group(plc, group):
                    unyielded = MAX_SCANS_WITHOUT_YIELD
                else:
                    unyielded += 1
                advance(plc.stats, group, clock())

    async def _scan_group(self, plc: _Plc, group: _Group) -> bool:
        """One scan of ``group`` awaiting the client; returns whether a request failed."""
        plan = group.plan
        if not (self.inline_single_request and len(plan.requests) == 1):
            return await self._scan(plc, group)
        request = plan.requests[0]
        plc.stats.scans += 1
        slots = self._slots
        if slots is not None:
            await slots.acquire()
        clock = time.perf_counter
        wall = time.time()
        start = clock()
        try:
            reply: Sequence[int | bool] | Exception = await plc.client.read(
                request.address, request.count
            )
        except Exception as exc:
            reply = exc
        finally:
            if slots is not None:
                slots.release()
        return self._single_done(plc, group, plan, reply, start, clock(), wall - start)

    def _single_done(
        self,
        plc: _Plc,
        group: _Group,
        plan: ScanPlan,
        reply: Sequence[int | bool] | Exception,
        start: float,
        end: float,
        offset: float,
    ) -> bool:
        """Deliver a scan of one request (its reply, or what the read raised); returns whether
        it failed. ``start``/``end`` are ``perf_counter`` times, ``offset`` makes them Unix
        times. The one definition for the task and the callback scans (scanner.py)."""
        if isinstance(reply, Exception):
            error = self._failed(plc, group, plan, 0, reply)
            self._deliver(plc, plan, (error,), start + offset, end + offset, None, None)
            return True
        whole = plan.whole_tag
        if whole is not None and self.whole_reply_samples and len(reply) == plan.requests[0].count:
            self._whole_reply(plc.stats, plc.config.name, whole, reply, start, end, offset)
        else:
            stats = plc.stats
            stats.latencies.append(end - start)
            stats.requests += 1
            self._deliver(plc, plan, (reply,), start + offset, end + offset, None, None)
        return False

    def _whole_reply(
        self,
        stats: PlcStats,
        name: str,
        tag: str,
        reply: Sequence[int | bool],
        start: float,
        end: float,
        offset: float,
    ) -> None:
        """A good reply to a plan of one request whose one tag is the whole reply
        (``ScanPlan.whole_reply_tag``): counted, and queued as the one sample ``_deliver``
        would give, without its copy of the reply. ``_single_done`` and the scanner's
        callback (which knows its plan's tag and checks the reply's length itself) both
        come here."""
        stats.latencies.append(end - start)
        stats.requests += 1
        queue = self._queue
        queue.append(
            make_sample(
                name,
                tag,
                reply,  # type: ignore[arg-type]  # the list client.read returned
                Quality.GOOD,
                start + offset,
                end + offset,
                None,
            )
        )
        stats.samples += 1
        if len(queue) > self.config.queue:
            self._trim()
        self._wakeup.set()

    def _failed(
        self, plc: _Plc, group: _Group, plan: ScanPlan, index: int, exc: Exception
    ) -> PlcError:
        """Account for a failed request of a scan; returns the error bound to PLC and request.

        A merged request that the PLC rejects with an error code has its tags read separately
        from the next scan on.
        """
        stats = plc.stats
        stats.requests += 1
        stats.errors += 1
        request = plan.requests[index]
        if isinstance(exc, PlcError):
            error = exc.bind(plc=plc.config.name, request=describe(request))
        else:  # a client bug must not end this PLC's polling
            error = PlcError(
                f"unexpected {type(exc).__name__}: {exc}",
                plc=plc.config.name,
                request=describe(request),
            )
        _log.debug("scan request failed: %s", error)  # the tags carry it too, as bad samples
        if isinstance(error, PlcErrorResponse | AddressError):
            names = {t.name for t in plan.tags_of(index)}
            if len(names) > 1 and not names <= group.isolate:
                group.isolate = group.isolate | names
                group.plan = build_plan(
                    plc.client, group.tags, max_gap=plc.config.max_gap, isolate=group.isolate
                )
        return error

    async def _scan(self, plc: _Plc, group: _Group) -> bool:
        """One scan of a group that needs several requests; returns whether one failed.

        When a request fails on the connection (timeout, connection lost), the rest of the
        scan is not attempted: those tags get the same error.
        """
        plan = group.plan
        stats = plc.stats
        client = plc.client
        slots = self._slots
        clock = time.perf_counter
        count = len(plan.requests)
        replies: list[Sequence[int | bool] | PlcError] = []
        sent: list[float] = []
        received: list[float] = []
        give_up: PlcError | None = None
        failed = False
        stats.scans += 1
        wall = time.time()
        offset = wall - clock()
        for index, request in enumerate(plan.requests):
            if give_up is not None:
                now = clock() + offset
                replies.extend([give_up] * (count - index))
                sent.extend([now] * (count - index))
                received.extend([now] * (count - index))
                break
            if slots is not None:
                await slots.acquire()
            start = clock()
            try:
                points = await client.read(request.address, request.count)
            except Exception as exc:
                error = self._failed(plc, group, plan, index, exc)
                failed = True
            else:
                end = clock()
                stats.latencies.append(end - start)
                stats.requests += 1
                replies.append(points)
                sent.append(start + offset)
                received.append(end + offset)
                continue
            finally:
                if slots is not None:
                    slots.release()
            replies.append(error)
            sent.append(start + offset)
            received.append(clock() + offset)
            if isinstance(error, PlcTimeout | ConnectionLost):
                give_up = error
        self._deliver(plc, plan, replies, 0.0, 0.0, sent, received)
        return failed

    def _deliver(
        self,
        plc: _Plc,
        plan: ScanPlan,
        replies: Sequence[Sequence[int | bool] | PlcError],
        source: float,
        receive: float,
        sent: list[float] | None,
        received: list[float] | None,
    ) -> None:
        """Queue one scan's samples; times are Unix seconds, per request when several."""
        name = plc.config.name
        order = plc.order
        extract = plan.extract
        queue = self._queue
        good, bad_q = Quality.GOOD, Quality.BAD
        bad = 0
        for tag_plan in plan.tags:
            if sent is not None and received is not None:
                ids = tag_plan.request_ids
                source = min(sent[r] for r in ids)
                receive = max(received[r] for r in ids)
            result = extract(tag_plan, replies, order)
            if isinstance(result, PlcError):
                bad += 1
                queue.append(
                    make_sample(
                        name,
                        tag_plan.tag.name,
                        None,
                        bad_q,
                        source,
                        receive,
                        str(result),
                        type(result),
                    )
                )
            else:
                queue.append(
                    make_sample(name, tag_plan.tag.name, result, good, source, receive, None)
                )
        stats = plc.stats
        stats.samples += len(plan.tags)
        stats.bad_samples += bad
        if len(queue) > self.config.queue:
            self._trim()
        self._wakeup.set()


def _due(group: _Group) -> float:
    return group.next_due


def timer_resolution(loop: asyncio.AbstractEventLoop) -> float:
    """Below this delay a loop's timer fires in its next pass anyway, so the poller does not sleep.

    asyncio's own loops treat timers due within the monotonic clock's resolution as ready
    (``BaseEventLoop._run_once``); other loops (uvloop: libuv) keep millisecond timers.
    """
    if isinstance(loop, asyncio.BaseEventLoop):
        return time.get_clock_info("monotonic").resolution
    return 1e-3
