"""Many network clients on a PLC's one connection: the native faces' fair queue beside the poll.

An S5-LAN module takes one connection, an AS511 port has one master, an E71 has eight. The
poller holds that connection; a native face (S5-LAN, FETCH/WRITE, E71 served on the network)
puts each of its clients' requests on it through one :class:`SharedConnection`:

* one bounded queue for every face of the PLC (``queue_size`` requests in all, ``per_source``
  of one client): a full queue answers at once instead of letting latency grow without bound;
* fair between the face clients: each client (``source``) has its own line, and the lines are
  served in turn, so one busy client cannot starve the others;
* fair between the faces and the poll: one face request at a time waits for the connection,
  in the client's first-come lock (:class:`~plcstack.clients.flight.SingleFlight`) with the
  scans. A scan therefore waits for at most one face request, and a face request for at most
  the scans already waiting; neither side can starve the other;
* a request that waited longer than ``max_wait`` is refused (:class:`WaitedTooLong`) and never
  sent: its client has given up by then, and a write executed after its client was told it
  failed would be a lie;
* a request whose client went away while it waited is never sent either; one already sent
  runs to its end (cutting it off would cost the poller its connection);
* each request is one turn (``Client.turn``): a request that needs several (the value before a
  write, for the audit; a monitor registration and its monitor) has nothing of anyone else's in
  between.

Without faces nothing of this exists: the poller's requests take the lock as before.
"""

from __future__ import annotations

import asyncio
import collections
import logging
from collections.abc import Awaitable, Callable, Hashable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from plcstack.clients.base import Client
from plcstack.durations import check_seconds
from plcstack.errors import AddressError, PlcError
from plcstack.resource import AsyncResource

__all__ = ["QueueFull", "ShareStats", "SharedConnection", "TurnRefused", "WaitedTooLong"]

log = logging.getLogger(__name__)

T = TypeVar("T")

#: requests that may wait for one PLC's connection, from all its faces together
DEFAULT_QUEUE_SIZE = 32
#: requests one face client may have waiting at once (a TCP client has one; a UDP peer that
#: repeats a request it thinks lost may have two)
DEFAULT_PER_SOURCE = 2
#: seconds a face request may wait for its turn before it is refused unsent
DEFAULT_MAX_WAIT = 2.0


class TurnRefused(PlcError):
    """A face request was refused before it was sent: nothing reached the PLC."""


class QueueFull(TurnRefused):
    """The queue of the PLC's connection (or its client's line in it) is full."""


class WaitedTooLong(TurnRefused):
    """The request waited longer than its limit for the connection, so it was not sent."""


@dataclass
class ShareStats:
    """Counters of one shared connection (what ``/metrics`` and the exit line show)."""

    #: requests that ran on the PLC's connection (answered by the PLC, or failed on it)
    executed: int = 0
    #: refused at once because the queue (or the client's line) was full
    busy: int = 0
    #: refused unsent because they waited longer than ``max_wait``
    expired: int = 0
    #: not sent because their client went away while they waited
    skipped: int = 0
    #: the most requests that waited at once
    queue_peak: int = 0


@dataclass(eq=False)
class _Job(Generic[T]):
    source: Hashable
    run: Callable[[], Awaitable[T]]
    #: seconds it may wait, and the loop time that ends
    limit: float
    deadline: float
    future: asyncio.Future[T] = field(repr=False)


