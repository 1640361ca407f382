"""The slots of the poller's concurrency cap: a FIFO counting semaphore with a synchronous
``try_acquire``.

``poll.concurrency`` caps the requests in flight across all PLCs. ``asyncio.Semaphore`` keeps
that cap but can only be taken by awaiting it, and the poller's callback scans
(:mod:`.scanner`) start their request in a timer callback, where nothing can be awaited: with
``asyncio.Semaphore`` a cap put every PLC back on the slower task path. :class:`Slots` has the
same contract plus :meth:`Slots.try_acquire`, which takes a free slot without creating anything
and never waits; a scan that finds no slot free runs on the task path and awaits
:meth:`Slots.acquire` there, in arrival order.

The hand-over is a baton pass, as in :class:`plcstack.clients.flight.SingleFlight`:
:meth:`Slots.release` with waiters does not free the slot but gives it to the first waiter that
is still waiting. Hence the invariant that makes :meth:`Slots.try_acquire` fair: a slot is free
only while nobody waits, so a callback scan can never overtake the queue of task-path scans.
A waiter cancelled after it was handed a slot passes it on (it never ran, so nothing was sent
on its behalf); one cancelled before leaves the queue.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib

__all__ = ["Slots"]


class Slots:
    """``size`` slots taken in FIFO order; the contract of :class:`asyncio.Semaphore` (bounded:
    releasing more than was taken is an error) plus a synchronous :meth:`try_acquire`."""

    __slots__ = ("_free", "_size", "_waiters")

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ValueError(f"Slots needs at least one slot, not {size!r}")
        self._size = size
        #: free slots; never above 0 while ``_waiters`` holds anyone (see the module docstring)
        self._free = size
        self._waiters: collections.deque[asyncio.Future[None]] = collections.deque()

    @property
    def size(self) -> int:
        return self._size

    def locked(self) -> bool:
        """Whether a slot cannot be taken without waiting."""
        return self._free == 0

    def try_acquire(self) -> bool:
        """Take a free slot; never waits. Refused while anyone waits: slots are free only when
        nobody does (a release with waiters hands its slot over instead of freeing it)."""
        if self._free == 0:
            return False
        self._free -= 1
        return True

    async def acquire(self) -> bool:
        """Take a slot, waiting behind every earlier waiter."""
        if self._free:
            self._free -= 1
            return True
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        waiters = self._waiters
        waiters.append(waiter)
        try:
            await waiter
        except asyncio.CancelledError:
            if waiter.done() and not waiter.cancelled():
                # a slot was handed to us just before the cancel: pass it on
                self.release()
            else:
                with contextlib.suppress(ValueError):  # a release may have skipped it already
                    waiters.remove(waiter)
            raise
        return True  # the releaser did not free the slot: it is ours

    def release(self) -> None:
        """Give a slot back: to the first waiter that still waits, else free it."""
        waiters = self._waiters
        while waiters:
            waiter = waiters.popleft()
            if not waiter.done():
                waiter.set_result(None)  # the slot stays taken: it is the waiter's now
                return
        if self._free >= self._size:
            raise RuntimeError(f"Slots released with all {self._size} slots free")
        self._free += 1

    def __repr__(self) -> str:
        return f"<Slots {self._free}/{self._size} free, {len(self._waiters)} waiting>"
