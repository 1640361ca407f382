"""The scan driver: every scan group of every PLC is scheduled and completed here, one way.

One :class:`Scanner` per group puts its next scan on the poller's :class:`Ticker` (one loop
timer for every PLC). When the scan is due:

* a plan of one request, on a client that can start it without waiting
  (``Client.start_read``: E71 with the lock free, the connection quiet, the read checked once
  before), starts it in the timer callback and gets the result in a callback from the
  transport: no task, no coroutine and no future per scan. At a thousand PLCs at 10 Hz that is
  what keeps the poller near a raw asyncio loop (the fleet case of ``plcstack bench``);
* anything else (connecting, a request queued behind a write, a plan of several requests) runs
  that scan's requests awaited, in a task of its own;
* a client that cannot start reads (S5-LAN, FETCH/WRITE, AS511) has one task per group that
  waits on the ticker and awaits each scan's requests: no task per scan.

Either way the scan ends in the same steps: it goes to the :class:`ScanQueue` as one
:class:`Scan` (PLC, group, times, a sample per tag), a
failed request is accounted once (:func:`account_failure`, which also isolates the tags of a
merged request the PLC refused), and the next scan goes on the ticker (:func:`advance`: missed
ticks are counted as overruns, never queued up).

Under a concurrency cap (``poll.concurrency``) a callback scan takes a slot without waiting
(``Slots.try_acquire``, which never succeeds while anyone waits, so it cannot overtake the
queue) and gives it back when its answer arrives; with no slot free the scan runs awaited and
queues for one.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

from plcstack.clients.base import Client
from plcstack.clients.flight import Slots
from plcstack.errors import AddressError, ConnectionLost, PlcError, PlcErrorResponse, PlcTimeout
from plcstack.poll.config import PlcConfig, TagConfig
from plcstack.poll.plan import ScanPlan, TagPlan, build_plan, describe
from plcstack.poll.samples import Quality, Sample, Scan, ScanQueue, make_sample
from plcstack.poll.stats import PlcStats
from plcstack.poll.ticker import Ticker
from plcstack.values import ByteOrder, Endian, WordOrder

__all__ = ["GroupState", "PlcState", "Scanner", "account_failure", "advance"]

_log = logging.getLogger(__name__)
#: the schedule's clock and the samples' wall clock: one ``time.time()`` per scan; each request
#: is timed with ``perf_counter`` (its latency), and its Unix send/receive times are that
#: ``time.time()`` plus ``perf_counter`` offsets, so ``receive_time >= source_time`` even if
#: the wall clock steps
_clock = time.perf_counter
_wall_clock = time.time
_GOOD, _BAD = Quality.GOOD, Quality.BAD
#: ``Scan(...)`` without the named tuple's ``__new__`` (a Python function): the same object
_new_tuple = tuple.__new__


@dataclass(slots=True)
class GroupState:
    """One scan group of one PLC: its tags, its current read plan and its schedule."""

    name: str
    interval: float
    tags: tuple[TagConfig, ...]
    plan: ScanPlan
    next_due: float = 0.0
    #: tags read separately since the PLC refused a merged request of theirs
    isolate: frozenset[str] = frozenset()


@dataclass(slots=True)
class PlcState:
    """One PLC of a poller: its client, groups, statistics and tag plans."""

    config: PlcConfig
    client: Client
    groups: list[GroupState]
    stats: PlcStats
    tags: dict[str, TagPlan]  # name -> the tag's plan (point bits, bit of a word)
    order: WordOrder = Endian.BIG
    byte_order: ByteOrder = Endian.BIG
    scanners: list[Scanner] = field(default_factory=list)
    #: scanners of earlier plans still ending a scan on this connection (a reload planned
    #: the PLC again): closed with it
    retired: list[Scanner] = field(default_factory=list)
    #: connections and failed connects of the clients this PLC had before its current one
    #: (a reload that changed its URL): the counters go on, never back
    connects_before: int = 0
    failures_before: int = 0


def advance(stats: PlcStats, group: GroupState, end: float) -> None:
    """Move ``group``'s schedule past a scan that ended at ``end``: to its next tick, or, when
    the scan ran past that, to the first tick in the future, counting the missed ones as
    overruns (missed scans are never queued up)."""
    interval = group.interval
    next_due = group.next_due + interval
    if next_due <= end:
        missed = int((end - next_due) // interval) + 1
        stats.overruns += missed
        next_due += missed * interval
    group.next_due = next_due


def account_failure(
    plc: PlcState, group: GroupState, plan: ScanPlan, index: int, exc: Exception
) -> PlcError:
    """Account for a failed request of a scan; returns the error bound to PLC and request.

    A merged request that the PLC rejects with an error code has its tags read separately
    from the next scan on, so one bad address does not blank its neighbours.
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


