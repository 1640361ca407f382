"""One event-loop timer for the request deadlines of every connection on a loop.

Each connection keeps one deadline timer, re-armed rarely (see ``QueueProtocolMixin._arm``).
With a thousand connections that is still a thousand ``TimerHandle`` objects in asyncio's timer
heap, which orders them with a Python-level ``__lt__``: every arm and every expiry costs 10-20
Python calls there (the fleet profile). :class:`Deadlines` keeps the connections'
timers in its own heap of plain tuples, compared in C, and arms a single loop timer for the
earliest. The poller's :class:`~plcstack.poll.ticker.Ticker` does the same for scan times.

Entries hold their connection weakly and are never removed early: a connection that re-arms
or closes leaves its old entry to come due and be ignored (the callback gets the time it was
armed for and compares it with the connection's current one). An entry lives at most until its
time, so the heap holds about one entry per connection.
"""

from __future__ import annotations

import asyncio
import functools
import heapq
import itertools
import math
import time
import weakref
from collections.abc import Callable
from typing import Any

__all__ = ["Deadlines", "deadlines_of", "future_factory"]


class Deadlines:
    """``call_at(when, callback)``: ``callback(when)`` once ``loop.time()`` reaches ``when``.

    Holds nothing that reaches its loop (the registry's key): the loop is held weakly, and the
    loop timer is not kept (a replaced one is told apart by its arming number and does nothing).
    """

    __slots__ = ("_armed", "_heap", "_loop", "_order", "_resolution", "_timer_at")

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = weakref.ref(loop)
        self._heap: list[tuple[float, int, weakref.WeakMethod[Callable[[float], None]]]] = []
        self._order = itertools.count()
        #: the loop time the current loop timer is armed for, and its arming number
        self._timer_at = math.inf
        self._armed = 0
        # asyncio's own loops run a timer up to the clock's resolution early; so may we
        self._resolution = (
            time.get_clock_info("monotonic").resolution
            if isinstance(loop, asyncio.BaseEventLoop)
            else 0.0
        )

    def call_at(self, when: float, callback: Callable[[float], None]) -> None:
        """``callback`` is a bound method, held weakly: a connection that is gone is not kept
        alive (nor, through it, its loop) until its entry comes due."""
        self.call_weak(when, weakref.WeakMethod(callback))

    def call_weak(self, when: float, entry: weakref.WeakMethod[Callable[[float], None]]) -> None:
        """:meth:`call_at` with the weak reference made by the caller: a connection re-arms
        with the one it made once, instead of a new object per arming."""
        heapq.heappush(self._heap, (when, next(self._order), entry))
        if when < self._timer_at:
            loop = self._loop()
            if loop is not None:  # else the loop is gone: nothing can wait on it any more
                self._arm(loop, when)

    def __len__(self) -> int:
        return len(self._heap)

    def _arm(self, loop: asyncio.AbstractEventLoop, when: float) -> None:
        self._armed += 1
        self._timer_at = when
        loop.call_at(when, self._fire, self._armed)

    def _fire(self, armed: int) -> None:
        if armed != self._armed:
            return  # replaced by an earlier timer, which has run or will
        self._timer_at = math.inf
        heap = self._heap
        loop = asyncio.get_running_loop()
        ready = loop.time() + self._resolution
        while heap and heap[0][0] <= ready:
            when, _, entry = heapq.heappop(heap)
            callback = entry()
            if callback is not None:
                callback(when)
        if heap and heap[0][0] < self._timer_at:  # a callback may have armed already
            self._arm(loop, heap[0][0])


_BY_LOOP: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Deadlines] = (
    weakref.WeakKeyDictionary()
)


def deadlines_of(loop: asyncio.AbstractEventLoop) -> Deadlines:
    """The loop's :class:`Deadlines` (made on first use; gone with the loop)."""
    found = _BY_LOOP.get(loop)
    if found is None:
        found = _BY_LOOP[loop] = Deadlines(loop)
    return found


def future_factory(loop: asyncio.AbstractEventLoop) -> Callable[[], asyncio.Future[Any]]:
    """``loop.create_future`` without its Python frame where that is all it is.

    asyncio's own loops implement ``create_future`` as a Python method that only calls the
    ``Future`` class; on the polling path (two futures a request) calling the class directly
    saves that call. Any other loop (uvloop, one that makes its own futures) keeps its method.
    """
    if type(loop).create_future is asyncio.BaseEventLoop.create_future:
        return functools.partial(asyncio.Future, loop=loop)
    return loop.create_future
