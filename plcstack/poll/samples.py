"""What the poller delivers: one :class:`Sample` per tag and scan, with its :class:`Quality`,
through one bounded :class:`SampleQueue`."""

from __future__ import annotations

import asyncio
import collections
import enum
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass, fields
from typing import Any

from plcstack.errors import PlcError
from plcstack.values import TagValue

__all__ = ["Quality", "Sample", "SampleQueue", "make_sample"]


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


class SampleQueue:
    """The bounded buffer between scans and their consumer: batches, drain, drop counts.

    Scans append to :attr:`items` (a deque; the hot path appends there itself), call
    :meth:`trim` when it holds more than :attr:`limit`, and :attr:`wake` the consumer. When it
    is full the oldest samples are dropped and counted, in :attr:`dropped` and per PLC (in the
    :class:`~plcstack.poll.stats.PlcStats` registered with :meth:`count_drops`): nothing is
    dropped silently. One queue may serve several pollers (the scale-out worker runs one per
    PLC it owns, all into its one queue), so the consumer sees one stream.
    """

    __slots__ = ("_owners", "_wakeup", "dropped", "items", "limit", "wake")

    def __init__(self, limit: int) -> None:
        self.items: collections.deque[Sample] = collections.deque()
        self.limit = limit
        #: samples dropped so far because the buffer was full
        self.dropped = 0
        self._owners: dict[str, Any] = {}
        self._wakeup = asyncio.Event()
        #: wake the consumer (bound once: called after every scan)
        self.wake: Callable[[], None] = self._wakeup.set

    def count_drops(self, plc: str, stats: Any) -> None:
        """Count the samples of ``plc`` dropped from here in ``stats.drops``."""
        self._owners[plc] = stats

    def trim(self) -> None:
        """Drop the oldest samples beyond :attr:`limit`, counting each against its PLC."""
        items = self.items
        excess = len(items) - self.limit
        while excess > 0:
            oldest = items.popleft()
            excess -= 1
            self.dropped += 1
            owner = self._owners.get(oldest.plc)
            if owner is not None:
                owner.drops += 1

    def put(self, samples: Iterable[Sample]) -> None:
        """Queue samples (the cold paths' way in), trimming and waking the consumer."""
        items = self.items
        items.extend(samples)
        if len(items) > self.limit:
            self.trim()
        self._wakeup.set()

    def __len__(self) -> int:
        return len(self.items)

    def drain(self) -> list[Sample]:
        """Take every buffered sample at once."""
        out = list(self.items)
        self.items.clear()
        return out

    async def next(self, closed: Callable[[], bool]) -> Sample:
        """The oldest sample, waiting for one; :class:`StopAsyncIteration` once ``closed()``
        says the producers are done and the buffer is empty."""
        items = self.items
        while not items:
            if closed():
                raise StopAsyncIteration
            self._wakeup.clear()
            await self._wakeup.wait()
        return items.popleft()

    async def batches(self, wait: float, closed: Callable[[], bool]) -> AsyncIterator[list[Sample]]:
        """Every sample, as lists: all that is buffered at each wake-up (never an empty list),
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
                await asyncio.sleep(wait)  # let more samples join this batch
            batch = list(items)
            items.clear()
            yield batch
