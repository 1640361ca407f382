"""What the poller delivers: one :class:`Scan` per completed scan of one PLC's scan group,
holding one :class:`Sample` per tag with its :class:`Quality`, through one bounded
:class:`ScanQueue`.

A scan crosses the north boundary as it was made: its PLC and its group are what the poller
knew when it read them, so no consumer has to guess the grouping back from a stream of samples.
Every sink takes scans through one method (:class:`ScanSink`).
"""

from __future__ import annotations

import asyncio
import collections
import enum
import itertools
import operator
from collections.abc import AsyncIterator, Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, fields
from typing import Any, NamedTuple, Protocol

from plcstack.errors import PlcError
from plcstack.values import TagValue

__all__ = [
    "Quality",
    "Sample",
    "Scan",
    "ScanQueue",
    "ScanSink",
    "each_sample",
    "flatten",
    "make_sample",
]


class Quality(enum.Enum):
    GOOD = "good"
    BAD = "bad"


@dataclass(frozen=True, slots=True)
class Sample:
    """One tag value. Times are Unix seconds; ``source_time`` is when the request was sent.

    None of these protocols timestamps its data, so the best statement of when the PLC held the
    value is "between ``source_time`` and ``receive_time``". A bad sample has ``value`` None and
    ``error`` saying why (the full :class:`PlcError` text, naming PLC and request) and
    ``error_type`` the :class:`PlcError` subclass, so a consumer can map the kind of failure
    (timeout, refused connection, PLC error code) to its own status codes without parsing text.
    """

    plc: str
    tag: str
    value: TagValue | None
    quality: Quality
    source_time: float
    receive_time: float
    error: str | None = None
    error_type: type[PlcError] | None = None


_new_object = object.__new__
(_set_plc, _set_tag, _set_value, _set_quality, _set_source, _set_receive, _set_error, _set_type) = (
    getattr(Sample, name).__set__ for name in (f.name for f in fields(Sample))
)


def make_sample(
    plc: str,
    tag: str,
    value: TagValue | None,
    quality: Quality,
    source_time: float,
    receive_time: float,
    error: str | None,
    error_type: type[PlcError] | None = None,
) -> Sample:
    """``Sample(...)`` for the hot path: the same frozen object, built in ~60 % of the time.

    A frozen dataclass's ``__init__`` goes through ``object.__setattr__`` once per field; the
    slot descriptors set the fields directly (what ``object.__setattr__`` ends up doing).
    """
    sample: Sample = _new_object(Sample)
    _set_plc(sample, plc)
    _set_tag(sample, tag)
    _set_value(sample, value)
    _set_quality(sample, quality)
    _set_source(sample, source_time)
    _set_receive(sample, receive_time)
    _set_error(sample, error)
    _set_type(sample, error_type)
    return sample


class Scan(NamedTuple):
    """One completed scan of one PLC's scan group: what the poller hands to the north side.

    ``group`` is the scan group of the configuration; ``source_time`` is when its first request
    was sent and ``receive_time`` when its last answer arrived (Unix seconds; each sample keeps
    its own request's times). ``samples`` holds one sample per tag of the group, in the group's
    order; after report-by-exception a scan holds only the samples that were reported.

    A frozen record made once per scan on the poller's hot path: a named tuple, since one is
    built in less than half the time of a frozen dataclass.
    """

    plc: str
    group: str
    source_time: float
    receive_time: float
    samples: tuple[Sample, ...]

    def with_samples(self, samples: tuple[Sample, ...]) -> Scan:
        """This scan (PLC, group, times) holding ``samples`` instead (a filtered or fixed
        copy)."""
        return self._replace(samples=samples)


#: a scan's samples, and the chaining of them: iterating scans' samples at C speed (a nested
#: Python loop costs a few bytecodes per scan on the north side's hot path)
_samples_of = operator.attrgetter("samples")
_chain = itertools.chain.from_iterable


def each_sample(scans: Iterable[Scan]) -> Iterator[Sample]:
    """The samples of ``scans``, in order, iterated in C (``for sample in each_sample(batch)``
    instead of a loop in a loop)."""
    return _chain(map(_samples_of, scans))


def flatten(scans: Iterable[Scan]) -> list[Sample]:
    """The samples of ``scans``, in order (for consumers that want samples, not scans)."""
    return list(each_sample(scans))


class ScanSink(Protocol):
    """What every sink and server of the north side implements: take a batch of scans.

    ``submit`` never blocks (a sink queues, or applies at once); a scan it cannot take raises,
    and the run's supervisor retries without the sample at fault.
    """

    def submit(self, scans: Sequence[Scan]) -> None: ...


