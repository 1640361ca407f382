"""Taking turns on connections and requests: FIFO, cancel-safe, free turns taken without waiting.

:class:`Slots` is a FIFO counting semaphore with a synchronous :meth:`Slots.try_acquire`;
:class:`SingleFlight`, the clients' one-request-per-connection lock, is ``Slots(1)``.

``asyncio.Lock`` and ``asyncio.Semaphore`` keep the same contracts, but can only be taken by
awaiting them: ``async with lock`` costs three coroutine objects (``__aenter__``, ``acquire``,
``__aexit__``) on every request, even when nobody else waits, which is almost always the case
on a polling connection; and the poller's callback scans (:mod:`plcstack.poll.scanner`) start
their request in a timer callback, where nothing can be awaited at all, so with
``asyncio.Semaphore`` a ``poll.concurrency`` cap put every PLC back on the slower task path.
Here a free turn is taken by :meth:`Slots.try_acquire` without creating anything; only a taker
that has to queue awaits :meth:`Slots.acquire`. ``async with`` still works on a SingleFlight,
for the paths where a few hundred nanoseconds do not matter (connect, the rarer commands).

The hand-over is a baton pass: :meth:`Slots.release` with waiters does not free the slot but
gives it to the first waiter that is still waiting. Hence the invariant that makes
:meth:`Slots.try_acquire` fair: a slot is free only while nobody waits, so nobody arriving
meanwhile (a request, a callback scan) can overtake the queue. A waiter cancelled after it was
handed the slot passes it on (it never ran, so nothing was sent on its behalf); one cancelled
before leaves the queue.

A turn (:meth:`SingleFlight.hold`) keeps a connection for one task across several requests: a
native face's request that must read before it writes, or register before it monitors, runs
with nothing of anyone else's in between. While it holds, that task's own acquisitions go
through without waiting (and their releases keep the lock held); everyone else queues. It is
waited for with a deadline: a face request that did not get its turn in time is answered
"busy" and never sent. The hot path pays nothing for it: ``try_acquire`` tests one number as
before, and ``release`` looks at the holder only when someone waits.

:class:`ConnectTurns` spaces the connects of many clients that share one event loop: a turn
ends when the connect does, or after ``hold`` seconds, whichever comes first.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
from collections.abc import AsyncIterator
from types import TracebackType

__all__ = ["ConnectTurns", "SingleFlight", "Slots"]


class Slots:
    """``size`` slots taken in FIFO order; the contract of :class:`asyncio.Semaphore` (bounded:
    releasing more than was taken is an error) plus a synchronous :meth:`try_acquire`."""

    __slots__ = ("_free", "_holder", "_size", "_waiters")

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ValueError(f"Slots needs at least one slot, not {size!r}")
        self._size = size
        #: free slots; never above 0 while ``_waiters`` holds anyone (see the module docstring);
        #: below 0 while requests of a turn's holder run inside its turn (one per request)
        self._free = size
        self._waiters: collections.deque[asyncio.Future[None]] = collections.deque()
        #: the task whose turn holds the lock (:meth:`SingleFlight.hold`), or None
        self._holder: asyncio.Task[object] | None = None

    @property
    def size(self) -> int:
        return self._size

    def locked(self) -> bool:
        """Whether a slot cannot be taken without waiting."""
        return self._free <= 0

    def try_acquire(self) -> bool:
        """Take a free slot; never waits. Refused while anyone waits: slots are free only when
        nobody does (a release with waiters hands its slot over instead of freeing it)."""
        if self._free <= 0:
            return False
        self._free -= 1
        return True

    async def acquire(self) -> bool:
        """Take a slot, waiting behind every earlier waiter (the holder of a turn: at once)."""
        if self._free > 0:
            self._free -= 1
            return True
        holder = self._holder
        if holder is not None and holder is asyncio.current_task():
            self._free -= 1  # a request inside its own turn: released, the turn keeps the lock
            return True
        await self._wait(None)
        return True  # the releaser did not free the slot: it is ours

    async def _wait(self, deadline: float | None) -> None:
        """Queue until a release hands a slot over; ``TimeoutError`` at loop time ``deadline``
        if none was handed over by then (nothing taken)."""
        loop = asyncio.get_running_loop()
        waiter: asyncio.Future[None] = loop.create_future()
        waiters = self._waiters
        waiters.append(waiter)
        timer = None if deadline is None else loop.call_at(deadline, _expire, waiter)
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
        except TimeoutError:
            with contextlib.suppress(ValueError):
                waiters.remove(waiter)
            raise
        finally:
            if timer is not None:
                timer.cancel()

    def release(self) -> None:
        """Give a slot back: to the first waiter that still waits, else free it. The end of a
        request inside a turn gives it back to the turn's holder, whoever waits."""
        waiters = self._waiters
        if waiters and self._free == 0:
            while waiters:
                waiter = waiters.popleft()
                if not waiter.done():
                    waiter.set_result(None)  # the slot stays taken: it is the waiter's now
                    return
        if self._free >= self._size:
            raise RuntimeError(f"{type(self).__name__} released with all {self._size} slot(s) free")
        self._free += 1

    def __repr__(self) -> str:
        return f"<Slots {self._free}/{self._size} free, {len(self._waiters)} waiting>"


