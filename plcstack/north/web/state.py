"""What the console knows: each tag's latest sample, each PLC's health, and trend rings.

Fed with every batch the north side reports (:meth:`ConsoleState.submit`, on the poller's loop,
so nothing here locks). Memory is bounded by the configuration, never by time or traffic: one
latest sample and one trend ring per configured tag (two float32 arrays of ``trend_seconds``
points: 2.4 KB a tag at the default 300), one health record per PLC, and the set of tags that
changed since the last push to the browsers (at most one entry per tag).

The trend keeps at most one point per :data:`TREND_STEP` seconds (the latest value within it),
so a 10 Hz tag covers the same minutes as a 1 Hz one; times are float32 seconds since the
console started (precise to a few milliseconds for weeks), values float32 (a chart's precision).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from plcstack.output import float32_short, json_safe
from plcstack.poll.config import PlcConfig, TagConfig
from plcstack.poll.samples import Quality, Sample, Scan
from plcstack.poll.stats import LatencyWindow, PlcStats

__all__ = ["TREND_STEP", "ConsoleState", "PlcHealth", "Trend", "plc_row", "tag_row"]

#: shortest spacing of two trend points in seconds (a 1 Hz tag's jitter stays above it)
TREND_STEP = 0.9
#: the recent requests whose latencies give the console's p50/p99 (a sort per PLC per look)
PERCENTILE_WINDOW = 256


class Trend:
    """A bounded ring of (time, value) points of one numeric tag."""

    __slots__ = ("_epoch", "last", "times", "values")

    def __init__(self, points: int, epoch: float) -> None:
        self._epoch = epoch
        self.times = LatencyWindow(maxlen=points)  # a float32 ring: seconds since epoch
        self.values = LatencyWindow(maxlen=points)
        self.last = -1e30

    def add(self, t: float, value: float) -> None:
        rel = t - self._epoch
        if rel - self.last < TREND_STEP:
            self.values.replace_newest(value)  # the latest value of this step wins
            return
        self.last = rel
        self.times.append(rel)
        self.values.append(value)

    def points(self) -> list[tuple[float, float]]:
        """Oldest first, times as Unix seconds."""
        epoch = self._epoch
        return [(epoch + t, v) for t, v in zip(self.times, self.values, strict=True)]


@dataclass(slots=True)
class PlcHealth:
    #: None until the first sample
    up: bool | None = None
    last_error: str | None = None
    #: when the last error was seen (Unix seconds)
    error_time: float | None = None


class ConsoleState:
    """The console's view of one poller's PLCs and tags (see the module's docstring)."""

    def __init__(
        self,
        plcs: Sequence[PlcConfig],
        *,
        trend_seconds: int = 300,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.plcs: dict[str, PlcConfig] = {p.name: p for p in plcs}
        self.tags: dict[tuple[str, str], TagConfig] = {
            (p.name, t.name): t for p in plcs for t in p.tags
        }
        #: tags whose values are float32 (shown at float32 precision: 59.4669, not the
        #: 59.46688461303711 its bits widen to)
        self.float32 = frozenset(
            key
            for key, t in self.tags.items()
            if t.type.kind == "float" and t.type.bits == 32 and t.scale is None
        )
        self.latest: dict[tuple[str, str], Sample] = {}
        self.health: dict[str, PlcHealth] = {name: PlcHealth() for name in self.plcs}
        self.trends: dict[tuple[str, str], Trend] = {}
        #: tags whose value, quality or error changed since :meth:`take_changes`
        self.changed: dict[tuple[str, str], Sample] = {}
        self._points = trend_seconds
        self._epoch = clock()

    def submit(self, scans: Iterable[Scan]) -> None:
        """Take one batch of scans (the north side's sink protocol)."""
        latest, changed, health, trends = self.latest, self.changed, self.health, self.trends
        good = Quality.GOOD
        for s in (s for scan in scans for s in scan.samples):
            key = (s.plc, s.tag)
            prev = latest.get(key)
            latest[key] = s
            value = s.value
            if (
                prev is None
                or prev.value != value
                or prev.quality is not s.quality
                or prev.error != s.error
            ):
                changed[key] = s
            h = health.get(s.plc)
            if h is None:
                continue  # a sample of a PLC this console was not configured with
            if s.quality is good:
                h.up = True
                kind = type(value)
                if kind is float or kind is int or kind is bool:
                    trend = trends.get(key)
                    if trend is None:
                        trend = trends[key] = Trend(self._points, self._epoch)
                    trend.add(s.source_time, value)  # type: ignore[arg-type]
            else:
                h.up = False
                h.last_error = s.error
                h.error_time = s.receive_time

    def take_changes(self) -> list[Sample]:
        """The samples that changed since the last call (latest of each tag), and forget them."""
        changes = list(self.changed.values())
        self.changed.clear()
        return changes

    def shown(self, s: Sample) -> Any:
        """The sample's value for JSON: non-finite floats as strings, float32 at its precision."""
        value = s.value
        if type(value) is float and (s.plc, s.tag) in self.float32:
            return json_safe(float32_short(value))
        if isinstance(value, list) and (s.plc, s.tag) in self.float32:
            return json_safe([float32_short(v) if type(v) is float else v for v in value])
        return json_safe(value)

    def trend(self, plc: str, tag: str) -> list[tuple[float, float]]:
        t = self.trends.get((plc, tag))
        return [] if t is None else t.points()


def tag_row(state: ConsoleState, s: Sample) -> dict[str, Any]:
    """One tag as the REST API gets it."""
    return {
        "plc": s.plc,
        "tag": s.tag,
        "value": state.shown(s),
        "quality": s.quality.value,
        "source_time": s.source_time,
        "error": s.error,
    }


def plc_row(name: str, health: PlcHealth, stats: PlcStats | None) -> dict[str, Any]:
    """One PLC's health and counters; p50/p99 in ms over its last 256 requests."""
    row: dict[str, Any] = {
        "name": name,
        "up": health.up,
        "last_error": health.last_error,
        "error_time": health.error_time,
    }
    if stats is not None:
        p50, p99 = stats.percentiles((50, 99), newest=PERCENTILE_WINDOW)
        row.update(
            requests=stats.requests,
            errors=stats.errors,
            reconnects=stats.reconnects,
            p50_ms=None if p50 is None else round(p50 * 1000.0, 3),
            p99_ms=None if p99 is None else round(p99 * 1000.0, 3),
        )
    return row