class ScanQueue:
    """The bounded buffer between scans and their consumer: batches, drain, drop counts.

    Scans append to :attr:`items` (a deque; the hot path appends there itself), add their
    samples to :attr:`held`, call :meth:`trim` when that is more than :attr:`limit` (counted
    in samples, ``poll.queue``, so memory is bounded by tags, not by scans), and :attr:`wake`
    the consumer. When it is full the oldest scans are dropped whole (a scan is never cut) and
    their samples counted, in :attr:`dropped` and per PLC (in the
    :class:`~plcstack.poll.stats.PlcStats` registered with :meth:`count_drops`); the newest
    scan is always kept, so a scan larger than the limit still reaches the consumer. Nothing is
    dropped silently. One queue may serve several pollers (the scale-out worker runs one per
    PLC it owns, all into its one queue), so the consumer sees one stream.
    """

    __slots__ = ("_owners", "_rest", "_wakeup", "dropped", "dropped_scans", "held", "items",
                 "limit", "wake")  # fmt: skip

    def __init__(self, limit: int) -> None:
        self.items: collections.deque[Scan] = collections.deque()
        self.limit = limit
        #: samples in :attr:`items`
        self.held = 0
        #: samples dropped so far because the buffer was full, and the scans they were in
        self.dropped = 0
        self.dropped_scans = 0
        self._owners: dict[str, Any] = {}
        #: the samples of a scan the sample iterator (:meth:`next_sample`) has begun
        self._rest: collections.deque[Sample] = collections.deque()
        self._wakeup = asyncio.Event()
        #: wake the consumer (bound once: called after every scan)
        self.wake: Callable[[], None] = self._wakeup.set

    def count_drops(self, plc: str, stats: Any) -> None:
        """Count the samples of ``plc`` dropped from here in ``stats.drops``."""
        self._owners[plc] = stats

    def forget(self, plc: str) -> None:
        """Count no more drops of ``plc`` on its own (it was removed; the total still counts)."""
        self._owners.pop(plc, None)

    def trim(self) -> None:
        """Drop the oldest scans while more than :attr:`limit` samples are held (never the
        newest), counting their samples against their PLC."""
        items = self.items
        while self.held > self.limit and len(items) > 1:
            oldest = items.popleft()
            n = len(oldest.samples)
            self.held -= n
            self.dropped += n
            self.dropped_scans += 1
            owner = self._owners.get(oldest.plc)
            if owner is not None:
                owner.drops += n

    def put(self, scans: Iterable[Scan]) -> None:
        """Queue scans (the cold paths' way in), trimming and waking the consumer."""
        items = self.items
        for scan in scans:
            items.append(scan)
            self.held += len(scan.samples)
        if self.held > self.limit:
            self.trim()
        self._wakeup.set()

    def __len__(self) -> int:
        """Samples buffered and not yet taken."""
        return self.held + len(self._rest)

    def drain(self) -> list[Scan]:
        """Take every buffered scan at once."""
        out = list(self.items)
        self.items.clear()
        self.held = 0
        return out

    async def next(self, closed: Callable[[], bool]) -> Scan:
        """The oldest scan, waiting for one; :class:`StopAsyncIteration` once ``closed()``
        says the producers are done and the buffer is empty."""
        items = self.items
        while not items:
            if closed():
                raise StopAsyncIteration
            self._wakeup.clear()
            await self._wakeup.wait()
        scan = items.popleft()
        self.held -= len(scan.samples)
        return scan

    async def next_sample(self, closed: Callable[[], bool]) -> Sample:
        """The oldest sample: the scans of :meth:`next`, one sample at a time (``async for
        sample in poller``). Ends like :meth:`next`."""
        rest = self._rest
        while not rest:
            rest.extend((await self.next(closed)).samples)
        return rest.popleft()

    async def batches(self, wait: float, closed: Callable[[], bool]) -> AsyncIterator[list[Scan]]:
        """Every scan, as lists: all that is buffered at each wake-up (never an empty list),
        gathered for ``wait`` seconds after the first. Ends like :meth:`next`."""
        if not (wait >= 0.0 and wait < float("inf")):
            raise ValueError(f"wait must be a finite number of seconds >= 0, not {wait!r}")
        items = self.items
        while True:
            while not items:
                if closed():
                    return
                self._wakeup.clear()
                await self._wakeup.wait()
            if wait and not closed():
                await asyncio.sleep(wait)  # let more scans join this batch
            batch = list(items)
            items.clear()
            self.held = 0
            yield batch
