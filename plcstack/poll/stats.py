"""The poller's per-PLC counters, request latencies and the table ``plcstack poll`` prints."""

from __future__ import annotations

import array
import itertools
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field

__all__ = ["LATENCY_WINDOW", "LatencyWindow", "PlcStats", "format_stats"]

#: how many recent request latencies each PLC keeps for its percentiles
LATENCY_WINDOW = 4096


class LatencyWindow:
    """The most recent ``maxlen`` request latencies in seconds (float32 ring buffer).

    4 bytes per latency in one array: a full window of 4096 is 16 KiB per PLC, where a deque of
    float objects took about 128 KiB (1000 PLCs: 16 MiB instead of 128 MiB). Iterates oldest
    first.
    """

    __slots__ = ("_data", "_next", "maxlen", "total")

    def __init__(self, values: Iterable[float] = (), maxlen: int = LATENCY_WINDOW) -> None:
        if maxlen < 1:
            raise ValueError("maxlen must be at least 1")
        self.maxlen = maxlen
        self._data = array.array("f")
        self._next = 0  # once full: the index of the oldest value, overwritten next
        #: latencies ever appended (for consumers that want only the new ones: see tail)
        self.total = 0
        for value in values:
            self.append(value)

    def append(self, value: float) -> None:
        self.total += 1
        data = self._data
        if len(data) < self.maxlen:
            data.append(value)
        else:
            i = self._next
            data[i] = value
            self._next = i + 1 if i + 1 < self.maxlen else 0

    def replace_newest(self, value: float) -> None:
        """Overwrite the newest entry (a trend's last point taking a later value of its
        second); nothing if empty."""
        data = self._data
        if data:
            data[(self._next if len(data) == self.maxlen else len(data)) - 1] = value

    def __len__(self) -> int:
        return len(self._data)

    def tail(self, n: int) -> list[float]:
        """The newest ``n`` latencies (fewer if the window holds fewer), oldest first.

        With :attr:`total`, a consumer such as the metrics histogram takes exactly what was
        appended since it last looked, without copying the whole window.
        """
        data, size = self._data, len(self._data)
        n = min(n, size)
        if n <= 0:
            return []
        end = self._next if size == self.maxlen else size  # one past the newest
        if n <= end:
            return list(data[end - n : end])
        return list(data[size - (n - end) :]) + list(data[:end])

    def __iter__(self) -> Iterator[float]:
        data, cut = self._data, self._next
        return itertools.chain(data[cut:], data[:cut])

    def __repr__(self) -> str:
        return f"LatencyWindow({len(self)} of {self.maxlen})"


@dataclass(slots=True)
class PlcStats:
    """Counters of one PLC as seen by the poller."""

    requests: int = 0
    errors: int = 0
    reconnects: int = 0
    connect_failures: int = 0
    overruns: int = 0
    drops: int = 0
    samples: int = 0
    bad_samples: int = 0
    scans: int = 0
    writes: int = 0
    latencies: LatencyWindow = field(default_factory=LatencyWindow, repr=False)

    def percentile(self, q: float) -> float | None:
        """Latency percentile in seconds over the recent window (nearest rank); None if empty."""
        return self.percentiles((q,))[0]

    def percentiles(self, qs: Sequence[float], newest: int | None = None) -> list[float | None]:
        """Several percentiles from one sort, over the ``newest`` latencies (default: the whole
        window); None each if there is none. A console looking at a thousand PLCs every few
        seconds takes a short window: a 4096-point sort per PLC per look adds up."""
        data = sorted(self.latencies if newest is None else self.latencies.tail(newest))
        if not data:
            return [None for _ in qs]
        n = len(data)
        return [data[max(0, min(n - 1, int(q / 100.0 * n + 0.5) - 1))] for q in qs]


#: widest line of the statistics table (a terminal's 80 columns, less one)
STATS_COLUMNS = 79


def format_stats(stats: dict[str, PlcStats], *, dropped_total: int | None = None) -> str:
    """A plain-text table of per-PLC statistics (what ``plcstack poll`` prints on stderr)."""

    def ms(value: float | None) -> str:
        return "-" if value is None else f"{value * 1000:.2f}"

    header: tuple[str, ...] = ("plc", "requests", "errors", "reconn", "overrun", "drops")
    header += ("samples", "p50 ms", "p99 ms")
    rows: list[tuple[str, ...]] = [header]
    totals = PlcStats()
    for name, st in stats.items():
        rows.append(
            (
                name,
                str(st.requests),
                str(st.errors),
                str(st.reconnects),
                str(st.overruns),
                str(st.drops),
                str(st.samples),
                ms(st.percentile(50)),
                ms(st.percentile(99)),
            )
        )
        totals.requests += st.requests
        totals.errors += st.errors
        totals.reconnects += st.reconnects
        totals.overruns += st.overruns
        totals.drops += st.drops
        totals.samples += st.samples
    if len(stats) > 1:
        # the total's percentiles are over the last LATENCY_WINDOW requests of all PLCs together
        all_lat: list[float] = []
        for st in stats.values():
            all_lat.extend(st.latencies)
        totals.latencies = LatencyWindow(all_lat, maxlen=max(1, len(all_lat)))
        rows.append(
            (
                f"TOTAL ({len(stats)} PLCs)",
                str(totals.requests),
                str(totals.errors),
                str(totals.reconnects),
                str(totals.overruns),
                str(totals.drops),
                str(totals.samples),
                ms(totals.percentile(50)),
                ms(totals.percentile(99)),
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    # Within STATS_COLUMNS: one space between columns, and a PLC name too long for what the
    # numbers leave is cut, its last kept character replaced by "~".
    room = STATS_COLUMNS - sum(widths[1:]) - len(widths) + 1
    widths[0] = max(8, min(widths[0], room))
    lines = []
    for r in rows:
        name = r[0] if len(r[0]) <= widths[0] else r[0][: widths[0] - 1] + "~"
        cells = [name.ljust(widths[0])] + [
            c.rjust(w) for c, w in zip(r[1:], widths[1:], strict=True)
        ]
        lines.append(" ".join(cells).rstrip())
    if dropped_total is not None:
        lines.append(f"samples dropped for a slow consumer: {dropped_total}")
    return "\n".join(lines)
