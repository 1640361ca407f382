"""The single-flight lock of a client: one request on a connection at a time, in arrival order.

``asyncio.Lock`` does the job, but ``async with lock`` costs three coroutine objects
(``__aenter__``, ``acquire``, ``__aexit__``) and their calls on every request, even when nobody
else waits, which is almost always the case on a polling connection. :class:`SingleFlight`
has the same contract with a synchronous fast path: :meth:`try_acquire` takes a free lock
without creating anything; only a request that has to queue behind another awaits
:meth:`acquire`. ``async with`` still works, for the paths where a few hundred nanoseconds do
not matter (connect, writes of the rarer commands).

The hand-over is a baton pass: :meth:`release` with waiters does not free the lock but gives it
to the first waiter that is still waiting, so a request arriving meanwhile cannot overtake the
queue. A waiter cancelled after it was given the baton passes it on (it never ran, so nothing
was sent on its behalf).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
from types import TracebackType

__all__ = ["SingleFlight"]


class SingleFlight:
    """A FIFO mutex for one connection; the same contract as :class:`asyncio.Lock`."""

    __slots__ = ("_busy", "_waiters")

    def __init__(self) -> None:
        self._busy = False
        self._waiters: collections.deque[asyncio.Future[None]] | None = None

    def locked(self) -> bool:
        return self._busy

    def try_acquire(self) -> bool:
        """Take the lock if it is free and nobody queues for it; never waits."""
        if self._busy:
            return False
        self._busy = True
        return True

    async def acquire(self) -> bool:
        """Take the lock, waiting behind every earlier waiter."""
        if not self._busy:
            self._busy = True
            return True
        waiters = self._waiters
        if waiters is None:
            waiters = self._waiters = collections.deque()
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        waiters.append(waiter)
        try:
            await waiter
        except asyncio.CancelledError:
            if waiter.done() and not waiter.cancelled():
                # the baton was handed to us just before the cancel: pass it on
                self.release()
            else:
                with contextlib.suppress(ValueError):  # a release may have skipped it already
                    waiters.remove(waiter)
            raise
        return True  # the releaser left ``_busy`` set for us

    def release(self) -> None:
        """Free the lock, or hand it to the first waiter that still waits."""
        if not self._busy:
            raise RuntimeError("SingleFlight released while not held")
        waiters = self._waiters
        while waiters:
            waiter = waiters.popleft()
            if not waiter.done():
                waiter.set_result(None)  # ``_busy`` stays set: it is the waiter's now
                return
        self._busy = False

    async def __aenter__(self) -> None:
        await self.acquire()

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.release()

    def __repr__(self) -> str:
        waiting = len(self._waiters) if self._waiters else 0
        state = "locked" if self._busy else "unlocked"
        return f"<SingleFlight {state}, {waiting} waiting>"
