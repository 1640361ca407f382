"""Which PLCs the overview shows: filtered, sorted by state, one page at a time.

A thousand PLCs in one table is a page nobody reads and a megabyte to send, so the overview
shows :data:`PAGE_SIZE` PLCs at a time, the ones that need a look first (offline, then online
with bad tags, then not yet polled, then online), and a filter: the words typed must each
appear in the PLC's name, its URL or its state. The page (``/?q=press&sort=name&page=2``)
and ``GET /api/overview`` take the same parameters and call :func:`select`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from plcstack.north.web.state import STATE_ORDER, PlcHealth, state_of
from plcstack.poll.config import PlcConfig

__all__ = ["PAGE_SIZE", "SORTS", "Selection", "select"]

PAGE_SIZE = 50
#: the orders the overview offers, by their parameter
SORTS = {"state": "problems first", "name": "by name"}
#: the longest filter taken (the rest is ignored)
MAX_QUERY = 100


@dataclass(frozen=True)
class Selection:
    """One page of the overview: the PLCs' names, and where the page is among all."""

    names: list[str]
    #: PLCs the filter matched
    matched: int
    #: 1-based, within 1..pages
    page: int
    pages: int
    query: str
    sort: str

    @property
    def first(self) -> int:
        """The 1-based position of the page's first PLC (0 when none matched)."""
        return (self.page - 1) * PAGE_SIZE + 1 if self.names else 0


def select(
    plcs: Mapping[str, PlcConfig],
    health: Mapping[str, PlcHealth],
    *,
    query: str = "",
    sort: str = "state",
    page: str | int = 1,
) -> Selection:
    """The page ``page`` of the PLCs matching ``query``, in the order ``sort`` (an unknown
    sort is ``state``; a page beyond the last is the last; anything not a number is 1)."""
    query = " ".join(query.split())[:MAX_QUERY]
    sort = sort if sort in SORTS else "state"
    words = query.casefold().split()
    matched = []
    for name, h in health.items():
        state = state_of(h)
        if words:
            config = plcs.get(name)
            haystack = f"{name} {config.url if config else ''} {state}".casefold()
            if not all(w in haystack for w in words):
                continue
        matched.append((STATE_ORDER[state] if sort == "state" else 0, name))
    matched.sort()
    pages = max(1, -(-len(matched) // PAGE_SIZE))
    try:
        number = min(max(1, int(page)), pages)
    except (TypeError, ValueError):
        number = 1
    start = (number - 1) * PAGE_SIZE
    names = [name for _, name in matched[start : start + PAGE_SIZE]]
    return Selection(names, len(matched), number, pages, query, sort)
