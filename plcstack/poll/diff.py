"""What changed between two poll configurations, PLC by PLC: what a reload asks of the poller.

A PLC is matched by its name. One only in the new file is *added*; one only in the old is
*removed*; one in both is *unchanged*, *replanned* (its tags, its scan groups or their
intervals, ``max_gap`` or ``word_order`` changed: its requests are planned again, on its open
connection) or *reconnected* (its URL or a connection option changed: ``timeout``,
``connect_timeout``, ``backoff_max``; a new connection, with its new tags). ``[poll]`` keys that
are no PLC's (``concurrency``, ``queue``, ``batch_wait``) are named apart.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from plcstack.poll.config import PlcConfig, PollConfig

__all__ = ["CONNECTION_FIELDS", "PlcChanges", "plc_changes"]

#: what a PLC's connection is made of: a change of any one of them is a new connection
CONNECTION_FIELDS = ("url", "timeout", "connect_timeout", "backoff_max")
#: the keys of ``[poll]`` that belong to the whole poller, not to a PLC
POLLER_FIELDS = ("concurrency", "queue", "batch_wait")


@dataclass(frozen=True)
class PlcChanges:
    """The difference between two :class:`PollConfig` (``old`` and ``new``), by PLC name; each
    tuple in the new file's order (``removed``: the old file's)."""

    old: PollConfig
    new: PollConfig
    added: tuple[PlcConfig, ...] = ()
    removed: tuple[PlcConfig, ...] = ()
    reconnected: tuple[PlcConfig, ...] = ()
    replanned: tuple[PlcConfig, ...] = ()
    #: ``[poll]`` keys of the whole poller whose value changed
    poller: tuple[str, ...] = ()

    @property
    def empty(self) -> bool:
        """Nothing of the poller's changed (a file re-read as it was)."""
        return not (self.added or self.removed or self.reconnected or self.replanned or self.poller)

    @property
    def unchanged(self) -> tuple[str, ...]:
        """The PLCs of both files that keep their connection and their plans."""
        touched = {p.name for p in (*self.added, *self.reconnected, *self.replanned)}
        return tuple(p.name for p in self.new.plcs if p.name not in touched)

    def summary(self) -> str:
        """One line for a log: ``2 added (a, b), 1 removed (c), 0 reconnected, 1 replanned (d)``."""
        parts = []
        for what, plcs in (
            ("added", self.added),
            ("removed", self.removed),
            ("reconnected", self.reconnected),
            ("replanned", self.replanned),
        ):
            names = _names(plcs)
            parts.append(f"{len(plcs)} {what}" + (f" ({names})" if names else ""))
        if self.poller:
            parts.append(f"[poll] {', '.join(self.poller)} changed")
        return ", ".join(parts)


def _names(plcs: Iterable[PlcConfig], most: int = 5) -> str:
    names = [p.name for p in plcs]
    shown = ", ".join(names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")


def _groups_of(plc: PlcConfig, groups: Mapping[str, float]) -> dict[str, float]:
    return {t.group: groups[t.group] for t in plc.tags}


def _connection(plc: PlcConfig) -> tuple[object, ...]:
    """The fields of :data:`CONNECTION_FIELDS`."""
    return (plc.url, plc.timeout, plc.connect_timeout, plc.backoff_max)


def _poller(config: PollConfig) -> dict[str, object]:
    """The fields of :data:`POLLER_FIELDS` by name."""
    return {
        "concurrency": config.concurrency,
        "queue": config.queue,
        "batch_wait": config.batch_wait,
    }


def plc_changes(old: PollConfig, new: PollConfig) -> PlcChanges:
    """What changed from ``old`` to ``new`` (see the module docstring)."""
    before = {p.name: p for p in old.plcs}
    after = {p.name: p for p in new.plcs}
    added, reconnected, replanned = [], [], []
    for name, plc in after.items():
        was = before.get(name)
        if was is None:
            added.append(plc)
        elif _connection(was) != _connection(plc):
            reconnected.append(plc)
        elif was != plc or _groups_of(was, old.groups) != _groups_of(plc, new.groups):
            replanned.append(plc)
    removed = tuple(p for p in old.plcs if p.name not in after)
    then, now = _poller(old), _poller(new)
    poller = tuple(f for f in POLLER_FIELDS if then[f] != now[f])
    return PlcChanges(old, new, tuple(added), removed, tuple(reconnected), tuple(replanned), poller)
