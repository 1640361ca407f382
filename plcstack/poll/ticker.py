"""One event-loop timer for the next scans of every PLC task of a poller.

``asyncio.sleep(delay)`` per scan puts one ``TimerHandle`` per PLC into the loop's timer heap.
On asyncio's own loop that heap orders handles with a Python-level ``__lt__``: with a thousand
PLCs, each a 10 Hz sleep timer plus its connection's deadline timer, every push and pop costs
10-20 Python calls (measured in the fleet profile: the single largest Python cost per request).
The ticker keeps the PLC tasks' due times in its own heap of plain tuples (compared in C) and
arms a single loop timer for the earliest; when it fires, every task that is due wakes. The
times are the poller's schedule clock (``time.perf_counter``); the loop only ever gets relative
delays, as with ``asyncio.sleep``.

Besides futures to await (``wait_until``, the PLC tasks), the heap holds plain callbacks
(``call_at``): the poller's callback-driven scans (``poll/scanner.py``) start their request
right in the ticker's timer callback, without a task step.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import logging
import math
from collections.abc import Callable

from plcstack.transports.deadlines import future_factory

__all__ = ["Ticker"]

_log = logging.getLogger(__name__)


class Ticker:
    """``await ticker.wait_until(due)``: like ``asyncio.sleep(due - clock())``, one timer for all.

    A waiter wakes no earlier than ``due - resolution`` (the loop's own timers fire up to its
    clock resolution early, and the poller treats anything due within ``resolution`` as due)
    and in due order. A cancelled waiter is simply skipped when its time comes.
    """

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        clock: Callable[[], float],
        resolution: float = 0.0,
    ) -> None:
        self._loop = loop
        self._new_future = future_factory(loop)
        self._clock = clock
        self._resolution = resolution
        self._heap: list[tuple[float, int, asyncio.Future[None] | Callable[[], None]]] = []
        self._order = itertools.count()
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = math.inf

    def wait_until(self, due: float) -> asyncio.Future[None]:
        """A future that completes once the clock reaches ``due`` (within the resolution)."""
        future: asyncio.Future[None] = self._new_future()
        heapq.heappush(self._heap, (due, next(self._order), future))
        if due < self._timer_at:
            self._arm(due)
        return future

    def call_at(self, due: float, callback: Callable[[], None]) -> None:
        """Call ``callback()`` once the clock reaches ``due`` (within the resolution), from the
        ticker's loop timer. An exception it raises is logged; the other entries still run."""
        heapq.heappush(self._heap, (due, next(self._order), callback))
        if due < self._timer_at:
            self._arm(due)

    def close(self) -> None:
        """Drop the loop timer, every waiter (cancelled) and every callback (never called)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._timer_at = math.inf
        for _, _, item in self._heap:
            if isinstance(item, asyncio.Future):
                item.cancel()
        self._heap.clear()

    def __len__(self) -> int:
        return len(self._heap)

    def _arm(self, due: float) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self._timer = self._loop.call_later(max(0.0, due - self._clock()), self._fire)
        self._timer_at = due

    def _fire(self) -> None:
        self._timer = None
        self._timer_at = math.inf
        heap = self._heap
        ready = self._clock() + self._resolution
        while heap and heap[0][0] <= ready:
            item = heapq.heappop(heap)[2]
            if isinstance(item, asyncio.Future):
                if not item.done():
                    item.set_result(None)
                continue
            try:
                item()
            except Exception:  # one broken callback must not stop the others' schedules
                _log.exception("ticker callback %r failed", item)
        if heap and heap[0][0] < self._timer_at:  # a callback may have armed already
            self._arm(heap[0][0])
