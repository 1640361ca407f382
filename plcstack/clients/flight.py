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
            raise RuntimeError(f"{type(self).__name__} released with all {self._size} slot(s) free")
        self._free += 1

    def __repr__(self) -> str:
        return f"<Slots {self._free}/{self._size} free, {len(self._waiters)} waiting>"


class SingleFlight(Slots):
    """The single-flight lock of a connection: one request at a time, in arrival order
    (``Slots(1)``, with the contract of :class:`asyncio.Lock`)."""

    __slots__ = ()

    def __init__(self) -> None:
        super().__init__(1)

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
