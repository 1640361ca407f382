"""What the console knows: each tag's latest and last good sample, each PLC's health, trends.

Fed with every batch the north side reports (:meth:`ConsoleState.submit`, on the poller's loop,
so nothing here locks). While a tag is bad its last good value stays, marked stale since the
first bad sample, so an operator keeps the last known value exactly when a PLC goes offline.
Memory is bounded by the configuration, never by time or traffic: one latest and one last good
sample and one trend ring per configured tag (two float32 arrays of ``trend_seconds``
points: 2.4 KB a tag at the default 300), one health record per PLC, and the set of tags that
changed since the last push to the browsers (at most one entry per tag).

The trend keeps at most one point per :data:`TREND_STEP` seconds (the latest value within it),
so a 10 Hz tag covers the same minutes as a 1 Hz one; times are float32 seconds since the
console started (precise to a few milliseconds for weeks), values float32 (a chart's precision).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, NotRequired, TypedDict

from plcstack.north.layout import Reachability
from plcstack.north.web.display import TagDisplay
from plcstack.output import float32_short, json_safe
from plcstack.poll.config import PlcConfig, TagConfig
from plcstack.poll.samples import Quality, Sample, Scan
from plcstack.poll.stats import LatencyWindow, PlcStats

__all__ = [
    "STATE_ORDER",
    "TREND_STEP",
    "ConsoleState",
    "PlcHealth",
    "Trend",
    "plc_row",
    "state_of",
    "tag_row",
]

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
    #: when ``up`` last changed (Unix seconds)
    since: float | None = None
    last_error: str | None = None
    #: when the last error was seen (Unix seconds)
    error_time: float | None = None
    #: tags whose latest sample is bad
    bad_tags: int = 0


#: how the overview orders PLCs by state: the ones that need a look first
STATE_ORDER = {"offline": 0, "errors": 1, "unknown": 2, "online": 3}


def state_of(health: PlcHealth) -> str:
    """``online``, ``offline``, ``errors`` (online, some tags bad) or ``unknown``."""
    if health.up is None:
        return "unknown"
    if not health.up:
        return "offline"
    return "errors" if health.bad_tags else "online"


class ConsoleState:
    """The console's view of one poller's PLCs and tags (see the module's docstring).

    ``reachable`` is the run's rule of whether a PLC is reachable (North's
    :class:`~plcstack.north.layout.Reachability`, fed with every scan before report-by-exception
    drops the unchanged samples); without it the console applies the same rule to the scans it
    gets."""

    def __init__(
        self,
        plcs: Sequence[PlcConfig],
        *,
        trend_seconds: int = 300,
        clock: Callable[[], float] = time.time,
        reachable: Callable[[str], bool | None] | None = None,
    ) -> None:
        self.plcs: dict[str, PlcConfig] = {p.name: p for p in plcs}
        self.tags: dict[tuple[str, str], TagConfig] = {
            (p.name, t.name): t for p in plcs for t in p.tags
        }
        #: how each tag is shown (decimals, labels, hex, unit)
        self.displays = {key: TagDisplay(t) for key, t in self.tags.items()}
        #: tags whose values are float32 (shown at float32 precision: 59.4669, not the
        #: 59.46688461303711 its bits widen to)
        self.float32 = frozenset(key for key, d in self.displays.items() if d.float32)
        self.latest: dict[tuple[str, str], Sample] = {}
        #: the last good sample of each tag: shown, marked stale, while the tag is bad
        self.good: dict[tuple[str, str], Sample] = {}
        #: when each tag that is bad now went bad (source time of its first bad sample)
        self.stale_since: dict[tuple[str, str], float] = {}
        #: when each tag's good value last changed (source time of the first sample with it)
        self.changed_at: dict[tuple[str, str], float] = {}
        self.health: dict[str, PlcHealth] = {name: PlcHealth() for name in self.plcs}
        self.trends: dict[tuple[str, str], Trend] = {}
        #: tags whose value, quality or error changed since :meth:`take_changes`
        self.changed: dict[tuple[str, str], Sample] = {}
        self._points = trend_seconds
        self._epoch = clock()
        self._reachability = Reachability()
        self._reachable = reachable

    def reconfigure(self, plcs: Sequence[PlcConfig], changed: Collection[str] = ()) -> None:
        """The PLCs of a reloaded configuration: a removed PLC's row and tags are gone, an
        added one's row is unknown until its first scan; of a PLC in ``changed`` the tags
        whose configuration differs start afresh. Everything else keeps its values, trends
        and health."""
        before = self.tags
        self.plcs = {p.name: p for p in plcs}
        self.tags = {(p.name, t.name): t for p in plcs for t in p.tags}
        self.displays = {key: TagDisplay(t) for key, t in self.tags.items()}
        self.float32 = frozenset(key for key, d in self.displays.items() if d.float32)
        kept = {key for key, tag in self.tags.items() if before.get(key) == tag}
        for table in (
            self.latest, self.good, self.stale_since, self.changed_at, self.trends, self.changed
        ):  # fmt: skip
            for key in [k for k in table if k not in kept]:
                del table[key]
        health = {}
        for name in self.plcs:
            h = self.health.get(name)
            if h is None or name in changed:
                h = PlcHealth()
                h.bad_tags = sum(1 for key in self.stale_since if key[0] == name)
            health[name] = h
        self.health = health

    def submit(self, scans: Iterable[Scan]) -> None:
        """Take one batch of scans (the north side's sink protocol)."""
        latest, changed, health, trends = self.latest, self.changed, self.health, self.trends
        good_samples, stale, changed_at = self.good, self.stale_since, self.changed_at
        good = Quality.GOOD
        for scan in scans:
            h = health.get(scan.plc)
            for s in scan.samples:
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
                if h is None:
                    continue  # a sample of a PLC this console was not configured with
                if s.quality is good:
                    last_good = good_samples.get(key)
                    if last_good is None or last_good.value != value:
                        changed_at[key] = s.source_time
                    good_samples[key] = s
                    if stale and stale.pop(key, None) is not None:
                        h.bad_tags -= 1
                    kind = type(value)
                    if kind is float or kind is int or kind is bool:
                        trend = trends.get(key)
                        if trend is None:
                            trend = trends[key] = Trend(self._points, self._epoch)
                        trend.add(s.source_time, value)  # type: ignore[arg-type]
                else:
                    if key not in stale:
                        stale[key] = s.source_time
                        h.bad_tags += 1
                    h.last_error = s.error
                    h.error_time = s.receive_time
            if h is not None:
                self._reach(scan, h)

    def _reach(self, scan: Scan, h: PlcHealth) -> None:
        if self._reachable is None:
            self._reachability.update(scan)
            up = self._reachability.get(scan.plc)
        else:
            up = self._reachable(scan.plc)
        if up is not None and up is not h.up:
            h.up = up
            h.since = scan.source_time if up else scan.receive_time

    def counts(self) -> dict[str, int]:
        """PLCs by state (``online`` counts only those without bad tags), and all of them."""
        out = dict.fromkeys(STATE_ORDER, 0)
        for h in self.health.values():
            out[state_of(h)] += 1
        out["total"] = len(self.health)
        return out

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

    def text(self, s: Sample) -> tuple[str, float | None, float | None]:
        """What a person sees of a tag: the display text of its last good value, since when
        it holds that value, and since when it is stale (None while the tag is good)."""
        key = (s.plc, s.tag)
        last = s if s.quality is Quality.GOOD else self.good.get(key)
        display = self.displays.get(key)
        if last is None:
            return "", None, self.stale_since.get(key)
        text = display.text(last.value) if display is not None else str(last.value)
        return text, self.changed_at.get(key, last.source_time), self.stale_since.get(key)

    def trend(self, plc: str, tag: str) -> list[tuple[float, float]]:
        t = self.trends.get((plc, tag))
        return [] if t is None else t.points()


def tag_row(state: ConsoleState, s: Sample) -> dict[str, Any]:
    """One tag as the REST API gets it: the latest sample, and what a person sees of it."""
    text, good_time, stale_since = state.text(s)
    last = state.good.get((s.plc, s.tag))
    return {
        "plc": s.plc,
        "tag": s.tag,
        "value": state.shown(s),
        "quality": s.quality.value,
        "source_time": s.source_time,
        "error": s.error,
        "text": text,
        "last_good": None if last is None else state.shown(last),
        "changed": good_time,
        "stale_since": stale_since,
    }


class PlcRow(TypedDict):
    """One PLC's row as the console's pages, events and REST API carry it; the counters are
    there once the poller has statistics of the PLC."""

    name: str
    tags: int
    up: bool | None
    state: str
    since: float | None
    last_error: str | None
    error_time: float | None
    bad_tags: int
    requests: NotRequired[int]
    errors: NotRequired[int]
    reconnects: NotRequired[int]
    p50_ms: NotRequired[float | None]
    p99_ms: NotRequired[float | None]


def plc_row(name: str, health: PlcHealth, stats: PlcStats | None, tags: int = 0) -> PlcRow:
    """One PLC's health and counters (``tags``: how many it has); p50/p99 in ms over its last
    256 requests."""
    row: PlcRow = {
        "name": name,
        "tags": tags,
        "up": health.up,
        "state": state_of(health),
        "since": health.since,
        "last_error": health.last_error,
        "error_time": health.error_time,
        "bad_tags": health.bad_tags,
    }
    if stats is not None:
        p50, p99 = stats.percentiles((50, 99), newest=PERCENTILE_WINDOW)
        row["requests"] = stats.requests
        row["errors"] = stats.errors
        row["reconnects"] = stats.reconnects
        row["p50_ms"] = None if p50 is None else round(p50 * 1000.0, 3)
        row["p99_ms"] = None if p99 is None else round(p99 * 1000.0, 3)
    return row
