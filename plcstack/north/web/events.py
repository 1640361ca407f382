"""Server-sent events to the browsers: changes only, pushed twice a second, bounded per client.

One :class:`EventHub` per console. Every :data:`PUSH_EVERY` seconds it takes the tags that
changed since the last push from the :class:`~.state.ConsoleState`, encodes them ONCE per scope
(every PLC for the overview, one PLC for its page) and offers the same bytes to each client of
that scope; the PLCs' health and counters go out every :data:`PLCS_EVERY` seconds, only the rows
that changed. A new client first gets a snapshot of its scope, so nothing that changed between
the page's rendering and the stream's start is missed.

Bounded memory: a client holds at most :data:`QUEUE_LIMIT` messages not yet written (each at
most one row per tag of its scope), and the socket's own buffer is bounded by aiohttp's flow
control (a write waits for the peer to read). A client whose queue is full does not read: it is
dropped (its connection aborted), never buffered without limit. At most :data:`MAX_CLIENTS`
streams at once; more get 503.

Three views: ``/events`` (every PLC and every tag, for scripts), ``/events?plc=NAME`` (one
PLC's page) and ``/events?view=overview[&show=NAME...]`` (the overview page: the rows of the
PLCs it shows and the counts, so a browser on a page of 50 of a thousand PLCs is sent neither
ten thousand tags a second nor a thousand rows every two seconds).

Event format (``data`` is JSON)::

    event: tags     data: [[plc, tag, value, quality, source_time, error,
                            text, changed, stale_since], ...]
    event: plcs     data: [{name, up, state, since, last_error, error_time, bad_tags,
                            requests, errors, ...}, ...]
    event: counts   data: {online, offline, errors, unknown, total}

``value`` is the latest sample's (null while bad); ``text`` is what a person sees: the last
good value in the tag's display form (with its unit), kept while the tag is bad and marked by
``stale_since``; ``changed`` is when that value was first read (Unix seconds).
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
from collections.abc import Callable, Iterable
from typing import Any

from plcstack.north.web.state import ConsoleState, PlcRow
from plcstack.poll.samples import Sample

__all__ = ["MAX_CLIENTS", "PUSH_EVERY", "QUEUE_LIMIT", "EventClient", "EventHub", "sse"]

log = logging.getLogger("plcstack.web")

PUSH_EVERY = 0.5
PLCS_EVERY = 2.0
QUEUE_LIMIT = 32
MAX_CLIENTS = 64


def sse(event: str, data: Any) -> bytes:
    """One server-sent event; JSON has no line breaks, so ``data`` is one line."""
    return f"event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n".encode()


def tag_rows(state: ConsoleState, samples: Iterable[Sample]) -> list[list[Any]]:
    shown, text = state.shown, state.text
    return [
        [s.plc, s.tag, shown(s), s.quality.value, s.source_time, s.error, *text(s)] for s in samples
    ]


class EventClient:
    """One browser's stream: a bounded queue of encoded events."""

    def __init__(
        self,
        plc: str | None,
        limit: int = QUEUE_LIMIT,
        *,
        overview: bool = False,
        names: frozenset[str] | None = None,
    ) -> None:
        #: the PLC whose page this is, None for every PLC
        self.plc = plc
        #: the overview page's stream: PLC rows and counts, no tags
        self.overview = overview
        #: the PLCs whose rows the overview shows (None: all)
        self.names = names
        self.limit = limit
        self.dropped = False
        self.closed = False
        #: called once when the client is dropped (the handler aborts its connection)
        self.on_drop: Callable[[], None] | None = None
        self._queue: collections.deque[bytes] = collections.deque()
        self._wake = asyncio.Event()

    def offer(self, data: bytes) -> None:
        if self.closed:
            return
        if len(self._queue) >= self.limit:
            log.warning(
                "web console: dropped a browser that read nothing of its last %d updates",
                self.limit,
            )
            self.drop()
            return
        self._queue.append(data)
        self._wake.set()

    def drop(self) -> None:
        """End a client that does not read: its queue freed, its connection aborted."""
        if self.closed:
            return
        self.dropped = True
        self.close()
        if self.on_drop is not None:
            self.on_drop()

    def close(self) -> None:
        """End the stream after nothing more (the console is closing)."""
        self.closed = True
        self._queue.clear()
        self._wake.set()

    async def next(self) -> bytes | None:
        """The next event to write, or None once dropped."""
        while not self._queue:
            if self.closed:
                return None
            self._wake.clear()
            await self._wake.wait()
        return self._queue.popleft()


