"""At most N points of a time range, keeping its peaks: min and max per bucket.

A chart 1000 pixels wide cannot show 86,400 points, and sending them costs the browser more
than drawing them. Averaging would hide the spike an operator is looking for, so the range is
cut into equal buckets of time and each bucket keeps its smallest and its largest value (at
their own times) and its first gap (a bad-quality point, or NaN): a step line through those
points touches every extreme the raw data touches. Text and arrays, which have no order, keep
the first and last point of each bucket. While the range holds no more than N points they are
all returned as they are.

The points arrive block by block in time order (:meth:`Downsampler.add`), so memory is bounded
by N and one block, whatever the range; a block of plain numbers is reduced with ``min``,
``max`` and ``index`` on slices (C work), so a day of a 1 Hz tag costs milliseconds.
"""

from __future__ import annotations

import bisect
import itertools
import math
from typing import Any

__all__ = ["Downsampler"]

_NUMBERS = (int, float, bool)


def _gap(value: Any) -> bool:
    """A point that is a hole in the line: bad quality, or a float that is not a number."""
    return value is None or (type(value) is float and math.isnan(value))


class Downsampler:
    """Points of ``[start, end]`` (ms) reduced to at most ``limit`` (see the module's docstring).

    ``before`` is the last point before ``start`` (the value that held at ``start``); it is
    returned first, unless a point sits on ``start`` itself, and counts toward ``limit``."""

    def __init__(self, start: int, end: int, limit: int) -> None:
        if limit < 4:
            raise ValueError(f"at least 4 points, not {limit}")
        if end < start:
            raise ValueError("the range ends before it starts")
        self.start, self.end, self.limit = start, end, limit
        self.before: tuple[int, Any] | None = None
        self._first: int | None = None
        self._raw_times: list[int] = []
        self._raw_values: list[Any] = []
        self._raw = True
        self._n = (limit - 1) // 2
        self._width = (end - start + 1) / self._n
        # per bucket: [min t, min v, max t, max v, gap t, gap v]; min/max hold first/last for
        # values that have no order
        self._buckets: dict[int, list[Any]] = {}

    def add(self, times: list[int], values: list[Any]) -> None:
        """Points in time order, all within the range."""
        if not times:
            return
        if self._first is None or times[0] < self._first:
            self._first = times[0]
        if self._raw:
            self._raw_times += times
            self._raw_values += values
            if len(self._raw_times) <= self.limit - 1:
                return
            self._raw = False
            times, values = self._raw_times, self._raw_values
            self._raw_times, self._raw_values = [], []
        self._into_buckets(times, values)

    def _into_buckets(self, times: list[int], values: list[Any]) -> None:
        start, width, last = self.start, self._width, self._n - 1
        first_b = min(last, int((times[0] - start) / width))
        last_b = min(last, int((times[-1] - start) / width))
        total = sum(values) if None not in values and _all_numbers(values) else None
        clean = total is not None and total == total  # no NaN (inf - inf says no too)
        lo_i = 0
        for b in range(first_b, last_b + 1):
            if b == last_b:
                hi_i = len(times)
            else:
                hi_i = bisect.bisect_left(times, start + (b + 1) * width, lo_i)
            if hi_i > lo_i:
                if clean:
                    self._numbers(b, times, values, lo_i, hi_i)
                else:
                    self._mixed(b, times, values, lo_i, hi_i)
            lo_i = hi_i

    def _numbers(self, b: int, times: list[int], values: list[Any], i: int, j: int) -> None:
        part = values[i:j]
        lo, hi = min(part), max(part)
        lo_i, hi_i = i + part.index(lo), i + part.index(hi)
        self._merge(b, times[lo_i], lo, times[hi_i], hi, None)

    def _mixed(self, b: int, times: list[int], values: list[Any], i: int, j: int) -> None:
        for k in range(i, j):
            t, v = times[k], values[k]
            if _gap(v):
                self._merge(b, None, None, None, None, (t, v))
            elif isinstance(v, _NUMBERS):
                self._merge(b, t, v, t, v, None)
            else:
                self._merge_unordered(b, t, v)

    def _merge(
        self,
        b: int,
        lo_t: int | None,
        lo: Any,
        hi_t: int | None,
        hi: Any,
        gap: tuple[int, Any] | None,
    ) -> None:
        bucket = self._buckets.get(b)
        if bucket is None:
            self._buckets[b] = [lo_t, lo, hi_t, hi, *(gap or (None, None))]
            return
        if lo_t is not None:
            if bucket[0] is None or not isinstance(bucket[1], _NUMBERS) or lo < bucket[1]:
                bucket[0], bucket[1] = lo_t, lo
            if bucket[2] is None or not isinstance(bucket[3], _NUMBERS) or hi > bucket[3]:
                bucket[2], bucket[3] = hi_t, hi
        if gap is not None and bucket[4] is None:
            bucket[4], bucket[5] = gap

    def _merge_unordered(self, b: int, t: int, v: Any) -> None:
        """Text or an array: the bucket keeps its first and its last."""
        bucket = self._buckets.get(b)
        if bucket is None:
            self._buckets[b] = [t, v, t, v, None, None]
            return
        if bucket[0] is None:
            bucket[0], bucket[1] = t, v
        bucket[2], bucket[3] = t, v

    def result(self) -> list[tuple[int, Any]]:
        """The points, oldest first: the one before the range, then the range's."""
        out: list[tuple[int, Any]] = []
        if self.before is not None and self._first != self.start:
            out.append(self.before)  # not needed when a point sits on the start itself
        if self._raw:
            raw = list(zip(self._raw_times, self._raw_values, strict=True))
            if any(b[0] < a[0] for a, b in itertools.pairwise(raw)):
                raw.sort(key=lambda p: p[0])  # blocks that overlap (a clock set back)
            return out + raw
        buckets = [self._buckets[b] for b in sorted(self._buckets)]
        room = self.limit - len(out)
        # two points a bucket fit; buckets with a gap take a third: while that is too many,
        # neighbours are merged (their extremes and first gap kept), so every peak and a gap
        # of every stretch stay, at half the resolution
        while len(buckets) > 1 and sum(len(_points(b)) for b in buckets) > room:
            buckets = [
                _merged(buckets[i], buckets[i + 1]) if i + 1 < len(buckets) else buckets[i]
                for i in range(0, len(buckets), 2)
            ]
        for bucket in buckets:
            out += sorted(_points(bucket).items())
        return out


