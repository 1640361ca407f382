"""Callback-driven scans: one scan group of one PLC without a task.

A PLC task spends, per scan of one request, two task steps (woken by its timer, then by the
answer) and two futures, on top of what the request itself costs; with a thousand PLCs at 10 Hz
that was the largest share of the poller's excess over a raw asyncio loop. A
:class:`Scanner` instead starts the request in the ticker's timer callback
(``Client.start_read``) and receives the result in a callback from the transport's
``buffer_updated``: the sample is queued and the next scan put on the ticker in the same loop
pass that received the answer.

Only the plain case runs this way: a group whose plan is one request, which the client can send
at once (lock free, connection open and quiet, codec settled, the read done once before).
Everything else (connecting, a stale-input check, a request queued behind a write, a plan of
several requests) runs that scan through the task path's own code (``Poller._scan_group``) in a
task of its own, and the next scan is tried the quick way again. Both paths deliver through
``Poller._single_done`` and schedule through :func:`advance`: tests/test_scanner.py compares
them sample for sample.

Under a concurrency cap (``poll.concurrency``) a callback scan takes one of the poller's slots
with :meth:`~plcstack.clients.flight.Slots.try_acquire` before it starts its request and gives
it back when the answer (or the failure) arrives. When no slot is free, the scan runs on the
task path, which awaits a slot behind the scans already waiting: ``try_acquire`` never succeeds
while anyone waits, so the callback scans cannot overtake that queue, and the cap holds across
both paths.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

from plcstack.clients.flight import Slots
from plcstack.poll.stats import PlcStats
from plcstack.poll.ticker import Ticker

if TYPE_CHECKING:
    from plcstack.poll.engine import Poller, _Group, _Plc
    from plcstack.poll.plan import ScanPlan

__all__ = ["Scanner", "advance"]

_log = logging.getLogger(__name__)
#: the schedule's clock and the samples' wall clock (see Poller: one time.time() per scan)
_clock = time.perf_counter
_wall_clock = time.time


class _Scheduled(Protocol):
    interval: float
    next_due: float


def advance(stats: PlcStats, group: _Scheduled, end: float) -> None:
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


class Scanner:
    """The scans of one group of one PLC, on the poller's :class:`Ticker`.

    ``start`` puts the first scan on the ticker; from then on every scan puts the next one there
    when it has ended, so a group never has two scans at once. ``close`` stops it: a scan
    waiting on the ticker never runs, a task-path scan in progress is cancelled (the caller
    awaits what ``close`` returns), and the poller abandons a callback request in flight;
    that request's slot of the concurrency cap is given back at once, since its ``done`` will
    never come.
    """

    __slots__ = (
        "_address",
        "_closed",
        "_count",
        "_done_cb",
        "_fire_cb",
        "_group",
        "_holding",
        "_name",
        "_offset",
        "_plan",
        "_plc",
        "_poller",
        "_single",
        "_slots",
        "_start",
        "_start_read",
        "_stats",
        "_task",
        "_ticker",
        "_whole",
    )

    def __init__(self, poller: Poller, plc: _Plc, group: _Group, ticker: Ticker) -> None:
        self._poller = poller
        self._plc = plc
        self._group = group
        self._ticker = ticker
        self._stats = plc.stats
        self._name = plc.config.name
        #: the poller's switch, read when scanning starts (as its tasks read it)
        self._single = poller.inline_single_request
        self._start_read = plc.client.start_read
        self._use(group.plan)
        self._start = 0.0  # its perf_counter send time, and the offset to Unix time
        self._offset = 0.0
        self._task: asyncio.Task[None] | None = None
        self._closed = False
        #: the concurrency cap's slots, and whether this scanner's callback request holds one
        #: (so that ``done``, a refusal, a raising ``start_read`` and ``close`` give it back
        #: exactly once between them)
        self._slots = poller._slots
        self._holding = False
        # bound once: a bound method made per scan would be one more object per request
        self._fire_cb = self._fire
        self._done_cb = self._done

    def start(self) -> None:
        self._ticker.call_at(self._group.next_due, self._fire_cb)

    def close(self) -> asyncio.Task[None] | None:
        """Stop scanning; returns the task-path scan in progress (cancelled), if any."""
        self._closed = True
        self._give_back()
        task = self._task
        if task is not None:
            task.cancel()
        return task

    def _use(self, plan: ScanPlan) -> None:
        """Take what ``_fire`` and ``_done`` need of ``plan`` once, not on every scan: the
        plan changes only when the poller isolates a tag after a PLC error."""
        #: the plan of the callback request in flight (the group's may change meanwhile)
        self._plan = plan
        requests = plan.requests
        #: the one request's address and count; count 0: not a plan for a callback scan
        if len(requests) == 1 and self._single:
            self._address, self._count = requests[0].address, requests[0].count
        else:
            self._address, self._count = "", 0
        #: the tag whose sample is the whole reply (``Poller._whole_reply``), or None
        self._whole = plan.whole_tag if self._poller.whole_reply_samples else None

    def _fire(self) -> None:
        """The scan is due (the ticker's callback): start its request, or its task."""
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
            try:
                started = self._start_read(self._address, self._count, self._done_cb)
            except Exception as exc:  # a client bug: this scan's failure, as a read's would be
                self._stats.scans += 1
                self._done(exc)
                return
            if started:
                self._stats.scans += 1
                return
            self._give_back()  # nothing was sent: the task path awaits a slot of its own
        self._task = asyncio.get_running_loop().create_task(self._scan_task())

    def _done(self, reply: Sequence[int | bool] | Exception) -> None:
        """The callback request's result (``start_read``'s ``done``)."""
        end = _clock()
        # The request is over: its slot goes back before the sample is delivered, as on the
        # task path (released in _scan_group before _single_done), so a scan waiting for a
        # slot is not held up by delivery, and a delivery that fails cannot keep the slot.
        if self._holding:  # tested here: no call per request without a cap
            self._give_back()
        if self._closed:
            return
        group = self._group
        try:
            whole = self._whole
            if whole is not None and type(reply) is list and len(reply) == self._count:
                # what _single_done decides for this reply, its checks done once in _use
                self._poller._whole_reply(
                    self._stats, self._name, whole, reply, self._start, end, self._offset
                )
            else:
                self._poller._single_done(
                    self._plc, group, self._plan, reply, self._start, end, self._offset
                )
        except Exception:  # a bug must not end this group's scans
            _log.exception("%s: delivering a scan failed", self._plc.config.name)
        advance(self._stats, group, end)
        self._ticker.call_at(group.next_due, self._fire_cb)

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

    async def _scan_task(self) -> None:
        """One scan the general way (connect, stale-input check, a queued request, several
        requests), then back to the callback path for the next."""
        try:
            await self._poller._scan_group(self._plc, self._group)
        except Exception:  # _scan_group turns read failures into samples: this is a bug
            _log.exception("%s: a scan failed", self._plc.config.name)
        self._task = None
        if not self._closed:
            group = self._group
            advance(self._stats, group, _clock())
            self._ticker.call_at(group.next_due, self._fire_cb)