class EventHub:
    """Pushes changes from the state to every connected client (see the module docstring)."""

    def __init__(
        self,
        state: ConsoleState,
        plc_rows: Callable[[str | None], list[PlcRow]],
        *,
        push_every: float = PUSH_EVERY,
        plcs_every: float = PLCS_EVERY,
        max_clients: int = MAX_CLIENTS,
    ) -> None:
        self.state = state
        #: PLC rows of one scope (None: every PLC)
        self.plc_rows = plc_rows
        self.push_every = push_every
        self.plcs_every = plcs_every
        self.max_clients = max_clients
        self.clients: set[EventClient] = set()
        self.dropped = 0
        self._since_plcs = 0.0
        self._last_plcs: dict[str, PlcRow] = {}
        self._last_counts: dict[str, int] = {}

    def connect(
        self, plc: str | None, *, overview: bool = False, names: Iterable[str] | None = None
    ) -> EventClient | None:
        """A new client with its snapshot queued; None when :attr:`max_clients` are connected.
        ``names``: the PLCs an overview shows (their rows only, not a thousand)."""
        if len(self.clients) >= self.max_clients:
            return None
        shown = frozenset(names) if overview and names is not None else None
        client = EventClient(None if overview else plc, overview=overview, names=shown)
        # the PLC rows first: a page shows a PLC's error once, so it needs to know it before
        # the tags come
        rows = self.plc_rows(client.plc)
        if shown is not None:
            rows = [r for r in rows if r["name"] in shown]
        client.offer(sse("plcs", rows))
        if overview:
            client.offer(sse("counts", self.state.counts()))
        else:
            latest = self.state.latest.values()
            samples = latest if plc is None else (s for s in latest if s.plc == plc)
            client.offer(sse("tags", tag_rows(self.state, samples)))
        self.clients.add(client)
        return client

    def disconnect(self, client: EventClient) -> None:
        if client in self.clients:
            self.clients.discard(client)
            if client.dropped:
                self.dropped += 1

    async def run(self) -> None:
        """Push until cancelled."""
        while True:
            await asyncio.sleep(self.push_every)
            self.push()

    def push(self) -> None:
        """One round: the changed tags, and every :attr:`plcs_every` the changed PLC rows."""
        changes = self.state.take_changes()
        self._since_plcs += self.push_every
        plcs_due = self._since_plcs >= self.plcs_every
        if plcs_due:
            self._since_plcs = 0.0
        clients = [c for c in self.clients if not c.closed]
        if not clients:
            self._last_plcs.clear()  # a client that comes gets a snapshot anyway
            self._last_counts = {}
            return
        if changes:
            self._fan_out(
                [c for c in clients if not c.overview],
                "tags",
                changes,
                lambda s: s.plc,
                lambda c: tag_rows(self.state, c),
            )
        if plcs_due:
            rows = self.plc_rows(None)
            last = self._last_plcs
            fresh = [r for r in rows if last.get(r["name"]) != r]
            self._last_plcs = {r["name"]: r for r in rows}
            if fresh:
                self._fan_out(clients, "plcs", fresh, lambda r: r["name"], list)
            counts = self.state.counts()
            if counts != self._last_counts:
                self._last_counts = counts
                data = sse("counts", counts)
                for client in clients:
                    if client.overview:
                        client.offer(data)

    def _fan_out(
        self,
        clients: list[EventClient],
        event: str,
        items: list[Any],
        plc_of: Callable[[Any], str],
        encode: Callable[[list[Any]], list[Any]],
    ) -> None:
        """Encode once per scope, offer to each client of it."""
        everything: bytes | None = None
        by_plc: dict[str, list[Any]] | None = None
        encoded: dict[str, bytes] = {}
        for client in clients:
            if client.names is not None:  # the overview's rows: its page's PLCs only
                rows = [item for item in items if plc_of(item) in client.names]
                if rows:
                    client.offer(sse(event, encode(rows)))
                continue
            if client.plc is None:
                if everything is None:
                    everything = sse(event, encode(items))
                client.offer(everything)
                continue
            if by_plc is None:
                by_plc = {}
                for item in items:
                    by_plc.setdefault(plc_of(item), []).append(item)
            mine = by_plc.get(client.plc)
            if not mine:
                continue
            data = encoded.get(client.plc)
            if data is None:
                data = encoded[client.plc] = sse(event, encode(mine))
            client.offer(data)