class SharedConnection(AsyncResource):
    """The faces' turns on ``client``, the PLC's one connection (see the module docstring).

    ``name`` names the PLC in the log. Start it with ``async with`` or :meth:`aopen`; it never
    opens or closes the client, which belongs to the poller (or to whoever made it).
    """

    def __init__(
        self,
        client: Client,
        *,
        name: str | None = None,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        per_source: int = DEFAULT_PER_SOURCE,
        max_wait: float = DEFAULT_MAX_WAIT,
    ) -> None:
        if queue_size < 1:
            raise AddressError(f"queue_size {queue_size} must be at least 1")
        if per_source < 1:
            raise AddressError(f"per_source {per_source} must be at least 1")
        self.client = client
        self.name = name or client.name
        self.queue_size = queue_size
        self.per_source = min(per_source, queue_size)
        self.max_wait = check_seconds("max_wait", max_wait)
        self.stats = ShareStats()
        #: each source's line, and the sources with a request waiting, in serving order
        self._lines: dict[Hashable, collections.deque[_Job[Any]]] = {}
        self._ring: collections.deque[Hashable] = collections.deque()
        self._waiting = 0
        self._wakeup = asyncio.Event()
        self._pump: asyncio.Task[None] | None = None
        #: a burst of refusals is said once (WARNING), its end once (INFO)
        self._refusing = False

    @property
    def worker(self) -> asyncio.Task[None] | None:
        """The one task that runs the face requests (None before :meth:`aopen`): whoever runs
        the faces watches it, so its failure ends the run instead of leaving requests waiting."""
        return self._pump

    @property
    def waiting(self) -> int:
        """Face requests waiting now."""
        return self._waiting

    async def aopen(self) -> None:
        if self._pump is None:
            self._pump = asyncio.get_running_loop().create_task(
                self._work(), name=f"faces of {self.name}"
            )

    async def aclose(self) -> None:
        """Stop: a request in flight is given up with its task, the waiting ones are refused."""
        pump, self._pump = self._pump, None
        if pump is not None:
            pump.cancel()
            await asyncio.gather(pump, return_exceptions=True)
        for line in self._lines.values():
            for job in line:
                if not job.future.done():
                    job.future.set_exception(
                        WaitedTooLong("the faces were stopped; not sent", plc=self.name)
                    )
        self._lines.clear()
        self._ring.clear()
        self._waiting = 0

    async def run(
        self,
        source: Hashable,
        job: Callable[[], Awaitable[T]],
        *,
        max_wait: float | None = None,
    ) -> T:
        """Run ``job`` (requests on the client) in its turn; returns what it returns.

        ``source`` is the face client (its own line in the queue). Raises :class:`QueueFull` at
        once when the queue or the client's line is full and :class:`WaitedTooLong` when the
        turn did not come within ``max_wait`` seconds (default: the connection's), both
        without sending anything; otherwise whatever ``job`` raises. Cancelling the caller
        (its client went away) skips a job that has not started; a started one runs to its end.
        """
        if self._pump is None:
            raise WaitedTooLong("the faces are not running; not sent", plc=self.name)
        line = self._lines.get(source)
        if self._waiting >= self.queue_size or (line is not None and len(line) >= self.per_source):
            self.stats.busy += 1
            why = (
                f"{self._waiting} face requests already wait for the PLC's connection"
                if self._waiting >= self.queue_size
                else f"this client already has {len(line or ())} requests waiting"
            )
            self._refused(why)
            raise QueueFull(why, plc=self.name)
        loop = asyncio.get_running_loop()
        wait = self.max_wait if max_wait is None else max_wait
        item: _Job[T] = _Job(source, job, wait, loop.time() + wait, loop.create_future())
        if line is None:
            line = self._lines[source] = collections.deque()
            self._ring.append(source)
        line.append(item)
        self._waiting += 1
        self.stats.queue_peak = max(self.stats.queue_peak, self._waiting)
        self._wakeup.set()
        # A cancelled caller cancels the future too; the pump then skips the job if it has not
        # started, and drops its result if it has.
        return await item.future

    # -- the pump -------------------------------------------------------------------------------
    def _next(self) -> _Job[Any] | None:
        """The next job in fair order: each source with a job waiting in turn."""
        ring = self._ring
        if not ring:
            return None
        source = ring.popleft()
        line = self._lines[source]
        job = line.popleft()
        if line:
            ring.append(source)
        else:
            del self._lines[source]
        self._waiting -= 1
        return job

    async def _work(self) -> None:
        loop = asyncio.get_running_loop()
        client = self.client
        while True:
            job = self._next()
            if job is None:
                self._drained()
                self._wakeup.clear()
                await self._wakeup.wait()
                continue
            if job.future.done():  # its client went away while it waited
                self.stats.skipped += 1
                continue
            if loop.time() >= job.deadline:
                self._expire(job)
                continue
            started = False
            try:
                async with client.turn(job.deadline):
                    if job.future.done():
                        self.stats.skipped += 1
                        continue
                    started = True
                    self.stats.executed += 1
                    result = await job.run()
            except asyncio.CancelledError:
                if not job.future.done():
                    job.future.set_exception(WaitedTooLong("the faces were stopped", plc=self.name))
                raise
            except TimeoutError as exc:
                if not started:  # the turn did not come in time: nothing was sent
                    self._expire(job)
                elif not job.future.done():
                    job.future.set_exception(exc)
            except Exception as exc:
                if not job.future.done():
                    job.future.set_exception(exc)
            else:
                if not job.future.done():
                    job.future.set_result(result)

    def _expire(self, job: _Job[Any]) -> None:
        self.stats.expired += 1
        self._refused("requests wait longer than their limit")
        if not job.future.done():
            job.future.set_exception(
                WaitedTooLong(
                    f"waited longer than {job.limit:g} s for the PLC's connection; not sent",
                    plc=self.name,
                )
            )

    def _refused(self, why: str) -> None:
        if not self._refusing:
            self._refusing = True
            log.warning(
                "%s: face requests refused unsent: %s (queue %d, wait limit %g s)",
                self.name,
                why,
                self.queue_size,
                self.max_wait,
            )

    def _drained(self) -> None:
        if self._refusing:
            self._refusing = False
            s = self.stats
            log.info(
                "%s: the face queue is empty again (%d busy, %d expired so far)",
                self.name,
                s.busy,
                s.expired,
            )