def _points(bucket: list[Any]) -> dict[int, Any]:
    """A bucket's points by time: its minimum, maximum and first gap (each once)."""
    lo_t, lo, hi_t, hi, gap_t, gap = bucket
    points: dict[int, Any] = {}
    if lo_t is not None:
        points[lo_t] = lo
        points.setdefault(hi_t, hi)
    if gap_t is not None:
        points.setdefault(gap_t, gap)
    return points


def _merged(a: list[Any], b: list[Any]) -> list[Any]:
    """Two neighbouring buckets as one: the smaller minimum, the larger maximum (or, for values
    without order, the first and the last), the first gap."""
    if a[0] is None:
        lo_t, lo = b[0], b[1]
    elif b[0] is None or not (isinstance(a[1], _NUMBERS) and isinstance(b[1], _NUMBERS)):
        lo_t, lo = a[0], a[1]
    else:
        lo_t, lo = (b[0], b[1]) if b[1] < a[1] else (a[0], a[1])
    if b[2] is None:
        hi_t, hi = a[2], a[3]
    elif a[2] is None or not (isinstance(a[3], _NUMBERS) and isinstance(b[3], _NUMBERS)):
        hi_t, hi = b[2], b[3]
    else:
        hi_t, hi = (b[2], b[3]) if b[3] > a[3] else (a[2], a[3])
    gap_t, gap = (a[4], a[5]) if a[4] is not None else (b[4], b[5])
    return [lo_t, lo, hi_t, hi, gap_t, gap]


def _all_numbers(values: list[Any]) -> bool:
    """Whether every value is an int, float or bool (checked on the types present, in C)."""
    return set(map(type, values)) <= {int, float, bool}