class Scanner:
    """The scans of one group of one PLC, on the poller's :class:`Ticker`.

    ``start`` puts the first scan on the ticker; from then on every scan puts the next one there
    when it has ended, so a group never has two scans at once. ``close`` stops it: a scan
    waiting on the ticker never runs, an awaited scan in progress is cancelled (the caller
    awaits what ``close`` returns), and the poller abandons a callback request in flight; that
    request's slot of the concurrency cap is given back at once, since its ``done`` will never
    come. ``retire`` stops it on a connection that stays open (a reload planned the group
    again): no next scan, but a request in flight is never cut (cutting it would cost the
    connection), and the scan it belongs to is delivered.
    """

    __slots__ = (
        "_address",
        "_busy",
        "_closed",
        "_count",
        "_done_cb",
        "_fire_cb",
        "_group",
        "_group_name",
        "_holding",
        "_items",
        "_keep",
        "_limit",
        "_name",
        "_offset",
        "_plan",
        "_plc",
        "_queue",
        "_size",
        "_slots",
        "_start",
        "_start_read",
        "_stats",
        "_task",
        "_ticker",
        "_wake",
        "_whole",
    )

    def __init__(
        self,
        plc: PlcState,
        group: GroupState,
        ticker: Ticker,
        queue: ScanQueue,
        slots: Slots | None,
    ) -> None:
        self._plc = plc
        self._group = group
        self._group_name = group.name
        self._ticker = ticker
        self._queue = queue
        self._items = queue.items
        self._limit = queue.limit
        self._wake = queue.wake
        self._stats = plc.stats
        self._name = plc.config.name
        client = plc.client
        self._start_read = client.start_read if client.callback_reads else None
        self._use(group.plan)
        self._start = 0.0  # its perf_counter send time, and the offset to Unix time
        self._offset = 0.0
        self._task: asyncio.Task[None] | None = None
        self._closed = False
        #: a request of this scanner is in flight (cutting it would cost the connection)
        self._busy = False
        #: closed by ``retire``: the scan in flight is still delivered
        self._keep = False
        #: the concurrency cap's slots, and whether this scanner's callback request holds one
        #: (so that ``done``, a refusal, a raising ``start_read`` and ``close`` give it back
        #: exactly once between them)
        self._slots = slots
        self._holding = False
        # bound once: a bound method made per scan would be one more object per request
        self._fire_cb = self._fire
        self._done_cb = self._done

    def start(self) -> None:
        if self._start_read is None:  # a client that only awaits: one task for every scan
            self._task = asyncio.get_running_loop().create_task(self._awaited_scans())
        else:
            self._ticker.call_at(self._group.next_due, self._fire_cb)

    def close(self) -> asyncio.Task[None] | None:
        """Stop scanning; returns the awaited scan in progress (cancelled), if any."""
        self._closed = True
        self._keep = False
        self._give_back()
        task = self._task
        if task is not None:
            task.cancel()
        return task

    def retire(self) -> asyncio.Task[None] | None:
        """Stop scanning on a connection that stays open: no next scan; a scan waiting for its
        time is cancelled, one with a request in flight ends and is delivered. Returns the
        task still running, if any (it ends by itself)."""
        self._closed = self._keep = True
        task = self._task
        if task is not None and not self._busy:
            task.cancel()  # waiting on the ticker or for a slot: nothing is cut
        return task

    @property
    def busy(self) -> bool:
        """Whether a request of this scanner is in flight."""
        return self._busy

    @property
    def ended(self) -> bool:
        """Closed or retired, with nothing in flight and no task left."""
        return self._closed and not self._busy and (self._task is None or self._task.done())

    def _use(self, plan: ScanPlan) -> None:
        """Take what ``_fire`` and ``_done`` need of ``plan`` once, not on every scan: the
        plan changes only when a tag is isolated after a PLC error."""
        #: the plan of the callback request in flight (the group's may change meanwhile)
        self._plan = plan
        requests = plan.requests
        #: the one request's size (0: several), and its address and count for a callback
        #: scan (count 0: not a plan for one)
        self._size = requests[0].count if len(requests) == 1 else 0
        if self._size and self._start_read is not None:
            self._address, self._count = requests[0].address, requests[0].count
        else:
            self._address, self._count = "", 0
        #: the tag whose sample is the whole reply (``ScanPlan.whole_tag``), or None
        self._whole = plan.whole_tag

    # -- the callback scan ----------------------------------------------------------------------
    def _fire(self) -> None:
        """The scan is due (the ticker's callback): start its request, or its awaited scan."""
        if self._closed:
            return
        plan = self._group.plan
        if plan is not self._plan:
            self._use(plan)
        slots = self._slots
        if self._count and (slots is None or self._take_slot(slots)):
            wall = _wall_clock()
            self._start = start = _clock()
            self._offset = wall - start
            self._busy = True
            try:
                started = self._start_read(self._address, self._count, self._done_cb)  # type: ignore[misc]  # count: set
            except Exception as exc:  # a client bug: this scan's failure, as a read's would be
                self._stats.scans += 1
                self._done(exc)
                return
            if started:
                self._stats.scans += 1
                return
            self._busy = False
            self._give_back()  # nothing was sent: the awaited scan waits for a slot itself
        self._task = asyncio.get_running_loop().create_task(self._scan_task())

    def _done(self, reply: Sequence[int | bool] | Exception) -> None:
        """The callback request's result (``start_read``'s ``done``)."""
        end = _clock()
        # The request is over: its slot goes back before the samples are delivered, as in an
        # awaited scan, so a scan waiting for a slot is not held up by delivery, and a
        # delivery that fails cannot keep the slot.
        if self._holding:  # tested here: no call per request without a cap
            self._give_back()
        self._busy = False
        if self._closed:
            if self._keep:  # retired: the scan is delivered, no next one
                self._complete(reply, self._start, end, self._offset)
            return
        self._complete(reply, self._start, end, self._offset)
        self._ticker.call_at(self._group.next_due, self._fire_cb)

    def _complete(
        self, reply: Sequence[int | bool] | Exception, start: float, end: float, offset: float
    ) -> None:
        """End a scan of one request: the scan queued, its schedule moved past ``end``.
        ``start``/``end`` are ``perf_counter`` times, ``offset`` makes them Unix times."""
        stats = self._stats
        try:
            whole = self._whole
            if whole is not None and type(reply) is list and len(reply) == self._size:
                # the usual poll: the one tag is the whole reply, handed out as it is
                stats.latencies.append(end - start)
                stats.requests += 1
                name = self._name
                source = start + offset
                receive = end + offset
                self._items.append(
                    _new_tuple(Scan, (name, self._group_name, source, receive,
                               (make_sample(name, whole, reply, _GOOD, source, receive, None),)))
                )  # fmt: skip
                stats.samples += 1
                queue = self._queue
                held = queue.held + 1
                queue.held = held
                if held > self._limit:
                    queue.trim()
                self._wake()
            elif isinstance(reply, Exception):
                error = account_failure(self._plc, self._group, self._plan, 0, reply)
                self._deliver(self._plan, (error,), start + offset, end + offset, None, None)
            else:
                stats.latencies.append(end - start)
                stats.requests += 1
                self._deliver(self._plan, (reply,), start + offset, end + offset, None, None)
        except Exception:  # a bug must not end this group's scans
            _log.exception("%s: delivering a scan failed", self._name, extra={"plc": self._name})
        group = self._group
        interval = group.interval
        next_due = group.next_due + interval
        if next_due <= end:  # ``advance``, spelled out on the polling path
            missed = int((end - next_due) // interval) + 1
            stats.overruns += missed
            next_due += missed * interval
        group.next_due = next_due

    def _take_slot(self, slots: Slots) -> bool:
        """Take a slot for a callback request if one is free without waiting."""
        if slots.try_acquire():
            self._holding = True
            return True
        return False

    def _give_back(self) -> None:
        """Give the callback request's slot back, if it holds one (at most once)."""
        slots = self._slots
        if self._holding and slots is not None:
            self._holding = False
            slots.release()

    # -- the awaited scan -----------------------------------------------------------------------
    async def _awaited_scans(self) -> None:
        """Every scan of a client that only awaits, in this one task: wait for the scan's time
        on the ticker, run it, again."""
        ticker, group = self._ticker, self._group
        while not self._closed:
            await ticker.wait_until(group.next_due)
            plan = group.plan
            if plan is not self._plan:
                self._use(plan)
            if self._size:  # the usual scan: completed as a callback scan is
                request = plan.requests[0]
                self._stats.scans += 1
                slots = self._slots
                if slots is not None:
                    await slots.acquire()
                wall = _wall_clock()
                start = _clock()
                self._busy = True
                try:
                    reply: Sequence[int | bool] | Exception = await self._plc.client.read(
                        request.address, request.count
                    )
                except Exception as exc:
                    reply = exc
                finally:
                    self._busy = False
                    if slots is not None:
                        slots.release()
                self._complete(reply, start, _clock(), wall - start)
                continue
            self._busy = True
            try:
                await self.scan()
            except Exception:  # scan turns read failures into samples: this is a bug
                _log.exception("%s: a scan failed", self._name, extra={"plc": self._name})
            finally:
                self._busy = False
            advance(self._stats, group, _clock())

    async def _scan_task(self) -> None:
        """One scan with its requests awaited, then the next on the ticker."""
        self._busy = True
        try:
            await self.scan()
        except Exception:  # scan turns read failures into samples: this is a bug
            _log.exception("%s: a scan failed", self._name, extra={"plc": self._name})
        finally:
            self._busy = False
        self._task = None
        if not self._closed:
            group = self._group
            advance(self._stats, group, _clock())
            self._ticker.call_at(group.next_due, self._fire_cb)

    async def scan(self) -> bool:
        """One scan of the group, each request of its plan awaited; returns whether one
        failed. When a request fails on the connection (timeout, connection lost), the rest of
        the scan is not attempted: those tags get the same error, and a slow PLC costs one
        deadline per scan instead of one per request."""
        plc, group = self._plc, self._group
        plan = group.plan
        stats = plc.stats
        client = plc.client
        slots = self._slots
        count = len(plan.requests)
        replies: list[Sequence[int | bool] | PlcError] = []
        sent: list[float] = []
        received: list[float] = []
        give_up: PlcError | None = None
        failed = False
        stats.scans += 1
        offset = _wall_clock() - _clock()
        for index, request in enumerate(plan.requests):
            if give_up is not None:
                now = _clock() + offset
                replies.extend([give_up] * (count - index))
                sent.extend([now] * (count - index))
                received.extend([now] * (count - index))
                break
            if slots is not None:
                await slots.acquire()
            start = _clock()
            try:
                points = await client.read(request.address, request.count)
            except Exception as exc:
                error = account_failure(plc, group, plan, index, exc)
                failed = True
            else:
                end = _clock()
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
            received.append(_clock() + offset)
            if isinstance(error, PlcTimeout | ConnectionLost):
                give_up = error
        self._deliver(plan, replies, 0.0, 0.0, sent, received)
        return failed

    # -- the scan out ---------------------------------------------------------------------------
    def _deliver(
        self,
        plan: ScanPlan,
        replies: Sequence[Sequence[int | bool] | PlcError],
        source: float,
        receive: float,
        sent: list[float] | None,
        received: list[float] | None,
    ) -> None:
        """Queue one scan; times are Unix seconds, per request when several (the scan's are
        its first send and its last answer)."""
        plc = self._plc
        name = self._name
        order = plc.order
        extract = plan.extract
        samples: list[Sample] = []
        append = samples.append
        bad = 0
        if sent is not None and received is not None:
            first, last = min(sent), max(received)
        else:
            first, last = source, receive
        for tag_plan in plan.tags:
            if sent is not None and received is not None:
                ids = tag_plan.request_ids
                source = min(sent[r] for r in ids)
                receive = max(received[r] for r in ids)
            result = extract(tag_plan, replies, order)
            if isinstance(result, PlcError):
                bad += 1
                append(
                    make_sample(
                        name, tag_plan.tag.name, None, _BAD, source, receive, str(result),
                        type(result),
                    )
                )  # fmt: skip
            else:
                append(make_sample(name, tag_plan.tag.name, result, _GOOD, source, receive, None))
        self._items.append(Scan(name, self._group_name, first, last, tuple(samples)))
        stats = plc.stats
        stats.samples += len(samples)
        stats.bad_samples += bad
        queue = self._queue
        queue.held += len(samples)
        if queue.held > self._limit:
            queue.trim()
        self._wake()
