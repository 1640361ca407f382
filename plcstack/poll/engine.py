"""The Poller: many PLCs, scan groups on intervals, scans (or samples) out as async iterators.

```python
async with Poller(load_config("plant.toml").poll) as poller:
    async for s in poller:
        print(s.plc, s.tag, s.value, s.quality)
```

The north side takes whole scans (:meth:`Poller.scans`: PLC, group, times, samples); iterating
the poller itself gives the same samples one by one.

How it behaves, and why:

* One client (one connection) per PLC. The client's lock keeps one request in flight per
  connection, so replies are never mixed up; the consumer's writes go through the same client and
  simply take the next turn.
* Every scan group is scheduled and completed one way (:mod:`.scanner`): a plan of one request
  on a client that can start reads without awaiting (E71) runs as callbacks (the shared timer
  starts the request, the transport hands the answer back, and the sample is queued in the same
  loop pass, with no task step and no future per request); anything else (connecting, a
  request queued behind a write, a scan of several requests, a client that only awaits) runs
  that scan awaited in a task of its own.
* An optional cap bounds how many requests are in flight across all PLCs (``poll.concurrency``;
  no cap by default, since a cap lets enough hung PLCs, each holding a slot for a whole
  deadline, delay the healthy ones). A slot (:class:`~plcstack.clients.flight.Slots`, FIFO) is
  held only around one request, never while a scan waits for its time, so a dead PLC costs a slot
  for at most one connect attempt, and while its client backs off, its requests fail at once.
  A callback scan takes a free slot without waiting; when none is free, that scan runs
  awaited, queued for a slot in arrival order. So a cap keeps the callback scans.
* When a request fails on the connection (timeout, connection lost, connect failed), the rest of
  that scan is not attempted: those tags get the same error, and a slow PLC costs one deadline
  per scan instead of one per request.
* A scan that runs past its next due time is not queued: the missed ticks are counted as overruns
  and the schedule moves to the next tick in the future.
* Scans wait in a bounded buffer (:class:`~plcstack.poll.samples.ScanQueue`, ``poll.queue``
  samples) for the consumer; when it is full, the oldest scans are dropped whole and their
  samples counted (per PLC and in total). Nothing is dropped silently. Several pollers may
  share one buffer (the scale-out worker).
* A merged request that the PLC rejects with an error code (e.g. a gap that crosses the end of a
  data block) is not retried in that scan; from the next scan on, its tags are read separately so
  one bad address does not blank its neighbours.

Cost (``plcstack bench``, the fleet case): with a thousand E71 PLCs at 10 Hz the poller
spends about what a raw asyncio loop spends on the same requests once that loop also turns each
reply into its words as Python ints; the rest of the difference to a loop that keeps the bytes is
allocating those ints. The north side takes scans in batches gathered for ``poll.batch_wait``
(a consumer woken once per loop pass cost more than the requests). The poller never touches
global GC settings.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from typing import Any, Self

from plcstack.clients import connect
from plcstack.clients.base import Client
from plcstack.clients.flight import ConnectTurns, Slots
from plcstack.errors import AddressError, LocalProtocolError, PlcError
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.diff import PlcChanges, plc_changes
from plcstack.poll.plan import ScanPlan, TagPlan, build_plan, encode_tag
from plcstack.poll.samples import Quality, Sample, Scan, ScanQueue, flatten
from plcstack.poll.scanner import GroupState, PlcState, Scanner
from plcstack.poll.stats import LATENCY_WINDOW, LatencyWindow, PlcStats, format_stats
from plcstack.poll.ticker import Ticker
from plcstack.resource import AsyncResource
from plcstack.transports.backoff import Backoff

_log = logging.getLogger(__name__)

__all__ = [
    "LATENCY_WINDOW",
    "Applied",
    "LatencyWindow",
    "PlcStats",
    "Poller",
    "Quality",
    "Sample",
    "Scan",
    "ScanQueue",
    "format_stats",
    "timer_resolution",
]

ClientFactory = Callable[[PlcConfig], Client]

#: Connects one poller lets run at once, and how long one may hold its turn (see
#: :class:`~plcstack.clients.flight.ConnectTurns`). Measured with 10,000 E71 PLCs at 1 Hz on a
#: loaded two-core machine: unspaced, every first connect timed out after 3 s; 500 at once, 412
#: of them did; 100 at once, none. A LAN connect takes milliseconds, so a turn held for half a
#: second is a peer that does not answer, not a busy loop.
CONNECTS_AT_ONCE = 100
CONNECT_TURN_HOLD = 0.5


def new_connect_turns() -> ConnectTurns:
    """A fresh set of connect turns for the pollers of one event loop (see CONNECTS_AT_ONCE)."""
    return ConnectTurns(CONNECTS_AT_ONCE, CONNECT_TURN_HOLD)


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


@dataclasses.dataclass(frozen=True)
class Applied:
    """What :meth:`Poller.apply` did, by PLC name."""

    added: tuple[str, ...] = ()
    #: each removed PLC's last statistics (its connection is closed)
    removed: Mapping[str, PlcStats] = dataclasses.field(default_factory=dict)
    reconnected: tuple[str, ...] = ()
    replanned: tuple[str, ...] = ()
    #: ``[poll]`` keys of the whole poller that changed and take effect at the next start
    not_applied: tuple[str, ...] = ()
    #: how long the apply took (seconds, wall clock: closing connections is waited for)
    seconds: float = 0.0


def _plans(
    plc: PlcConfig, client: Client, intervals: Mapping[str, float]
) -> tuple[list[GroupState], dict[str, TagPlan]]:
    """The scan groups of ``plc`` (a plan per group with tags) on ``client``, and each tag's
    plan; :class:`AddressError` naming the PLC for an address the client refuses."""
    groups: list[GroupState] = []
    tags: dict[str, TagPlan] = {}
    for name, interval in intervals.items():
        members = tuple(t for t in plc.tags if t.group == name)
        if not members:
            continue
        try:
            plan = build_plan(client, members, max_gap=plc.max_gap)
        except AddressError as exc:
            exc.plc = plc.name
            raise
        groups.append(GroupState(name, interval, members, plan))
        for tag_plan in plan.tags:
            tags[tag_plan.tag.name] = tag_plan
    return groups, tags


class Poller(AsyncResource):
    """Polls every PLC of a :class:`PollConfig`: :meth:`scans` for :class:`Scan` objects, or
    iterate over it for their :class:`Sample` objects one by one.

    Clients and read plans are built in the constructor, so every bad URL or address raises
    :class:`AddressError` (naming PLC and tag) before anything is sent. ``client_factory`` builds
    the client of one PLC (tests pass in-memory fakes; the default is :func:`plcstack.connect`).
    Its clients connect ``CONNECTS_AT_ONCE`` at a time (``connect_turns``: turns shared with
    other pollers in the same event loop).
    """

    def __init__(
        self,
        config: PollConfig,
        *,
        client_factory: ClientFactory | None = None,
        queue: ScanQueue | None = None,
        connect_turns: ConnectTurns | None = None,
    ) -> None:
        self.config = config
        #: builds the client of a PLC (at start and for the PLCs a reload adds)
        self._factory = factory = client_factory or default_client_factory
        #: where the scans go (``queue``: one shared with other pollers)
        self.queue = queue if queue is not None else ScanQueue(config.queue)
        #: the concurrency cap's slots (``poll.concurrency``), shared by both kinds of scan
        self._slots: Slots | None = (
            Slots(config.concurrency) if config.concurrency is not None else None
        )
        #: the turns its clients connect in (see CONNECTS_AT_ONCE; ``connect_turns``: turns
        #: shared with other pollers of the same event loop)
        self._connects = connect_turns if connect_turns is not None else new_connect_turns()
        self._resolution = 0.0  # the running loop's timer resolution, set by start()
        self._ticker: Ticker | None = None  # set by start()
        self._running = False
        self._closed = False
        self._plcs: dict[str, PlcState] = {}
        try:
            for plc_config in config.plcs:
                self._plcs[plc_config.name] = self._prepare(plc_config, factory)
        except BaseException:
            for plc in self._plcs.values():
                plc.client.transport.abort()
            raise

    def _prepare(
        self,
        plc: PlcConfig,
        factory: ClientFactory,
        intervals: Mapping[str, float] | None = None,
        stats: PlcStats | None = None,
    ) -> PlcState:
        """A PLC's client (not connected) and plans; ``stats``: the counters it goes on with."""
        try:
            client = factory(plc)
        except AddressError as exc:
            raise AddressError(exc.message, plc=plc.name, request=exc.request) from None
        try:
            groups, tags = _plans(
                plc, client, self.config.groups if intervals is None else intervals
            )
        except BaseException:
            client.transport.abort()
            raise
        stats = stats if stats is not None else PlcStats()
        self.queue.count_drops(plc.name, stats)
        client.connect_turns = self._connects
        return PlcState(plc, client, groups, stats, tags, plc.order, client.byte_order)

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
        self._begin(list(self._plcs.values()))

    def _begin(self, plcs: list[PlcState]) -> None:
        """Start scanning ``plcs``, their first scans spread over an interval (at most a
        second) so hundreds of PLCs configured alike do not all send in the same millisecond,
        every interval."""
        assert self._ticker is not None  # started
        now = time.perf_counter()
        count = len(plcs)
        for i, plc in enumerate(plcs):
            for group in plc.groups:
                spread = min(group.interval, 1.0)
                group.next_due = now + spread * (i / count if count > 1 else 0.0)
        for plc in plcs:
            self._scan(plc)

    def _scan(self, plc: PlcState) -> None:
        """Start a scanner for each of ``plc``'s groups, on their ``next_due``."""
        assert self._ticker is not None  # started
        plc.scanners = [Scanner(plc, g, self._ticker, self.queue, self._slots) for g in plc.groups]
        for scanner in plc.scanners:
            scanner.start()

    async def aclose(self) -> None:
        """Stop polling, close every connection; iteration ends after the buffered samples."""
        if self._closed:
            return
        self._closed = True
        self._update_connection_stats()  # what the last clients counted, kept after closing
        await asyncio.gather(*(self._close(plc) for plc in self._plcs.values()))
        if self._ticker is not None:
            self._ticker.close()
        self._update_connection_stats()
        self.queue.wake()

    async def _close(self, plc: PlcState) -> None:
        """Stop ``plc``'s scans and close its connection (a request in flight dies with it, as
        a cancelled read does); never raises."""
        tasks = [t for s in (*plc.scanners, *plc.retired) if (t := s.close()) is not None]
        plc.client.abandon_exchange()
        await asyncio.gather(*tasks, return_exceptions=True)
        try:
            await plc.client.aclose()
        except Exception as exc:  # its connection is gone either way
            _log.warning("%s: closing its connection failed: %s", plc.config.name, exc)

    # -- reconfigured while it runs ---------------------------------------------------------
    async def apply(self, changes: PlcChanges) -> Applied:
        """Change the PLCs while polling, as ``changes`` (:func:`~plcstack.poll.diff.plc_changes`
        of this poller's configuration and the new one) says; returns what happened.

        Added PLCs start scanning. Removed PLCs stop: their scans end, their connections close,
        and their last statistics are in the result. A PLC whose URL or a connection option
        changed closes its connection and opens one to the new URL, its counters going on. A PLC
        whose tags or groups changed is planned again on its open connection: its scanners of
        the old plan end (a request in flight is never cut) and the new ones go on from their
        group's next scan. Every other PLC keeps its connection and its schedule.

        Every new client and plan is built before anything changes: an address that cannot be
        planned raises :class:`AddressError` and the poller goes on as it was. ``[poll]`` keys
        of the whole poller (``concurrency``, ``queue``, ``batch_wait``) are not changed while
        it runs: they are named in :attr:`Applied.not_applied`.
        """
        if self._closed:
            raise LocalProtocolError(
                "the poller is closed: start a new one with the new configuration"
            )
        if changes.old != self.config:
            raise LocalProtocolError(
                "these changes were made from another configuration than the poller's:"
                " make them with plc_changes(poller.config, new)"
            )
        started = time.perf_counter()
        new = changes.new
        current = self._plcs
        # everything that can fail, before anything changes
        fresh: dict[str, PlcState] = {}
        plans: dict[str, tuple[list[GroupState], dict[str, TagPlan]]] = {}
        try:
            for plc in changes.added:
                fresh[plc.name] = self._prepare(plc, self._factory, new.groups)
            for plc in changes.reconnected:
                stats = current[plc.name].stats
                fresh[plc.name] = self._prepare(plc, self._factory, new.groups, stats)
            for plc in changes.replanned:
                plans[plc.name] = _plans(plc, current[plc.name].client, new.groups)
        except BaseException:
            for state in fresh.values():
                state.client.transport.abort()
            raise
        self.config = new
        # planned again on the open connection: the old scanners end, the new take their time
        for plc in changes.replanned:
            old = current[plc.name]
            groups, tags = plans[plc.name]
            state = PlcState(
                plc, old.client, groups, old.stats, tags, plc.order, old.byte_order,
                connects_before=old.connects_before, failures_before=old.failures_before,
            )  # fmt: skip
            self._take_over(old, state)
            current[plc.name] = state
        # removed, and reconnected: the old connection closes before the new one opens
        closing = [current[p.name] for p in (*changes.removed, *changes.reconnected)]
        self._update_connection_stats()
        await asyncio.gather(*(self._close(plc) for plc in closing))
        removed = {p.name: current.pop(p.name).stats for p in changes.removed}
        for plc in changes.removed:
            self.queue.forget(plc.name)
        for plc in changes.reconnected:
            old = current[plc.name]
            state = fresh[plc.name]
            state.connects_before = old.connects_before + old.client.stats.connects
            state.failures_before = old.failures_before + old.client.stats.connect_failures
            current[plc.name] = state
        for plc in changes.added:
            current[plc.name] = fresh[plc.name]
        self._plcs = {p.name: current[p.name] for p in new.plcs}
        if self._running:
            self._begin([fresh[p.name] for p in (*changes.reconnected, *changes.added)])
        return Applied(
            added=tuple(p.name for p in changes.added),
            removed=removed,
            reconnected=tuple(p.name for p in changes.reconnected),
            replanned=tuple(p.name for p in changes.replanned),
            not_applied=changes.poller,
            seconds=time.perf_counter() - started,
        )

    async def reconfigure(self, config: PollConfig) -> Applied:
        """:meth:`apply` of the changes from this poller's configuration to ``config``."""
        return await self.apply(plc_changes(self.config, config))

    def _take_over(self, old: PlcState, new: PlcState) -> None:
        """``new``'s scanners take over from ``old``'s on the same connection: a group of the
        same name keeps its next scan (the one after, if the old scanner's request is in flight
        now: that scan is delivered), a new group starts at once."""
        new.retired = [s for s in (*old.retired, *old.scanners) if not s.ended]
        if not self._running:
            return
        now = time.perf_counter()
        before = {g.name: (g, s) for g, s in zip(old.groups, old.scanners, strict=True)}
        for group in new.groups:
            due = now
            if group.name in before:
                was, scanner = before[group.name]
                due = was.next_due + (group.interval if scanner.busy else 0.0)
                due = min(due, now + group.interval)
            group.next_due = due
        for scanner in old.scanners:
            scanner.retire()
        self._scan(new)

    async def aopen(self) -> None:
        await self.start()

    # -- scans and samples ------------------------------------------------------------------
    def scans(self, wait: float = 0.0) -> AsyncIterator[list[Scan]]:
        """Every completed scan, as lists: all that is buffered at each wake-up (never an empty
        list); ends once the poller is closed and the buffer is empty.

        What the north side consumes: one wake-up and one list per event-loop pass instead of
        one step per sample (at 1000 PLCs, 10 Hz: 10,000 coroutine steps a second). ``wait``
        (seconds) lets a batch gather for that long after its first scan: fewer, larger
        batches (a historian or a broker sink loses nothing by a few milliseconds; the samples
        keep their own times). Keep it well below the time the buffer (``poll.queue`` samples)
        takes to fill, or the oldest scans are dropped (and counted).
        """
        return self.queue.batches(wait, self._ended)

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> Sample:
        """The samples of :meth:`scans`, one at a time."""
        return await self.queue.next_sample(self._ended)

    def _ended(self) -> bool:
        return self._closed

    async def batches(self, wait: float = 0.0) -> AsyncIterator[list[Sample]]:
        """The samples of :meth:`scans`, each list of scans flattened into one list of their
        samples, in the order ``async for sample in poller`` gives them (for consumers that
        want samples and no grouping)."""
        async for scans in self.queue.batches(wait, self._ended):
            yield flatten(scans)

    def pending(self) -> int:
        """Samples buffered and not yet taken by the consumer."""
        return len(self.queue)

    def drain(self) -> list[Scan]:
        """Take every buffered scan at once (what is left after the poller was closed)."""
        return self.queue.drain()

    @property
    def dropped(self) -> int:
        """Samples dropped because the buffer was full (of every poller sharing it); a full
        buffer drops whole scans, each counting its samples."""
        return self.queue.dropped

    # -- statistics -------------------------------------------------------------------------
    def _update_connection_stats(self) -> None:
        for plc in self._plcs.values():
            cs = plc.client.stats
            plc.stats.reconnects = max(0, plc.connects_before + cs.connects - 1)
            plc.stats.connect_failures = plc.failures_before + cs.connect_failures

    @property
    def stats(self) -> dict[str, PlcStats]:
        """Per-PLC statistics (live objects; connection counters refreshed on access)."""
        self._update_connection_stats()
        return {name: plc.stats for name, plc in self._plcs.items()}

    # -- writes -----------------------------------------------------------------------------
    def _plc(self, name: str) -> PlcState:
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


def timer_resolution(loop: asyncio.AbstractEventLoop) -> float:
    """Below this delay a loop's timer fires in its next pass anyway, so the poller does not sleep.

    asyncio's own loops treat timers due within the monotonic clock's resolution as ready
    (``BaseEventLoop._run_once``); other loops (uvloop: libuv) keep millisecond timers.
    """
    if isinstance(loop, asyncio.BaseEventLoop):
        return time.get_clock_info("monotonic").resolution
    return 1e-3
