"""The Poller: many PLCs, scan groups on intervals, samples out as an async iterator.

```python
async with Poller(load_config("plant.toml")) as poller:
    async for s in poller:
        print(s.plc, s.tag, s.value, s.quality)
```

How it behaves, and why:

* One task per PLC and one client (one connection) per PLC. The client's lock keeps one request
  in flight per connection, so replies are never mixed up; the consumer's writes go through the
  same client and simply take the next turn.
* An optional semaphore bounds how many requests are in flight across all PLCs
  (``poll.concurrency``; no cap by default, since a cap lets enough hung PLCs, each holding a slot
  for a whole deadline, delay the healthy ones). It is held only around one request, never
  while a task sleeps, so a dead PLC costs a slot for at most one connect attempt, and while
  its client backs off, its requests fail at once.
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
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import enum
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Self

from plcstack.clients.base import Client
from plcstack.errors import (
    AddressError,
    ConnectionLost,
    PlcError,
    PlcErrorResponse,
    PlcTimeout,
)
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.plan import ScanPlan, build_plan, describe
from plcstack.poll.values import TagValue, WordOrder
from plcstack.transports.backoff import Backoff
from plcstack.url import connect

__all__ = ["PlcStats", "Poller", "Quality", "Sample", "format_stats"]

#: how many recent request latencies each PLC keeps for its percentiles
LATENCY_WINDOW = 4096


class Quality(enum.Enum):
    GOOD = "good"
    BAD = "bad"


@dataclass(frozen=True, slots=True)
class Sample:
    """One tag value. Times are Unix seconds; ``source_time`` is when the request was sent.

    None of these protocols timestamps its data, so the best statement of when the PLC held the
    value is "between ``source_time`` and ``receive_time``". A bad sample has ``value`` None and
    ``error`` saying why (the full :class:`PlcError` text, naming PLC and request).
    """

    plc: str
    tag: str
    value: TagValue | None
    quality: Quality
    source_time: float
    receive_time: float
    error: str | None = None


@dataclass
class PlcStats:
    """Counters of one PLC as seen by the poller."""

    requests: int = 0
    errors: int = 0
    reconnects: int = 0
    connect_failures: int = 0
    overruns: int = 0
    drops: int = 0
    samples: int = 0
    bad_samples: int = 0
    scans: int = 0
    writes: int = 0
    latencies: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=LATENCY_WINDOW), repr=False
    )

    def percentile(self, q: float) -> float | None:
        """Latency percentile in seconds over the recent window (nearest rank); None if empty."""
        if not self.latencies:
            return None
        data = sorted(self.latencies)
        rank = max(0, min(len(data) - 1, int(q / 100.0 * len(data) + 0.5) - 1))
        return data[rank]

    def as_dict(self) -> dict[str, Any]:
        p50, p99 = self.percentile(50), self.percentile(99)
        return {
            "requests": self.requests,
            "errors": self.errors,
            "reconnects": self.reconnects,
            "connect_failures": self.connect_failures,
            "overruns": self.overruns,
            "drops": self.drops,
            "samples": self.samples,
            "bad_samples": self.bad_samples,
            "scans": self.scans,
            "writes": self.writes,
            "p50_ms": None if p50 is None else round(p50 * 1000, 3),
            "p99_ms": None if p99 is None else round(p99 * 1000, 3),
        }


@dataclass
class _Group:
    name: str
    interval: float
    tags: tuple[TagConfig, ...]
    plan: ScanPlan
    next_due: float = 0.0
    isolate: frozenset[str] = frozenset()


@dataclass
class _Plc:
    config: PlcConfig
    client: Client
    groups: list[_Group]
    stats: PlcStats
    tags: dict[str, tuple[TagConfig, int]]  # name -> (tag, point bits)
    order: WordOrder = WordOrder.BIG
    task: asyncio.Task[None] | None = None


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


class Poller:
    """Polls every PLC of a :class:`PollConfig`; iterate over it for :class:`Sample` objects.

    Clients and read plans are built in the constructor, so every bad URL or address raises
    :class:`AddressError` (naming PLC and tag) before anything is sent. ``client_factory`` builds
    the client of one PLC (tests pass in-memory fakes; the default is :func:`plcstack.connect`).
    """

    def __init__(self, config: PollConfig, *, client_factory: ClientFactory | None = None) -> None:
        self.config = config
        factory = client_factory or default_client_factory
        self.dropped = 0
        self._queue: collections.deque[Sample] = collections.deque()
        self._wakeup = asyncio.Event()
        self._semaphore: asyncio.Semaphore | contextlib.nullcontext[None] = (
            asyncio.Semaphore(config.concurrency)
            if config.concurrency is not None
            else contextlib.nullcontext()
        )
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
        tags: dict[str, tuple[TagConfig, int]] = {}
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
                tags[tag_plan.tag.name] = (tag_plan.tag, tag_plan.point_bits)
        return _Plc(plc, client, groups, PlcStats(), tags, plc.order)

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

    async def start(self) -> None:
        if self._running or self._closed:
            return
        self._running = True
        loop = asyncio.get_running_loop()
        now = loop.time()
        count = len(self._plcs)
        for i, plc in enumerate(self._plcs.values()):
            for group in plc.groups:
                # Spread the first scans (over one interval, at most a second) so hundreds of PLCs
                # configured alike do not all send in the same millisecond, every interval.
                spread = min(group.interval, 1.0)
                group.next_due = now + spread * (i / count if count > 1 else 0.0)
            plc.task = asyncio.create_task(self._run(plc), name=f"poll {plc.config.name}")

    async def aclose(self) -> None:
        """Stop polling, close every connection; iteration ends after the buffered samples."""
        if self._closed:
            return
        self._closed = True
        tasks = [p.task for p in self._plcs.values() if p.task is not None]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await asyncio.gather(
            *(p.client.aclose() for p in self._plcs.values()), return_exceptions=True
        )
        self._update_connection_stats()
        self._wakeup.set()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

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

    def pending(self) -> int:
        """Samples buffered and not yet taken by the consumer."""
        return len(self._queue)

    def drain(self) -> list[Sample]:
        """Take every buffered sample at once (for consumers that batch)."""
        out = list(self._queue)
        self._queue.clear()
        return out

    def _emit(self, plc: _Plc, sample: Sample) -> None:
        plc.stats.samples += 1
        if sample.quality is Quality.BAD:
            plc.stats.bad_samples += 1
        if len(self._queue) >= self.config.queue:
            oldest = self._queue.popleft()
            self.dropped += 1
            owner = self._plcs.get(oldest.plc)
            if owner is not None:
                owner.stats.drops += 1
        self._queue.append(sample)
        self._wakeup.set()

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
            config, bits = state.tags[tag]
        except KeyError:
            raise AddressError(f"no tag named {tag!r}", plc=plc, request=f"write {tag}") from None
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
        points: list[int | bool] = []
        order = state.order
        for item in items:
            try:
                points.extend(config.type.encode(item, bits, order))
            except AddressError as exc:
                raise AddressError(
                    f"tag {tag!r}: {exc.message}", plc=plc, request=f"write {tag}"
                ) from None
        if all(isinstance(p, bool) for p in points):
            await self.write(plc, config.address, [bool(p) for p in points])
        else:
            await self.write(plc, config.address, [int(p) for p in points])

    # -- the polling task -------------------------------------------------------------------
    async def _run(self, plc: _Plc) -> None:
        loop = asyncio.get_running_loop()
        while True:
            due = min(g.next_due for g in plc.groups) if plc.groups else None
            if due is None:
                return
            delay = due - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            now = loop.time()
            for group in sorted(plc.groups, key=lambda g: g.next_due):
                if group.next_due > now:
                    continue
                await self._scan(plc, group)
                group.next_due += group.interval
                after = loop.time()
                if group.next_due <= after:
                    missed = int((after - group.next_due) // group.interval) + 1
                    plc.stats.overruns += missed
                    group.next_due += missed * group.interval

    async def _scan(self, plc: _Plc, group: _Group) -> None:
        loop = asyncio.get_running_loop()
        plan = group.plan
        replies: list[Sequence[int | bool] | PlcError] = []
        times: list[tuple[float, float]] = []
        give_up: PlcError | None = None
        rejected: set[str] = set()
        plc.stats.scans += 1
        for index, request in enumerate(plan.requests):
            sent = time.time()
            if give_up is not None:
                replies.append(give_up)
                times.append((sent, sent))
                continue
            async with self._semaphore:
                start = loop.time()
                sent = time.time()
                try:
                    points = await plc.client.read(request.address, request.count)
                except PlcError as exc:
                    error: PlcError = exc.bind(plc=plc.config.name, request=describe(request))
                except Exception as exc:  # a client bug must not end this PLC's polling
                    error = PlcError(
                        f"unexpected {type(exc).__name__}: {exc}",
                        plc=plc.config.name,
                        request=describe(request),
                    )
                else:
                    plc.stats.latencies.append(loop.time() - start)
                    plc.stats.requests += 1
                    replies.append(points)
                    times.append((sent, time.time()))
                    continue
            plc.stats.requests += 1
            plc.stats.errors += 1
            replies.append(error)
            times.append((sent, time.time()))
            if isinstance(error, PlcTimeout | ConnectionLost):
                give_up = error
            elif isinstance(error, PlcErrorResponse | AddressError):
                names = [t.name for t in plan.tags_of(index)]
                if len(names) > 1:
                    rejected.update(names)
        for result, tag_plan in zip(plan.split(replies, plc.order), plan.tags, strict=True):
            reqs = sorted(tag_plan.requests)
            source = min(times[r][0] for r in reqs) if reqs else time.time()
            received = max(times[r][1] for r in reqs) if reqs else source
            if result.error is None:
                sample = Sample(
                    plc.config.name, result.tag.name, result.value, Quality.GOOD, source, received
                )
            else:
                sample = Sample(
                    plc.config.name,
                    result.tag.name,
                    None,
                    Quality.BAD,
                    source,
                    received,
                    str(result.error),
                )
            self._emit(plc, sample)
        if rejected - group.isolate:
            group.isolate = group.isolate | rejected
            group.plan = build_plan(
                plc.client, group.tags, max_gap=plc.config.max_gap, isolate=group.isolate
            )


def format_stats(stats: dict[str, PlcStats], *, dropped_total: int | None = None) -> str:
    """A plain-text table of per-PLC statistics (what ``plcstack poll`` prints on stderr)."""

    def ms(value: float | None) -> str:
        return "-" if value is None else f"{value * 1000:.2f}"

    header: tuple[str, ...] = ("plc", "requests", "errors", "reconnects", "overruns", "drops")
    header += ("samples", "p50 ms", "p99 ms")
    rows: list[tuple[str, ...]] = [header]
    totals = PlcStats()
    for name, st in stats.items():
        rows.append(
            (
                name,
                str(st.requests),
                str(st.errors),
                str(st.reconnects),
                str(st.overruns),
                str(st.drops),
                str(st.samples),
                ms(st.percentile(50)),
                ms(st.percentile(99)),
            )
        )
        totals.requests += st.requests
        totals.errors += st.errors
        totals.reconnects += st.reconnects
        totals.overruns += st.overruns
        totals.drops += st.drops
        totals.samples += st.samples
    if len(stats) > 1:
        # the total's percentiles are over the last LATENCY_WINDOW requests of all PLCs together
        all_lat: list[float] = []
        for st in stats.values():
            all_lat.extend(st.latencies)
        totals.latencies = collections.deque(all_lat)
        rows.append(
            (
                f"TOTAL ({len(stats)} PLCs)",
                str(totals.requests),
                str(totals.errors),
                str(totals.reconnects),
                str(totals.overruns),
                str(totals.drops),
                str(totals.samples),
                ms(totals.percentile(50)),
                ms(totals.percentile(99)),
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = []
    for r in rows:
        cells = [r[0].ljust(widths[0])] + [
            c.rjust(w) for c, w in zip(r[1:], widths[1:], strict=True)
        ]
        lines.append("  ".join(cells).rstrip())
    if dropped_total is not None:
        lines.append(f"samples dropped for a slow consumer: {dropped_total}")
    return "\n".join(lines)