def _expire(waiter: asyncio.Future[None]) -> None:
    """A waiter's deadline passed before a slot was handed to it."""
    if not waiter.done():
        waiter.set_exception(TimeoutError())


class SingleFlight(Slots):
    """The single-flight lock of a connection: one request at a time, in arrival order
    (``Slots(1)``, with the contract of :class:`asyncio.Lock`)."""

    __slots__ = ()

    def __init__(self) -> None:
        super().__init__(1)

    async def hold(self, deadline: float | None = None) -> None:
        """Take the lock for the calling task's turn, until :meth:`unhold`: its own requests
        meanwhile take and give back the lock without waiting, everyone else's wait. Waits in
        arrival order like any taker; ``TimeoutError`` (nothing held) if loop time ``deadline``
        comes first."""
        task = asyncio.current_task()
        if task is None:
            raise RuntimeError("a turn is held by a task")
        if self._holder is task:
            raise RuntimeError("this task already holds its turn")
        if self._free > 0:
            self._free -= 1
        else:
            await self._wait(deadline)
        self._holder = task

    def unhold(self) -> None:
        """End the turn: the lock goes to the first waiter, or is free."""
        if self._holder is None:
            raise RuntimeError("no turn is held")
        self._holder = None
        self.release()

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
        state = "locked" if self.locked() else "unlocked"
        return f"<SingleFlight {state}, {len(self._waiters)} waiting>"


class ConnectTurns:
    """Connects of many clients, ``at_once`` at a time; a turn lasts at most ``hold`` seconds.

    Thousands of PLCs of one poller connect within the same second. Unspaced, every connect's
    steps queue behind every other's in the one event loop, and that backlog, not the network,
    outlasts the connect timeout. A connect waits for its turn before its timeout starts. The
    turn ends when the connect does; a connect still running after ``hold`` seconds waits on
    its peer, not on this process, and gives its turn back, so dead PLCs (each connect running
    for its whole timeout) can never take every turn and keep the live ones from reconnecting.
    """

    __slots__ = ("_slots", "hold")

    def __init__(self, at_once: int, hold: float) -> None:
        if hold <= 0:
            raise ValueError(f"ConnectTurns needs a hold above 0 s, not {hold!r}")
        self._slots = Slots(at_once)
        self.hold = hold

    @contextlib.asynccontextmanager
    async def turn(self) -> AsyncIterator[None]:
        """Wait for a turn; hold it while the body runs, for ``hold`` seconds at most."""
        slots = self._slots
        await slots.acquire()
        held = True

        def give_back() -> None:
            nonlocal held
            if held:
                held = False
                slots.release()

        timer = asyncio.get_running_loop().call_later(self.hold, give_back)
        try:
            yield
        finally:
            timer.cancel()
            give_back()

    def __repr__(self) -> str:
        return f"<ConnectTurns {self._slots!r}, hold {self.hold:g} s>"
